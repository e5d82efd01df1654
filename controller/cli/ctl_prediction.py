"""`dobtune ctl prediction` and `dobtune ctl rollback N` (command bodies): the watch's check
of the twin's prediction after each Apply, and going back to a version whose prediction held.

    dobtune ctl ... prediction [--all] [--wait-s S] [--json]
    dobtune ctl ... rollback VERSION [--confirm]

`prediction` shows the check of the running version (`--all`: every version's the watch
kept); with `--wait-s` it waits up to S s for that check's verdict (default 0: no wait). Exit 0 the
prediction held, 6 it failed (the check says what that means and, when it failed badly, which
version to roll back to), 5 no verdict in time (or the check could not be made), 4 no watch
answers.

`rollback VERSION` applies the configuration the history keeps for VERSION, through the gate
like any Apply (a caution needs `--confirm`)."""

from __future__ import annotations

import argparse
import json
import queue
import time
from typing import Any, TextIO

import msgspec

from controller import protocol as proto

__all__ = ["EXIT_FAILED", "prediction", "rollback_candidate"]

EXIT_OK, EXIT_NO_VERDICT, EXIT_FAILED = 0, 5, 6


def _emit(out: TextIO, as_json: bool, obj: Any, text: str) -> None:
    out.write(json.dumps(msgspec.to_builtins(obj)) + "\n" if as_json else text + "\n")


def prediction(c: Any, args: argparse.Namespace, out: TextIO, version: int) -> int:
    """See the module docstring. `c`: a connected ControllerClient; `version`: the running
    configuration's (from its status)."""
    from controller.client import ControllerUnavailable
    from controller.process.prediction_check import describe_check

    rig = args.rig_name
    got: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    sub = c.session.declare_subscriber(proto.key_prediction(rig),
                                       lambda s: got.put(s.payload.to_bytes()))
    try:
        checks = {k.config_version: k for k in c.prediction_checks(args.timeout_s)}
        if not checks:
            raise ControllerUnavailable(
                f"no prediction check for rig {rig!r}: is `dobtune watch` running (the "
                "controller starts it unless --no-watch) and has the loop run since?")
        if args.all:
            ordered = [checks[v] for v in sorted(checks)]
            if args.json:
                out.write(json.dumps([msgspec.to_builtins(k) for k in ordered]) + "\n")
            else:
                out.write("\n".join(describe_check(k) for k in ordered) + "\n")
            return EXIT_OK
        deadline = time.monotonic() + max(0.0, args.wait_s)
        while True:
            k = checks.get(version)
            left = deadline - time.monotonic()
            if (k is not None and k.state != "predicted") or left <= 0:
                break
            try:
                data = got.get(timeout=left)
            except queue.Empty:
                break
            try:
                came = proto.decode(data, proto.PredictionCheck)
            except proto.ProtocolError:
                continue  # not a check this version reads: wait on
            checks[came.config_version] = came
        k = checks.get(version)
        if k is None:
            text = f"no prediction check for v{version} yet"
            _emit(out, args.json, {"check": None, "text": text}, text)
            return EXIT_NO_VERDICT
        _emit(out, args.json, k, describe_check(k))
        if k.state == "held":
            return EXIT_OK
        return EXIT_FAILED if k.state.startswith("failed") else EXIT_NO_VERDICT
    finally:
        sub.undeclare()


def rollback_candidate(c: Any, rest: list[str]) -> tuple[int, Any]:
    """(version, its configuration) from the history, for `ctl rollback VERSION`; ValueError
    naming what is wrong."""
    if len(rest) != 1 or not rest[0].isdigit():
        raise ValueError("rollback: give the version to go back to (`dobtune ctl rollback 3`)")
    want = int(rest[0])
    h = c.history(1000)
    if not h.ok:
        raise ValueError(f"rollback: the history was refused: {h.message}")
    for e in h.entries:
        if e.version == want:
            return want, e.config
    have = ", ".join(str(e.version) for e in h.entries[-10:])
    raise ValueError(f"rollback: version {want} is not in the history (newest: {have})")
