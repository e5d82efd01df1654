"""The controller process: rig + servo loop + Zenoh node, from options to a clean stop.

The loop's own thread is the main thread (`Runtime.run()`, optionally SCHED_FIFO), so signals
stop it between ticks; the Zenoh side (`controller.process.node`) and the request handlers
(`controller.process.service`) run in threads, the stability gate and the filter design in a
worker process (`controller.process.analysis_worker`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import secrets
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec

from controller import protocol as proto
from controller.auth import User
from controller.client.session import (
    SessionOptions,
    check_endpoint,
    connect,
    exposure_problem,
    is_loopback,
)
from controller.core.config import LoopConfig, NominalModel, config_from_builtins
from controller.core.errors import ConfigError
from controller.core.heap import freeze_startup_heap
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.verdict import Verdict
from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord, PlantKnowledge
from controller.process.access import Access
from controller.process.analysis_worker import AnalysisWorker
from controller.process.audit import AuditError, AuditLog, audit_path
from controller.process.edge import EdgeSpec
from controller.process.edge_link import EdgeLink, free_loopback_port
from controller.process.node import ZenohNode
from controller.process.options import ControllerOptions
from controller.process.persistence import (
    Change,
    ChangeLogError,
    PendingRollback,
    PersistenceError,
    StateStore,
)
from controller.process.runtime import (
    ESTOP,
    FAULT,
    Rig,
    Runtime,
    RuntimeOptions,
    try_realtime_priority,
)
from controller.process.service import TWIN_TIMEOUT_S, ControllerService

if TYPE_CHECKING:
    from controller.sim.rig_disturbances import RigSetup

__all__ = ["StartupError", "run_controller"]

log = logging.getLogger(__name__)


#: How long a controller behind an authenticating router tries to log in at start.
ROUTER_LOGIN_S = 10.0
#: How long the start waits for the edge process to serve requests (it loads and connects
#: beside the rest of the start-up) before the loop starts without it.
EDGE_READY_S = 60.0


class StartupError(RuntimeError):
    """The controller cannot start (bad options, a configuration the gate rejects, ...)."""


def _check_options(opts: ControllerOptions) -> None:
    if opts.plant not in ("sim", "can"):
        raise StartupError(f"--plant: expected sim or can, got {opts.plant!r}")
    try:
        proto.check_rig_name(opts.rig_name)
        for e in (*opts.listen, *opts.connect):
            check_endpoint(e)
    except ValueError as exc:
        raise StartupError(str(exc)) from exc
    if opts.sim_disturbances:
        _sim_setup(opts)
    if opts.rate_hz is not None and not math.isfinite(opts.rate_hz):
        raise StartupError(f"--rate-hz: must be finite, got {opts.rate_hz}")
    if not (math.isfinite(opts.request_budget_per_s) and opts.request_budget_per_s > 0):
        raise StartupError(f"--request-budget: {opts.request_budget_per_s} is not a positive "
                           "number of requests a second")
    if not (0.01 <= opts.status_period_s <= 10.0):
        raise StartupError(f"status_period_s: {opts.status_period_s} out of range [0.01, 10]")
    if opts.auth_dir is None:
        why = exposure_problem(opts.listen, opts.connect, opts.insecure)
        if why:
            raise StartupError(why)
    if opts.auth_dir is not None and opts.connect:
        if not opts.auth_user:
            raise StartupError(
                "--connect with --auth: give --user, the account (role controller) to log in "
                "to the authenticating router with (a controller that serves clients itself "
                "cannot dial out: the remote would be unauthenticated)"
            )
        if opts.listen:
            raise StartupError(
                "--listen with --auth --connect: behind an authenticating router the "
                "controller listens nowhere (the router enforces the access control); drop "
                "--listen"
            )
    elif opts.auth_user:
        raise StartupError("--user: only with --auth and --connect (a router to log in to)")


def _warn_log(text: str, key: str | None = None) -> None:
    """Access's warnings before the service takes them over: the log."""
    log.warning("%s", text)


def _open_access(opts: ControllerOptions, warn: Callable[..., None]) -> Access:
    """Users (with --auth) and the audit log of the state directory."""
    users = None
    if opts.auth_dir is not None:
        from controller.auth import AuthError, load_users

        try:
            users = load_users(opts.auth_dir)
        except (AuthError, OSError) as exc:
            raise StartupError(f"--auth {opts.auth_dir}: {exc}") from exc
    try:
        audit = AuditLog(audit_path(opts.state_path), rig=opts.rig_name)
    except (AuditError, OSError) as exc:
        raise StartupError(f"state_dir: the audit log cannot be opened: {exc}") from exc
    if audit.recovered:
        log.warning("audit log: %s", audit.recovered)
    return Access(users, opts.rig_name, audit, warn)


