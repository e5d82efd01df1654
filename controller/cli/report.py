"""`dobtune report FILE.mcap [FILE2.mcap] --out REPORT.html [--csv FILE.csv]` (command body).

A self-contained HTML report of a recording (metrics, error against time and against
turntable angle, the error spectrum in orders of rotation, events), or of two compared with
the difference of their configurations; `--csv` writes the first recording's samples.
Exit codes: 0 written, 2 bad input (an unreadable file is named).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TextIO

__all__ = ["report_main"]


def report_main(files: list[Path], out: Path | None, csv: Path | None, stdout: TextIO) -> int:
    from controller.recording.mcap_io import read_recordings
    from controller.recording.report import html_report, metrics, to_csv

    if not 1 <= len(files) <= 2:
        stdout.write("error: give one recording, or two to compare\n")
        return 2
    if out is None and csv is None:
        stdout.write("error: nothing to write: give --out REPORT.html and/or --csv FILE.csv\n")
        return 2
    try:
        recs = [(f.name, r) for f, r in zip(files, read_recordings(files), strict=True)]
    except (OSError, ValueError) as exc:
        stdout.write(f"error: {exc}\n")
        return 2
    try:
        if out is not None:
            out.write_text(html_report(recs), encoding="utf-8")
        if csv is not None:
            to_csv(recs[0][1], csv)
    except OSError as exc:
        stdout.write(f"error: cannot write: {exc}\n")
        return 2
    for name, rec in recs:
        m = metrics(rec)
        stdout.write(f"{name}: {m.samples} samples, peak |error| {m.peak_error_deg:.4g} deg, "
                     f"RMSE {m.rmse_deg:.4g} deg, {m.gaps} lost\n")
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", type=Path, metavar="FILE.mcap")
    p.add_argument("--out", type=Path, default=None, metavar="REPORT.html")
    p.add_argument("--csv", type=Path, default=None, metavar="FILE.csv")


def run(args: argparse.Namespace) -> int:
    return report_main(args.files, args.out, args.csv, sys.stdout)

