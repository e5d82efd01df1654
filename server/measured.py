"""Measured frequency responses uploaded from the browser (CSV as in the gate: freq_hz,
mag_db, phase_deg), parsed with the controller's own reader so both sides agree."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

__all__ = ["read_measured"]

MAX_BYTES = 5_000_000


def read_measured(name: str, content: bytes) -> Any:
    """Parse an uploaded CSV; ValueError with a readable message when it cannot be used."""
    if len(content) > MAX_BYTES:
        raise ValueError(f"file too large ({len(content)} bytes > {MAX_BYTES})")
    reader = _reader()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / (Path(name).name or "upload.csv")
        path.write_bytes(content)
        try:
            return reader(path)
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(str(exc)) from exc


def _reader() -> Any:
    from controller.gate.frd_csv import read_frd_csv

    return read_frd_csv
