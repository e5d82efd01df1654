"""Running an identification: offline against a rig object, or from the records of the
controller's program (no I/O).

`run_identification` drives a rig-like object (``read() -> (pos_deg, speed_deg_s)``,
``step(command_deg_s)``) tick by tick, exactly as the controller would, and returns the
measured responses, the second-order fit of Mn Pn, Delta per position and the gate's
recommended Q cut-offs. It never sleeps: against `SimRig` it runs faster than real time.
Inside the controller the loop executes a `controller.ident.plan.ProgramPlan`; here
`result_from_program` and, for live results, `segment_data` + `estimate_segment` turn its
records into the same results.

* Open mode: the command sent is ``u = +-v0 + x`` (no controller in the loop); the estimate is
  H1 from u to w. Closed mode: the speed loop (Cv and the DOB of `cfg`) tracks ``r = +-v0`` and
  the excitation is added after it, ``u = sat(loop.tick_speed(r, w) + x)``; the DOB is fed the
  command actually sent (``loop.u_prev = u``), as it must be, so it does not cancel the
  excitation as if it were a disturbance. The estimate is ``S_xw / S_xu``, unbiased under the
  feedback.

Limits: the excitation amplitude (``|x| <= amplitude_deg_s`` by construction; offset plus
amplitude must stay below the command limit), the position window (checked every tick, during
excitation and repositioning) and the maximum duration (checked before the start against the
plan and every tick). Offline, a limit hit stops the motor (command 0 for
`OfflineOptions.stop_s`), then holds the position with the position loop for
`OfflineOptions.hold_s`, keeps all data recorded so far (marked incomplete) and raises
`IdentifyAborted` carrying the partial result.
"""

from __future__ import annotations

import dataclasses
import math
from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from controller.core.arrays import FloatArray, IntArray
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.ident.estimate import FrdEstimate
from controller.ident.excitation import SteppedSine
from controller.ident.plan import (
    Excitation,
    ProgramPlan,
    Segment,
    check_duration,
    move_label,
    move_profile,
    plan_segments,
    planned_ticks,
    segment_label,
)
from controller.ident.result import (
    PHASE_ABORT,
    PHASE_EXCITE,
    PHASE_MOVE,
    IdentifyAborted,
    IdentifyResult,
    PositionRecord,
    RawRecord,
    analyse_result,
    continuous_equivalent,
    estimate_signals,
    position_record,
)
from controller.ident.spec import IdentifySpec, OfflineOptions

__all__ = [
    "ProgressFn",
    "RigLike",
    "SegmentData",
    "estimate_segment",
    "result_from_program",
    "run_identification",
    "segment_data",
]

ProgressFn = Callable[[float, str], None]


class RigLike(Protocol):
    """What identification needs from a rig (SimRig, CanRig, ...)."""

    def read(self) -> tuple[float, float]: ...

    def step(self, command_deg_s: float) -> None: ...


# ------------------------------------------------------------------------------- offline


class _LimitHit(Exception):
    def __init__(self, reason: str, limit: str) -> None:
        super().__init__(reason)
        self.reason = reason
        self.limit = limit