@dataclass(frozen=True)
class _EdgeLogin:
    """How the edge process reaches the loop process's session (or the router)."""

    session: SessionOptions
    """The edge process's own session."""
    listen: tuple[str, ...] = ()
    """A private loopback endpoint the loop process's session listens on for it."""
    internal: tuple[User, ...] = ()
    """Its account on the loop process's session (with authentication)."""


def _edge_login(opts: ControllerOptions) -> _EdgeLogin:
    """The edge process's way in: without authentication, a private loopback endpoint of the
    loop process's session; with it, that endpoint and an account of its own (role
    controller, a random password, accepted by this session only); behind an authenticating
    router, the router, as this controller's own account."""
    if opts.auth_dir is not None and opts.connect:
        return _EdgeLogin(SessionOptions(connect=opts.connect, auth=opts.auth_dir,
                                         user=opts.auth_user, mode="client"))
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    if opts.auth_dir is None:
        return _EdgeLogin(SessionOptions(connect=(endpoint,), mode="client"), (endpoint,))
    account = User(f"edge-{secrets.token_hex(6)}", "controller", (opts.rig_name,),
                   secrets.token_urlsafe(24))
    return _EdgeLogin(SessionOptions(connect=(endpoint,), auth=account.password,
                                     user=account.name, mode="client"), (endpoint,), (account,))


def _session(opts: ControllerOptions, edge: _EdgeLogin | None = None,
             private_dir: Path | None = None) -> Any:
    import zenoh

    from controller.auth import AuthError, load_users

    auth_errors: tuple[type[Exception], ...] = ()
    extra = edge.listen if edge is not None else ()
    internal = edge.internal if edge is not None else ()
    try:
        if opts.auth_dir is None:
            so = SessionOptions(listen=(*opts.listen, *extra), connect=opts.connect,
                                insecure=opts.insecure)
            unreachable = (f"--listen {', '.join(opts.listen)}: cannot open the Zenoh session (is "
                           f"the port in use by another controller? choose another with "
                           f"--listen)")
        else:
            auth_errors = (AuthError, OSError, ValueError)
            if opts.connect:  # behind an authenticating router, logged in as a "controller"
                role = load_users(opts.auth_dir)[opts.auth_user].role
                if role != "controller":
                    raise AuthError(f"--user {opts.auth_user}: role {role!r}, expected "
                                    f"controller (add one with `dobtune auth init --user "
                                    f"NAME=controller`)")
                so = SessionOptions(connect=opts.connect, auth=opts.auth_dir,
                                    user=opts.auth_user, fail_after_s=ROUTER_LOGIN_S)
                unreachable = (f"--connect {', '.join(opts.connect)}: no connection as "
                               f"{opts.auth_user!r} within {ROUTER_LOGIN_S:g} s (router "
                               f"unreachable, or it refused the credentials)")
            else:
                so = SessionOptions(listen=(*opts.listen, *extra), auth=opts.auth_dir,
                                    serve=(opts.rig_name,), internal=internal,
                                    internal_dir=private_dir)
                unreachable = (f"--listen {', '.join(opts.listen)}: cannot open the Zenoh "
                               f"session (port in use?)")
        return connect(so)
    except auth_errors as exc:
        raise StartupError(f"--auth {opts.auth_dir}: {exc}") from exc
    except zenoh.ZError as exc:
        raise StartupError(f"{unreachable}: {exc}") from exc


def _candidate(
    opts: ControllerOptions, saved: LoopConfig | None, saved_from: Path, rig_limit: float | None
) -> tuple[LoopConfig, str]:
    """The configuration to start with and where it came from: --config, else the saved one,
    else the default; --rate-hz overrides the rate."""
    if opts.config_path is not None:
        source = f"--config {opts.config_path}"
        try:
            candidate = config_from_builtins(
                msgspec.json.decode(Path(opts.config_path).read_bytes())
            )
        except (OSError, msgspec.DecodeError, ConfigError) as exc:
            raise StartupError(f"{source}: {exc}") from exc
    elif saved is not None:
        candidate, source = saved, f"saved {saved_from}"
    else:
        candidate, source = LoopConfig(), "default"
        if rig_limit is not None and candidate.command_limit_deg_s > rig_limit:
            candidate = candidate.with_(command_limit_deg_s=rig_limit)
            source = "default, command limit from the rig file"
    if opts.rate_hz is not None:
        try:
            candidate = candidate.with_(rate_hz=opts.rate_hz)
        except ConfigError as exc:
            raise StartupError(f"--rate-hz: {exc}") from exc
    return candidate, source


