"""`dobtune identify`: measure the plant on the loop, fit Mn Pn, recommend Q cut-offs (command
body, no argv).

Writes into ``out_dir``: ``pos<k>_<deg>deg.csv`` per position (``freq_hz,mag_db,phase_deg,
coherence``, the continuous-equivalent response u -> w, readable by ``dobtune check --frd``),
``raw_pos<k>.npz`` (every tick: t_s, u, w, x, pos, offset, phase, exc_index) and
``summary.json``. With ``--connect`` the run executes inside the controller's loop (see
`controller.process.node`); the same files are written except the raw records. Exit codes: 0 done,
1 aborted by a limit (partial data written, marked incomplete), 2 bad input (the message
names the flag or field).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TextIO

import msgspec
import numpy as np

from controller.cli.frd_files import write_frd_csv
from controller.core.config import LoopConfig, config_from_builtins, config_to_builtins
from controller.core.errors import ConfigError
from controller.ident.engine import RigLike, run_identification
from controller.ident.report import (
    FITTED_CONFIG_NAME,
    csv_name,
    nominal_from_summary,
    raw_name,
    report_text,
    summary_json,
)
from controller.ident.result import IdentifyAborted, IdentifyResult, position_name
from controller.ident.spec import IDENTIFY_FIELDS, IdentifySpec

__all__ = ["EXIT_ABORTED", "EXIT_BAD_INPUT", "EXIT_OK", "identify_main"]

EXIT_OK, EXIT_ABORTED, EXIT_BAD_INPUT = 0, 1, 2

#: The IdentifySpec fields on the command line (their `Param.flag`), in order.
CLI_FIELDS = tuple(f for f in IDENTIFY_FIELDS if f.param.flag)
#: IdentifySpec field -> command-line flag, for error messages.
_FLAGS = {f.name: f.param.flag for f in CLI_FIELDS}


def _write_json(path: Path, obj: Any) -> None:
    path.write_text(json.dumps(obj, indent=2, allow_nan=False) + "\n", encoding="utf-8")


def _write(result: IdentifyResult, out_dir: Path, wall_s: float) -> dict[str, Any]:
    """Write the CSVs, raw records, fitted configuration and summary.json; the summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files: dict[int, tuple[str | None, str]] = {}
    for p in result.positions:
        csv: str | None = None
        est = p.estimate
        if est is not None:
            csv = csv_name(p)
            write_frd_csv(out_dir / csv, est.freq_hz, est.response, est.coherence)
        raw = raw_name(p)
        np.savez_compressed(
            out_dir / raw,
            center_deg=np.float64(p.center_deg),
            complete=np.bool_(p.complete),
            **p.raw.as_arrays(),  # type: ignore[arg-type]
        )
        files[p.index] = (csv, raw)
    fitted = _write_config(result.fitted_config, out_dir)
    summary = summary_json(result, files, wall_s, fitted)
    summary["twin"] = _write_knowledge_and_twin(result, out_dir)
    _write_json(out_dir / "summary.json", summary)
    return summary


def _write_knowledge_and_twin(result: IdentifyResult, out_dir: Path) -> dict[str, Any] | None:
    """knowledge.json (what "Use fit" adopts: the measured responses with their uncertainty,
    the fitted model, the commissioning bound; `dobtune autotune --knowledge` reads it) and
    twin.json (the rig's twin built from it); the twin's summary (None: nothing measured)."""
    from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord, PlantKnowledge
    from controller.twin.fit import twin_from_knowledge
    from controller.twin.model import encode

    measured = result.measured_responses()
    if not measured:
        return None
    knowledge = PlantKnowledge(measured=measured, bound=COMMISSIONING_BOUND,
                               model=result.nominal or result.config.nominal, version=1,
                               source="identified")
    (out_dir / KNOWLEDGE_NAME).write_bytes(msgspec.json.encode(KnowledgeRecord.of(knowledge)))
    twin = twin_from_knowledge(knowledge, rate_hz=result.config.rate_hz)
    (out_dir / TWIN_NAME).write_bytes(encode(twin))
    return {
        "file": TWIN_NAME,
        "knowledge_file": KNOWLEDGE_NAME,
        "fitted": dict(twin.fitted),
        "positions": [msgspec.to_builtins(p) for p in twin.positions],
        "nonlinear": list(twin.nonlinear.how) if twin.nonlinear is not None else [],
    }


