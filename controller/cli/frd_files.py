"""Measured-response CSV files (``freq_hz,mag_db,phase_deg[,coherence]``): read and written at
the edge, the codec (`controller.gate.frd_csv`) and the conversion to plant knowledge
(`controller.gate.frd`) stay pure."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from numpy.typing import ArrayLike

from controller.gate.frd import measured_from_frd
from controller.gate.frd_csv import FrdData, frd_csv_text, parse_frd_csv
from controller.gate.knowledge import MeasuredResponse

__all__ = ["load_measured", "measured_from_csv", "read_frd_csv", "write_frd_csv"]


def write_frd_csv(
    path: str | Path,
    freq_hz: ArrayLike,
    response: ArrayLike,
    coherence: ArrayLike | None = None,
) -> None:
    """Write ``freq_hz,mag_db,phase_deg[,coherence]`` with the phase unwrapped."""
    Path(path).write_text(frd_csv_text(freq_hz, response, coherence), encoding="utf-8")


def read_frd_csv(path: str | Path) -> FrdData:
    """Read a response file; ``ValueError("<file>:<line>: <what>")`` when it is malformed."""
    return parse_frd_csv(Path(path).read_text(encoding="utf-8-sig"), str(path))


def measured_from_csv(
    path: str | Path,
    name: str | None = None,
    *,
    sampled: bool = False,
    min_coherence: float = 0.0,
) -> MeasuredResponse:
    """Read one response file as plant knowledge; `name` defaults to the file stem (see
    `measured_from_frd`)."""
    return measured_from_frd(read_frd_csv(path), name if name is not None else Path(path).stem,
                             sampled=sampled, min_coherence=min_coherence)


def load_measured(
    paths: Sequence[str | Path], *, sampled: bool = False, min_coherence: float = 0.0
) -> tuple[MeasuredResponse, ...]:
    """Read several files; names are the file stems, made unique with a suffix if needed."""
    out: list[MeasuredResponse] = []
    seen: dict[str, int] = {}
    for p in paths:
        stem = Path(p).stem
        seen[stem] = seen.get(stem, 0) + 1
        name = stem if seen[stem] == 1 else f"{stem}#{seen[stem]}"
        out.append(measured_from_csv(p, name, sampled=sampled, min_coherence=min_coherence))
    return tuple(out)