def initial_knowledge(opts: ControllerOptions, store: StateStore) -> KnowledgeRecord:
    """The plant knowledge to judge on: the saved record, else the rig's commissioning model
    with its stated bound (saved as version 1). Raises PersistenceError for a saved record
    that cannot be read: the controller never judges on a silent default."""
    saved = store.load_knowledge()
    if saved is not None:
        return saved
    if opts.plant == "sim":
        source = "simulated rig model"
    else:
        source = "default model (the rig file states none: identify and adopt a measurement)"
    rec = KnowledgeRecord.of(
        PlantKnowledge(bound=COMMISSIONING_BOUND, model=NominalModel(), version=1, source=source)
    )
    store.save_knowledge(rec)
    log.info("plant knowledge v1 (%s) saved", source)
    return rec


@dataclass(frozen=True)
class _Start:
    """The configuration the controller starts with, and whether the loop starts faulted."""

    config: LoopConfig
    version: int
    verdict: Verdict
    fault: str = ""
    """Why the loop starts latched in fault ("": it does not)."""
    unsaved: PendingRollback | None = None
    """The watchdog's rollback the change log records, which could not be saved at start
    either (the service retries it)."""
    rolled_back_from: LoopConfig | None = None
    note: str = ""
    """For Status.notes ("": none)."""


def _initial_config(
    opts: ControllerOptions,
    store: StateStore,
    check: Callable[[LoopConfig], Verdict],
    rig_limit_deg_s: float | None = None,
) -> _Start:
    """The configuration to start with; the gate must not reject it (a caution is started
    with and reported); a change is saved and logged. A watchdog rollback the change log
    records as not saved replaces the saved configuration (the one it rolled back from,
    judged unsafe: never started again); it is saved now, or the loop starts faulted. A state
    directory that cannot be written starts the loop faulted (nothing it would have to
    record, a rollback or an e-stop, could be)."""
    saved = store.load()
    pending = store.pending_rollback(saved) if opts.config_path is None else None
    start_from = saved.config if saved is not None else None
    if pending is not None:
        start_from = pending.config
        log.warning("the watchdog's rollback from v%d to v%d was not saved before the restart "
                    "(the change log records it): starting on v%d", pending.from_version,
                    pending.version, pending.version)
    candidate, source = _candidate(opts, start_from, store.active_path, rig_limit_deg_s)
    if pending is not None:
        source = (f"the watchdog's rollback to v{pending.version} recorded in {store.log_path} "
                  f"(not saved before the restart)")
    verdict = check(candidate)
    if not verdict.applicable:
        raise StartupError(
            f"{source}: rejected by the stability gate: " + "; ".join(verdict.reasons)
        )
    if verdict.verdict == "caution":
        log.warning("%s: the gate's verdict is caution: %s", source, "; ".join(verdict.reasons))
    try:
        store.check_writable()
    except PersistenceError as exc:
        unwritable = str(exc)
    else:
        unwritable = ""
    if pending is None and saved is not None and saved.config == candidate:
        return _Start(candidate, saved.version, verdict, fault=_unwritable_fault(unwritable))
    if pending is not None:
        version, client = pending.version, f"watchdog rollback: {pending.kind} (saved at start)"
    else:
        version, client = (saved.version if saved is not None else 0) + 1, f"startup ({source})"
    change = Change(
        old=None if saved is None else saved.config,
        old_version=None if saved is None else saved.version,
        verdict=verdict,
        client=client,
    )
    try:
        store.save(candidate, version, change)
    except PersistenceError as exc:
        if pending is None or isinstance(exc, ChangeLogError):
            raise
        fault = (f"state_dir: the watchdog's rollback to v{version} (from v{pending.from_version}"
                 f", before the restart) cannot be saved ({exc}): the loop starts stopped on "
                 f"v{version}, never on v{pending.from_version}; the save is retried")
        return _Start(candidate, version, verdict, fault=fault, unsaved=pending,
                      rolled_back_from=None if saved is None else saved.config)
    log.info("config v%d from %s saved", version, source)
    note = "" if pending is None else (
        f"the watchdog's rollback from v{pending.from_version} to v{version}, not saved before "
        "the restart, was saved at start")
    return _Start(candidate, version, verdict, fault=_unwritable_fault(unwritable), note=note)