KNOWLEDGE_NAME = "knowledge.json"
TWIN_NAME = "twin.json"


def _write_config(cfg: LoopConfig | None, out_dir: Path) -> str | None:
    """The run's LoopConfig with the fitted nominal, for `dobtune check <it> --frd ...`."""
    if cfg is None:
        return None
    _write_json(out_dir / FITTED_CONFIG_NAME, config_to_builtins(cfg))
    return FITTED_CONFIG_NAME


def _write_remote(status: Any, out_dir: Path, wall_s: float) -> dict[str, Any]:
    """The files of a run on the controller (no raw records: those stay in the state stream)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = json.loads(status.summary_json) if status.summary_json else {}
    if not summary:
        raise OSError(f"the controller sent no summary ({status.text})")
    summary["wall_s"] = wall_s
    by_index = {p["index"]: p for p in summary["positions"]}
    for p in status.positions:
        if p.freq_hz:
            name = f"{position_name(p.index, p.center_deg)}.csv"
            resp = 10.0 ** (np.asarray(p.mag_db) / 20.0) * np.exp(1j * np.radians(p.phase_deg))
            write_frd_csv(out_dir / name, p.freq_hz, resp, p.coherence)
            by_index[p.index]["csv"] = name
        by_index[p.index]["raw"] = None
    if summary.get("nominal") is not None:
        cfg = config_from_builtins(summary["config"])
        nominal = nominal_from_summary(summary["nominal"])
        summary["fitted_config"] = _write_config(cfg.with_(nominal=nominal), out_dir)
    _write_json(out_dir / "summary.json", summary)
    return summary


class _Progress:
    """A one-line terminal progress indicator (carriage return, at most every 1 %)."""

    def __init__(self, err: TextIO) -> None:
        self.err = err
        self.last = -1
        self.text = ""

    def __call__(self, fraction: float, text: str) -> None:
        pct = int(fraction * 100)
        if pct == self.last and text == self.text:
            return
        self.last, self.text = pct, text
        self.err.write(f"\r[{pct:3d}%] {text[:70]:<70}")
        self.err.flush()

    def done(self) -> None:
        if self.last >= 0:
            self.err.write("\n")
            self.err.flush()


def _bad(msg: str, as_json: bool, out: TextIO, err: TextIO) -> int:
    if as_json:
        out.write(json.dumps({"error": msg}) + "\n")
    else:
        err.write(f"error: {msg}\n")
    return EXIT_BAD_INPUT


def _flagged(exc: ConfigError) -> str:
    """The error naming the command-line flag of the field (or the field)."""
    return f"{_FLAGS.get(exc.field, exc.field)}: {exc}"


def _connection_error(plant: str | None, connect: str | None, rig_name: str | None) -> str | None:
    """Why the --plant / --connect / --rig-name combination cannot run, or None."""
    if connect is None:
        if plant not in (None, "sim"):
            return f"--plant: only 'sim' is supported here (got {plant!r})"
        return None
    if plant is not None:
        return "--plant and --connect are exclusive"
    if not rig_name:
        return "--connect needs --rig-name"
    from controller import protocol as proto
    from controller.client.session import check_endpoint

    try:
        check_endpoint(connect)
        proto.check_rig_name(rig_name)
    except ValueError as exc:
        return f"--connect/--rig-name: {exc}"
    return None


def _from_error(plant: str | None, connect: str | None, spec: Mapping[str, Any]) -> str | None:
    """Why --from cannot run with these options (the spec comes from the recording), or None."""
    if plant is not None or connect is not None:
        return "--from is exclusive with --plant and --connect"
    given = [f.param.flag for f in CLI_FIELDS if f.name in spec and spec[f.name] != f.default]
    if given:
        return f"--from: the spec comes from the recording; remove {', '.join(given)}"
    return None


def identify_main(
    plant: str | None,
    connect: str | None,
    rig_name: str | None,
    spec_fields: Mapping[str, Any],
    out_dir: Path,
    as_json: bool,
    out: TextIO,
    err: TextIO,
    *,
    cfg: LoopConfig | None = None,
    rig_factory: Callable[[], RigLike] | None = None,
    from_file: Path | None = None,
    auth: Path | None = None,
    user: str = "",
) -> int:
    """Run the identification and report; returns the exit code (0 ok, 1 aborted, 2 bad input).

    ``spec_fields``: `IdentifySpec` fields by name (the command's options; tests add more for
    short runs), checked here as the controller checks them, before anything connects or
    moves. ``rig_factory`` replaces the simulated rig (tests: a faulty rig).
    """
    if from_file is not None:  # the run analysed again from its recording
        problem = _from_error(plant, connect, spec_fields)
    else:
        problem = _connection_error(plant, connect, rig_name)
    if problem is not None:
        return _bad(problem, as_json, out, err)
    try:
        spec = IdentifySpec(**spec_fields)
    except ConfigError as exc:
        return _bad(_flagged(exc), as_json, out, err)
    except TypeError as exc:  # an unknown field name
        return _bad(f"spec: {exc}", as_json, out, err)
    progress = _Progress(err)
    t0 = time.perf_counter()
    try:
        if from_file is not None:
            from controller.cli.identify_from import RecordingProblem, status_from_recording

            try:
                status = status_from_recording(from_file, rig_name or "")
            except RecordingProblem as exc:
                return _bad(f"--from: {exc}", as_json, out, err)
            summary = _write_remote(status, out_dir, time.perf_counter() - t0)
        elif connect is not None and rig_name is not None:
            status = _remote(connect, rig_name, spec, progress, auth=auth, user=user)
            if isinstance(status, str):
                return _bad(status, as_json, out, err)
            summary = _write_remote(status, out_dir, time.perf_counter() - t0)
        else:
            result = _offline(spec, cfg if cfg is not None else LoopConfig(), rig_factory, progress)
            summary = _write(result, out_dir, time.perf_counter() - t0)
    except ConfigError as exc:
        return _bad(_flagged(exc), as_json, out, err)
    except OSError as exc:
        return _bad(f"--out: cannot write to {out_dir}: {exc}", as_json, out, err)
    if as_json:
        out.write(json.dumps(summary, allow_nan=False) + "\n")
    else:
        out.write(report_text(summary, out_dir))
    if not summary["complete"]:
        err.write(f"error: identification aborted: {summary['abort_reason']}\n")
        return EXIT_ABORTED
    return EXIT_OK


def _offline(
    spec: IdentifySpec,
    cfg: LoopConfig,
    rig_factory: Callable[[], RigLike] | None,
    progress: _Progress,
) -> IdentifyResult:
    """The run on the simulated rig (or `rig_factory`'s); the partial result after an abort."""
    try:
        return run_identification(spec, cfg, rig_factory, progress)
    except IdentifyAborted as exc:
        return exc.result
    finally:
        progress.done()


#: How long `_no_controller` waits for a Zenoh peer at the endpoint, then for the rig's token.
_PEER_WAIT_S = 2.0
_TOKEN_WAIT_S = 3.0


def _no_controller(session: Any, endpoint: str, rig_name: str) -> str | None:
    """Why no run can start at `endpoint` (None: the rig's controller is alive there): nothing
    answers there at all (no Zenoh peer or router within `_PEER_WAIT_S`), or something does
    but no controller of `rig_name` (its liveliness token, `dobtune ctl rigs`) within
    `_TOKEN_WAIT_S`. Instead of the requests' own timeouts (10 s before). Without credentials
    only: with them, opening the session already fails when nothing is reached, and the
    access rules may hide other rigs' tokens."""
    from controller import protocol as proto

    start = time.monotonic()
    while not (list(session.info.peers_zid()) or list(session.info.routers_zid())):
        if time.monotonic() - start >= _PEER_WAIT_S:
            return (f"--connect: nothing answers at {endpoint} within {_PEER_WAIT_S:g} s (no "
                    f"Zenoh peer or router there): is the controller running, on that port?")
        time.sleep(0.05)
    start = time.monotonic()
    while not list(session.liveliness().get(proto.key_alive(rig_name), timeout=1.0)):
        if time.monotonic() - start >= _TOKEN_WAIT_S:
            alive = sorted({str(r.ok.key_expr).split("/")[1] for r in session.liveliness().get(
                proto.key_alive("*"), timeout=1.0) if r.ok is not None})
            there = ", ".join(repr(a) for a in alive) if alive else "none"
            return (f"--connect: no controller of rig {rig_name!r} at {endpoint} (a Zenoh "
                    f"session answers there; rigs alive: {there}): check --rig-name")
        time.sleep(0.1)
    return None


def _remote(
    endpoint: str, rig_name: str, spec: IdentifySpec, progress: _Progress, poll_s: float = 0.2,
    auth: Path | None = None, user: str = "",
) -> Any:
    """Start the run in the controller's loop and follow it: its final IdentifyStatus, or why
    not (a message naming the option)."""
    from controller import protocol as proto
    from controller.client import ClientOptions, ControllerClient, ControllerUnavailable

    opts = ClientOptions(connect=(endpoint,), rig_name=rig_name, client_name="identify",
                         auth=auth, user=user, subscribe=False, query_timeout_s=5.0)
    status: proto.IdentifyStatus | None = None
    try:
        with ControllerClient(opts) as c:
            absent = None if auth is not None else _no_controller(c.session, endpoint, rig_name)
            if absent is not None:
                return absent
            reply = None
            deadline = time.monotonic() + 10.0
            while reply is None:  # the session may still connect
                try:
                    reply = c.command(proto.IdentifyStart(spec=spec))
                except ControllerUnavailable:
                    if time.monotonic() >= deadline:
                        return f"--connect: no reply from rig {rig_name!r} at {endpoint}"
            if not reply.ok:
                return f"controller refused: {reply.message}"
            deadline = time.monotonic() + spec.max_duration_s + 300.0
            while time.monotonic() < deadline:
                try:
                    status = c.identify_status()
                except ControllerUnavailable:
                    pass  # a reply lost on a loaded machine: ask again
                else:
                    progress(min(status.progress, 0.99), status.text)
                    if status.state in ("done", "aborted"):
                        break
                time.sleep(poll_s)
    except ControllerUnavailable as exc:  # credentials that reach nothing
        return f"--connect: {exc}"
    finally:
        progress.done()
    if status is None or status.state not in ("done", "aborted"):
        return "controller: no result before the deadline"
    return status


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plant", default=None, metavar="sim", help="offline simulated rig (default)")
    p.add_argument("--connect", default=None, metavar="ENDPOINT", help="running controller")
    p.add_argument("--rig-name", default=None, metavar="NAME", help="with --connect")
    p.add_argument("--auth", type=Path, default=None, metavar="DIR",
                   help="with --connect: credentials (an auth directory or a password file)")
    p.add_argument("--user", default="", help="with --auth: the user to log in as")
    p.add_argument("--from", dest="from_file", type=Path, default=None, metavar="FILE.mcap",
                   help="analyse again an identification run recorded by `dobtune record`")
    for f in CLI_FIELDS:  # generated from the spec: flag, type, default, unit, help
        p.add_argument(
            f.param.flag,
            dest=f.name,
            type=f.type,
            default=f.default,
            metavar=f.metavar,
            help=f"{f.param.help} (default: {f.default})",
        )
    p.add_argument("--disturbance", action="append", default=[], metavar="NAME",
                   help="offline simulated rig only: its named disturbances (repeatable; those "
                   "of dobtune experiment; default article-rig, ideal: the reference rig alone)")
    p.add_argument("--out", type=Path, default=Path("identify-out"), metavar="DIR")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")


def _sim_rig_factory(
    names: list[str], connect: str | None, from_file: Path | None
) -> Callable[[], RigLike] | None:
    """The offline simulated rig with the named disturbances (the default rig without names;
    None for a rig that is not simulated offline); ConfigError
    naming --disturbance for an unknown name or a run that is not offline."""
    if connect is not None or from_file is not None:
        if names:
            raise ConfigError("disturbance", "only with the offline simulated rig (--plant sim)")
        return None
    from controller.sim.rig_disturbances import build_rig, rig_names, rig_setup

    setup = rig_setup(rig_names(names))
    return lambda: build_rig(setup, rate_hz=LoopConfig().rate_hz, seed=0,
                             initial_position_deg=0.0)


def run(args: argparse.Namespace) -> int:
    try:
        factory = _sim_rig_factory(args.disturbance, args.connect, args.from_file)
    except ConfigError as exc:
        return _bad(f"--disturbance: {exc}", args.json, sys.stdout, sys.stderr)
    return identify_main(
        plant=args.plant,
        connect=args.connect,
        rig_name=args.rig_name,
        spec_fields={f.name: getattr(args, f.name) for f in CLI_FIELDS},
        out_dir=args.out,
        as_json=args.json,
        out=sys.stdout,
        err=sys.stderr,
        from_file=args.from_file,
        auth=args.auth,
        user=args.user,
        rig_factory=factory,
    )

