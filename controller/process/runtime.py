"""The real-time loop: deadline scheduling, the tick, timing statistics and sample hand-off.

Scheduling: tick k is due at t0 + k T. The thread sleeps until `spin_s` before the deadline,
then spins on the clock. A tick that ends after the next deadline is an overrun; the next
tick then starts at once (late, never early). If a whole period or more was lost, the missed
deadlines are skipped (counted in `skipped_ticks`) instead of running ticks back to back to
catch up: a burst would hand the plant a train of commands it cannot follow. The simulated
plant advances one tick per executed tick (lockstep), so skipping never desynchronises it.

The tick (`_tick`) reads the rig, runs the servo loop, writes the command and stores a sample
in preallocated column buffers; no I/O, no logging, no locks, no containers created on the
steady path. Requests from other threads (`controller.process.requests`: commands, new
coefficients, identification programs; domain types, never wire messages) reach the tick
through a deque and one flag (e-stop) and are honoured at the next tick boundary. Full blocks
of `batch_size` samples (fewer when the configuration version or the mode changes, so a block
is homogeneous) go to a publisher thread through a ring of blocks; if the publisher falls
behind by the whole ring, samples are dropped and counted, and the sequence numbers show
the gap.

Modes: running (tracks the trajectory), stopped (holds the position where it stopped),
estop (speed command 0, drive disabled, until reset), fault (the rig reported lost I/O:
command 0, drive stopped, until reset). Only the tick changes the mode.
"""

from __future__ import annotations

import array
import contextlib
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from controller.core.loop import PreparedCoefficients, ServoLoop
from controller.core.ramp import Ramp
from controller.core.samples import STATE_COLUMNS
from controller.core.timing import LoopTiming
from controller.core.trajectory import Trajectory
from controller.core.watchdog import Watchdog, WatchdogLimits, WatchdogTrip
from controller.ident.program import ExcitationProgram
from controller.process.requests import (
    AbortProgram,
    ApplyCoefficients,
    DriftRig,
    DropFallback,
    EStop,
    InjectFault,
    RequestBody,
    ResetFault,
    RunProgram,
    SetTrajectory,
    Start,
    Stop,
)
from controller.process.sample_ring import BatchSink, SampleRing

__all__ = [
    "COLUMNS",
    "ESTOP",
    "FAULT",
    "RUNNING",
    "STOPPED",
    "Rig",
    "Runtime",
    "RuntimeOptions",
    "Ticket",
    "try_realtime_priority",
]

RUNNING = "running"
STOPPED = "stopped"
ESTOP = "estop"
FAULT = "fault"

COLUMNS = STATE_COLUMNS


class Rig(Protocol):
    """What the loop needs of a plant (SimRig and CanRig fit). Optional extras, used when
    present: `fault: str | None` (lost I/O), `start()` (enable the drive), `stop()` (safe
    state: zero speed, drive disabled)."""

    def read(self) -> tuple[float, float]: ...

    def step(self, command_deg_s: float) -> None: ...