def _unwritable_fault(why: str) -> str:
    """The fault the loop starts in when the state directory cannot be written ("" if it can)."""
    if not why:
        return ""
    return (f"state_dir: cannot be written ({why}): the loop starts stopped, since neither a "
            "watchdog rollback nor an e-stop could be recorded; make it writable, then reset")


def _rig_command_limit(opts: ControllerOptions) -> float | None:
    """The CAN rig file's command limit (None for the simulated rig)."""
    if opts.plant != "can" or opts.rig_file is None:
        return None
    from controller.rig.rig_file import load_rig_file

    try:
        return float(load_rig_file(opts.rig_file).limits.command_limit_deg_s)
    except (OSError, ValueError) as exc:
        raise StartupError(f"--rig {opts.rig_file}: {exc}") from exc


def _sim_setup(opts: ControllerOptions) -> RigSetup:
    """The simulated rig's named disturbances; StartupError naming --disturbance."""
    from controller.sim.rig_disturbances import rig_setup

    if opts.plant != "sim":
        raise StartupError("--disturbance: only with --plant sim (a real rig has its own)")
    try:
        setup = rig_setup(list(opts.sim_disturbances))
    except ConfigError as exc:
        raise StartupError(f"--disturbance: {exc}") from exc
    if setup.friction_changes:
        raise StartupError(
            f"--disturbance: {setup.label} schedules a friction change (offline experiments "
            "only: dobtune experiment)"
        )
    return setup


@contextlib.contextmanager
def _open_rig(opts: ControllerOptions, rate_hz: float) -> Iterator[tuple[Rig, list[str]]]:
    """The plant, with anything it needs running; yields (rig, startup faults)."""
    if opts.plant == "sim":
        from controller.sim.sim_rig import SimRig

        if opts.sim_disturbances:
            setup = _sim_setup(opts)
            yield SimRig(setup.params, rate_hz=rate_hz, seed=opts.seed,
                         disturbance=setup.torque), []
        else:
            yield SimRig(rate_hz=rate_hz, seed=opts.seed), []
        return
    from controller.rig.can_rig import CanRig, RigFault
    from controller.rig.rig_file import load_rig_file

    if opts.rig_file is None:
        raise StartupError("--plant can needs --rig FILE")
    try:
        rig_file = load_rig_file(opts.rig_file)
    except (OSError, ValueError) as exc:
        raise StartupError(f"--rig {opts.rig_file}: {exc}") from exc
    with contextlib.ExitStack() as stack:
        if opts.sim_drive_node:
            from controller.rig.sim_drive_node import SimDriveNode
            from controller.sim.sim_rig import SimRig

            plant = SimRig(rate_hz=rate_hz, seed=opts.seed)
            # The simulated drive answers from a thread of this process: real-time priority
            # (below the loop's) keeps the host's load from starving it, as hardware is not.
            node = SimDriveNode(rig_file, plant, rate_hz=rate_hz,
                                on_thread_start=lambda: try_realtime_priority(45))
            stack.enter_context(node)
        rig = stack.enter_context(CanRig(rig_file, rate_hz=rate_hz))
        faults: list[str] = []
        try:
            rig.start()
        except RigFault as exc:
            faults.append(f"drive did not start: {exc}")
        yield rig, faults


def _restore_latch(store: StateStore, runtime: Runtime, notes: list[str]) -> None:
    """Come back in the e-stop or fault the previous run was latched in (until a reset)."""
    try:
        latch = store.load_latch()
    except PersistenceError as exc:
        reason = f"state_dir: the e-stop/fault latch is unreadable ({exc}); send reset"
        runtime.restore_latch(FAULT, reason)
        log.warning("%s", reason)
        return
    if latch is None:
        return
    runtime.restore_latch(latch.mode, latch.reason)
    if latch.fault:
        runtime.fault = latch.fault
    notes.append(f"{latch.mode} latched before the restart ({latch.reason}): send reset")
    log.warning("%s", notes[-1])


