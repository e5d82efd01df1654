"""`dobtune record`: record a running controller into an MCAP file (command body, no argv).

    dobtune record --connect EP --rig-name R --out FILE.mcap [--duration S]
                   [--auth DIR --user NAME]

The recorder is `controller.client.recorder.Recorder`; this prints its result. Foxglove and
PlotJuggler open the file directly (`docs/foxglove_layout.json`). Ctrl-C ends the recording
cleanly. Exit codes: 0 recorded (samples lost are reported and recorded as events, not an
error), 2 bad input, 4 nothing received from the controller.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path
from typing import TextIO

__all__ = ["record_main"]

EXIT_OK, EXIT_BAD_INPUT, EXIT_NOTHING = 0, 2, 4


def record_main(args: argparse.Namespace, out: TextIO, stop: threading.Event | None = None) -> int:
    from controller.client.controller_client import ControllerUnavailable
    from controller.client.recorder import Recorder, RecordOptions

    try:
        recorder = Recorder(RecordOptions(
            connect=tuple(args.connect), out=Path(args.out), rig_name=args.rig_name,
            duration_s=args.duration, auth=args.auth, user=args.user or "",
            timeout_s=args.timeout_s))
    except ValueError as exc:
        out.write(f"error: {exc}\n")
        return EXIT_BAD_INPUT
    try:
        result = recorder.run(stop)
    except ControllerUnavailable as exc:
        out.write(f"error: {exc}\n")
        return EXIT_NOTHING
    out.write(result.summary() + "\n")
    return EXIT_OK


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", action="append", required=True, metavar="ENDPOINT")
    p.add_argument("--rig-name", default="demo")
    p.add_argument("--out", required=True, type=Path, metavar="FILE.mcap")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: until Ctrl-C)")
    p.add_argument("--auth", type=Path, default=None, metavar="DIR")
    p.add_argument("--user", default="")
    p.add_argument("--timeout-s", type=float, default=10.0,
                   help="give up when nothing arrives within this long")


def run(args: argparse.Namespace) -> int:
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        return record_main(args, sys.stdout, stop)
    finally:
        signal.signal(signal.SIGINT, previous)

