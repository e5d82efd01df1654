"""Cut-off autotune: the article's last tuning step (Fig. 16: which Q bandwidth is best) done by
search instead of by hand.

For each Q type, the cut-off is swept on a log grid (then refined around the best point) with
the loop's other settings fixed; every candidate is judged first by the gate on the plant
knowledge (`controller.gate.verdict.judge`: a rejected one is never run; a caution is run and
marked), then run on the nonlinear simulated plant (`controller.sim.experiment.run_experiment`,
the controller's own loop) on the chosen trajectory and disturbance: the rig's twin when the
plant knowledge holds measured responses, the built-in model only when nothing was measured
(`controller.tune.plant.plant_for`; the result names it). The score is the chosen
error metric (RMSE or peak |error|, deg) plus `noise_weight` x the RMS of the speed command
above `NOISE_BAND_HZ` (deg/s): a cut-off that buys a little error with a noisy drive is not
best. Only candidates the gate accepts count for the best (with `allow_caution`, cautions
too); cautions are run and shown, and named when they would have beaten the best. The
baseline is the same configuration with the DOB off; a DOB setting beats it only by more than
`SIGNIFICANT_REL` (a smaller difference is no difference: the result says so).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from controller.core.config import LoopConfig
from controller.core.lti import butter_sos, sosfilt
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import PlantKnowledge
from controller.gate.verdict import NonlinearCheck, judge
from controller.sim.disturbance import Disturbance
from controller.sim.experiment import ExperimentResult, run_experiment
from controller.sim.rig_disturbances import RigSetup, build_rig, rig_setup
from controller.tune.plant import BUILT_IN, SimPlant, plant_for

__all__ = ["NOISE_BAND_HZ", "SIGNIFICANT_REL", "Point", "TuneResult", "autotune",
           "command_noise_deg_s", "differs", "run_point"]

NOISE_BAND_HZ = 20.0
OBJECTIVES = ("rmse", "peak")

#: Two predicted errors (RMSE, peak or score) closer than this, relative, are no difference:
#: the prediction itself is good to about 1 % (tests/bench/bench_twin_fit.py: recorded runs
#: replayed on the rig's twin, RMSE predicted vs measured 0.6 %, 1.0 %, 0.3 % apart for DOB
#: off, Q31 0.5 Hz, Q20 3.85 Hz). The simulation's own run-to-run spread is far smaller (the
#: demo rig, default sine, 8 s runs with noise seeds 0-5: RMSE std 0.02-0.03 % of the mean):
#: the band is the prediction's, not the noise's.
SIGNIFICANT_REL = 0.01


def differs(new: float, old: float) -> int:
    """-1 if `new` is lower than `old` by more than `SIGNIFICANT_REL` of `old`, +1 if higher by
    more, 0 inside the band (no significant difference)."""
    if new < old * (1.0 - SIGNIFICANT_REL):
        return -1
    if new > old * (1.0 + SIGNIFICANT_REL):
        return 1
    return 0


@dataclass(frozen=True)
class Point:
    config: LoopConfig
    verdict: str
    rmse_deg: float = math.nan
    peak_error_deg: float = math.nan
    command_noise_deg_s: float = math.nan
    score: float = math.inf
    why: str = ""
    """The gate's first reason for a caution or a rejection ("" for an accept)."""

    @property
    def q_type(self) -> str:
        return self.config.q_type

    @property
    def q_cutoff_hz(self) -> float:
        return self.config.q_cutoff_hz