def _check_clean_stop(store: StateStore, runtime: Runtime, notes: list[str]) -> None:
    """A run marker left by the previous run (`StateStore.unclean_stop`: it was killed, crashed
    or lost power while its loop ran) starts this one latched in fault until a reset: what the
    rig did since is unknown, and a latch the previous run had no time to write (the fault
    came a moment before the crash) is not lost. A fault already latched keeps its reason."""
    previous = store.unclean_stop()
    if not previous:
        return
    reason = (f"controller: the previous run ({previous}) ended without a clean stop (killed, "
              "crashed or powered off while the loop ran); check the rig, then send reset")
    if runtime.fault:
        notes.append(reason)
        log.warning("%s", reason)
    else:
        _start_faulted(runtime, reason, notes)


def _mark_running(store: StateStore, service: ControllerService) -> None:
    """The run marker written just before the loop runs; a directory that refuses it is
    reported (the loop runs: its latch and configuration are the store's other files)."""
    try:
        store.mark_running(os.getpid(), time.time())
    except PersistenceError as exc:
        service.warn(f"state_dir: the run marker was not written ({exc}): a crash of this run "
                     "will not be seen at the next start", key="run_marker")


def _start_faulted(runtime: Runtime, reason: str, notes: list[str]) -> None:
    """The loop starts latched in fault for `reason` (an e-stop or fault latched before
    stays, this one reported beside it)."""
    if runtime.mode == ESTOP:
        runtime.fault = reason
    elif runtime.mode != FAULT:
        runtime.restore_latch(FAULT, reason)
    notes.append(reason)
    log.warning("fault at start: %s", reason)


