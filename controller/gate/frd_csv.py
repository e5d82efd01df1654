"""Measured frequency-response data and its CSV format ``freq_hz,mag_db,phase_deg[,coherence]``.

Plain data and a codec between text and data (no file I/O: `controller.cli.frd_files` reads and
writes the files, the dashboard parses an upload). Errors name the source and line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from controller.core.arrays import ComplexArray, FloatArray
from controller.core.validate import finite_nonzero, frequency_grid

CSV_COLUMNS = ("freq_hz", "mag_db", "phase_deg", "coherence")

__all__ = [
    "CSV_COLUMNS",
    "FrdData",
    "FrdLike",
    "frd_csv_text",
    "mag_db_of",
    "parse_frd_csv",
    "phase_deg_of",
]


class FrdLike(Protocol):
    """Anything with a frequency grid and a complex response on it."""

    @property
    def freq_hz(self) -> FloatArray: ...

    @property
    def response(self) -> ComplexArray: ...


def mag_db_of(h: ComplexArray) -> FloatArray:
    """Magnitude in dB."""
    return 20.0 * np.log10(np.abs(h))


def phase_deg_of(h: ComplexArray) -> FloatArray:
    """Unwrapped phase in degrees."""
    return np.degrees(np.unwrap(np.angle(h)))


@dataclass(frozen=True, eq=False)
class FrdData:
    """A response read from a CSV file."""

    freq_hz: FloatArray
    mag_db: FloatArray
    phase_deg: FloatArray
    coherence: FloatArray | None
    """None when the file has no coherence column."""
    source: str = field(default="")
    """Where it came from (a file name)."""

    @property
    def response(self) -> ComplexArray:
        mag = 10.0 ** (self.mag_db / 20.0)
        return (mag * np.exp(1j * np.radians(self.phase_deg))).astype(np.complex128)


def frd_csv_text(
    freq_hz: ArrayLike,
    response: ArrayLike,
    coherence: ArrayLike | None = None,
) -> str:
    """The text ``freq_hz,mag_db,phase_deg[,coherence]`` with the phase unwrapped."""
    f = np.asarray(freq_hz, dtype=np.float64)
    h = np.asarray(response, dtype=np.complex128)
    if f.ndim != 1 or h.shape != f.shape:
        raise ValueError(f"freq_hz {f.shape} and response {h.shape} must be 1-D of equal size")
    frequency_grid(f, "freq_hz")
    finite_nonzero(h, "response")
    cols = [f, mag_db_of(h), phase_deg_of(h)]
    header = list(CSV_COLUMNS[:3])
    if coherence is not None:
        c = np.asarray(coherence, dtype=np.float64)
        if c.shape != f.shape or not np.all((c >= 0) & (c <= 1)):
            raise ValueError("coherence: must be in [0, 1], one value per frequency")
        cols.append(c)
        header.append("coherence")
    lines = [",".join(header)]
    lines += [",".join(f"{v:.10g}" for v in row) for row in zip(*cols, strict=True)]
    return "\n".join(lines) + "\n"


def parse_frd_csv(text: str, source: str) -> FrdData:
    """A response from the text of :func:`frd_csv_text` (or one written by hand, same columns).

    Blank lines and lines starting with ``#`` are skipped; extra columns are ignored. Any
    problem raises ``ValueError("<source>:<line>: <what>")``.
    """
    name = source
    lines = text.removeprefix("\ufeff").splitlines()

    def fail(line_no: int, msg: str) -> ValueError:
        return ValueError(f"{name}:{line_no}: {msg}")

    rows = [
        (i + 1, ln) for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if not rows:
        raise fail(1, "empty file, expected header freq_hz,mag_db,phase_deg[,coherence]")
    header_no, header_line = rows[0]
    header = [h.strip().lower() for h in header_line.split(",")]
    for col in header:
        if header.count(col) > 1:
            raise fail(header_no, f"duplicate column {col!r}")
    for col in CSV_COLUMNS[:3]:
        if col not in header:
            raise fail(header_no, f"missing column {col!r} (header: {header_line.strip()!r})")
    wanted = [c for c in CSV_COLUMNS if c in header]
    index = {c: header.index(c) for c in wanted}
    data: dict[str, list[float]] = {c: [] for c in wanted}
    if len(rows) < 2:
        raise fail(header_no, "no data rows after the header")
    for line_no, line in rows[1:]:
        fields = line.split(",")
        if len(fields) != len(header):
            raise fail(line_no, f"expected {len(header)} fields, got {len(fields)}")
        for col in wanted:
            raw = fields[index[col]].strip()
            try:
                v = float(raw)
            except ValueError:
                raise fail(line_no, f"{col}: not a number: {raw!r}") from None
            if not math.isfinite(v):
                raise fail(line_no, f"{col}: not finite: {raw!r}")
            if col == "freq_hz":
                if v <= 0:
                    raise fail(line_no, f"freq_hz: must be > 0 (got {v})")
                if data["freq_hz"] and v <= data["freq_hz"][-1]:
                    raise fail(
                        line_no,
                        f"freq_hz: not increasing ({v} after {data['freq_hz'][-1]})",
                    )
            if col == "coherence" and not 0.0 <= v <= 1.0:
                raise fail(line_no, f"coherence: must be in [0, 1] (got {v})")
            data[col].append(v)
    return FrdData(
        freq_hz=np.array(data["freq_hz"]),
        mag_db=np.array(data["mag_db"]),
        phase_deg=np.array(data["phase_deg"]),
        coherence=np.array(data["coherence"]) if "coherence" in data else None,
        source=name,
    )
