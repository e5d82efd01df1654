"""Measured frequency responses uploaded from the browser (CSV as in the gate: freq_hz,
mag_db, phase_deg), parsed with the controller's own codec so both sides agree."""

from __future__ import annotations

from pathlib import Path

from controller.gate.frd_csv import FrdData, parse_frd_csv

__all__ = ["read_measured"]

MAX_BYTES = 5_000_000


def read_measured(name: str, content: bytes) -> FrdData:
    """Parse an uploaded CSV; ValueError with a readable message (naming the file and line)
    when it cannot be used."""
    if len(content) > MAX_BYTES:
        raise ValueError(f"file too large ({len(content)} bytes > {MAX_BYTES})")
    source = Path(name).name or "upload.csv"
    try:
        text = content.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{source}: not UTF-8 text ({exc})") from exc
    return parse_frd_csv(text, source)