class _Stopper:
    """SIGINT/SIGTERM: stop the loop (command 0) and let the process wind down."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.runtime: Runtime | None = None

    def on_signal(self, signum: int, _frame: Any) -> None:
        self.event.set()
        runtime = self.runtime
        if runtime is not None:
            runtime.stop()


def run_controller(opts: ControllerOptions, *, ready: Callable[[str], None] | None = None) -> int:
    """Run the controller until SIGINT/SIGTERM; 0 on a clean stop. Raises StartupError if it
    cannot start. `ready(text)` is called once the loop is about to run (the CLI prints it)."""
    stopper = _Stopper()
    # Our handlers stay installed until everything is shut down: a second Ctrl-C (a terminal
    # signals the whole process group, then a launcher may signal again) never interrupts
    # the shutdown half-way.
    previous = {s: signal.signal(s, stopper.on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    runner: AnalysisWorker | None = None
    twin_runner: AnalysisWorker | None = None
    edge: EdgeLink | None = None
    try:
        runner = AnalysisWorker(subprocess=opts.gate_in_subprocess)
        # The twin's fit and its estimate from running, off the analysis worker (no request
        # waits behind them). Started on its first job, none before: its start (imports, the
        # rig kernel) gets the twin's bound, not a verdict's (over 60 s seen under load).
        twin_runner = AnalysisWorker(subprocess=opts.gate_in_subprocess,
                                     start_timeout_s=TWIN_TIMEOUT_S)
        _check_options(opts)
        edge_login = _edge_login(opts) if opts.edge_in_subprocess else None
        if edge_login is not None:
            # Started first: it loads and connects beside the rest of the start-up.
            edge = EdgeLink(EdgeSpec(
                rig=opts.rig_name, session=edge_login.session, auth_dir=opts.auth_dir,
                state_dir=opts.state_path, max_payload_bytes=opts.max_payload_bytes,
                max_pending_queries=opts.max_pending_queries,
                budget_per_s=opts.request_budget_per_s if opts.auth_dir is not None else None,
                parent_pid=os.getpid()))
            edge.start()  # from this (the main) thread: its death signal
        _run(opts, runner, stopper, ready, edge_login, edge, twin_runner)
    finally:
        if edge is not None:
            edge.close()
        if runner is not None:
            runner.close()
        if twin_runner is not None:
            twin_runner.close(wait=False)  # a fit in progress (minutes) never holds up the stop
        for s, h in previous.items():
            signal.signal(s, h)
    return 0


def _run(
    opts: ControllerOptions,
    runner: AnalysisWorker,
    stopper: _Stopper,
    ready: Callable[[str], None] | None,
    edge_login: _EdgeLogin | None = None,
    edge: EdgeLink | None = None,
    twin_runner: AnalysisWorker | None = None,
) -> None:
    runner.command_limit_max_deg_s = _rig_command_limit(opts)
    # The analysis worker starts loading now, beside the rest of the start-up; the first check
    # runs here, before the loop (the worker may still be loading: behind a busy machine it
    # took tens of seconds to give the first verdict).
    runner.start()
    try:
        store = StateStore(opts.state_path)
        knowledge = initial_knowledge(opts, store)
        start = _initial_config(
            opts,
            store,
            lambda c: runner.check_here(c, knowledge),
            runner.command_limit_max_deg_s,
        )
        cfg, version, verdict = start.config, start.version, start.verdict
    except PersistenceError as exc:
        raise StartupError(str(exc)) from exc
    # The worker judges the running configuration once it has loaded: the first apply finds
    # the knowledge converted and the analysis run (else it waited for that too).
    runner.prime(cfg, knowledge)
    previous_switch = sys.getswitchinterval()
    sys.setswitchinterval(opts.switch_interval_s)
    try:
        with _open_rig(opts, cfg.rate_hz) as (rig, rig_faults):
            loop = ServoLoop(LoopCoefficients.build(cfg, version))
            runtime = Runtime(
                loop,
                rig,
                options=RuntimeOptions(rate_hz=cfg.rate_hz, spin_s=opts.spin_s),
                trajectory=opts.trajectory,
            )
            stopper.runtime = runtime
            notes: list[str] = []
            _restore_latch(store, runtime, notes)
            if start.fault:
                _start_faulted(runtime, start.fault, notes)
            _check_clean_stop(store, runtime, notes)
            if start.note:
                notes.append(start.note)
            if rig_faults:
                runtime.fault = rig_faults[0]
                if runtime.mode != ESTOP:
                    runtime.mode = FAULT
                log.warning("fault at start: %s", rig_faults[0])
            access = _open_access(opts, _warn_log)
            service = ControllerService(
                opts, runtime, store, runner, verdict, notes, knowledge, access,
                twin_worker=twin_runner,
            )
            access.warn = service.warn
            if start.unsaved is not None:
                service.rollback_not_saved(start.unsaved, start.rolled_back_from)
            access.start()
            access.record("controller.start", "controller", "noted", version_after=version,
                          auth=access.auth, listen=list(opts.listen))
            if access.auth:
                notes.append(f"authentication on ({opts.auth_dir}): requests on per-user scopes")
                plain = [e for e in opts.listen if not is_loopback(e) and not e.startswith("tls/")]
                if plain:
                    notes.append(
                        f"{', '.join(plain)}: not TLS: the traffic is not encrypted and clients "
                        "cannot check they reach this controller (`dobtune auth init --tls`)"
                    )
            with contextlib.ExitStack() as closing:
                closing.callback(access.close)
                closing.callback(
                    lambda: access.record("controller.stop", "controller", "noted",
                                          version_before=runtime.loop.active.version)
                )
                private_dir = Path(closing.enter_context(
                    tempfile.TemporaryDirectory(prefix="dobtune-edge-")))
                session = closing.enter_context(_session(opts, edge_login, private_dir))
                if edge is not None:
                    edge.connect_now()
                node = ZenohNode(service)
                clean = False
                try:
                    node.declare(session, queryables=edge is None)
                    if edge is not None:
                        node.edge = edge
                        edge.attach(node)
                        # Requests are served before the first status says the rig is there.
                        if not edge.ready.wait(EDGE_READY_S):
                            service.warn(f"edge process: not serving requests after "
                                         f"{EDGE_READY_S:g} s; the loop starts without")
                    node.start_threads(workers=edge is None)
                    if opts.realtime_priority:
                        notes.append(try_realtime_priority())
                        log.info("%s", notes[-1])
                    freeze_startup_heap()  # never scanned again (fewer, shorter GC pauses)
                    text = (
                        f"rig {opts.rig_name!r} plant {opts.plant} at {cfg.rate_hz:g} Hz, "
                        f"config v{version}, listening on {', '.join(opts.listen) or '-'}"
                        + (f", connected to {', '.join(opts.connect)}" if opts.connect else "")
                        + (f" as {opts.auth_user}" if opts.auth_user else "")
                    )
                    _mark_running(store, service)
                    if ready is not None:
                        ready(text)
                    if not stopper.event.is_set():
                        runtime.run()
                    clean = True
                finally:
                    runtime.stop()
                    if edge is not None:
                        edge.close()  # no request reaches the node any more
                    node.close()  # its last act: the latch of the mode the loop ended in
                if clean:
                    # Only now: a stop that raised on the way leaves the marker.
                    try:
                        store.clear_running()
                    except PersistenceError as exc:
                        log.error("state_dir: the run marker was not removed (%s): the next "
                                  "start comes back in fault", exc)
    finally:
        sys.setswitchinterval(previous_switch)