class _Recorder:
    """Per-position tick records in Python lists (cheap appends on the hot path)."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.u: list[float] = []
        self.w: list[float] = []
        self.x: list[float] = []
        self.pos: list[float] = []
        self.offset: list[float] = []
        self.phase: list[int] = []
        self.exc_index: list[int] = []

    def add(
        self,
        t: float,
        u: float,
        w: float,
        x: float,
        pos: float,
        offset: float,
        phase: int,
        exc_index: int,
    ) -> None:
        self.t.append(t)
        self.u.append(u)
        self.w.append(w)
        self.x.append(x)
        self.pos.append(pos)
        self.offset.append(offset)
        self.phase.append(phase)
        self.exc_index.append(exc_index)

    def freeze(self) -> RawRecord:
        return RawRecord(
            t_s=np.asarray(self.t, dtype=np.float64),
            u_deg_s=np.asarray(self.u, dtype=np.float64),
            w_deg_s=np.asarray(self.w, dtype=np.float64),
            x_deg_s=np.asarray(self.x, dtype=np.float64),
            pos_deg=np.asarray(self.pos, dtype=np.float64),
            offset_deg_s=np.asarray(self.offset, dtype=np.float64),
            phase=np.asarray(self.phase, dtype=np.int8),
            exc_index=np.asarray(self.exc_index, dtype=np.int64),
        )


class _Runner:
    """Drives the rig tick by tick and enforces the limits."""

    def __init__(
        self,
        spec: IdentifySpec,
        offline: OfflineOptions,
        cfg: LoopConfig,
        rig: RigLike,
        planned_ticks: int,
        progress: ProgressFn | None,
    ) -> None:
        self.spec = spec
        self.offline = offline
        self.rig = rig
        self.rate = cfg.rate_hz
        self.ts = 1.0 / cfg.rate_hz
        self.limit = cfg.command_limit_deg_s
        self.loop = ServoLoop(LoopCoefficients.build(cfg))
        self.tick = 0
        self.max_ticks = math.floor(spec.max_duration_s * cfg.rate_hz)
        self.planned = max(1, planned_ticks)
        self.progress = progress
        self.label = ""
        self.rec = _Recorder()
        self.center = 0.0
        self.window_on = False

    def report(self) -> None:
        if self.progress is not None:
            self.progress(min(0.99, self.tick / self.planned), self.label)

    def _window_check(self, pos: float) -> None:
        if abs(pos - self.center) > self.spec.window_deg:
            raise _LimitHit(
                f"position window: {pos:.3f} deg is outside {self.center:g} +- "
                f"{self.spec.window_deg:g} deg",
                "window",
            )

    def _duration_check(self) -> None:
        if self.tick >= self.max_ticks:
            raise _LimitHit(f"maximum duration {self.spec.max_duration_s:g} s reached", "duration")

    def position_phase(
        self, ref: FloatArray, ref_rate: FloatArray, phase: int = PHASE_MOVE, check: bool = True
    ) -> None:
        """Position loop following (ref, ref_rate); starts from fresh loop states."""
        self.loop.reset()
        tick = self.loop.tick
        read, step = self.rig.read, self.rig.step
        add = self.rec.add
        ts = self.ts
        n0 = self.tick
        chunk = max(1, round(self.rate))
        window = self.window_on and check
        for k, (r, rr) in enumerate(zip(ref.tolist(), ref_rate.tolist(), strict=True)):
            if check:
                self._duration_check()
            pos, w = read()
            if window:
                self._window_check(pos)
            u = tick(r, rr, pos, w)
            step(u)
            add((n0 + k) * ts, u, w, 0.0, pos, 0.0, phase, -1)
            self.tick += 1
            if k % chunk == 0:
                self.report()

    def move_to(self, target_deg: float) -> None:
        """Smooth (raised-cosine) move with the position loop, then hold for settle_s."""
        start = self.rig.read()[0]
        dist = target_deg - start
        shape, slope = move_profile(dist, self.spec, self.rate)
        self.position_phase(start + dist * shape, dist * slope)

    def excite(self, seg: Segment) -> None:
        read, step = self.rig.read, self.rig.step
        add = self.rec.add
        ts = self.ts
        lim = self.limit
        n0 = self.tick
        chunk = max(1, round(self.rate))
        loop = self.loop
        tick_speed = loop.tick_speed
        closed = self.spec.closed
        offs = seg.offset.tolist()
        xs = seg.x.tolist()
        idx = seg.exc_index.tolist()
        for k in range(len(offs)):
            self._duration_check()
            pos, w = read()
            self._window_check(pos)
            off = offs[k]
            x = xs[k]
            u = (tick_speed(off, w) if closed else off) + x
            if u > lim:
                u = lim
            elif u < -lim:
                u = -lim
            if closed:
                loop.u_prev = u  # the DOB must see the command actually sent
            step(u)
            add((n0 + k) * ts, u, w, x, pos, off, PHASE_EXCITE, idx[k])
            self.tick += 1
            if k % chunk == 0:
                self.report()

    def stop_and_hold(self) -> None:
        """Abort path: command 0, then hold where the load stopped with the position loop."""
        read, step = self.rig.read, self.rig.step
        for _ in range(round(self.offline.stop_s * self.rate)):
            pos, w = read()
            step(0.0)
            self.rec.add(self.tick * self.ts, 0.0, w, 0.0, pos, 0.0, PHASE_ABORT, -1)
            self.tick += 1
        n_hold = round(self.offline.hold_s * self.rate)
        here = read()[0]
        self.position_phase(np.full(n_hold, here), np.zeros(n_hold), phase=PHASE_ABORT, check=False)


def _default_rig(offline: OfflineOptions, cfg: LoopConfig) -> RigLike:
    from controller.sim.sim_rig import SimRig

    return SimRig(rate_hz=cfg.rate_hz, seed=offline.seed)


def run_identification(
    spec: IdentifySpec,
    cfg: LoopConfig,
    rig_factory: Callable[[], RigLike] | None = None,
    progress: ProgressFn | None = None,
    offline: OfflineOptions | None = None,
) -> IdentifyResult:
    """Measure at every position, estimate, fit, compute Delta and ask the gate.

    ``rig_factory`` builds the rig (default: the simulated rig at ``cfg.rate_hz`` with
    ``offline.seed``). ``progress(fraction, text)`` is called about once per simulated second.
    Raises `ConfigError` (naming the field) before anything moves if the spec cannot be
    planned, and `IdentifyAborted` (with the partial result) when a limit is hit.
    """
    opts = offline if offline is not None else OfflineOptions()
    exc, segments = plan_segments(spec, cfg)
    rig = rig_factory() if rig_factory is not None else _default_rig(opts, cfg)
    planned = planned_ticks(spec, segments, rig.read()[0], cfg.rate_hz)
    check_duration(spec, planned, cfg.rate_hz)
    run = _Runner(spec, opts, cfg, rig, planned, progress)
    records: list[PositionRecord] = []
    n_pos = len(spec.centers_deg)
    tol = max(0.5, 0.02 * spec.window_deg)
    abort: _LimitHit | None = None
    for i, c in enumerate(spec.centers_deg):
        run.rec = _Recorder()
        run.center = c
        done = 0
        try:
            for k, seg in enumerate(segments):
                target = c + seg.start_rel_deg
                if k == 0:  # the move between positions: no window yet
                    run.window_on = False
                    run.label = move_label(i, n_pos, c, True)
                    run.move_to(target)
                    run.window_on = True
                elif seg.reposition or abs(rig.read()[0] - target) > tol:
                    run.label = move_label(i, n_pos, c, False)
                    run.move_to(target)
                run.label = segment_label(exc, seg, i, n_pos, len(segments))
                run.excite(seg)
                done += 1
        except _LimitHit as hit:
            abort = hit
            run.label = f"aborted: {hit.reason}"
            run.stop_and_hold()
        raw = run.rec.freeze()
        n_seg = len(segments)
        records.append(position_record(exc, raw, i, c, done, n_seg, spec.closed, cfg.rate_hz))
        if abort is not None:
            break
    result = IdentifyResult.measured(spec, cfg, exc, records,
                                     None if abort is None else abort.reason,
                                     run.tick / cfg.rate_hz)
    if abort is not None:
        raise IdentifyAborted(abort.reason, abort.limit, result)
    if progress is not None:
        progress(0.99, "fitting and checking")
    result = analyse_result(result)
    if progress is not None:
        progress(1.0, "done")
    return result


# ------------------------------------------------------- from the controller's program records


def result_from_program(
    plan: ProgramPlan,
    u: Sequence[float],
    w: Sequence[float],
    pos: Sequence[float],
    n_done: int,
    abort_reason: str | None,
    analyse: bool = True,
) -> IdentifyResult:
    """Estimate (and, for a complete run, fit and check) from the records of a program.

    `u`, `w`, `pos` hold at least `n_done` executed ticks. After an abort the positions
    reached are kept, the last one incomplete; nothing is fitted.
    """
    spec, cfg, exc = plan.spec, plan.config, plan.excitation
    rate = cfg.rate_hz
    kind = plan.column("kind", n_done).copy()
    pidx = plan.column("pos_index", n_done)
    a = plan.column("a", n_done)
    bx = plan.column("b", n_done)
    exc_i = plan.column("exc_index", n_done).copy()
    t = np.arange(n_done) * (1.0 / rate)
    uu = np.array(u[:n_done], dtype=np.float64)
    ww = np.array(w[:n_done], dtype=np.float64)
    pp = np.array(pos[:n_done], dtype=np.float64)
    excite = kind == PHASE_EXCITE
    records: list[PositionRecord] = []
    n_seg = plan.n_segments
    for i, c in enumerate(spec.centers_deg):
        m = pidx == i
        if not m.any():
            break
        ends = plan.seg_end[i * n_seg : (i + 1) * n_seg]
        done = sum(1 for e in ends if e <= n_done)
        raw = RawRecord(
            t_s=t[m],
            u_deg_s=uu[m],
            w_deg_s=ww[m],
            x_deg_s=np.where(excite, bx, 0.0)[m],
            pos_deg=pp[m],
            offset_deg_s=np.where(excite, a, 0.0)[m],
            phase=kind[m],
            exc_index=exc_i[m],
        )
        records.append(position_record(exc, raw, i, c, done, n_seg, spec.closed, rate))
    result = IdentifyResult.measured(spec, cfg, exc, records, abort_reason, n_done / rate)
    if abort_reason is None and analyse:
        result = analyse_result(result)
    return result


@dataclass(frozen=True, eq=False)
class SegmentData:
    """One finished excitation segment of a program run, cut out of the records so it can be
    estimated off the loop: only this segment's excitation ticks (small to pickle).

    For a stepped sine `excitation` holds the segment's single point with indices relative to
    its first sample (and no signal); a multisine segment is the whole excitation."""

    excitation: Excitation = field(repr=False)
    closed: bool
    rate_hz: float
    position: int
    point: int
    exc_index: IntArray = field(repr=False)
    """Excitation-sample index of each excitation tick (relative, see above)."""
    u: FloatArray = field(repr=False)
    w: FloatArray = field(repr=False)
    x: FloatArray = field(repr=False)


def segment_data(
    plan: ProgramPlan, k: int, u: Sequence[float] | array[float], w: Sequence[float] | array[float]
) -> SegmentData:
    """Segment `k` (over all positions) of `plan`, from the program's records `u`, `w` (which
    must hold at least ``plan.seg_end[k]`` executed ticks). Only slices: cheap."""
    n_seg = plan.n_segments
    lo = plan.seg_end[k - 1] if k > 0 else 0
    hi = plan.seg_end[k]
    ei = plan.column("exc_index")[lo:hi]
    m = ei >= 0
    exc = plan.excitation
    base = 0
    part: Excitation = exc
    if isinstance(exc, SteppedSine):
        p = exc.points[k % n_seg]
        base = p.start
        part = SteppedSine(
            spec=exc.spec, points=(dataclasses.replace(p, start=0),), signal=np.zeros(0)
        )
    return SegmentData(
        excitation=part,
        closed=plan.spec.closed,
        rate_hz=plan.config.rate_hz,
        position=k // n_seg,
        point=k % n_seg,
        exc_index=ei[m] - base,
        u=np.asarray(u[lo:hi], dtype=np.float64)[m],
        w=np.asarray(w[lo:hi], dtype=np.float64)[m],
        x=plan.column("b")[lo:hi][m],
    )


def estimate_segment(seg: SegmentData) -> FrdEstimate:
    """The continuous-equivalent response of one finished segment: the same numbers as
    `result_from_program` gives for its frequencies (each point is estimated on its own)."""
    exc = seg.excitation
    n = exc.points[0].stop if isinstance(exc, SteppedSine) else exc.signal.size

    def aligned(v: FloatArray) -> FloatArray:
        out = np.zeros(n)
        out[seg.exc_index] = v
        return out

    x = aligned(seg.x) if seg.closed else None
    sampled = estimate_signals(exc, aligned(seg.u), aligned(seg.w), x)
    return continuous_equivalent(sampled, seg.rate_hz)
