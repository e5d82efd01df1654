"""The controller process: rig + servo loop + Zenoh, the config gate, commands and e-stop.

Threads (the loop's own thread is the main thread, so signals stop it between ticks):
- main: `Runtime.run()`, the 1 kHz loop (optionally SCHED_FIFO).
- state publisher: encodes finished sample blocks as StateBatch and puts them.
- status: Status every `status_period_s`.
- config worker: decodes ConfigRequest, runs the stability gate (`controller.gate.analysis`) in
  this process, persists, asks the loop to swap at a tick boundary, waits for it, replies.
- command worker: decodes Command; an EStop sets the loop's flag before anything else.
Zenoh callbacks only hand the query to a worker's queue (or, for the e-stop key, set the
loop's flag); they never decode, block or call Zenoh.

The controller is the single authority: nothing but an accepted candidate changes what runs.
An operator lease (`dobtune/<rig>/lease`) is not implemented yet: any peer that can reach
the endpoints may apply configurations and commands (Status.operator stays "").
"""

from __future__ import annotations

import contextlib
import gc
import math
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import msgspec

from controller import protocol as proto
from controller.core.config import LoopConfig, config_from_builtins
from controller.core.errors import ConfigError
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.process.persistence import PersistenceError, StateStore
from controller.process.runtime import (
    ESTOP,
    AbortProgram,
    ApplyCoefficients,
    ExcitationProgram,
    Rig,
    RunProgram,
    Runtime,
    RuntimeOptions,
    try_realtime_priority,
)
from controller.zenoh_session import DEFAULT_LISTEN, check_endpoint, open_session

__all__ = ["ControllerOptions", "gate", "margins_dict", "run_controller"]

_SHUTDOWN = object()


@dataclass(frozen=True)
class ControllerOptions:
    """Everything `run_controller` needs; built by `controller.__main__` from the command line."""

    plant: str = "sim"
    """"sim" (the simulated rig, in lockstep with the loop) or "can" (needs rig_file)."""
    rig_file: Path | None = None
    rig_name: str = "demo"
    """The `<rig>` chunk of every key."""
    listen: tuple[str, ...] = DEFAULT_LISTEN
    connect: tuple[str, ...] = ()
    config_path: Path | None = None
    """An initial LoopConfig (JSON). It goes through the gate like any candidate."""
    state_dir: Path | None = None
    """Active config + applied-changes log; default ./var/<rig_name>."""
    rate_hz: float | None = None
    """Loop rate override (otherwise the configuration's rate_hz)."""
    seed: int = 0
    realtime_priority: bool = False
    trajectory: Trajectory = field(default_factory=Trajectory)
    status_period_s: float = 0.2
    max_payload_bytes: int = 64 * 1024
    """Larger queries are rejected before decoding."""
    max_pending_queries: int = 256
    """Per queryable; beyond this, new queries are dropped unanswered."""
    apply_timeout_s: float = 1.0
    """How long a request waits for the loop's tick boundary before replying with an error."""
    command_timeout_s: float = 5.0
    """The same for commands: a reset re-enables the drive inside the loop (CAN: up to the
    rig file's enable_timeout_s)."""
    spin_s: float = 0.0002
    switch_interval_s: float = 0.0002
    """sys.setswitchinterval for this process: bounds how long another Python thread can
    keep the loop's thread waiting for the interpreter lock."""
    gate_in_subprocess: bool = True
    """Run the stability analysis in a worker process (see GateRunner)."""
    sim_drive_node: bool = False
    """plant="can" only: run a simulated CiA 402 drive node in this process on the rig
    file's bus (python-can `virtual`): the whole CAN path without hardware."""


# -- the stability gate (one adapter to controller.gate.analysis) ----------------------------


def gate(cfg: LoopConfig) -> tuple[bool, tuple[str, ...], proto.Margins]:
    """Run the stability analysis; (accepted, reasons, margins). Never raises."""
    from controller.gate.analysis import analyse

    try:
        a = analyse(cfg)
    except Exception as exc:
        return False, (f"analysis failed: {type(exc).__name__}: {exc}",), _nan_margins()
    margins = proto.Margins(
        gain_margin_db=float(a.gain_margin_db),
        phase_margin_deg=float(a.phase_margin_deg),
        peak_sensitivity_db=float(a.peak_sensitivity_db),
        small_gain_peak=float(a.small_gain_peak),
        max_pole_radius=float(a.max_pole_radius),
    )
    accepted = bool(a.accepted)
    reasons = tuple(a.reasons) if not accepted else ()
    if not accepted and not reasons:
        reasons = ("rejected by the stability analysis",)
    return accepted, reasons, margins


