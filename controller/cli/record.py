"""`dobtune record`: record a running controller into an MCAP file (command body, no argv).

    dobtune record --connect EP --rig-name R --out FILE.mcap [--duration S]
                   [--auth DIR --user NAME]

One message per loop tick on `/state`, every Status on `/status`, each configuration version on
`/config`, and events (lost samples, mode changes, watchdog trips, identification runs with
what they executed, for `dobtune identify --from`) on `/events`; Foxglove and PlotJuggler open
the file directly (`docs/foxglove_layout.json`). Ctrl-C ends the recording cleanly. Exit
codes: 0 recorded (samples lost are reported and recorded as events, not an error), 2 bad
input, 4 nothing received from the controller.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, TextIO

from controller.cli import Command

__all__ = ["identify_event", "record_main"]

EXIT_OK, EXIT_BAD_INPUT, EXIT_NOTHING = 0, 2, 4


def _session(args: argparse.Namespace) -> Any:
    import zenoh

    if args.auth is not None:
        from controller.auth import client_config

        return zenoh.open(client_config(args.auth, args.user, args.connect,
                                        fail_after_s=args.timeout_s))
    from controller.zenoh_session import open_session

    return open_session(listen=(), connect=args.connect)


#: How often the recorder asks the controller for its identification status.
IDENTIFY_POLL_S = 0.5


class _IdentifyWatch:
    """Records an `identify` event whenever the controller's identification run changes state
    (run id, state): the run's spec, configuration, start position and first tick
    (`IdentifyRun`), which `dobtune identify --from` needs to analyse the run again."""

    def __init__(self) -> None:
        self.last: tuple[int, str] | None = None
        self.failed = False

    def poll(self, session: Any, key: str, rec: Any) -> None:
        from controller import protocol as proto

        try:
            replies = list(session.get(key, timeout=1.0))
            ok = [r.ok for r in replies if r.ok is not None]
            if not ok:
                raise ValueError("no reply")
            st = proto.decode(ok[0].payload.to_bytes(), proto.IdentifyStatus)
        except Exception as exc:  # said once in the recording, the recording goes on
            if not self.failed:
                self.failed = True
                rec.event("note", f"identification status unavailable: {exc}")
            return
        now = (st.run_id, st.state)
        if st.run is None or now == self.last:
            return
        self.last = now
        identify_event(rec, st)


def identify_event(rec: Any, st: Any) -> None:
    """Record the `identify` event of an IdentifyStatus `st` (which carries `run`) into the
    Recorder `rec`: what `dobtune identify --from` reads."""
    import msgspec

    rec.event(
        "identify",
        f"identification {st.run_id}: {st.state}"
        + (f" ({st.abort_reason})" if st.abort_reason else ""),
        run_id=st.run_id,
        state=st.state,
        abort_reason=st.abort_reason,
        run=msgspec.to_builtins(st.run),
    )


def record_main(args: argparse.Namespace, out: TextIO, stop: threading.Event | None = None) -> int:
    import zenoh

    from controller import protocol as proto
    from controller.recording.mcap_io import Recorder

    stop = stop if stop is not None else threading.Event()
    if args.duration is not None and not (0.0 < args.duration <= 86_400.0):
        out.write(f"error: --duration: {args.duration} not in (0, 86400] s\n")
        return EXIT_BAD_INPUT
    try:
        proto.check_rig_name(args.rig_name)
    except ValueError as exc:
        out.write(f"error: --rig-name: {exc}\n")
        return EXIT_BAD_INPUT
    out_path = Path(args.out)
    if not out_path.parent.is_dir():
        out.write(f"error: --out: directory {out_path.parent} does not exist\n")
        return EXIT_BAD_INPUT
    try:
        session = _session(args)
    except Exception as exc:  # zenoh.ZError, AuthError: said plainly
        out.write(f"error: no connection to {', '.join(args.connect)}: {exc}\n")
        return EXIT_NOTHING
    t0 = time.monotonic()
    last_status = ""
    bad = 0
    identify_key = proto.key_identify(args.rig_name)
    if args.auth is not None:
        identify_key = proto.user_key(identify_key, args.user)
    identify = _IdentifyWatch()
    next_poll = t0
    with session, Recorder(out_path, rig=args.rig_name) as rec:
        state = session.declare_subscriber(proto.key_state(args.rig_name),
                                           zenoh.handlers.FifoChannel(16384))
        status = session.declare_subscriber(proto.key_status(args.rig_name),
                                            zenoh.handlers.FifoChannel(256))
        try:
            while not stop.is_set():
                if args.duration is not None and time.monotonic() - t0 >= args.duration:
                    break
                if rec.samples == 0 and time.monotonic() - t0 > args.timeout_s:
                    break
                got = False
                for sample in iter(state.try_recv, None):
                    got = True
                    try:
                        rec.state(proto.decode(sample.payload.to_bytes(), proto.StateBatch))
                    except proto.ProtocolError as exc:
                        bad += 1
                        rec.event("note", f"undecodable state message: {exc}")
                for sample in iter(status.try_recv, None):
                    got = True
                    try:
                        st = proto.decode(sample.payload.to_bytes(), proto.Status)
                    except proto.ProtocolError as exc:
                        bad += 1
                        rec.event("note", f"undecodable status message: {exc}")
                        continue
                    rec.status(st, time.time())
                    text = f"{st.mode}|{st.watchdog}|{';'.join(st.faults)}"
                    if text != last_status and last_status:
                        rec.event("status", f"mode {st.mode}; faults: "
                                  f"{'; '.join(st.faults) or '-'}; {st.watchdog}", time.time())
                    last_status = text
                if time.monotonic() >= next_poll:
                    next_poll = time.monotonic() + IDENTIFY_POLL_S
                    identify.poll(session, identify_key, rec)
                if not got:
                    time.sleep(0.01)
            identify.poll(session, identify_key, rec)  # a run that ended in the last interval
        finally:
            state.undeclare()
            status.undeclare()
        n, gaps = rec.samples, rec.gaps
    if n == 0:
        out.write(f"error: no state from rig {args.rig_name!r} on {', '.join(args.connect)} "
                  f"within {args.timeout_s:g} s (wrong endpoint, rig name or credentials)\n")
        return EXIT_NOTHING
    out.write(f"recorded {n} samples ({gaps} lost{', ' + str(bad) + ' undecodable' if bad else ''})"
              f" in {time.monotonic() - t0:.1f} s to {out_path} "
              f"({out_path.stat().st_size / 1e6:.2f} MB)\n")
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


COMMAND = Command("record", "record a running controller into an MCAP file", add_arguments, run)