@dataclass(frozen=True)
class TuneResult:
    best: Point | None
    """The best DOB setting that counts (accepted; None: none did)."""
    baseline: Point
    """The same gains, DOB off."""
    curve: tuple[Point, ...] = field(default_factory=tuple)
    objective: str = "rmse"
    plant_source: str = BUILT_IN
    """What the runs were made on (the rig's twin, or the built-in model)."""
    counted: tuple[str, ...] = ("accept",)
    """The verdicts that may be the best (with `allow_caution`, caution too)."""

    @property
    def dob_helps(self) -> bool:
        """The best DOB setting's score is below the DOB off's by more than SIGNIFICANT_REL."""
        return self.best is not None and differs(self.best.score, self.baseline.score) < 0

    @property
    def not_counted(self) -> tuple[Point, ...]:
        """Points run but not counted (the gate's caution) that beat the DOB off and the best
        by more than SIGNIFICANT_REL: shown on the chart, named in the text."""
        bar = self.baseline.score if self.best is None else min(self.best.score,
                                                               self.baseline.score)
        return tuple(p for p in self.curve if p.verdict not in self.counted
                     and p.verdict != "reject" and differs(p.score, bar) < 0)

    def summary(self) -> str:
        return f"{self._verdict_text()}{self._not_counted_text()} (predicted on the " \
               f"{self.plant_source})"

    def _score_name(self) -> str:
        return f"{self.objective} + command-noise price"

    def _verdict_text(self) -> str:
        b = self.baseline
        band = f"{SIGNIFICANT_REL:.0%}"
        if self.best is None:
            return "no DOB setting tried is accepted by the gate: keep the DOB off"
        p = self.best
        change = p.score / b.score - 1.0
        if not self.dob_helps:
            if differs(p.score, b.score) == 0:
                return (f"no significant difference: the best accepted DOB setting, {p.q_type} "
                        f"at {p.q_cutoff_hz:.3g} Hz, scores {change:+.1%} against the DOB off "
                        f"({self._score_name()} {p.score:.4g} vs {b.score:.4g} deg), inside the "
                        f"+-{band} the prediction is good to: keep the DOB off")
            return (f"no accepted DOB setting beats the DOB off (best {p.q_type} at "
                    f"{p.q_cutoff_hz:.3g} Hz: {self._score_name()} {p.score:.4g} vs "
                    f"{b.score:.4g} deg, {change:+.1%}): keep it off for this trajectory and "
                    f"disturbance")
        return (f"best: {p.q_type} at {p.q_cutoff_hz:.3g} Hz ({p.verdict}), RMSE "
                f"{p.rmse_deg:.4g} deg, peak {p.peak_error_deg:.4g} deg; DOB off: RMSE "
                f"{b.rmse_deg:.4g} deg, peak {b.peak_error_deg:.4g} deg ({self._score_name()} "
                f"{change:+.1%}, beyond the +-{band} band)")

    def _not_counted_text(self) -> str:
        pts = self.not_counted
        if not pts:
            return ""
        p = min(pts, key=lambda q: q.score)
        why = f": {p.why}" if p.why else ""
        more = f" ({len(pts)} such settings)" if len(pts) > 1 else ""
        return (f"; {p.q_type} at {p.q_cutoff_hz:.3g} Hz would score lower ({p.score:.4g} deg, "
                f"RMSE {p.rmse_deg:.4g} deg){more} but is not counted: the gate's "
                f"{p.verdict}{why} (hollow on the chart)")


def command_noise_deg_s(command_deg_s: npt.ArrayLike, rate_hz: float) -> float:
    """RMS of the speed command above `NOISE_BAND_HZ` (2nd-order Butterworth high-pass), deg/s,
    after the first fifth of the run (the start-up transient): the DOB's price in the drive."""
    hp = sosfilt(butter_sos(2, NOISE_BAND_HZ, "highpass", rate_hz), command_deg_s)
    n0 = len(hp) // 5  # skip the start-up transient
    return float(np.sqrt(np.mean(hp[n0:] ** 2)))


def run_point(
    cfg: LoopConfig,
    trajectory: Trajectory,
    duration_s: float,
    *,
    setup: RigSetup | None = None,
    disturbance: Disturbance | None = None,
    plant: SimPlant | None = None,
) -> ExperimentResult:
    """One run as the autotune makes it: the nonlinear simulated rig (with `setup`'s named
    disturbances, noise seed 0, starting on the trajectory) and `cfg`'s loop; with `plant`,
    that plant (the rig's twin) instead. The dashboard's preview makes the same run, so its
    numbers are the search's."""
    if sum(x is not None for x in (setup, disturbance, plant)) > 1:
        raise ValueError("disturbance: give a torque profile, a rig setup or a plant, not two")
    if plant is not None:
        return run_experiment(cfg, trajectory, duration_s,
                              rig=plant.rig_on(trajectory, cfg.rate_hz),
                              disturbance_name=plant.label)
    rig = None if setup is None else build_rig(
        setup, rate_hz=cfg.rate_hz, seed=0, initial_position_deg=trajectory.at(0.0)[0])
    return run_experiment(cfg, trajectory, duration_s, disturbance=disturbance, rig=rig,
                          disturbance_name="none" if setup is None else setup.label)