def _nan_margins() -> proto.Margins:
    nan = float("nan")
    return proto.Margins(
        gain_margin_db=nan,
        phase_margin_deg=nan,
        peak_sensitivity_db=nan,
        small_gain_peak=nan,
        max_pole_radius=nan,
    )


def _worker_init() -> None:
    # Ctrl-C in a terminal reaches the whole process group: the parent decides, not us.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The loop's process wins the CPU over an analysis on a busy machine.
    with contextlib.suppress(OSError):
        os.nice(10)


GateResult = tuple[bool, tuple[str, ...], proto.Margins]


def gate_and_build(
    cfg: LoopConfig, version: int
) -> tuple[bool, tuple[str, ...], proto.Margins, LoopCoefficients | None]:
    """`gate`, then (if accepted) the loop's filters for `version`. Never raises."""
    accepted, reasons, margins = gate(cfg)
    if not accepted:
        return accepted, reasons, margins, None
    try:
        return True, (), margins, LoopCoefficients.build(cfg, version)
    except Exception as exc:
        return False, (f"candidate: filters could not be built: {exc}",), margins, None


class GateRunner:
    """Runs `gate` in a worker process (default) or in the calling thread.

    In a worker the analysis (NumPy + Python, ~10 ms) never competes with the loop's thread
    for this interpreter's lock: run in a thread of the controller it made the loop overrun
    on a busy machine. A worker that hangs is killed after `timeout_s` and the candidate
    rejected; the next check starts a fresh one.
    """

    def __init__(
        self,
        *,
        subprocess: bool = True,
        timeout_s: float = 10.0,
        command_limit_max_deg_s: float | None = None,
    ) -> None:
        self._subprocess = subprocess
        #: The rig's own command limit (CAN rig file): a config may not exceed it, or the drive
        #: would clamp commands the DOB believes were sent.
        self.command_limit_max_deg_s = command_limit_max_deg_s
        self._timeout_s = timeout_s
        self._pool: Any = None
        self._lock = threading.Lock()

    def _executor(self) -> Any:
        if self._pool is None:
            import concurrent.futures
            import multiprocessing

            self._pool = concurrent.futures.ProcessPoolExecutor(
                max_workers=1,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_worker_init,
            )
        return self._pool

    def check(self, cfg: LoopConfig) -> GateResult:
        """The gate's verdict on `cfg`."""
        accepted, reasons, margins, _ = self.check_and_build(cfg, 0, build=False)
        return accepted, reasons, margins

    def check_and_build(
        self, cfg: LoopConfig, version: int, *, build: bool = True
    ) -> tuple[bool, tuple[str, ...], proto.Margins, LoopCoefficients | None]:
        """The gate's verdict and, if accepted and `build`, the coefficients to swap in."""
        rig_max = self.command_limit_max_deg_s
        if rig_max is not None and cfg.command_limit_deg_s > rig_max:
            return (
                False,
                (
                    f"command_limit_deg_s {cfg.command_limit_deg_s:g} deg/s > the rig's limit "
                    f"{rig_max:g} deg/s (rig file limits.command_limit_deg_s): the drive would "
                    "clamp commands the DOB believes were sent",
                ),
                _nan_margins(),
                None,
            )
        if not self._subprocess:
            return gate_and_build(cfg, version) if build else (*gate(cfg), None)
        import concurrent.futures

        with self._lock:
            try:
                if build:
                    fut = self._executor().submit(gate_and_build, cfg, version)
                    result: tuple[bool, tuple[str, ...], proto.Margins, LoopCoefficients | None] = (
                        fut.result(timeout=self._timeout_s)
                    )
                    return result
                fut = self._executor().submit(gate, cfg)
                verdict: GateResult = fut.result(timeout=self._timeout_s)
                return (*verdict, None)
            except concurrent.futures.TimeoutError:
                self._kill()
                reason = f"analysis: no verdict within {self._timeout_s:g} s"
            except Exception as exc:  # a dead worker (BrokenProcessPool), pickling, ...
                self._kill()
                reason = f"analysis worker failed: {type(exc).__name__}: {exc}"
            return False, (reason,), _nan_margins(), None

    def call(self, fn: Callable[..., Any], *args: Any, timeout_s: float = 120.0) -> Any:
        """Run `fn(*args)` in the worker process (or here without one); raises on failure."""
        if not self._subprocess:
            return fn(*args)
        import concurrent.futures

        with self._lock:
            try:
                return self._executor().submit(fn, *args).result(timeout=timeout_s)
            except concurrent.futures.TimeoutError:
                self._kill()
                raise
            except Exception:
                self._kill()
                raise

    def _kill(self) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        for proc in list(getattr(pool, "_processes", {}).values()):
            with contextlib.suppress(Exception):
                proc.kill()
        with contextlib.suppress(Exception):
            pool.shutdown(wait=False, cancel_futures=True)

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


