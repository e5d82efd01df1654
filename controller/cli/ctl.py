"""`dobtune ctl`: every controller action from the command line (command body, no argv).

    dobtune ctl --connect EP --rig-name R [--auth DIR --user NAME] ACTION [ARGS] [--json]

Actions: `status`, `config`, `apply key=value ...` (`--expect-version N`, `--confirm`),
`start`, `stop`, `estop`, `reset`, `lease acquire|renew|release|takeover|show`,
`identify [key=value ...]` (IdentifySpec fields), `knowledge`, `twin` (the rig's twin the
controller built from its plant knowledge: its fit per position), `drift` (the watch's latest
drift state: `dobtune watch`), `wait-alarm` (wait up to `--wait-s`, 0 for ever, for the watch's
next drift alarm, or one raised since `--since EPOCH_S`: exit 0 one came (printed), 5 none
came), `prediction [--all] [--wait-s S]` (the watch's check of the twin's prediction after
the latest Apply: exit 0 held, 6 failed, 5 no verdict yet) and `rollback VERSION` (apply the
configuration the history keeps for VERSION, through the gate): see
`controller.cli.ctl_prediction`. An action that changes the rig
takes the operator lease for its duration when nobody holds it (and releases it after).
Values are JSON where they parse as JSON (`q_cutoff_hz=1.5`, `dob_on=false`), else strings.

Exit codes: 0 done (apply: applied), 1 refused or rejected (the reasons are printed),
3 the verdict is caution and `--confirm` was not given, 2 bad input, 4 the controller is not
reachable, the credentials reach nothing, or it speaks another protocol version (the error
names both).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, TextIO

import msgspec

from controller.core.verdict import kind_of

__all__ = ["ACTIONS", "ctl_main"]

EXIT_OK, EXIT_REFUSED, EXIT_BAD_INPUT, EXIT_CAUTION, EXIT_UNREACHABLE = 0, 1, 2, 3, 4
EXIT_NO_ALARM = 5
ACTIONS = (
    "status",
    "config",
    "apply",
    "start",
    "stop",
    "estop",
    "reset",
    "lease",
    "identify",
    "knowledge",
    "twin",
    "rigs",
    "drift",
    "wait-alarm",
    "prediction",
    "rollback",
)
CHANGES = ("apply", "start", "stop", "reset", "identify", "rollback")


class _BadInput(Exception):
    pass


def parse_assignments(items: list[str]) -> dict[str, Any]:
    """`key=value` pairs; a value is JSON if it parses as JSON, else a string."""
    out: dict[str, Any] = {}
    for item in items:
        key, eq, raw = item.partition("=")
        if not eq or not key:
            raise _BadInput(f"{item!r}: expected key=value")
        try:
            out[key] = json.loads(raw)
        except json.JSONDecodeError:
            out[key] = raw
    return out


def _emit(out: TextIO, as_json: bool, reply: Any, text: str) -> None:
    if as_json:
        # Strict JSON: a non-finite figure (a margin not computed: NaN) is null.
        out.write(msgspec.json.encode(reply).decode() + "\n")
    else:
        out.write(text + "\n")


def ctl_main(args: argparse.Namespace, out: TextIO) -> int:
    from controller import protocol as proto
    from controller.client import ClientOptions, ControllerClient, ControllerUnavailable

    try:
        if args.action not in ACTIONS:
            raise _BadInput(f"action {args.action!r}: one of {', '.join(ACTIONS)}")
        if args.action == "rigs":
            return _rigs(args, out)
        opts = ClientOptions(
            connect=tuple(args.connect),
            rig_name=args.rig_name,
            client_name="ctl",
            auth=args.auth,
            user=args.user or "",
            query_timeout_s=args.timeout_s,
            connect_timeout_s=args.timeout_s,
        )
        if args.action in ("drift", "wait-alarm"):
            return _drift(opts, args, out, proto)
        with ControllerClient(opts) as c:
            c.lease_token = args.lease
            return _run(c, args, out, proto)
    except _BadInput as exc:
        out.write(json.dumps({"error": str(exc)}) + "\n" if args.json else f"error: {exc}\n")
        return EXIT_BAD_INPUT
    except proto.ProtocolError as exc:  # a reply that cannot be read (another version...)
        text = f"the controller's reply cannot be read: {exc}"
        out.write(json.dumps({"error": text}) + "\n" if args.json else f"error: {text}\n")
        return EXIT_UNREACHABLE
    except ValueError as exc:
        out.write(f"error: {exc}\n")
        return EXIT_BAD_INPUT
    except ControllerUnavailable as exc:
        out.write(json.dumps({"error": str(exc)}) + "\n" if args.json else f"error: {exc}\n")
        return EXIT_UNREACHABLE


def _run(c: Any, args: argparse.Namespace, out: TextIO, proto: Any) -> int:
    action = args.action
    rest: list[str] = args.args
    # The first query also tells whether the credentials reach anything (a denied query gets
    # no reply: the client times out and says so).
    cfg = c.get_config()
    if action == "config":
        _emit(
            out,
            args.json,
            cfg,
            f"version {cfg.version}: {json.dumps(msgspec.to_builtins(cfg.config))}",
        )
        return EXIT_OK
    if action == "status":
        st = c.status or _wait_status(c)
        _emit(
            out,
            args.json,
            st,
            f"{st.rig}: {st.mode}, config v{st.config_version}, verdict {kind_of(st.verdict)}, "
            f"operator {st.operator or '-'}, knowledge {st.knowledge}, faults "
            f"{'; '.join(st.faults) or '-'}",
        )
        return EXIT_OK
    if action == "estop":
        # The put is what stops (any user, viewers included: no reply needed); the status
        # confirms it.
        before = (c.status or _wait_status(c)).estop_seq
        c.put_estop()
        st = _wait_status_until(c, lambda s: s.mode == "estop" and s.estop_seq != before)
        _emit(out, args.json, st, f"estop: mode {st.mode} from seq {st.estop_seq}")
        return EXIT_OK if st.mode == "estop" else EXIT_REFUSED
    if action == "lease":
        what = rest[0] if rest else "show"
        r = c.lease("status" if what == "show" else what, args.duration_s)
        _emit(
            out,
            args.json,
            r,
            f"lease {what}: {'ok' if r.ok else 'refused'}; holder {r.holder or '-'} "
            f"({r.expires_in_s:.0f} s left)"
            + (f"; token {r.token}" if r.token else "")
            + (f": {r.message}" if r.message else ""),
        )
        return EXIT_OK if r.ok else EXIT_REFUSED
    if action == "twin":
        from controller.twin.model import decode

        r = c.knowledge()
        if not r.twin:
            _emit(out, args.json, {"twin": None, "note": r.twin_note}, r.twin_note)
            return EXIT_OK
        twin = decode(r.twin)
        lines = [twin.describe(), *(f"  {p.describe()}" for p in twin.positions)]
        if twin.nonlinear is not None:
            lines += [f"  {h}" for h in twin.nonlinear.how]
        lines += [f"  note: {n}" for n in twin.notes]
        _emit(out, args.json, twin, "\n".join(lines))
        return EXIT_OK
    if action == "prediction":
        from controller.cli.ctl_prediction import prediction

        return prediction(c, args, out, (c.status or _wait_status(c)).config_version)
    if action == "knowledge":
        r = c.knowledge()
        _emit(
            out,
            args.json,
            r.record,
            f"plant knowledge v{r.record.version} ({r.record.source}): "
            f"{len(r.record.measured)} measured response(s)",
        )
        return EXIT_OK
    took = False
    if action in CHANGES:
        held = c.lease("status")
        if not held.holder:
            got = c.lease("acquire", args.duration_s)
            took = got.ok
    try:
        return _change(c, action, rest, cfg, args, out, proto)
    finally:
        if took:
            c.lease("release")


def _change(
    c: Any,
    action: str,
    rest: list[str],
    cfg: Any,
    args: argparse.Namespace,
    out: TextIO,
    proto: Any,
) -> int:
    from controller.core.config import config_from_builtins, config_to_builtins
    from controller.core.errors import ConfigError

    if action in ("apply", "rollback"):
        if action == "rollback":
            from controller.cli.ctl_prediction import rollback_candidate

            try:
                _, cand = rollback_candidate(c, rest)
            except ValueError as exc:
                raise _BadInput(str(exc)) from exc
        else:
            changes = parse_assignments(rest)
            if not changes:
                raise _BadInput("apply: give key=value pairs (LoopConfig fields)")
            try:
                cand = config_from_builtins({**config_to_builtins(cfg.config), **changes})
            except ConfigError as exc:
                raise _BadInput(str(exc)) from exc
        expect = args.expect_version
        r = c.apply(cand, confirm=args.confirm, expect_version=expect)
        reasons = "".join(f"\n  - {x}" for x in r.reasons)
        _emit(
            out,
            args.json,
            r,
            f"{'applied' if r.accepted else 'not applied'}: version "
            f"{r.version}, verdict {kind_of(r.verdict)}{reasons}",
        )
        if r.accepted:
            return EXIT_OK
        return EXIT_CAUTION if r.field == "confirm" else EXIT_REFUSED
    if action == "identify":
        from controller.ident.spec import IdentifySpec

        try:
            spec = msgspec.convert(parse_assignments(rest), IdentifySpec)
        except msgspec.ValidationError as exc:
            raise _BadInput(f"identify: {exc}") from exc
        body: Any = proto.IdentifyStart(spec=spec)
    elif action == "reset":
        # The reset acknowledges the latest e-stop this status shows (a newer one refuses it).
        st = c.status or _wait_status(c)
        body = proto.ResetFault(estop_seq=st.estop_seq)
    else:
        body = {"start": proto.Start(), "stop": proto.Stop()}[action]
    r = c.command(body)
    _emit(
        out,
        args.json,
        r,
        f"{action}: {'ok' if r.ok else 'refused'} (mode {r.mode})"
        f"{': ' + r.message if r.message else ''}",
    )
    return EXIT_OK if r.ok else EXIT_REFUSED


def _rigs(args: argparse.Namespace, out: TextIO) -> int:
    """The rigs reachable through the endpoints (their liveliness tokens), with the state each
    publishes: mode, configuration version, error RMS over the listening time (the fleet
    watcher's decimated trace), faults, lease."""
    import math
    import time

    from controller.client import ClientOptions, open_client_session
    from controller.client.fleet import FleetMonitor

    def finite(v: float | None) -> float | None:
        return v if v is not None and math.isfinite(v) else None

    session = open_client_session(ClientOptions(
        connect=tuple(args.connect), auth=args.auth, user=args.user or "",
        connect_timeout_s=args.timeout_s))
    with session, FleetMonitor(session) as fleet:
        time.sleep(args.listen_s)  # the listening time the command was given
        rows: list[dict[str, Any]] = [{
            "rig": r.rig, "mode": r.mode, "plant": r.plant,
            "config_version": r.config_version, "error_rms_deg": finite(r.error_rms_deg),
            "faults": list(r.faults), "operator": r.operator, "unread": r.unread,
        } for r in fleet.rows() if r.alive]
    if args.json:
        out.write(json.dumps(rows) + "\n")
    else:
        for r in rows:
            err = "-" if r["error_rms_deg"] is None else f"{r['error_rms_deg']:.4f} deg"
            out.write(f"{r['rig']}: {r['mode'] or '?'} ({r['plant'] or '?'}), config "
                      f"v{r['config_version']}, error RMS {err}, lease {r['operator'] or '-'}, "
                      f"faults {'; '.join(r['faults']) or '-'}"
                      + (f", status not read: {r['unread']}" if r["unread"] else "") + "\n")
        if not rows:
            out.write("no rig reachable\n")
    return EXIT_OK


def _wait_status_until(c: Any, pred: Any, timeout_s: float = 3.0) -> Any:
    """The first status that satisfies `pred` (or the latest when the time is up)."""
    import time

    deadline = time.monotonic() + timeout_s
    st = _wait_status(c)
    while not pred(st) and time.monotonic() < deadline:
        time.sleep(0.02)
        st = c.status
    return st


def _drift(opts: Any, args: argparse.Namespace, out: TextIO, proto: Any) -> int:
    """`drift`: the watch's latest state; `wait-alarm`: its next alarm (or none in time)."""
    import dataclasses
    import queue

    from controller.client import ControllerClient, ControllerUnavailable
    from controller.process.watch import describe_state

    opts = dataclasses.replace(opts, subscribe=False)
    with ControllerClient(opts) as c:
        if args.action == "drift":
            for reply in c.session.get(proto.key_drift(args.rig_name), timeout=args.timeout_s):
                if reply.ok is not None:
                    st = proto.decode(reply.ok.payload.to_bytes(), proto.DriftState)
                    _emit(out, args.json, st, describe_state(st))
                    return EXIT_OK
            raise ControllerUnavailable(
                f"no drift state for rig {args.rig_name!r}: is `dobtune watch` running and past "
                "its first window?")
        got: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        sub = c.session.declare_subscriber(proto.key_drift_alarm(args.rig_name),
                                           lambda s: got.put(s.payload.to_bytes()))
        if args.since is not None:
            # Subscribed first, then asked: an alarm since then is in one or the other.
            import zenoh

            # One reply per alarm on the same key: NONE keeps them all (the default
            # consolidation kept only the newest, so an alarm followed by its clearing was lost).
            for reply in c.session.get(proto.key_drift_alarm(args.rig_name),
                                       timeout=args.timeout_s,
                                       consolidation=zenoh.ConsolidationMode.NONE):
                if reply.ok is not None:
                    got.put(reply.ok.payload.to_bytes())
        try:
            while True:
                try:
                    data = got.get(timeout=args.wait_s if args.wait_s > 0 else None)
                except queue.Empty:
                    text = f"no drift alarm within {args.wait_s:g} s"
                    out.write(json.dumps({"alarm": None, "text": text}) + "\n" if args.json
                              else text + "\n")
                    return EXIT_NO_ALARM
                try:
                    alarm = proto.decode(data, proto.DriftAlarm)
                except proto.ProtocolError:
                    continue  # not an alarm this version reads: wait on
                if args.since is not None and alarm.epoch_s < args.since:
                    continue
                text = (f"{'cleared' if alarm.cleared else 'ALARM'} {alarm.part}: {alarm.text}"
                        + (f"\n  {alarm.action}" if alarm.action else ""))
                _emit(out, args.json, alarm, text)
                return EXIT_OK
        finally:
            sub.undeclare()


def _wait_status(c: Any, timeout_s: float = 3.0) -> Any:
    import time

    from controller.client import ControllerUnavailable

    deadline = time.monotonic() + timeout_s
    while c.status is None:
        mismatch = c.counters.version_mismatch
        if mismatch:  # it will never be read: say why at once
            raise ControllerUnavailable(f"the controller's status cannot be read: {mismatch}")
        if time.monotonic() > deadline:
            raise ControllerUnavailable(f"no status within {timeout_s:g} s")
        time.sleep(0.02)
    return c.status


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", action="append", required=True, metavar="ENDPOINT")
    p.add_argument("--rig-name", default="demo")
    p.add_argument(
        "--auth",
        type=Path,
        default=None,
        metavar="DIR",
        help="credentials: an auth directory or a password file",
    )
    p.add_argument("--user", default=None, help="the user to log in as (with --auth)")
    p.add_argument("--json", action="store_true")
    p.add_argument(
        "--expect-version",
        type=int,
        default=None,
        help="apply: only if this is still the active version",
    )
    p.add_argument(
        "--confirm", action="store_true", help="apply: apply a candidate whose verdict is caution"
    )
    p.add_argument("--duration-s", type=float, default=60.0, help="lease duration")
    p.add_argument("--lease", default="", metavar="TOKEN",
                   help="the lease token `lease acquire` printed (to act under a held lease)")
    p.add_argument("--timeout-s", type=float, default=5.0, help="reply / connection timeout")
    p.add_argument("--listen-s", type=float, default=1.0,
                   help="rigs: how long to listen to the rigs' status and state")
    p.add_argument("--wait-s", type=float, default=0.0,
                   help="wait-alarm: give up after this long (exit 5; default 0: wait for "
                   "ever); prediction: wait up to this long for the verdict (default 0: none)")
    p.add_argument("--all", action="store_true",
                   help="prediction: every version's check the watch kept")
    p.add_argument("--since", type=float, default=None, metavar="EPOCH_S",
                   help="wait-alarm: an alarm the watch raised at or after this UNIX time "
                   "counts too (none missed between a change and the wait)")
    p.add_argument("action", help=" | ".join(ACTIONS))
    p.add_argument("args", nargs="*",
                   help="key=value pairs (apply, identify), a lease action or a version "
                   "(rollback)")


def run(args: argparse.Namespace) -> int:
    return ctl_main(args, sys.stdout)

