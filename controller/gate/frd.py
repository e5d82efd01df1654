"""Measured plant responses for the stability check: CSV files -> `MeasuredResponse`.

The CSV codec is `controller.gate.frd_csv.read_frd_csv` (format ``freq_hz,mag_db,phase_deg
[,coherence]``; errors name the file and line); this module only turns its data into the
analysis's plant knowledge and builds model variants.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from controller.gate.frd_csv import read_frd_csv
from controller.gate.knowledge import MeasuredResponse

__all__ = ["load_measured", "measured_from_csv", "measured_from_model"]


def measured_from_csv(
    path: str | Path,
    name: str | None = None,
    *,
    sampled: bool = False,
    min_coherence: float = 0.0,
) -> MeasuredResponse:
    """Read one response file. `name` defaults to the file stem.

    Points whose coherence is below `min_coherence` are dropped (when the file has that
    column). `sampled` says the data are already the sampled u[k] -> w[k] response.
    Raises ValueError("<file>:<line>: ...") for malformed files.
    """
    data = read_frd_csv(path)
    keep = np.ones(data.freq_hz.shape, dtype=bool)
    if data.coherence is not None and min_coherence > 0.0:
        keep = data.coherence >= min_coherence
    if np.count_nonzero(keep) < 2:
        raise ValueError(f"{path}: fewer than 2 points left (coherence >= {min_coherence})")
    return MeasuredResponse(
        name=name if name is not None else Path(path).stem,
        freq_hz=data.freq_hz[keep],
        response=data.response[keep],
        sampled=sampled,
    )


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


def measured_from_model(
    name: str, freq_hz: ArrayLike, num: ArrayLike, den: ArrayLike
) -> MeasuredResponse:
    """A model variant (continuous num(s)/den(s), u -> load rate) sampled at `freq_hz`."""
    f = np.asarray(freq_hz, dtype=np.float64)
    s = 2j * np.pi * f
    h = np.polyval(np.asarray(num, dtype=np.float64), s) / np.polyval(
        np.asarray(den, dtype=np.float64), s
    )
    return MeasuredResponse(name=name, freq_hz=f, response=h)
