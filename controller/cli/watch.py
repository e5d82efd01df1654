"""`dobtune watch`: the twin beside a running controller (command body).

    dobtune watch --connect EP --rig-name R [--window-s 10] [--trend-dir DIR]
                  [--prediction-window-s 10] [--prediction-log FILE]
                  [--disturbance NAME ...] [--auth DIR --user NAME] [--priority low|idle]

Reads the loop's state stream (nothing added to the tick), fits the twin's parts to each
window, publishes the drift state and alarms (`dobtune ctl drift`, `dobtune ctl wait-alarm`),
and keeps the rig's trend in DIR (MCAP, one file per hour). After each Apply it checks the
twin's prediction against what the rig then did (`dobtune ctl prediction`). Runs niced
(`--priority idle`: SCHED_IDLE): the controller's process wins the CPU. Exit codes: 0
stopped (Ctrl-C / SIGTERM), 2 bad input, 4 the controller is not reachable.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from controller.cli.common import add_parent_pid, end_with_parent

__all__: list[str] = []


def run(args: argparse.Namespace) -> int:
    from controller.client import ClientOptions, ControllerUnavailable
    from controller.logs import setup_logging
    from controller.process.watch import WatchOptions, run_watch

    def say(text: str) -> None:
        print(f"dobtune watch: {text}", file=sys.stderr, flush=True)

    end_with_parent(args.parent_pid, say)
    setup_logging(args.log_level, args.rig_name)
    if not (1.5 <= args.window_s <= 600.0):
        say(f"--window-s: {args.window_s!r} out of range [1.5, 600]")
        return 2
    if not (0.0 <= args.resonance_hz <= 200.0) or not (0.0 < args.resonance_damping <= 1.0):
        say(f"--resonance-hz/--resonance-damping: {args.resonance_hz!r}/"
            f"{args.resonance_damping!r} out of range [0, 200] Hz / (0, 1]")
        return 2
    if not (1.0 <= args.prediction_window_s <= 600.0):
        say(f"--prediction-window-s: {args.prediction_window_s!r} out of range [1, 600]")
        return 2
    prediction_log = args.prediction_log or (
        args.trend_dir / f"{args.rig_name}-predictions.jsonl" if args.trend_dir else None)
    _yield_cpu(args.priority, say)
    opts = WatchOptions(
        client=ClientOptions(connect=tuple(args.connect), rig_name=args.rig_name,
                             client_name="watch", auth=args.auth, user=args.user or "",
                             query_timeout_s=args.timeout_s, connect_timeout_s=args.timeout_s,
                             mode="client"),
        window_s=args.window_s,
        disturbances=(tuple(d for d in args.disturbance if d != "none") if args.disturbance
                      else ("article-rig",)),
        resonance=(args.resonance_hz, args.resonance_damping),
        trend_dir=args.trend_dir, prediction_window_s=args.prediction_window_s,
        prediction_log=prediction_log)
    stop = threading.Event()
    def on_signal(*_: object) -> None:
        # Stop now, also in the middle of a window's fit (seconds on a loaded machine, and
        # whoever stopped the watch waits for it): the exception unwinds run_watch, whose
        # finally closes the trend file and undeclares what it declared.
        stop.set()
        raise _Stopped

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        say(f"watching rig {args.rig_name!r}, windows of {args.window_s:g} s")
        return run_watch(opts, stop)
    except _Stopped:
        say("stopped")
        return 0
    except ControllerUnavailable as exc:
        say(str(exc))
        return 4
    except ValueError as exc:
        say(str(exc))
        return 2
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _yield_cpu(priority: str, say: Callable[[str], None]) -> None:
    """The controller's process wins the CPU: `low` nice 10 (the watch still gets a share of
    a saturated machine), `idle` SCHED_IDLE (only what nothing else wants)."""
    if priority == "idle":
        from controller.process.worker_start import idle_priority

        try:
            say(f"priority: {idle_priority()}")
            return
        except OSError as exc:
            say(f"priority: no SCHED_IDLE ({exc}); nice 10 instead")
    try:
        os.nice(10)
    except OSError as exc:
        say(f"runs at the controller's priority (os.nice: {exc})")


class _Stopped(BaseException):
    """SIGINT or SIGTERM: the watch ends (exit 0)."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", action="append", required=True, metavar="ENDPOINT")
    p.add_argument("--rig-name", default="demo")
    p.add_argument("--auth", type=Path, default=None, metavar="DIR")
    p.add_argument("--user", default=None)
    p.add_argument("--window-s", type=float, default=10.0,
                   help="seconds of samples per fit (default: 10)")
    p.add_argument("--prediction-window-s", type=float, default=10.0,
                   help="after each Apply: the rig's figures over at least this long (whole "
                   "periods of a sine; default 10), against the twin's prediction")
    p.add_argument("--prediction-log", type=Path, default=None, metavar="FILE",
                   help="every version's prediction check, one JSON line each (default: "
                   "<trend-dir>/<rig>-predictions.jsonl with --trend-dir, else kept in memory)")
    p.add_argument("--trend-dir", type=Path, default=None, metavar="DIR",
                   help="keep the rig's trend here (MCAP, one file per hour)")
    p.add_argument("--resonance-hz", type=float, default=0.0, metavar="HZ",
                   help="without a twin: the simulated rig's extra mode (as added by a "
                   "sim_fault), whose frequency and damping are then estimated too (default 0: "
                   "none)")
    p.add_argument("--resonance-damping", type=float, default=0.02, metavar="ZETA",
                   help="that mode's damping ratio (default 0.02, the sim_fault's)")
    p.add_argument("--disturbance", action="append", default=[], metavar="NAME",
                   help="without a twin: the simulated rig the controller runs (as its "
                   "--disturbance; default article-rig; 'none': the plain rig)")
    p.add_argument("--priority", choices=("low", "idle"), default="low",
                   help="low: nice 10 (default; still a share of a saturated machine); idle: "
                   "SCHED_IDLE, every thread (Linux): runs only on a core nothing else wants")
    p.add_argument("--timeout-s", type=float, default=30.0,
                   help="a query's reply timeout (the controller may be busy; default: 30)")
    add_parent_pid(p, "watch")