def autotune(
    base: LoopConfig,
    plant: PlantKnowledge,
    trajectory: Trajectory,
    *,
    duration_s: float = 15.0,
    disturbance: Disturbance | None = None,
    setup: RigSetup | None = None,
    objective: str = "rmse",
    noise_weight: float = 0.001,
    q_types: tuple[str, ...] = ("q31", "q20"),
    lowest_hz: float = 0.1,
    highest_hz: float = 20.0,
    points: int = 10,
    refine: int = 4,
    nonlinear: NonlinearCheck | None = None,
    allow_caution: bool = False,
    progress: Callable[[float], None] | None = None,
    sim_plant: SimPlant | None = None,
) -> TuneResult:
    """Search the Q type and cut-off; see the module's docstring. `setup`: the named belt
    disturbances (`controller.sim.rig_disturbances.rig_setup`) the runs are made with, instead
    of a load-torque `disturbance`. The runs are made on `sim_plant`, default the twin of the
    rig `plant` describes when it holds measured responses (`controller.tune.plant.plant_for`,
    with `setup`'s disturbances), the built-in model when nothing was measured (or with a
    load-torque `disturbance`); the result says which."""
    if setup is not None and disturbance is not None:
        raise ValueError("disturbance: give a torque profile or a rig setup, not both")
    if sim_plant is None and disturbance is None:
        sim_plant = plant_for(plant, setup if setup is not None else rig_setup(()))
    if objective not in OBJECTIVES:
        raise ValueError(f"objective: {objective!r} is not one of {', '.join(OBJECTIVES)}")
    if not (0.0 < lowest_hz < highest_hz < base.rate_hz / 2):
        raise ValueError(f"cut-off range: need 0 < {lowest_hz} < {highest_hz} < Nyquist")
    if points < 2 or refine < 0:
        raise ValueError("points: >= 2; refine: >= 0")
    if not (math.isfinite(noise_weight) and noise_weight >= 0.0):
        raise ValueError(f"noise_weight: {noise_weight!r} must be >= 0")
    total = len(q_types) * (points + refine) + 1
    done = [0]

    def tick() -> None:
        done[0] += 1
        if progress is not None:
            progress(min(1.0, done[0] / total))

    def evaluate(cfg: LoopConfig) -> Point:
        v = judge(cfg, plant, nonlinear=nonlinear)
        verdict, why = v.verdict, (v.reasons[0] if v.reasons else "")
        if verdict == "reject":
            tick()
            return Point(cfg, verdict, why=why)
        res = (run_point(cfg, trajectory, duration_s, plant=sim_plant) if sim_plant is not None
               else run_point(cfg, trajectory, duration_s, disturbance=disturbance))
        noise = command_noise_deg_s(res.command_deg_s, cfg.rate_hz)
        err = res.rmse_deg if objective == "rmse" else res.peak_error_deg
        tick()
        return Point(cfg, verdict, res.rmse_deg, res.peak_error_deg, noise,
                     err + noise_weight * noise, why)

    counted = ("accept", "caution") if allow_caution else ("accept",)
    baseline = evaluate(base.with_(dob_on=False))
    curve: list[Point] = []
    for qt in q_types:
        grid = np.geomspace(lowest_hz, highest_hz, points)
        pts = [evaluate(base.with_(dob_on=True, q_type=qt, q_cutoff_hz=float(fc)))
               for fc in grid]
        ok = [i for i, p in enumerate(pts) if p.verdict in counted]
        if ok and refine:
            i = min(ok, key=lambda k: pts[k].score)
            lo = grid[max(i - 1, 0)]
            hi = grid[min(i + 1, len(grid) - 1)]
            for fc in np.geomspace(lo, hi, refine + 2)[1:-1]:
                pts.append(evaluate(base.with_(dob_on=True, q_type=qt, q_cutoff_hz=float(fc))))
        curve += sorted(pts, key=lambda p: p.q_cutoff_hz)
    if progress is not None:
        progress(1.0)
    runnable = [p for p in curve if p.verdict in counted]
    best = min(runnable, key=lambda p: p.score) if runnable else None
    return TuneResult(best, baseline, tuple(curve), objective,
                      sim_plant.source if sim_plant is not None else BUILT_IN, counted)