def margins_dict(m: proto.Margins | None) -> dict[str, float] | None:
    return None if m is None else msgspec.to_builtins(m)  # type: ignore[no-any-return]


# -- identification (results computed off the loop: the gate's worker process) ----------------


def identify_analysis(
    plan: Any,
    u: Sequence[float],
    w: Sequence[float],
    pos: Sequence[float],
    n_done: int,
    abort_reason: str | None,
    wall_s: float,
) -> dict[str, Any]:
    """Estimate (fit and gate when complete) from a program's records; the IdentifyStatus
    fields that carry results. Runs in the gate's worker process."""
    import json

    import numpy as np

    from controller.cli.identify import csv_name, summary_json
    from controller.ident.identify import result_from_program

    result = result_from_program(plan, u, w, pos, n_done, abort_reason)
    positions = []
    files: dict[int, tuple[str | None, str]] = {}
    for p in result.positions:
        est = p.estimate
        files[p.index] = (None if est is None else csv_name(p), "")
        positions.append(
            proto.PositionResponse(
                index=p.index,
                center_deg=p.center_deg,
                complete=p.complete,
                points_done=p.points_done,
                points_total=p.points_total,
                freq_hz=[] if est is None else est.freq_hz.tolist(),
                mag_db=[] if est is None else (20.0 * np.log10(np.abs(est.response))).tolist(),
                phase_deg=[] if est is None else np.degrees(np.angle(est.response)).tolist(),
                coherence=[] if est is None else est.coherence.tolist(),
                mag_std_db=[] if est is None else est.mag_std_db.tolist(),
                phase_std_deg=[] if est is None else est.phase_std_deg.tolist(),
            )
        )
    summary = summary_json(result, files, wall_s)
    summary["plant"] = "controller"

    def finite(v: float | None) -> float | None:
        return float(v) if v is not None and math.isfinite(v) else None

    fit = result.fit
    return {
        "positions": positions,
        "natural_freq_hz": None if fit is None else finite(fit.natural_freq_hz),
        "zeta": None if fit is None else finite(fit.zeta),
        "agreement_freq_hz": finite(summary["agreement_freq_hz"]),
        "recommended_cutoff_hz": {k: finite(v) for k, v in result.recommended_cutoff_hz.items()},
        "summary_json": json.dumps(summary, allow_nan=False),
    }


def identify_segments(segments: Sequence[Any]) -> list[tuple[list[float], ...]]:
    """Estimate finished segments (`controller.ident.identify.SegmentData`) of a running program:
    per segment (freq_hz, mag_db, phase_deg, coherence, mag_std_db, phase_std_deg) lists.
    Runs in the gate's worker process."""
    import numpy as np

    from controller.ident.identify import estimate_segment

    out: list[tuple[list[float], ...]] = []
    for seg in segments:
        est = estimate_segment(seg)
        out.append(
            (
                est.freq_hz.tolist(),
                (20.0 * np.log10(np.abs(est.response))).tolist(),
                np.degrees(np.angle(est.response)).tolist(),
                est.coherence.tolist(),
                est.mag_std_db.tolist(),
                est.phase_std_deg.tolist(),
            )
        )
    return out


class _IdentifyJob:
    """The latest identification run as the node sees it."""

    def __init__(self, run_id: int, plan: Any, program: ExcitationProgram) -> None:
        self.run_id = run_id
        self.plan = plan
        self.program = program
        self.state = "running"
        self.t0 = time.monotonic()
        self.results: dict[str, Any] = {}
        self.abort_reason = ""
        self.text = ""
        #: live results: segments estimated so far, and per position the lists of
        #: PositionResponse fields (replaced, never mutated, once published in `partial`)
        self.segments_estimated = 0
        self.columns: dict[int, tuple[list[float], ...]] = {}
        self.partial: list[proto.PositionResponse] = []
        self.partial_failed = False

    def add_segments(self, first: int, estimates: list[tuple[list[float], ...]]) -> None:
        """Append the estimates of segments first, first + 1, ... and publish `partial`."""
        plan = self.plan
        n_seg = plan.n_segments
        for k, cols in enumerate(estimates, start=first):
            i = k // n_seg
            old = self.columns.get(i, ((),) * len(cols))
            self.columns[i] = tuple([*a, *b] for a, b in zip(old, cols, strict=True))
        self.segments_estimated = first + len(estimates)
        centers = plan.spec.centers_deg
        partial = []
        for i, cols in sorted(self.columns.items()):
            done = min(n_seg, self.segments_estimated - i * n_seg)
            f, mag, ph, coh, mstd, pstd = cols
            partial.append(
                proto.PositionResponse(
                    index=i,
                    center_deg=float(centers[i]),
                    complete=done == n_seg,
                    points_done=done,
                    points_total=n_seg,
                    freq_hz=f,
                    mag_db=mag,
                    phase_deg=ph,
                    coherence=coh,
                    mag_std_db=mstd,
                    phase_std_deg=pstd,
                )
            )
        self.partial = partial


