"""An identification run offline, position by position, on a simulated rig that the caller can
pace and stop (what the dashboard's Identify panel runs in a worker thread).

One `run_identification` per measurement position on one rig (the load moves on from where the
previous position left it), so each position's response can be drawn as soon as it is measured;
the positions are then fitted together (fit, Delta, agreement, the gate's recommended cut-offs).
A pace ("x real time") slows the simulation down so a run can be watched and stopped; a stop
ends the simulation at the next 10 simulated ms, keeping the positions measured so far (the
interrupted position is dropped) as an incomplete result.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Protocol

from controller.core.config import LoopConfig
from controller.ident.engine import ProgressFn, RigLike, run_identification
from controller.ident.result import IdentifyAborted, IdentifyResult, analyse_result
from controller.ident.spec import IdentifySpec, OfflineOptions

__all__ = [
    "OfflineRun",
    "PacedRig",
    "StopFlag",
    "Stopped",
    "combine_positions",
    "run_offline",
    "sim_rig",
]

STOPPED_BY_USER = "aborted by the user"


class Stopped(Exception):
    """Raised inside the simulation at the next tick chunk after the stop flag is set."""


class StopFlag(Protocol):
    """A flag another thread sets (a `threading.Event`)."""

    def is_set(self) -> bool: ...

    def wait(self, timeout: float | None = None) -> bool: ...


class PacedRig:
    """A rig wrapper: raises `Stopped` at the next tick chunk after `stop` is set and, with
    ``pace > 0``, keeps simulated time at most `pace` x the wall time."""

    def __init__(self, rig: RigLike, rate_hz: float, stop: StopFlag, pace: float) -> None:
        self.rig = rig
        self.read = rig.read  # no extra call layer on the hot path
        self._step = rig.step
        self.stop = stop
        self.ts = 1.0 / rate_hz
        self.pace = pace
        self.ticks = 0
        self.t0 = time.monotonic()
        self.chunk = max(1, round(0.01 * rate_hz))  # stop within 10 simulated ms

    def step(self, command_deg_s: float) -> None:
        self._step(command_deg_s)
        self.ticks += 1
        if self.ticks % self.chunk == 0:
            if self.stop.is_set():
                raise Stopped(STOPPED_BY_USER)
            if self.pace > 0.0:
                ahead = self.ticks * self.ts / self.pace - (time.monotonic() - self.t0)
                if ahead > 0.0:
                    self.stop.wait(ahead)


def combine_positions(spec: IdentifySpec, cfg: LoopConfig, results: list[IdentifyResult],
                      complete: bool, reason: str | None) -> IdentifyResult:
    """One result from the per-position runs (`results` not empty), fitted together when
    complete."""
    positions = tuple(
        dataclasses.replace(p, index=k) for k, r in enumerate(results) for p in r.positions[:1]
    )
    if complete and len(results) == 1:
        return dataclasses.replace(results[0], spec=spec, positions=positions)
    base = IdentifyResult(
        spec=spec,
        config=cfg,
        excitation=results[0].excitation,
        positions=positions,
        complete=complete,
        abort_reason=reason,
        simulated_s=sum(r.simulated_s for r in results),
    )
    if not complete:
        return base
    # The positions were measured in separate runs: fit them together as one run does.
    return analyse_result(base)


@dataclasses.dataclass(frozen=True)
class OfflineRun:
    """How an offline run ended."""

    result: IdentifyResult | None
    """None when stopped before the first position was measured."""
    complete: bool
    reason: str | None = None
    """Why it is incomplete (a limit, or the user's stop)."""


def sim_rig(cfg: LoopConfig, seed: int) -> RigLike:
    """The built-in simulated rig at the loop's rate."""
    from controller.sim.sim_rig import SimRig

    return SimRig(rate_hz=cfg.rate_hz, seed=seed)


def run_offline(
    spec: IdentifySpec,
    cfg: LoopConfig,
    stop: StopFlag,
    pace: float = 0.0,
    rig_factory: Callable[[LoopConfig, int], RigLike] = sim_rig,
    progress: ProgressFn | None = None,
    on_position: Callable[[IdentifyResult], None] | None = None,
) -> OfflineRun:
    """Run `spec` position by position on one rig from `rig_factory(cfg, seed)`;
    `progress(fraction, text)` over the whole run, `on_position(result)` after each position.
    Raises `ConfigError` (naming the field) before anything moves if the spec cannot be
    planned."""
    n = spec.positions
    offline = OfflineOptions()
    rig = PacedRig(rig_factory(cfg, offline.seed), cfg.rate_hz, stop, pace)
    results: list[IdentifyResult] = []
    try:
        for k, c in enumerate(spec.centers_deg):
            one = spec.with_(positions=1, first_position_deg=c, span_deg=spec.span_deg / n)

            def one_progress(frac: float, text: str, k: int = k) -> None:
                if progress is not None:
                    progress((k + min(frac, 0.99)) / n,
                             text.replace("position 1/1", f"position {k + 1}/{n}"))

            try:
                r = run_identification(one, cfg, lambda: rig, one_progress, offline)
            except IdentifyAborted as exc:
                # a limit: keep what was measured, the position is incomplete
                results.append(exc.result)
                return OfflineRun(combine_positions(spec, cfg, results, False, exc.reason),
                                  False, exc.reason)
            results.append(r)
            if on_position is not None:
                on_position(r)
    except Stopped:
        final = combine_positions(spec, cfg, results, False, STOPPED_BY_USER) if results else None
        return OfflineRun(final, False, STOPPED_BY_USER)
    return OfflineRun(combine_positions(spec, cfg, results, True, None), True)