@dataclass(frozen=True)
class RuntimeOptions:
    rate_hz: float = 1000.0
    spin_s: float = 0.0002
    """Sleep until this long before a deadline, then spin (absorbs the sleep's overshoot)."""
    batch_size: int = 20
    """Samples per StateBatch (20 ms at 1 kHz)."""
    ring_blocks: int = 256
    """Blocks buffered for the publisher (5 s at 1 kHz with batches of 20)."""
    timing_capacity: int = 16384
    """Ticks of period/compute history kept for statistics."""
    approach_speed_deg_s: float = 20.0
    """Start (and a new trajectory while running) moves onto the trajectory at most this fast
    (`controller.core.ramp`): no jump of the reference after a reset far from it."""
    approach_accel_deg_s2: float = 40.0
    watchdog: WatchdogLimits | None = None
    """The loop watchdog's limits (None: `WatchdogLimits()`); it is always on while the loop
    runs a configuration (not during an identification program, which has its own limits)."""
    rollback_guard_s: float = 10.0
    """A watchdog trip within this time after a rollback (the previous configuration
    misbehaves too), or with no previous configuration to go back to, is a fault."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_hz) and 1.0 <= self.rate_hz <= 20000.0):
            raise ValueError(f"rate_hz: {self.rate_hz!r} out of range [1, 20000]")
        if not (0.0 <= self.spin_s < 1.0 / self.rate_hz):
            raise ValueError(f"spin_s: {self.spin_s!r} must be in [0, period)")
        if not 1 <= self.batch_size <= 1000:
            raise ValueError(f"batch_size: {self.batch_size!r} out of range [1, 1000]")
        if not 2 <= self.ring_blocks <= 1 << 16:
            raise ValueError(f"ring_blocks: {self.ring_blocks!r} out of range [2, 65536]")
        if not 16 <= self.timing_capacity <= 1 << 22:
            raise ValueError(f"timing_capacity: {self.timing_capacity!r} out of range")
        if not (math.isfinite(self.rollback_guard_s) and 0.0 <= self.rollback_guard_s <= 3600):
            raise ValueError(f"rollback_guard_s: {self.rollback_guard_s!r} out of range [0, 3600]")
        for name in ("approach_speed_deg_s", "approach_accel_deg_s2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 < value <= 1e4):
                raise ValueError(f"{name}: {value!r} out of range (0, 1e4]")


class Ticket:
    """One request to the tick; the tick fills the result and sets `done`."""

    __slots__ = (
        "arrival", "body", "done", "field", "message", "mode", "ok", "received_seq", "seq",
    )

    def __init__(self, body: RequestBody, received_seq: int, arrival: int = -1) -> None:
        self.body = body
        self.received_seq = received_seq
        self.arrival = arrival
        """Order of arrival at the controller (`Runtime.next_arrival`), shared with e-stops."""
        self.done = threading.Event()
        self.ok = False
        self.message = ""
        self.field = ""
        """The request's field a refusal is about ("" none)."""
        self.mode = ""
        self.seq = -1

    def wait(self, timeout_s: float) -> bool:
        return self.done.wait(timeout_s)


def try_realtime_priority(priority: int = 50) -> str:
    """Ask for SCHED_FIFO for the calling thread; returns what happened (never raises)."""
    if not hasattr(os, "sched_setscheduler"):
        return "realtime priority: not supported on this platform"
    try:
        lo = os.sched_get_priority_min(os.SCHED_FIFO)
        hi = os.sched_get_priority_max(os.SCHED_FIFO)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(max(lo, min(hi, priority))))
    except (PermissionError, OSError) as exc:
        return f"realtime priority: not permitted ({exc.strerror or exc})"
    return f"realtime priority: SCHED_FIFO {priority}"