# -- startup ----------------------------------------------------------------------------------


class StartupError(RuntimeError):
    """The controller cannot start (bad options, a configuration the gate rejects, ...)."""


def _initial_config(
    opts: ControllerOptions,
    store: StateStore,
    check: Callable[[LoopConfig], GateResult],
    rig_limit_deg_s: float | None = None,
) -> tuple[LoopConfig, int, proto.Margins]:
    """The configuration to start with: --config, else the saved one, else the default;
    --rate-hz overrides the rate. It must pass the gate; a change is saved and logged."""
    saved = store.load()
    if opts.config_path is not None:
        try:
            data = msgspec.json.decode(Path(opts.config_path).read_bytes())
            candidate = config_from_builtins(data)
        except (OSError, msgspec.DecodeError) as exc:
            raise StartupError(f"--config {opts.config_path}: {exc}") from exc
        except ConfigError as exc:
            raise StartupError(f"--config {opts.config_path}: {exc}") from exc
        source = f"--config {opts.config_path}"
    elif saved is not None:
        candidate = saved.config
        source = f"saved {store.active_path}"
    else:
        candidate = LoopConfig()
        source = "default"
        if rig_limit_deg_s is not None and candidate.command_limit_deg_s > rig_limit_deg_s:
            candidate = candidate.with_(command_limit_deg_s=rig_limit_deg_s)
            source = "default, command limit from the rig file"
    if opts.rate_hz is not None:
        try:
            candidate = candidate.with_(rate_hz=opts.rate_hz)
        except ConfigError as exc:
            raise StartupError(f"--rate-hz: {exc}") from exc
    accepted, reasons, margins = check(candidate)
    if not accepted:
        raise StartupError(f"{source}: rejected by the stability gate: " + "; ".join(reasons))
    if saved is not None and saved.config == candidate:
        return candidate, saved.version, margins
    version = (saved.version if saved is not None else 0) + 1
    store.save(candidate, version)
    store.append_change(
        old=None if saved is None else saved.config,
        old_version=None if saved is None else saved.version,
        new=candidate,
        version=version,
        margins=margins_dict(margins),
        client=f"startup ({source})",
    )
    return candidate, version, margins


def _rig_command_limit(opts: ControllerOptions) -> float | None:
    """The CAN rig file's command limit (None for the simulated rig)."""
    if opts.plant != "can" or opts.rig_file is None:
        return None
    from controller.rig.rig_file import load_rig_file

    try:
        return float(load_rig_file(opts.rig_file).limits.command_limit_deg_s)
    except (OSError, ValueError) as exc:
        raise StartupError(f"--rig {opts.rig_file}: {exc}") from exc


@contextlib.contextmanager
def _open_rig(opts: ControllerOptions, rate_hz: float) -> Iterator[tuple[Rig, list[str]]]:
    """The plant, with anything it needs running; yields (rig, startup faults)."""
    if opts.plant == "sim":
        from controller.sim.sim_rig import SimRig

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
            stack.enter_context(SimDriveNode(rig_file, plant, rate_hz=rate_hz))
        rig = stack.enter_context(CanRig(rig_file, rate_hz=rate_hz))
        faults: list[str] = []
        try:
            rig.start()
        except RigFault as exc:
            faults.append(f"drive did not start: {exc}")
        yield rig, faults


# -- the node ---------------------------------------------------------------------------------


class _Node:
    """The Zenoh side of one controller: handlers, publishers and their threads."""

    def __init__(
        self,
        opts: ControllerOptions,
        runtime: Runtime,
        store: StateStore,
        margins: proto.Margins,
        notes: list[str],
        log: TextIO,
        gate_runner: GateRunner,
    ) -> None:
        self.opts = opts
        self.gate = gate_runner
        self.rt = runtime
        self.store = store
        self.rig_name = opts.rig_name
        self.margins = margins
        self.notes = notes
        self.log = log
        self.stop_event = threading.Event()
        self.config_q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.command_q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.identify_q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._job: _IdentifyJob | None = None
        self._job_lock = threading.Lock()
        self._apply_lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._entities: list[Any] = []
        self.state_pub: Any = None
        self.status_pub: Any = None
        self.errors: list[str] = []
        self.shed_queries = 0

    # -- lifecycle ---------------------------------------------------------------------------

    def declare(self, session: Any) -> None:
        import zenoh

        rig = self.rig_name
        self.state_pub = session.declare_publisher(
            proto.key_state(rig),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self.status_pub = session.declare_publisher(
            proto.key_status(rig), congestion_control=zenoh.CongestionControl.DROP
        )
        self._entities += [self.state_pub, self.status_pub]
        # Callbacks: hand over and return (no decoding, no Zenoh calls, no blocking).
        self._entities.append(
            session.declare_queryable(proto.key_config(rig), self._enqueue(self.config_q))
        )
        self._entities.append(
            session.declare_queryable(proto.key_command(rig), self._enqueue(self.command_q))
        )
        self._entities.append(
            session.declare_queryable(proto.key_identify(rig), self._enqueue(self.identify_q))
        )
        rt = self.rt
        self._entities.append(
            session.declare_subscriber(proto.key_estop(rig), lambda _s: rt.estop("estop key"))
        )

    def _enqueue(self, q: queue.SimpleQueue[Any]) -> Callable[[Any], None]:
        limit = self.opts.max_pending_queries

        def put(query: Any) -> None:
            # A flood beyond the bound is shed: the query is released unanswered (the client
            # times out) instead of growing memory without limit.
            if q.qsize() < limit:
                q.put(query)
            else:
                self.shed_queries += 1

        return put

    def start_threads(self) -> None:
        for name, target in (
            ("state-publisher", self._publish_state),
            ("status", self._publish_status),
            ("config-worker", self._config_worker),
            ("command-worker", self._command_worker),
            ("identify-worker", self._identify_worker),
        ):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    def close(self) -> None:
        """Stop the threads (after the loop has finished), then undeclare everything."""
        self.stop_event.set()
        self.config_q.put(_SHUTDOWN)
        self.command_q.put(_SHUTDOWN)
        self.identify_q.put(_SHUTDOWN)
        for t in self._threads:
            t.join(timeout=5.0)
        for e in reversed(self._entities):
            with contextlib.suppress(Exception):
                e.undeclare()
        self._entities.clear()
        # Queries that arrived after the workers ended are dropped (the client times out).
        for q in (self.config_q, self.command_q, self.identify_q):
            with contextlib.suppress(queue.Empty):
                while True:
                    item = q.get_nowait()
                    if item is not _SHUTDOWN:
                        with contextlib.suppress(Exception):
                            item.drop()

    def _warn(self, text: str) -> None:
        self.errors.append(text)
        del self.errors[:-8]
        with contextlib.suppress(Exception):
            print(f"dobtune controller: {text}", file=self.log, flush=True)

    # -- state and status --------------------------------------------------------------------

    def _publish_state(self) -> None:
        rt = self.rt
        rig = self.rig_name
        rate = rt.options.rate_hz
        encode = proto.encode
        put = self.state_pub.put

        def sink(seq0: int, version: int, mode: str, cols: Sequence[list[float]]) -> None:
            msg = proto.state_batch(
                rig=rig,
                seq0=seq0,
                rate_hz=rate,
                config_version=version,
                columns=cols,
                epoch_s=rt.epoch_s,
                mode=mode,
            )
            try:
                put(encode(msg))
            except Exception as exc:
                self._warn(f"state put failed: {exc}")

        rt.publisher(sink, self.stop_event)

    def status(self) -> proto.Status:
        rt = self.rt
        snap = rt.timing_snapshot()
        timing = proto.Timing(
            period_p50_us=snap.period_p50_us,
            period_p99_us=snap.period_p99_us,
            period_max_us=snap.period_max_us,
            compute_p50_us=snap.compute_p50_us,
            compute_p99_us=snap.compute_p99_us,
            compute_max_us=snap.compute_max_us,
            ticks=snap.ticks,
            overruns=snap.overruns,
            skipped_ticks=snap.skipped_ticks,
            dropped_samples=snap.dropped_samples,
        )
        faults = [rt.fault] if rt.fault else []
        if rt.mode == ESTOP:
            faults.append(f"e-stop ({rt.estop_source}) at seq {rt.estop_seq}")
        active = rt.loop.active
        return proto.Status(
            rig=self.rig_name,
            plant=self.opts.plant,
            mode=rt.mode,
            t_s=time.perf_counter() - rt.t0,
            seq=rt.seq,
            trajectory=rt.trajectory,
            config_version=active.version,
            config=active.config,
            timing=timing,
            faults=faults,
            estop_seq=rt.estop_seq,
            notes=[
                *self.notes,
                *self.errors,
                *([f"{self.shed_queries} queries shed (flood)"] if self.shed_queries else []),
            ],
        )

    def _publish_status(self) -> None:
        period = self.opts.status_period_s
        while not self.stop_event.wait(period):
            try:
                self.status_pub.put(proto.encode(self.status()))
            except Exception as exc:
                self._warn(f"status put failed: {exc}")

    # -- queries -----------------------------------------------------------------------------

    def _serve(self, q: queue.SimpleQueue[Any], handle: Callable[[bytes], bytes]) -> None:
        while True:
            query = q.get()
            if query is _SHUTDOWN:
                return
            try:
                payload = query.payload
                data = b"" if payload is None else payload.to_bytes()
                reply = handle(data)
                query.reply(query.key_expr, reply)
            except Exception as exc:  # never let a query end the worker
                self._warn(f"query handler error: {type(exc).__name__}: {exc}")
                with contextlib.suppress(Exception):
                    query.reply_err(f"internal error: {type(exc).__name__}: {exc}".encode())
            finally:
                with contextlib.suppress(Exception):
                    query.drop()

    def _config_worker(self) -> None:
        self._serve(self.config_q, self.handle_config)

    def _command_worker(self) -> None:
        self._serve(self.command_q, self.handle_command)

    def _identify_worker(self) -> None:
        self._serve(self.identify_q, self.handle_identify)

    # -- identification ------------------------------------------------------------------------

    def handle_identify(self, data: bytes) -> bytes:
        """Any payload -> IdentifyStatus of the latest run."""
        return proto.encode(self.identify_status())

    def identify_status(self) -> proto.IdentifyStatus:
        job = self._job
        if job is None:
            return proto.IdentifyStatus(rig=self.rig_name, state="idle")
        prog = job.program
        state = job.state
        if state == "running":
            progress = prog.n_done / prog.n
            text = job.plan.label_at(prog.n_done)
        else:
            progress = 1.0 if state == "done" else prog.n_done / prog.n
            text = job.text
        fields = dict(job.results)
        fields.setdefault("positions", job.partial)  # live: the segments finished so far
        return proto.IdentifyStatus(
            rig=self.rig_name,
            state=state,
            run_id=job.run_id,
            progress=progress,
            text=text,
            abort_reason=job.abort_reason,
            **fields,
        )

    def start_identify(self, msg: proto.IdentifySpecMsg, client: str) -> proto.CommandReply:
        """Plan (here, off the loop), hand the program to the tick, watch it in a thread."""
        from controller.ident.identify import IdentifySpec, plan_program, to_program

        rt = self.rt
        with self._job_lock:
            if self._job is not None and self._job.state in ("running", "analysing"):
                return proto.CommandReply(
                    ok=False, message="an identification is already running", mode=rt.mode
                )
            try:
                spec = IdentifySpec(**msgspec.structs.asdict(msg))
                plan = plan_program(spec, rt.loop.active.config, rt.last_pos_deg)
            except ConfigError as exc:
                name = f"body.spec.{exc.field}"
                return proto.CommandReply(
                    ok=False, message=f"{name}: {exc}", mode=rt.mode, field=name
                )
            program = to_program(plan)
            ticket = rt.submit(RunProgram(program))
            if not ticket.wait(self.opts.command_timeout_s) or not ticket.ok:
                return proto.CommandReply(
                    ok=False,
                    message=ticket.message or "loop did not reach a tick boundary in time",
                    mode=rt.mode,
                    received_seq=ticket.received_seq,
                )
            run_id = (self._job.run_id if self._job is not None else 0) + 1
            job = self._job = _IdentifyJob(run_id, plan, program)
        t = threading.Thread(target=self._watch, args=(job,), name="identify-watch", daemon=True)
        t.start()
        return proto.CommandReply(
            ok=True,
            message=f"identification {run_id}: {plan.n_ticks / plan.config.rate_hz:.1f} s planned",
            mode=ticket.mode,
            seq=ticket.seq,
            received_seq=ticket.received_seq,
        )

    def _watch(self, job: _IdentifyJob) -> None:
        prog = job.program
        while not prog.over:
            if self.stop_event.wait(0.05):
                prog._abort("controller shutting down", "shutdown")  # the loop has ended
                break
            self._estimate_finished_segments(job)
        if not self.stop_event.is_set():
            self._estimate_finished_segments(job)  # those that ended with the run
        aborted = prog.state == "aborted"
        job.abort_reason = prog.reason if aborted else ""
        job.text = "analysing"
        job.state = "analysing"
        try:
            job.results = self.gate.call(
                identify_analysis,
                job.plan,
                prog.rec_u,
                prog.rec_w,
                prog.rec_pos,
                prog.n_done,
                prog.reason if aborted else None,
                time.monotonic() - job.t0,
            )
            job.text = f"aborted: {prog.reason}" if aborted else "done"
        except Exception as exc:
            self._warn(f"identification analysis failed: {type(exc).__name__}: {exc}")
            job.text = f"analysis failed: {type(exc).__name__}: {exc}"
        job.state = "aborted" if aborted else "done"

    def _estimate_finished_segments(self, job: _IdentifyJob) -> None:
        """Live results: estimate the segments that finished since the last call (in the gate's
        worker; here only slices of their ticks are cut out). Nothing when none finished."""
        from controller.ident.identify import segment_data, segments_done

        if job.partial_failed:
            return
        prog = job.program
        first = job.segments_estimated
        done = segments_done(job.plan, prog.n_done)
        if done <= first:
            return
        try:
            segs = [segment_data(job.plan, k, prog.rec_u, prog.rec_w) for k in range(first, done)]
            estimates = self.gate.call(identify_segments, segs, timeout_s=30.0)
            job.add_segments(first, estimates)
        except Exception as exc:  # the run goes on; the results come at its end
            job.partial_failed = True
            self._warn(f"identification live results failed: {type(exc).__name__}: {exc}")

    def _config_reply(self, **kw: Any) -> bytes:
        active = self.rt.loop.active
        kw.setdefault("version", active.version)
        kw.setdefault("config", active.config)
        return proto.encode(proto.ConfigReply(**kw))

    def _too_large(self, data: bytes) -> str | None:
        if len(data) > self.opts.max_payload_bytes:
            return f"payload: {len(data)} bytes is over the limit of {self.opts.max_payload_bytes}"
        return None

    def handle_config(self, data: bytes) -> bytes:
        """ConfigRequest -> ConfigReply (always a ConfigReply, also for a malformed request)."""
        big = self._too_large(data)
        if big is not None:
            return self._config_reply(accepted=False, reasons=[big], field="payload")
        if not data:
            return self._config_reply(accepted=True, margins=self.margins)
        try:
            req = proto.decode(data, proto.ConfigRequest)
        except proto.ProtocolError as exc:
            return self._config_reply(accepted=False, reasons=[str(exc)], field=exc.field)
        if req.candidate is None:
            return self._config_reply(accepted=True, margins=self.margins)
        return self.apply(req.candidate, req.client)

    def apply(self, candidate: LoopConfig, client: str) -> bytes:
        """Gate, persist, swap at a tick boundary, log; one candidate at a time."""
        with self._apply_lock:
            active = self.rt.loop.active
            if candidate.rate_hz != active.config.rate_hz:
                reason = (
                    f"candidate.rate_hz: {candidate.rate_hz} Hz differs from the running loop's "
                    f"{active.config.rate_hz} Hz; the rate changes only on restart (--rate-hz)"
                )
                return self._config_reply(
                    accepted=False, reasons=[reason], field="candidate.rate_hz"
                )
            version = active.version + 1
            same = candidate == active.config
            # The analysis and the filter design run in the gate's worker process.
            accepted, reasons, margins, coefficients = self.gate.check_and_build(
                candidate, version, build=not same
            )
            if not accepted:
                return self._config_reply(accepted=False, reasons=list(reasons), margins=margins)
            if same or coefficients is None:
                return self._config_reply(accepted=True, margins=margins)
            try:
                self.store.save(candidate, version)
            except PersistenceError as exc:
                reason = f"state_dir: not applied, the configuration could not be saved: {exc}"
                return self._config_reply(accepted=False, reasons=[reason], margins=margins)
            ticket = self.rt.submit(ApplyCoefficients(coefficients))
            if not ticket.wait(self.opts.apply_timeout_s) or not ticket.ok:
                # Saved but not (yet) swapped: only while shutting down. Report it.
                reason = f"loop: not applied at a tick boundary ({ticket.message or 'timeout'})"
                return self._config_reply(accepted=False, reasons=[reason], margins=margins)
            self._wait_version(version)
            self.margins = margins
            try:
                self.store.append_change(
                    old=active.config,
                    old_version=active.version,
                    new=candidate,
                    version=version,
                    margins=margins_dict(margins),
                    client=client,
                )
            except PersistenceError as exc:
                self._warn(str(exc))
            return self._config_reply(
                accepted=True, version=version, config=candidate, margins=margins
            )

    def _wait_version(self, version: int) -> None:
        # The loop swaps at the start of the tick that served the ticket; this returns at
        # once unless that tick is still running.
        deadline = time.monotonic() + self.opts.apply_timeout_s
        while self.rt.loop.active.version < version and time.monotonic() < deadline:
            time.sleep(0.0005)

    def handle_command(self, data: bytes) -> bytes:
        """Command -> CommandReply. An EStop engages before the payload is even validated
        further than its type."""
        rt = self.rt
        big = self._too_large(data)
        if big is not None:
            return proto.encode(
                proto.CommandReply(ok=False, message=big, mode=rt.mode, field="payload")
            )
        try:
            cmd = proto.decode(data, proto.Command)
        except proto.ProtocolError as exc:
            return proto.encode(
                proto.CommandReply(ok=False, message=str(exc), mode=rt.mode, field=exc.field)
            )
        body = cmd.body
        if isinstance(body, proto.IdentifyStart):
            return proto.encode(self.start_identify(body.spec, cmd.client))
        ticket = rt.submit(
            AbortProgram(f"aborted by {cmd.client or 'a client'}")
            if isinstance(body, proto.IdentifyAbort)
            else body
        )  # EStop: the loop's flag is set inside submit
        if not ticket.wait(self.opts.command_timeout_s):
            return proto.encode(
                proto.CommandReply(
                    ok=False,
                    message="loop did not reach a tick boundary in time",
                    mode=rt.mode,
                    received_seq=ticket.received_seq,
                )
            )
        return proto.encode(
            proto.CommandReply(
                ok=ticket.ok,
                message=ticket.message,
                mode=ticket.mode,
                seq=ticket.seq,
                received_seq=ticket.received_seq,
            )
        )


def _check_options(opts: ControllerOptions) -> None:
    if opts.plant not in ("sim", "can"):
        raise StartupError(f"--plant: expected sim or can, got {opts.plant!r}")
    try:
        proto.check_rig_name(opts.rig_name)
        for e in (*opts.listen, *opts.connect):
            check_endpoint(e)
    except ValueError as exc:
        raise StartupError(str(exc)) from exc
    if opts.rate_hz is not None and not math.isfinite(opts.rate_hz):
        raise StartupError(f"--rate-hz: must be finite, got {opts.rate_hz}")
    if not (0.01 <= opts.status_period_s <= 10.0):
        raise StartupError(f"status_period_s: {opts.status_period_s} out of range [0.01, 10]")


def run_controller(opts: ControllerOptions, *, log: TextIO | None = None) -> int:
    """Run the controller until SIGINT/SIGTERM; 0 on a clean stop, 2 if it cannot start."""
    out = log if log is not None else sys.stderr
    stopper = _Stopper()
    # Our handlers stay installed until everything is shut down: a second Ctrl-C (a terminal
    # signals the whole process group, then a launcher may signal again) never interrupts
    # the shutdown half-way.
    previous = {s: signal.signal(s, stopper.on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    runner: GateRunner | None = None
    try:
        runner = GateRunner(subprocess=opts.gate_in_subprocess)
        return _run(opts, runner, out, stopper)
    finally:
        if runner is not None:
            runner.close()
        for s, h in previous.items():
            signal.signal(s, h)


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


def _run(opts: ControllerOptions, runner: GateRunner, out: TextIO, stopper: _Stopper) -> int:
    try:
        _check_options(opts)
        state_dir = opts.state_dir if opts.state_dir is not None else Path("var") / opts.rig_name
        store = StateStore(state_dir)
        runner.command_limit_max_deg_s = _rig_command_limit(opts)
        # The first check also starts the gate's worker process, before the loop runs.
        cfg, version, margins = _initial_config(
            opts, store, runner.check, runner.command_limit_max_deg_s
        )
    except (StartupError, PersistenceError) as exc:
        print(f"dobtune controller: {exc}", file=out, flush=True)
        return 2

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
            if rig_faults:
                runtime.fault = rig_faults[0]
                runtime.mode = "fault"
            notes: list[str] = []
            with open_session(opts.listen, opts.connect) as session:
                node = _Node(opts, runtime, store, margins, notes, out, runner)
                try:
                    node.declare(session)
                    node.start_threads()
                    if opts.realtime_priority:
                        notes.append(try_realtime_priority())
                    gc.collect()
                    gc.freeze()  # what exists now is never scanned again (fewer GC pauses)
                    print(
                        f"dobtune controller: rig {opts.rig_name!r} plant {opts.plant} at "
                        f"{cfg.rate_hz:g} Hz, config v{version}, listening on "
                        f"{', '.join(opts.listen) or '-'}",
                        file=out,
                        flush=True,
                    )
                    if not stopper.event.is_set():
                        runtime.run()
                finally:
                    runtime.stop()
                    node.close()
    except StartupError as exc:
        print(f"dobtune controller: {exc}", file=out, flush=True)
        return 2
    finally:
        sys.setswitchinterval(previous_switch)
    print("dobtune controller: stopped", file=out, flush=True)
    return 0