class Runtime:
    """Runs the servo loop against a rig at a fixed rate until `stop()`."""

    def __init__(
        self,
        loop: ServoLoop,
        rig: Rig,
        *,
        options: RuntimeOptions | None = None,
        trajectory: Trajectory | None = None,
        mode: str = RUNNING,
        clock: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if mode not in (RUNNING, STOPPED):
            raise ValueError(f"mode: {mode!r} must be running or stopped")
        self.options = opts = options if options is not None else RuntimeOptions()
        self.loop = loop
        self.rig = rig
        self.period_s = 1.0 / opts.rate_hz
        self._clock = clock
        self._sleep = sleep
        self._has_fault = hasattr(rig, "fault")
        self._rig_start: Callable[[], None] | None = getattr(rig, "start", None)
        self._rig_stop: Callable[[], None] | None = getattr(rig, "stop", None)
        # Trajectory: `run_trajectory` is what Start resumes; `trajectory` is what the tick
        # follows now (a hold while stopped). Trajectory time counts ticks since it was set.
        self.run_trajectory = trajectory if trajectory is not None else Trajectory()
        self.trajectory = self.run_trajectory
        self._traj_at = self.trajectory.at
        self._traj_k = 0
        self._ramp = Ramp(self.period_s, opts.approach_speed_deg_s, opts.approach_accel_deg_s2)
        self.last_ref_deg = 0.0
        self.last_ref_rate_deg_s = 0.0
        self.mode = RUNNING
        self._initial_mode = mode
        self.fault: str | None = None
        self.estop_seq = -1
        self.estop_source = ""
        # Requests from other threads. Every request and e-stop is stamped with its order of
        # arrival (`next_arrival`): a reset that arrived before an e-stop never clears it.
        self._inbox: deque[Ticket] = deque()
        self._estop_request: str | None = None
        self._fault_request: str | None = None
        self._arrival_lock = threading.Lock()
        self._last_arrival = 0
        self._arrival_local = threading.local()
        self._estop_lock = threading.Lock()
        self._estop_arrival = -1
        #: E-stops relayed by another process (`controller.process.edge`): [flag, arrival]
        #: in shared memory, set by it, read and cleared by the tick (a plain int read).
        self.estop_flag: Any = [0, 0, 0]  # estop_keys: flag, arrival, active version
        self.latch_changed = threading.Event()
        """Set whenever the mode enters or leaves estop/fault (the latch is persisted), and on
        a watchdog rollback (the configuration rolled back to is persisted)."""
        self._stop = False
        # Counters (written by the tick only).
        self.seq = -1  # sequence number of the last completed tick
        self.ticks = 0
        self.overruns = 0
        self.skipped_ticks = 0
        self.dropped_samples = 0
        self.t0 = 0.0
        self.epoch_s = 0.0  # UNIX time of t_s = 0
        self.running = threading.Event()
        self.finished = threading.Event()
        # Timing history.
        cap = opts.timing_capacity
        # C doubles: the status thread reads numpy views, not 2 x cap floats under the GIL.
        self._period_us = array.array("d", bytes(8 * cap))
        self._compute_us = array.array("d", bytes(8 * cap))
        self._period_np = np.frombuffer(self._period_us, dtype=np.float64)
        self._compute_np = np.frombuffer(self._compute_us, dtype=np.float64)
        self._ti = 0  # total timing entries written
        self._snap_i = 0
        # Sample ring.
        self._ring = SampleRing(opts.batch_size, opts.ring_blocks, len(COLUMNS), RUNNING)
        self._blk: list[list[float]] | None = None
        self._blk_n = 0
        self._blk_version = -1
        self._blk_mode = ""
        self.last_pos_deg = 0.0
        self.program: ExcitationProgram | None = None
        self._program_from = RUNNING
        """The mode a program started from: a completed one returns to it (`_end_program`)."""
        self._rig_params0: Any = None
        """The simulated rig's parameters before its first `DriftRig` (None: none yet)."""
        self._rig_mode0_hz = 0.0
        """The simulated rig's extra mode as the last `InjectFault` set it (0: none): what a
        `DriftRig.resonance_factor` multiplies."""
        # The watchdog and the configuration it rolls back to.
        self.watchdog = Watchdog(
            opts.watchdog,
            rate_hz=opts.rate_hz,
            command_limit_deg_s=loop.active.config.command_limit_deg_s,
        )
        self._wd_step = self.watchdog.step
        self._fallback: PreparedCoefficients | None = None
        self._fallback_dropped = ""
        """Why there is no fallback (`DropFallback`; "": none was dropped)."""
        self._guard_ticks = round(opts.rollback_guard_s * opts.rate_hz)
        self._rollback_seq = -(1 << 62)
        self.rollbacks = 0
        """Rollbacks done (the service persists each; `last_rollback` describes the latest)."""
        self.last_rollback: tuple[int, int, int, WatchdogTrip] | None = None
        """(seq of the first tick with the previous configuration, version from, version to,
        the trip)."""
        self.last_trip: WatchdogTrip | None = None

    # -- requests (any thread) -----------------------------------------------------------------

    def next_arrival(self) -> int:
        """A new arrival stamp (any thread; increasing): the edge stamps each request when it
        arrives, in the order the transport delivered it. The stamps are `time.monotonic_ns`
        (one clock for the whole machine: the edge process stamps its queries with it too),
        made strictly increasing within this process."""
        now = time.monotonic_ns()
        with self._arrival_lock:
            stamp = self._last_arrival = max(now, self._last_arrival + 1)
        return stamp

    @contextlib.contextmanager
    def arrival_scope(self, arrival: int) -> Iterator[None]:
        """Requests submitted by this thread inside the block carry `arrival` (the stamp the
        edge gave the query when it arrived), not the time they reach `submit`."""
        local = self._arrival_local
        previous = getattr(local, "arrival", None)
        local.arrival = arrival
        try:
            yield
        finally:
            local.arrival = previous

    def submit(self, body: RequestBody) -> Ticket:
        """Queue a request for the next tick boundary; wait on the returned ticket."""
        arrival = getattr(self._arrival_local, "arrival", None)
        if arrival is None:
            arrival = self.next_arrival()
        if isinstance(body, EStop):
            # Armed first, then stamped: received_seq is the tick during which the loop could
            # first see it (a request thread preempted between the two, as happens on a loaded
            # machine, used to stamp a tick or two earlier than the e-stop was armed).
            self.estop("command", arrival)
        ticket = Ticket(body, self.seq, arrival)
        self._inbox.append(ticket)
        return ticket

    def estop(self, source: str = "estop key", arrival: int | None = None) -> None:
        """Emergency stop from any thread: command 0 from the next tick. Never blocks on the
        loop. Requests that arrived before `arrival` (default: now) can no longer reset it."""
        with self._estop_lock:
            if arrival is None:
                arrival = self.next_arrival()
            if arrival > self._estop_arrival:
                self._estop_arrival = arrival
            self._estop_request = source

    def request_fault(self, reason: str) -> None:
        """Fault from any thread (command 0 from the next tick, until reset): for what the
        loop cannot see itself, e.g. a rollback that could not be persisted. Never blocks."""
        self._fault_request = reason

    def restore_latch(self, mode: str, reason: str) -> None:
        """Before `run()`: come back in the e-stop or fault a previous run left latched
        (persisted); only an explicit reset leaves it."""
        if mode == ESTOP:
            self.mode = ESTOP
            self.estop_source = reason
        elif mode == FAULT:
            self.mode = FAULT
            self.fault = reason
        else:
            raise ValueError(f"mode: {mode!r} is not estop or fault")

    def stop(self) -> None:
        """End `run()` after the current tick (any thread, signal handlers included)."""
        self._stop = True

    @property
    def approaching(self) -> bool:
        """True while the reference approaches the trajectory (after Start or a new
        trajectory) instead of following it."""
        return self._ramp.active

    def approach_from(self, pos_deg: float, speed_deg_s: float = 0.0) -> None:
        """Approach the trajectory from `pos_deg` (what Start does; tests, benchmarks)."""
        self._ramp.begin(pos_deg, speed_deg_s)

    @property
    def config_version(self) -> int:
        return self.loop.active.version

    # -- timing statistics (any thread) --------------------------------------------------------

    def timing_snapshot(self) -> LoopTiming:
        """Percentiles over the ticks since the previous snapshot (at most the history)."""
        end = self._ti
        cap = len(self._period_us)
        start = max(self._snap_i, end - cap, 1 if end > 1 else 0)
        self._snap_i = end
        n = end - start
        if n <= 0:
            p = c = np.zeros(1)
        else:
            idx = np.arange(start, end) % cap
            p = self._period_np[idx]
            c = self._compute_np[idx]
        pp = np.percentile(p, [50, 99])
        cp = np.percentile(c, [50, 99])
        return LoopTiming(
            period_p50_us=float(pp[0]),
            period_p99_us=float(pp[1]),
            period_max_us=float(p.max()),
            compute_p50_us=float(cp[0]),
            compute_p99_us=float(cp[1]),
            compute_max_us=float(c.max()),
            samples=max(n, 0),
            ticks=self.ticks,
            overruns=self.overruns,
            skipped_ticks=self.skipped_ticks,
            dropped_samples=self.dropped_samples,
        )

    def timing_history(self) -> tuple[np.ndarray, np.ndarray]:
        """(period_us, compute_us) of the last ticks, oldest first (benchmarks)."""
        end = self._ti
        cap = len(self._period_us)
        start = max(0, end - cap, 1 if end > 1 else 0)
        idx = np.arange(start, end) % cap
        return self._period_np[idx], self._compute_np[idx]

    # -- publisher side --------------------------------------------------------------------------

    def publisher(self, sink: BatchSink, stop: threading.Event, poll_s: float = 0.05) -> None:
        """Publisher thread body: hand every finished block to `sink`, in order, until `stop`
        is set and the loop has finished (then the last blocks are flushed).

        The loop does not wake this thread for each full block: waking a thread from the tick
        (`Event.set`, a futex wake of another CPU's thread) cost the tick that handed the block
        off ~35 us (86 against 51 us median; 1 in 20 ticks, so most of the tick's compute
        p99). This thread sleeps instead until the middle of the period after the tick that
        should fill the block (`_next_block_due`), while the loop sleeps: it neither takes
        the GIL in the middle of a tick nor is woken by it. A block cut short (a new
        configuration or mode) and the loop's end still wake it at once (`ready`)."""
        ring = self._ring
        while True:
            ring.ready.wait(self._next_block_due(poll_s))
            ring.ready.clear()
            ring.drain(sink)
            loop_done = self.finished.is_set() or not self.running.is_set()
            if stop.is_set() and loop_done and ring.consumed >= ring.produced:
                return

    def _next_block_due(self, poll_s: float) -> float:
        """Seconds until the middle of the period after the tick that completes the block
        being filled, from the loop's deadline grid (at least one period, at most `poll_s`;
        a block's time while the loop has not started). Read without a lock: a stale value
        only moves the wake by a tick."""
        period = self.period_s
        if not self.running.is_set() or self.finished.is_set():
            return min(poll_s, self._ring.batch * period)
        left = self._ring.batch - self._blk_n if self._blk is not None else self._ring.batch
        due = self.t0 + (self.seq + left + self.skipped_ticks + 0.5) * period
        return min(poll_s, max(period, due - self._clock()))

    # -- the loop ------------------------------------------------------------------------------

    def run(self, max_ticks: int | None = None) -> None:
        """Run ticks until `stop()` (or `max_ticks`); then command 0 and stop the drive."""
        clock = self._clock
        sleep = self._sleep
        period = self.period_s
        spin = self.options.spin_s
        cap = len(self._period_us)
        period_us = self._period_us
        compute_us = self._compute_us
        tick = self._tick
        self.t0 = t0 = clock()
        self.epoch_s = time.time() - (clock() - t0)
        if self.mode in (ESTOP, FAULT):
            self._safe_state()  # a latch restored from the state directory
        elif self._initial_mode == STOPPED:
            self._enter_stopped(0.0)
        self.running.set()
        next_t = t0
        prev_start = t0
        remaining_ticks = -1 if max_ticks is None else max_ticks
        try:
            while not self._stop and remaining_ticks != 0:
                remaining_ticks -= 1
                now = clock()
                wait = next_t - now
                if wait > spin:
                    sleep(wait - spin)
                while clock() < next_t:
                    pass
                start = clock()
                tick(start - t0)
                end = clock()
                i = self._ti % cap
                period_us[i] = (start - prev_start) * 1e6
                compute_us[i] = (end - start) * 1e6
                self._ti += 1
                prev_start = start
                next_t += period
                if end > next_t:
                    self.overruns += 1
                    late = end - next_t
                    if late >= period:
                        skip = int(late / period)
                        self.skipped_ticks += skip
                        next_t += skip * period
        finally:
            self._shutdown()

    def _shutdown(self) -> None:
        with contextlib.suppress(Exception):
            self.rig.step(0.0)
        if self._rig_stop is not None:
            with contextlib.suppress(Exception):
                self._rig_stop()
        self._hand_off()
        # Requests that arrived too late still get an answer.
        while self._inbox:
            t = self._inbox.popleft()
            t.ok, t.message, t.mode = False, "controller is shutting down", self.mode
            t.done.set()
        self.finished.set()
        self._ring.ready.set()

    def _tick(self, t_s: float) -> None:
        if self.estop_flag[0] or self._estop_request is not None:
            self._take_estops()
        if self._fault_request is not None:
            self._enter_fault(self._fault_request)
            self._fault_request = None
        if self._inbox:
            self._serve_requests()
        rig = self.rig
        try:
            pos, w = rig.read()
        except Exception as exc:
            self._enter_fault(f"rig read failed: {exc}")
            pos, w = self.last_pos_deg, 0.0
        if self._has_fault and self.mode != FAULT and rig.fault is not None:  # type: ignore[attr-defined]
            self._enter_fault(str(rig.fault))  # type: ignore[attr-defined]
        self.last_pos_deg = pos
        k = self._traj_k
        self._traj_k = k + 1
        ref, ref_rate = self._traj_at(k * self.period_s)
        ramp = self._ramp
        if ramp.active:
            ref = ramp.step(ref, ref_rate)
            ref_rate = ramp.speed_deg_s
        self.last_ref_deg = ref
        self.last_ref_rate_deg_s = ref_rate
        loop = self.loop
        mode = self.mode
        prog = self.program
        if prog is not None:
            if mode == RUNNING:
                u = prog.step(t_s, pos, w, loop)
                if prog.state == "aborted":
                    self._end_program(pos, done=False)
                    u = loop.tick(pos, 0.0, pos, w)
                else:
                    ref = prog.ref
                    if prog.state == "done":
                        self._end_program(pos, done=True)
            else:  # e-stop or fault (engaged at the start of this tick): command 0
                self._abort_program(f"{mode} ({self.fault or self.estop_source})", mode)
                loop.tick(pos, 0.0, pos, w)
                u = 0.0
            d_hat = loop.d_hat
        elif mode in (RUNNING, STOPPED):
            u = loop.tick(ref, ref_rate, pos, w)
            d_hat = loop.d_hat
            if self._wd_step(u, ref - pos):
                self._on_trip(u)
        else:
            # Keep coefficient swaps flowing while disabled (the states are reset on leaving).
            loop.tick(pos, 0.0, pos, w)
            u = 0.0
            d_hat = 0.0
        try:
            rig.step(u)
        except Exception as exc:
            self._enter_fault(f"rig write failed: {exc}")
            u = 0.0
        seq = self.seq + 1
        self.seq = seq
        self.ticks += 1
        r = loop.speed_ref_deg_s if prog is None else prog.r
        self._store(seq, t_s, ref, pos, w, r, u, d_hat, ref - pos)

    def _store(
        self,
        seq: int,
        t_s: float,
        ref: float,
        pos: float,
        w: float,
        r: float,
        u: float,
        d_hat: float,
        err: float,
    ) -> None:
        blk = self._blk
        version = self.loop.active.version
        mode = self.mode
        if blk is not None and (version != self._blk_version or mode != self._blk_mode):
            self._hand_off()
            blk = None
        if blk is None:
            self.estop_flag[2] = version  # estop_keys.ACTIVE_VERSION, for the edge
            ring = self._ring
            if ring.produced - ring.consumed >= ring.blocks:
                self.dropped_samples += 1
                return
            i = ring.produced % ring.blocks
            blk = self._blk = ring.cols[i]
            ring.seq0[i] = seq
            ring.version[i] = self._blk_version = version
            ring.mode[i] = self._blk_mode = mode
            self._blk_n = 0
        n = self._blk_n
        blk[0][n] = t_s
        blk[1][n] = ref
        blk[2][n] = pos
        blk[3][n] = w
        blk[4][n] = r
        blk[5][n] = u
        blk[6][n] = d_hat
        blk[7][n] = err
        n += 1
        self._blk_n = n
        if n == self._ring.batch:
            self._hand_off(wake=False)  # the publisher wakes on its own (`publisher`)

    def _hand_off(self, wake: bool = True) -> None:
        if self._blk is None:
            return
        ring = self._ring
        ring.n[ring.produced % ring.blocks] = self._blk_n
        ring.produced += 1
        self._blk = None
        if wake:
            ring.ready.set()

    # -- the rare paths (mode changes, requests): may allocate --------------------------------

    def _set_trajectory(self, traj: Trajectory) -> None:
        self.trajectory = traj
        self._traj_at = traj.at
        self._traj_k = 0

    @property
    def following(self) -> tuple[Trajectory, int, float]:
        """(the trajectory the tick follows, the sequence number of its time 0, the period):
        sample seq's reference is `trajectory.at((seq - seq0) x period)` unless the approach
        or an identification gives it. Read off the loop's thread: seq0 give or take a tick
        (`controller.process.twin_running` finds the exact one in the samples)."""
        return self.trajectory, self.seq + 1 - self._traj_k, self.period_s

    def _on_trip(self, u: float) -> None:
        """The watchdog tripped: roll back to the previous configuration (swapped at the next
        tick, bumpless), or, with none or again soon after a rollback, fault (command 0)."""
        wd = self.watchdog
        trip = wd.trip
        assert trip is not None
        self.last_trip = trip
        seq = self.seq + 1
        fallback = self._fallback
        if fallback is not None and seq - self._rollback_seq > self._guard_ticks:
            self._fallback = None
            from_version = self.loop.active.version
            self.loop.request(fallback)
            self._rollback_seq = seq + 1
            self.last_rollback = (seq + 1, from_version, fallback.coefficients.version, trip)
            self.rollbacks += 1
            wd.command_limit_deg_s = fallback.limit
            wd.reset(u)
            self.latch_changed.set()  # wakes the thread that persists it (rare path)
            return
        if fallback is None and self._fallback_dropped:
            why = self._fallback_dropped
        elif fallback is None and self.rollbacks == 0:
            why = "no previous configuration to roll back to"
        else:  # (the text names the rollback: an alarm shown after both still says it)
            last = self.last_rollback
            why = ("again after a rollback" if last is None
                   else f"again after it rolled back to v{last[2]}")
        self._enter_fault(f"watchdog: {trip.reason} ({why})")

    def _end_program(self, pos: float, done: bool) -> None:
        """The program is over. Done, started while running: back onto the trajectory the rig
        ran before (`run_trajectory`, from `pos` with the bounded approach, as Start does): an
        identification leaves the rig doing what it did. Aborted (a limit, a request), or
        started while stopped: stopped, holding `pos` (Start resumes `run_trajectory`), so the
        mode says what the rig does."""
        self.program = None
        self.loop.reset()
        self.watchdog.reset()
        if done and self._program_from == RUNNING:
            self._ramp.begin(pos)
            self._set_trajectory(self.run_trajectory)
        else:
            self._enter_stopped(pos)

    def _abort_program(self, reason: str, limit: str) -> None:
        prog = self.program
        if prog is not None:
            prog._abort(reason, limit)
            self.program = None

    def _enter_stopped(self, pos: float) -> None:
        self.mode = STOPPED
        self._ramp.cancel()
        self._set_trajectory(Trajectory(kind="hold", offset_deg=pos))

    def _safe_state(self) -> None:
        if self._rig_stop is not None:
            try:
                self._rig_stop()
            except Exception as exc:
                self.fault = self.fault or f"drive stop failed: {exc}"
        self.loop.reset()

    def _take_estops(self) -> None:
        """E-stops raised since the last look: the relayed flag (cleared before its stamp is
        read: one raised meanwhile is seen by the next look; none is lost), then a request."""
        flag = self.estop_flag
        if flag[0]:
            flag[0] = 0
            self.estop("estop key", flag[1])
        if self._estop_request is not None:
            self._enter_estop(self._estop_request)

    def _enter_estop(self, source: str) -> None:
        self._estop_request = None
        if self.mode == ESTOP:
            # Already latched: still a new e-stop. A reset acknowledges only the e-stop its
            # sender saw (`estop_seq`), so one pressed meanwhile in another session is not
            # cleared by a reset that was sent for the earlier one.
            self.estop_seq = self.seq + 1
            self.estop_source = source
            self.latch_changed.set()
            return
        self.mode = ESTOP
        self.estop_seq = self.seq + 1
        self.estop_source = source
        self._ramp.cancel()
        self._safe_state()
        self.latch_changed.set()

    def _enter_fault(self, reason: str) -> None:
        if self.mode == FAULT:
            return
        self.fault = reason
        self.latch_changed.set()
        if self.mode == ESTOP:
            return  # already safe; the fault is reported, the e-stop latch stays
        self.mode = FAULT
        self._ramp.cancel()
        self._safe_state()

    def _serve_requests(self) -> None:
        flag = self.estop_flag
        while self._inbox:
            # Raised since this tick's first look (by another process, or a thread): before
            # any request, so a request that arrived after an e-stop is served after it too.
            if flag[0] or self._estop_request is not None:
                self._take_estops()
            t = self._inbox.popleft()
            try:
                self._serve(t)
            except Exception as exc:  # a request must never end the loop
                t.ok, t.message = False, f"internal error: {exc}"
            t.mode = self.mode
            t.done.set()

    def _serve(self, t: Ticket) -> None:
        b = t.body
        next_seq = self.seq + 1
        t.seq = next_seq
        pos = self.last_pos_deg
        if isinstance(b, ApplyCoefficients):
            self.loop.request(b.prepared)  # prepared by the requesting thread
            self._fallback = b.fallback
            self._fallback_dropped = ""
            self.watchdog.command_limit_deg_s = b.prepared.limit
            self.watchdog.reset(self.loop.u_prev)
            t.ok = True
        elif isinstance(b, DropFallback):
            self._fallback = None
            self._fallback_dropped = b.reason
            t.ok = True
        elif isinstance(b, InjectFault):
            set_faults = getattr(self.rig, "set_faults", None)
            if set_faults is None:
                t.ok, t.message = False, "sim_fault: only the simulated rig takes injected faults"
            else:
                set_faults(b.faults)  # between ticks, in the tick's own thread: no race
                self._rig_mode0_hz = b.faults.resonance_hz  # what resonance_factor moves
                t.ok = True
        elif isinstance(b, DriftRig):
            self._drift_rig(t, b)
        elif isinstance(b, RunProgram):
            if self.program is not None:
                t.ok, t.message = False, "an identification is already running"
            elif self.mode not in (RUNNING, STOPPED):
                t.ok, t.message = False, f"mode is {self.mode}: send reset and start first"
            else:
                self._program_from = self.mode
                self.mode = RUNNING
                self._ramp.cancel()
                b.program.start_seq = next_seq
                self.program = b.program
                t.ok = True
        elif isinstance(b, AbortProgram):
            if self.program is None:
                t.ok, t.message = True, "no identification running"
            else:
                self._abort_program(b.reason, "request")
                self._end_program(pos, done=False)
                t.ok = True
        elif isinstance(b, EStop):
            t.ok = self.mode == ESTOP
            t.seq = self.estop_seq
            t.message = "" if t.ok else "e-stop did not engage"
        elif isinstance(b, SetTrajectory):
            self.run_trajectory = b.trajectory
            if self.program is not None:
                t.ok, t.message = True, "trajectory set; it runs after the identification"
            elif self.mode == RUNNING:
                # From the present reference onto the new trajectory: no jump.
                self._ramp.begin(self.last_ref_deg, self.last_ref_rate_deg_s)
                self._set_trajectory(b.trajectory)
            t.ok = True
            t.message = "" if self.mode == RUNNING else f"trajectory set; mode is {self.mode}"
        elif isinstance(b, Start):
            if self.mode in (ESTOP, FAULT):
                t.ok, t.message = False, f"mode is {self.mode}: send reset first"
            else:
                if self.mode != RUNNING:
                    # From the reference the loop holds now (stopped: the hold set when it
                    # stopped or was reset) onto the trajectory, bounded speed and
                    # acceleration (after a reset it may be far from it).
                    held_deg = self._traj_at(self._traj_k * self.period_s)[0]
                    self.mode = RUNNING
                    self._ramp.begin(held_deg)
                    self._set_trajectory(self.run_trajectory)
                t.ok = True
        elif isinstance(b, Stop):
            if self.program is not None:
                self._abort_program("stop command", "request")
                self.loop.reset()  # the program may have left the position loop's states
            if self.mode == RUNNING:
                self._enter_stopped(pos)
            t.ok = self.mode == STOPPED
            t.message = "" if t.ok else f"mode is {self.mode}"
        elif isinstance(b, ResetFault):
            self._reset(t, b.estop_seq, pos)
        else:
            t.ok, t.message = False, f"unknown request {type(b).__name__}"

    def _drift_rig(self, t: Ticket, b: DriftRig) -> None:
        """The simulated plant drifts (`SimRig.set_params`, between ticks in the tick's own
        thread): factors on the parameters it started with."""
        set_params = getattr(self.rig, "set_params", None)
        if set_params is None:
            t.ok, t.message = False, "sim_drift: only the simulated rig drifts on request"
            return
        if self._rig_params0 is None:
            self._rig_params0 = self.rig.params  # type: ignore[attr-defined]
        p0 = self._rig_params0
        mode0 = self._rig_mode0_hz
        if b.resonance_factor != 1.0 and mode0 <= 0.0:
            t.ok, t.field = False, "resonance_factor"
            t.message = ("resonance_factor: the simulated rig has no extra mode to move (add one "
                         "first: sim_fault resonance_hz)")
            return
        set_params(replace(
            p0, belt_stiffness_n_m_rad=p0.belt_stiffness_n_m_rad * b.belt_stiffness_factor,
            load_inertia_kg_m2=p0.load_inertia_kg_m2 * b.load_inertia_factor,
            motor_coulomb_n_m=p0.motor_coulomb_n_m * b.motor_friction_factor))
        if mode0 > 0.0:
            faults = self.rig.faults  # type: ignore[attr-defined]
            self.rig.set_faults(  # type: ignore[attr-defined]
                replace(faults, resonance_hz=mode0 * b.resonance_factor))
        t.ok = True

    def _reset(self, t: Ticket, seen: int, pos: float) -> None:
        if t.arrival < self._estop_arrival:
            # Sent before the latest e-stop (served late only because the e-stop needs no
            # queue): it must not undo it. Also when that e-stop is still pending.
            t.ok = False
            t.message = "e-stop: an e-stop arrived after this reset; send reset again"
            return
        if self.mode not in (ESTOP, FAULT):
            t.ok, t.message = True, f"nothing to reset (mode {self.mode})"
            return
        if seen != self.estop_seq:
            t.ok, t.field = False, "estop_seq"
            t.message = (
                f"estop_seq: this reset acknowledges the e-stop at seq {seen}, the latest "
                f"e-stop is at seq {self.estop_seq} ({self.estop_source}): it was not seen "
                "by the sender; look at the rig and send reset again with that estop_seq"
            )
            return
        if self._rig_start is not None:
            # Re-enabling a drive (CAN: NMT + enable state machine) blocks this tick; the
            # drive is disabled meanwhile, and the timing statistics show the pause.
            try:
                self._rig_start()
            except Exception as exc:
                self.fault = str(exc)
                self.mode = FAULT
                t.ok, t.message = False, f"drive did not enable: {exc}"
                return
        # (An e-stop requested meanwhile stays pending: the next tick honours it.)
        self.fault = None
        self.loop.reset()
        self.watchdog.reset()
        self._enter_stopped(pos)
        self.latch_changed.set()
        t.ok = True

    @property
    def ring_depth(self) -> int:
        """Blocks waiting for the publisher."""
        return self._ring.produced - self._ring.consumed
