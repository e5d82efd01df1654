"""Tune the whole loop (pure): the speed PI, the position PI, the velocity feedforward gain and
the DOB's Q type and cut-off together, for a chosen objective, on the measured plant, accepted
by the gate. It applies nothing: the result is a candidate for the gate and Apply.

The procedure, as a field engineer tunes a cascade (control.md, "Tuning the whole loop on a
measured plant"):
1. Speed and position PIs by the field's rules on every piece of evidence in the plant
   knowledge (every measured position, the model, the stated bound):
   `controller.tune.loop_design` (speed crossover as high as gain margin >= 8 dB, phase
   margin >= 45 deg and the robust figure <= 0.7 allow; position loop 4x below; integral
   corners a quarter of each crossover). Rounded to three significant figures.
   Where a measured resonance limits the speed loop (the first target the PI alone misses is
   missed near the mode), a notch at the mode or a low-pass below it on the speed command is
   designed with the PI (`controller.tune.filter_design`). Steps 3-5b then run from both
   designed loops (with and without the filter) and step 6 ranks what both found: the filter
   is kept when the tuned loop with it scores better on the plant than the tuned loop without
   it (a comparison of the designed loops alone kept a notch whose faster speed loop the gate
   then held at its sensitivity limit, while the loop without it took the position loop's
   refinement further: 0.0184 against 0.0104 deg). Otherwise the filter is off.
2. Feedforward gain: Re(1 / T_v) at the trajectory's frequency (about 1), if allowed.
3. The gate judges this loop with the DOB off (`controller.gate.verdict.judge`); should it not
   accept it (the gate's evidence is wider than the design's), both loops' gains step down by
   15 % until it does. Here and in every step below the gate's limits are the tune's
   (`tune_limits`): the peak sensitivity 0.5 dB inside the gate's 6 dB, for the twin's
   uncertainty; the gate itself judges what the tune proposes.
4. The DOB: every Q type over a log grid of cut-offs (then refined around the best), each
   judged first (only `accept` counts; a rejected one is never run), then run on the plant
   (`SimPlant`: the rig's twin when the knowledge holds measurements; the compiled offline
   loop, `controller.sim.offline`) on the objective's trajectory; the DOB off is a candidate.
   Score: the objective's error (RMSE or peak, deg) + `noise_weight` x the command noise
   (RMS above 20 Hz, deg/s); a candidate whose command noise exceeds the budget does not
   count.
5. A small local refinement by coordinate steps (each loop's gain x/÷ 1.15, each loop's
   integral gain alone x/÷ 1.3 (its corner: the field's quarter of the crossover is a start,
   not a law; a slow trajectory gains from more integral action where the margins allow it),
   the feedforward gain +- 0.03, the cut-off x/÷ 1.3), each step kept only if it meets the
   design's targets on the evidence, the gate accepts it, and it scores better; two rounds at
   most.
5b. The position loop refined below the design's phase margin (`_refine_position`): from
   the best, a line search along the position PI's gain, its integral gain alone and the
   feedforward gain, each step kept while the loop meets the targets with the position
   loop's floors (`DesignTargets.position_floor_pm_deg` 35 deg and `position_floor_gm_db`
   7 dB for the position loop and the whole servo: the gate's 30 deg and 6 dB + 5 deg and
   1 dB for the twin's uncertainty; the integral corner at most 1/`position_corner_floor` =
   1/2 of the crossover), the gate accepts it and it scores better; step 6's variants check
   then passes over a fragile one. The design's 45 deg stays the start: the family's
   gate-checked brute force found its best loops at 30-36 deg, and the design alone came
   1.13-1.45x behind them. The explanation says which margin the candidate has and why.
6. The best is judged once more with the nonlinear check (if given) and the recommended
   cut-off; if that does not accept it, the next best that does is taken. On a twin (the
   plant measured), it is also run on the twin's variants (`twin_variants`: the command delay
   a tick either way, the load inertia x/÷ 1.3, what a fitted twin gets that wrong): one that
   scores worse than `FRAGILE_RATIO` x its twin score on a variant is fragile and passed over
   for the next (the best DOB-off candidate among them), and the explanation says so.
   A DOB is kept only where it beats the same loop with the DOB off by more than
   `SIGNIFICANT_REL` (1 %, the prediction's accuracy: the rule Suggest follows).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from controller.core.command_filter import CommandFilter
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import PlantKnowledge
from controller.gate.limits import GateLimits
from controller.gate.verdict import NonlinearCheck, judge
from controller.sim.experiment import run_experiment
from controller.tune.autotune import SIGNIFICANT_REL, command_noise_deg_s, differs
from controller.tune.filter_design import (
    MIN_RAISE,
    FilterDesign,
    design_filter,
    mode_band_hz,
    mode_limits,
    plain_crossover_hz,
)
from controller.tune.loop_design import (
    DesignTargets,
    NoSpeedDesign,
    PositionDesign,
    SpeedDesign,
    design_grid,
    design_position,
    design_speed,
    evidence_of,
    feedforward_gain,
    filtered,
    first_resonance_hz,
    loop_margins,
    pi_response,
    speed_closed,
)
from controller.tune.plant import SimPlant

__all__ = ["Candidate", "Objective", "WholeLoopResult", "evaluate", "reference_lag", "tune_limits",
           "tune_whole_loop"]

OBJECTIVES = ("rmse", "peak")


def tune_limits(targets: DesignTargets) -> GateLimits:
    """The gate's limits as the tune holds its candidates to them: the peak sensitivity
    `targets.sensitivity_inside_db` inside the gate's, for the twin's uncertainty (as the
    position loop's floors add 5 deg and 1 dB to the gate's 30 deg and 6 dB). What the tune
    proposes is judged again by the gate itself."""
    gate = GateLimits()
    return replace(gate, peak_sensitivity_max_db=gate.peak_sensitivity_max_db
                   - targets.sensitivity_inside_db)


TWO_PI = 2.0 * math.pi
GAIN_STEP = 1.15
CUTOFF_STEP = 1.3
CORNER_STEP = 1.3
FF_STEP = 0.03


@dataclass(frozen=True)
class Objective:
    """What the tune optimises: `metric` of the position error on `trajectory` (run for
    `duration_s`), + `noise_weight` x the command noise; a candidate whose command noise is
    above `noise_budget_deg_s` (None: twice the designed loop's without DOB) does not count.
    `feedforward`: whether velocity feedforward may be used."""

    trajectory: Trajectory = field(default_factory=Trajectory)
    metric: str = "rmse"
    duration_s: float = 15.0
    noise_weight: float = 0.001
    noise_budget_deg_s: float | None = None
    feedforward: bool = True

    def __post_init__(self) -> None:
        if self.metric not in OBJECTIVES:
            raise ValueError(f"objective: {self.metric!r} is not one of {', '.join(OBJECTIVES)}")
        if not (math.isfinite(self.noise_weight) and self.noise_weight >= 0):
            raise ValueError(f"noise_weight: {self.noise_weight!r} must be >= 0")
        b = self.noise_budget_deg_s
        if b is not None and not (math.isfinite(b) and b > 0):
            raise ValueError(f"noise_budget_deg_s: {b!r} must be > 0")
        if not 2.5 < self.duration_s <= 600:
            raise ValueError(f"duration_s: {self.duration_s!r} must be in (2.5, 600] s")


@dataclass(frozen=True)
class Candidate:
    config: LoopConfig
    verdict: str
    rmse_deg: float = math.nan
    peak_error_deg: float = math.nan
    command_noise_deg_s: float = math.nan
    score: float = math.inf
    """The objective (inf: not run, or diverged)."""

    def error_deg(self, metric: str) -> float:
        return self.rmse_deg if metric == "rmse" else self.peak_error_deg


def evaluate(cfg: LoopConfig, plant: SimPlant, objective: Objective,
             knowledge: PlantKnowledge | None, *, nonlinear: NonlinearCheck | None = None,
             limits: GateLimits | None = None) -> Candidate:
    """Judge `cfg` on `knowledge` with `limits` (None: the gate's; `knowledge` None: not
    judged, verdict "unjudged"); run it on `plant` unless rejected. A run that diverges
    scores inf."""
    verdict = "unjudged"
    if knowledge is not None:
        verdict = judge(cfg, knowledge, limits, nonlinear=nonlinear,
                        recommendation=False).verdict
        if verdict == "reject":
            return Candidate(cfg, verdict)
    traj = objective.trajectory
    try:
        res = run_experiment(cfg, traj, objective.duration_s,
                             rig=plant.rig_on(traj, cfg.rate_hz), disturbance_name=plant.label)
    except ValueError:  # the rig refuses a non-finite command: the loop diverged
        return Candidate(cfg, verdict)
    noise = command_noise_deg_s(res.command_deg_s, cfg.rate_hz)
    err = res.rmse_deg if objective.metric == "rmse" else res.peak_error_deg
    score = err + objective.noise_weight * noise
    return Candidate(cfg, verdict, res.rmse_deg, res.peak_error_deg, noise,
                     score if math.isfinite(score) else math.inf)


def reference_lag(cfg: LoopConfig, knowledge: PlantKnowledge, trajectory: Trajectory) -> float:
    """The position error a linear loop on the knowledge's model makes following `trajectory`
    alone (no disturbance, no friction): RMS deg for a sine (A |E(j w0)| / sqrt 2), the steady
    error for a ramp (slope |E(jw)/jw| as w -> 0), 0 otherwise. E = (1 - k_ff I T_v jw) /
    (1 + I T_v Cp), I = Ts / (1 - z^-1): the reference lag the DOB cannot remove (eq. 15 =
    eq. 18)."""
    if trajectory.kind == "sine":
        f0 = trajectory.omega_rad_s / (2 * math.pi)
    elif trajectory.kind == "ramp":
        f0 = 1e-3
    else:
        return 0.0
    rate = cfg.rate_hz
    f = np.array([f0])
    ev = filtered(evidence_of(PlantKnowledge(model=knowledge.model), rate, f),
                  cfg.command_filter, f, rate)
    tv = speed_closed(ev, cfg.cv_kp, cfg.cv_ki_per_s, f, rate)[0]
    zi = np.exp(-2j * math.pi * f / rate)
    integ = (1.0 / rate) / (1.0 - zi)
    cp = pi_response(cfg.pos_kp_per_s, cfg.pos_ki_per_s, f, rate)
    kff = cfg.ff_gain if cfg.ff_on else 0.0
    e = complex(((1.0 - kff * integ * tv * 2j * math.pi * f) / (1.0 + integ * tv * cp))[0])
    if trajectory.kind == "sine":
        return abs(trajectory.amplitude_deg) * abs(e) / math.sqrt(2.0)
    return abs(trajectory.slope_deg_s) * abs(e) / (2 * math.pi * f0)


def crossovers_hz(cfg: LoopConfig, knowledge: PlantKnowledge) -> tuple[float, float]:
    """(speed loop, position loop) gain crossovers of `cfg` on the knowledge's model."""
    rate = cfg.rate_hz
    f = design_grid(rate, 800)
    ev = filtered(evidence_of(PlantKnowledge(model=knowledge.model), rate, f),
                  cfg.command_filter, f, rate)
    lv = pi_response(cfg.cv_kp, cfg.cv_ki_per_s, f, rate) * ev[0].g
    integ = (1.0 / rate) / (1.0 - np.exp(-2j * math.pi * f / rate))
    lp = pi_response(cfg.pos_kp_per_s, cfg.pos_ki_per_s, f, rate) * lv / (1.0 + lv) * integ
    return loop_margins(lv, f).crossover_hz, loop_margins(lp, f).crossover_hz


def _r3(v: float) -> float:
    return float(f"{v:.3g}")


def meets_targets(cfg: LoopConfig, knowledge: PlantKnowledge, targets: DesignTargets,
                  *, floor: bool = False) -> str | None:
    """The speed and position loops of `cfg` (DOB off) against the design's targets on every
    evidence: None if met, else what is missed. With `floor` (step 5b's refinement), the
    position loop and the whole servo need only `position_floor_pm_deg` of phase margin and
    `position_floor_gm_db` of gain margin, and the position integral corner at most
    1/`position_corner_floor` of the position loop's crossover (the speed loop keeps the
    targets)."""
    rate = cfg.rate_hz
    f = design_grid(rate, 800)
    ev = filtered(evidence_of(knowledge, rate, f), cfg.command_filter, f, rate)
    c = pi_response(cfg.cv_kp, cfg.cv_ki_per_s, f, rate)
    zi = np.exp(-2j * math.pi * f / rate)
    integ = (1.0 / rate) / (1.0 - zi)
    cp = pi_response(cfg.pos_kp_per_s, cfg.pos_ki_per_s, f, rate)
    for e in ev:
        lv = c * e.g
        t = lv / (1.0 + lv)
        loops = (("speed", loop_margins(lv, f)), ("position", loop_margins(cp * t * integ, f)),
                 ("whole servo", loop_margins(lv * (1.0 + cp * integ), f)))
        for which, m in loops:
            relaxed = floor and which != "speed"
            pm_min = targets.position_floor_pm_deg if relaxed else targets.phase_margin_deg
            gm_min = targets.position_floor_gm_db if relaxed else targets.gain_margin_db
            if not (m.gain_margin_db >= gm_min and m.phase_margin_deg >= pm_min):
                return (f"{which} loop on {e.name}: GM {m.gain_margin_db:.1f} dB, PM "
                        f"{m.phase_margin_deg:.1f} deg")
        if floor:
            ratio = TWO_PI * loops[1][1].crossover_hz / cfg.pos_ki_per_s if (
                cfg.pos_ki_per_s > 0) else math.inf
            if not ratio >= targets.position_corner_floor:
                return f"position integral corner at 1/{ratio:.2g} of the crossover on {e.name}"
        lw = lv * (1.0 + cp * integ)
        peak = max(float(np.max(e.allowance * np.abs(t))),
                   float(np.max(e.allowance * np.abs(lw / (1.0 + lw)))))
        if peak > targets.robust_peak_max:
            return f"robust figure {peak:.2f} on {e.name}"
    return None


@dataclass(frozen=True)
class WholeLoopResult:
    best: Candidate | None
    """The candidate (accepted by the gate; None: nothing the gate accepts was found)."""
    designed: Candidate
    """Steps 1-3: the PIs and feedforward, DOB off."""
    start: Candidate
    """The configuration the tune started from (`base`), as it is, on the same plant."""
    speed: SpeedDesign
    position: PositionDesign
    dob_curve: tuple[Candidate, ...]
    explanation: tuple[str, ...]
    targets: DesignTargets
    objective: Objective
    plant_source: str
    runs: int
    elapsed_s: float
    backoff_steps: int = 0
    best_dob_off: Candidate | None = None
    """The candidate's PIs and feedforward with the DOB off (what the DOB adds)."""
    filter_design: FilterDesign | None = None
    """The speed-command filter designed for a measured resonance that limits the speed loop
    (None: no such resonance, or no filter raised the crossover); `kept` says whether the
    designed loop has it."""
    filter_tried: bool = True
    """Whether the tune was to design a filter (`design_command_filter`)."""
    designed_other: Candidate | None = None
    """With `filter_design`: the designed loop (steps 1-3, DOB off) the other way (without the
    filter when it was kept, with it when not)."""
    passed_over: tuple[Candidate, ...] = ()
    """The candidates found fragile, best first: on a variant of the twin (`variants`) they
    scored worse than `FRAGILE_RATIO` x their score on the twin. The twin ranked them above the
    result, or the result is the first of them (every one checked was fragile)."""
    variants: tuple[str, ...] = ()
    """The twin's variants each candidate was also run on (none: not a twin, or not asked)."""
    unrefined: Candidate | None = None
    """The best candidate before step 5b refined the position loop toward its floor (the
    same as `best` when no refinement scored better, or `best` passed it over)."""
    beaten: Candidate | None = None
    """Set when `best` is the starting loop: the best the tune found (None: none), which
    scored worse on the plant (step 6b)."""
    other_best: Candidate | None = None
    """With `filter_design` and both designed loops accepted: the tuned best (steps 4-5b) the
    other way (without the filter when it was kept, with it when not)."""
    dob_dropped: Candidate | None = None
    """Set when step 6a turned the DOB off: the candidate with it, which scored within
    `SIGNIFICANT_REL` of `best` (the same loop without it)."""


#: A candidate is fragile when one of the twin's variants scores it worse than this times its
#: score on the twin (family rig 17 of seed 2632146472: the twin's best, q31 at 3.42 Hz on a
#: fast speed loop, scored 0.0050 on the twin and 0.022-0.026 on each variant, 0.0150 on the
#: true rig; a robust loop moves by 5-10 % on them).
FRAGILE_RATIO = 1.5
#: Step 5b: rounds over the position loop's coordinates, and steps along one at most.
POSITION_ROUNDS = 2
POSITION_STEPS = 6
#: The variants: what a twin fitted to responses gets wrong by this much on the family (the
#: same rig: the twin's delay 4 ticks against the true 3, its load inertia 25 % low).
VARIANT_DELAY_TICKS = 1
VARIANT_INERTIA = 1.3


def twin_variants(plant: SimPlant) -> list[tuple[str, SimPlant]]:
    """The twin with its command delay a tick shorter (where it has one) and longer, and its
    load inertia x and / `VARIANT_INERTIA` (named); none for the built-in model (not a twin)."""
    if not plant.measured:
        return []
    p = plant.params
    d = p.command_delay_ticks
    out = []
    for dd in (-VARIANT_DELAY_TICKS, VARIANT_DELAY_TICKS):
        if d + dd >= 0:
            out.append((f"delay {d + dd} ticks",
                        replace(plant, params=replace(p, command_delay_ticks=d + dd))))
    for s in (VARIANT_INERTIA, 1.0 / VARIANT_INERTIA):
        out.append((f"load inertia x{s:.2g}",
                    replace(plant, params=replace(p, load_inertia_kg_m2=p.load_inertia_kg_m2 * s))))
    return out


def _fragile(c: Candidate, variants: list[tuple[str, SimPlant]], objective: Objective,
             runs: list[int]) -> bool:
    """Whether a variant of the twin scores `c` worse than `FRAGILE_RATIO` x its score."""
    for _, vp in variants:
        runs[0] += 1
        if evaluate(c.config, vp, objective, None).score > FRAGILE_RATIO * c.score:
            return True
    return False


def tune_whole_loop(
    base: LoopConfig,
    knowledge: PlantKnowledge,
    plant: SimPlant,
    objective: Objective | None = None,
    targets: DesignTargets | None = None,
    *,
    q_types: tuple[str, ...] = ("q31", "q20"),
    cutoffs: int = 7,
    lowest_hz: float = 0.1,
    highest_hz: float = 20.0,
    refine_rounds: int = 2,
    refine_position: bool = True,
    design_command_filter: bool = True,
    robust: bool = True,
    nonlinear: NonlinearCheck | None = None,
    progress: Callable[[float], None] | None = None,
) -> WholeLoopResult:
    """The procedure of the module docstring; `base` gives the rate, the DOB's nominal model
    and the command limit (and is the starting point the result is compared with)."""
    t0 = time.perf_counter()
    objective = objective or Objective()
    targets = targets or DesignTargets()
    limits = tune_limits(targets)
    if not 0.0 < lowest_hz < highest_hz < base.rate_hz / 2:
        raise ValueError(f"cut-off range: need 0 < {lowest_hz} < {highest_hz} < Nyquist")
    rate = base.rate_hz
    runs = [0]
    total = 3 + len(q_types) * (cutoffs + 2) + refine_rounds * 12

    def run(cfg: LoopConfig, judged: bool = True) -> Candidate:
        runs[0] += 1
        if progress is not None:
            progress(min(0.99, runs[0] / total))
        return evaluate(cfg, plant, objective, knowledge if judged else None,
                        limits=limits)

    # 1-2: the linear design, without a filter on the speed command; then, where a measured
    # resonance limits the speed loop, with the filter designed for it (filter_design): the
    # filtered loop is kept if the gate accepts it and it scores better on the plant.
    # No speed loop that meets the targets without a filter: one with a filter may.
    placed: tuple[SpeedDesign, PositionDesign] | None = None
    alone: SpeedDesign | NoSpeedDesign
    try:
        placed = _place(knowledge, rate, targets, None)
        alone = placed[0]
    except NoSpeedDesign as exc:
        if not design_command_filter:
            raise
        alone = exc
    traj = objective.trajectory
    f0 = traj.omega_rad_s / (2 * math.pi) if traj.kind == "sine" else 1e-3

    def gated(sp: SpeedDesign, po: PositionDesign) -> tuple[Candidate, int]:
        """3: the gate on the design, DOB off; both loops' gains down 15 % a step until it
        accepts (6 steps at most)."""
        ff = feedforward_gain(knowledge, rate, sp, f0) if objective.feedforward else 1.0
        cfg0 = base.with_(cv_kp=_r3(sp.kp), cv_ki_per_s=_r3(sp.ki_per_s),
                          pos_kp_per_s=_r3(po.kp_per_s), pos_ki_per_s=_r3(po.ki_per_s),
                          ff_on=objective.feedforward, ff_gain=round(ff, 3), dob_on=False,
                          command_filter=sp.command_filter)
        steps = 0
        c = run(cfg0)
        while c.verdict != "accept" and steps < 6:
            steps += 1
            s = GAIN_STEP ** -steps
            c = run(cfg0.with_(cv_kp=_r3(cfg0.cv_kp * s), cv_ki_per_s=_r3(cfg0.cv_ki_per_s * s),
                               pos_kp_per_s=_r3(cfg0.pos_kp_per_s * s),
                               pos_ki_per_s=_r3(cfg0.pos_ki_per_s * s)))
        return c, steps

    fd = design_filter(knowledge, rate, alone, targets) if design_command_filter else None
    filtered_design: tuple[SpeedDesign, PositionDesign] | None = None
    if fd is not None:
        try:
            filtered_design = _place(knowledge, rate, targets, fd.command_filter)
        except ValueError:  # no position loop fits the filtered speed loop
            filtered_design = None
    if placed is None and filtered_design is None:
        assert isinstance(alone, NoSpeedDesign)
        raise alone
    # The designed loops, each gated (step 3): without the filter and, where one was designed,
    # with it. Steps 4-5b search from each one the gate accepts; the better tuned loop is kept,
    # so the filter is kept only where the tuned loop with it scores better than the tuned loop
    # without it (the position loop's refinement can lift a slower speed loop past a faster
    # one whose whole servo the gate then holds at its sensitivity limit).
    branches: list[tuple[Candidate, int, SpeedDesign, PositionDesign]] = []
    if placed is not None:
        branches.append((*gated(*placed), *placed))
    if fd is not None and filtered_design is not None:
        branches.append((*gated(*filtered_design), *filtered_design))
    elif fd is not None:
        fd = replace(fd, kept=False)
    # the budget comes from the loop the designed scores prefer (as before a tuned comparison)
    lead = branches[0]
    if len(branches) == 2 and branches[1][0].verdict == "accept" and (
            lead[0].verdict != "accept" or branches[1][0].score < lead[0].score):
        lead = branches[1]
    start = run(base, judged=True)
    budget = (objective.noise_budget_deg_s if objective.noise_budget_deg_s is not None
              else 2.0 * lead[0].command_noise_deg_s)

    def counts(c: Candidate) -> bool:
        return (c.verdict == "accept" and math.isfinite(c.score)
                and c.command_noise_deg_s <= budget)

    seen: dict[tuple[object, ...], Candidate] = {}

    def key(cfg: LoopConfig) -> tuple[object, ...]:
        return (cfg.cv_kp, cfg.cv_ki_per_s, cfg.pos_kp_per_s, cfg.pos_ki_per_s, cfg.ff_on,
                cfg.ff_gain, cfg.dob_on, cfg.q_type if cfg.dob_on else "",
                cfg.q_cutoff_hz if cfg.dob_on else 0.0, cfg.command_filter)

    def cached(cfg: LoopConfig) -> Candidate:
        k = key(cfg)
        if k not in seen:
            seen[k] = run(cfg)
        return seen[k]

    def search(designed: Candidate) -> tuple[list[Candidate], Candidate | None,
                                             Candidate | None]:
        """Steps 4-5b from one designed loop: the DOB's curve, the best, and the best before
        step 5b."""
        seen[key(designed.config)] = designed
        # 4: the DOB's Q type and cut-off on the plant.
        curve: list[Candidate] = []
        pi_cfg = designed.config
        if designed.verdict == "accept":
            for qt in q_types:
                grid = np.geomspace(lowest_hz, highest_hz, cutoffs)
                pts = [cached(pi_cfg.with_(dob_on=True, q_type=qt, q_cutoff_hz=_r3(float(fc))))
                       for fc in grid]
                ok = [i for i, p in enumerate(pts) if counts(p)]
                if ok:
                    i = min(ok, key=lambda k: pts[k].score)
                    lo = grid[max(i - 1, 0)]
                    hi = grid[min(i + 1, len(grid) - 1)]
                    for fc in np.geomspace(lo, hi, 4)[1:-1]:
                        pts.append(cached(pi_cfg.with_(dob_on=True, q_type=qt,
                                                       q_cutoff_hz=_r3(float(fc)))))
                curve += sorted(pts, key=lambda p: p.config.q_cutoff_hz)
        pool = [c for c in [designed, *curve] if counts(c)]
        best = min(pool, key=lambda c: c.score) if pool else None
        # 5: local refinement.
        if best is not None:
            for _ in range(refine_rounds):
                improved = False
                for cfg in _neighbours(best.config, objective.feedforward):
                    if key(cfg) in seen:
                        c = seen[key(cfg)]
                    else:
                        if meets_targets(cfg, knowledge, targets) is not None:
                            continue
                        c = cached(cfg)
                    if counts(c) and c.score < best.score:
                        best, improved = c, True
                if not improved:
                    break
        # 5b: the position loop refined below the design's phase margin, down to the floor.
        refined_from = best
        if best is not None and refine_position:
            best = _refine_position(best, knowledge, targets, objective.feedforward, cached,
                                    counts)
        return curve, best, refined_from

    searched = [(b, search(b[0])) for b in branches]
    # 6: the final verdict, with the nonlinear check and the recommendation; on a twin, the
    # candidate also run on the twin's variants (`twin_variants`): a fragile one is passed over.
    ranked = sorted((c for c in seen.values() if counts(c)), key=lambda c: c.score)
    variants = twin_variants(plant) if robust else []
    shortlist = ranked[:5] + [c for c in ranked[5:] if not c.config.dob_on][:1]
    final: Candidate | None = None
    fragile: list[Candidate] = []
    for c in shortlist:
        if judge(c.config, knowledge, limits, nonlinear=nonlinear).verdict != "accept":
            continue
        if _fragile(c, variants, objective, runs):
            fragile.append(c)
            continue
        final = c
        break
    if final is None and fragile:  # every one fragile: the twin's best, and the words say so
        final = fragile[0]
    # 6a: the DOB is kept only where it beats the same loop without it by more than the
    # prediction's accuracy (`SIGNIFICANT_REL`, the rule Suggest follows): a DOB the twin
    # ranks 0.5 % ahead is no gain, and costs command noise and a rate-disturbance waterbed.
    dob_dropped: Candidate | None = None
    if final is not None and final.config.dob_on:
        off = cached(final.config.with_(dob_on=False))
        if counts(off) and differs(final.score, off.score) >= 0 and judge(
                off.config, knowledge, limits, nonlinear=nonlinear).verdict == "accept":
            dob_dropped, final = final, off
    # 6b: never worse than where the tune started: an accepted starting loop that scores
    # better on the plant than what was found is what the tune proposes (the words say so).
    found = final
    if counts(start) and (final is None or start.score < final.score) and judge(
            start.config, knowledge, limits, nonlinear=nonlinear).verdict == "accept":
        final = start
    # the branch of what was found (ranked over both: its filter says which); none found: the
    # branch whose designed loop the scores prefer
    pick = next((i for i, s in enumerate(searched) if found is not None
                 and s[0][0].config.command_filter == found.config.command_filter),
                next(i for i, s in enumerate(searched) if s[0] is lead))
    (designed, backoff, speed, position), (curve, _, refined_from) = searched[pick]
    plain: Candidate | None = None  # the designed loop the other way
    other_best: Candidate | None = None  # and its tuned best
    if len(searched) == 2:
        plain, other_best = searched[1 - pick][0][0], searched[1 - pick][1][1]
    if fd is not None and filtered_design is not None:
        kept = designed.config.command_filter == fd.command_filter
        if kept != fd.kept:
            fd = replace(fd, kept=kept)
    same_off = cached(final.config.with_(dob_on=False)) if final is not None else None
    elapsed = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    res = WholeLoopResult(final, designed, start, speed, position, tuple(curve), (), targets,
                          objective, plant.source, runs[0], elapsed, backoff, same_off, fd,
                          design_command_filter, plain,
                          tuple(fragile),
                          tuple(name for name, _ in variants), refined_from,
                          found if final is start else None, other_best,
                          dob_dropped if final is not start else None)
    return _explained(res, knowledge)


def _refine_position(best: Candidate, knowledge: PlantKnowledge, targets: DesignTargets,
                     ff_allowed: bool, cached: Callable[[LoopConfig], Candidate],
                     counts: Callable[[Candidate], bool]) -> Candidate:
    """Step 5b: from `best`, a line search along each of the position PI's gain (kp and ki
    together, x/÷ `GAIN_STEP`), its integral gain alone (x/÷ `CORNER_STEP`) and the
    feedforward gain (+- `FF_STEP`): each step kept while it meets the targets with the
    position loop's floor (`meets_targets(floor=True)`), the gate accepts it and the twin
    scores it better; the coordinates again while any moved (`POSITION_ROUNDS` at most).
    Step 6 then checks the result on the twin's variants like any candidate."""

    def moves(cfg: LoopConfig) -> list[Callable[[LoopConfig, int], LoopConfig]]:
        out: list[Callable[[LoopConfig, int], LoopConfig]] = [
            lambda c, d: c.with_(pos_kp_per_s=_r3(c.pos_kp_per_s * GAIN_STEP ** d),
                                 pos_ki_per_s=_r3(c.pos_ki_per_s * GAIN_STEP ** d)),
            lambda c, d: c.with_(pos_ki_per_s=_r3(c.pos_ki_per_s * CORNER_STEP ** d)),
        ]
        if ff_allowed and cfg.ff_on:
            out.append(lambda c, d: c.with_(
                ff_gain=round(min(2.0, max(0.0, c.ff_gain + d * FF_STEP)), 3)))
        return out

    for _ in range(POSITION_ROUNDS):
        moved = False
        for move in moves(best.config):
            for d in (1, -1):
                went = False
                for _ in range(POSITION_STEPS):
                    cfg = move(best.config, d)
                    if cfg == best.config or meets_targets(cfg, knowledge, targets,
                                                           floor=True) is not None:
                        break
                    c = cached(cfg)
                    if not (counts(c) and c.score < best.score):
                        break
                    best, went = c, True
                moved = moved or went
                if went:
                    break  # this coordinate moved: the other way cannot be better
        if not moved:
            break
    return best


#: The speed loop's targets tightened in turn when no position loop fits it: (phase margin
#: added, gain margin added). More phase margin flattens the closed speed loop's peak; more gain
#: margin lowers the speed loop's gain where a resonance lifts the whole servo's response (a
#: mode just above the speed crossover: its gain margin is what the position loop lacks).
_TIGHTER = ((0.0, 0.0), (10.0, 0.0), (0.0, 2.0), (10.0, 2.0), (20.0, 0.0), (0.0, 4.0),
            (10.0, 4.0), (0.0, 6.0))


def _place(knowledge: PlantKnowledge, rate: float, targets: DesignTargets,
           cf: CommandFilter | None) -> tuple[SpeedDesign, PositionDesign]:
    """Steps 1-2 (with the speed-command filter `cf`, None: none). A speed loop whose closed
    response peaks can leave the position loop no placement that meets the targets: then the
    speed loop is designed again with tighter targets (`_TIGHTER`: more phase margin, more
    gain margin), the position loop always against the stated ones."""
    first: ValueError | None = None
    for dpm, dgm in _TIGHTER:
        if targets.phase_margin_deg + dpm >= 90.0:
            continue
        speed_targets = replace(targets, phase_margin_deg=targets.phase_margin_deg + dpm,
                                gain_margin_db=targets.gain_margin_db + dgm)
        try:
            speed = design_speed(knowledge, rate, speed_targets, command_filter=cf)
        except NoSpeedDesign:
            if first is None:  # the stated targets: no speed loop at all
                raise
            break  # tighter ones: none left to try
        try:
            return speed, design_position(knowledge, rate, speed, targets)
        except ValueError as exc:
            first = first or exc
    assert first is not None
    raise first


def _neighbours(cfg: LoopConfig, ff_allowed: bool) -> list[LoopConfig]:
    out = []
    for s in (GAIN_STEP, 1.0 / GAIN_STEP):
        out.append(cfg.with_(cv_kp=_r3(cfg.cv_kp * s), cv_ki_per_s=_r3(cfg.cv_ki_per_s * s)))
        out.append(cfg.with_(pos_kp_per_s=_r3(cfg.pos_kp_per_s * s),
                             pos_ki_per_s=_r3(cfg.pos_ki_per_s * s)))
    for s in (CORNER_STEP, 1.0 / CORNER_STEP):
        out.append(cfg.with_(cv_ki_per_s=_r3(cfg.cv_ki_per_s * s)))
        out.append(cfg.with_(pos_ki_per_s=_r3(cfg.pos_ki_per_s * s)))
    if ff_allowed and cfg.ff_on:
        for d in (FF_STEP, -FF_STEP):
            out.append(cfg.with_(ff_gain=round(min(2.0, max(0.0, cfg.ff_gain + d)), 3)))
    if cfg.dob_on:
        for s in (CUTOFF_STEP, 1.0 / CUTOFF_STEP):
            fc = _r3(cfg.q_cutoff_hz * s)
            if fc < cfg.rate_hz / 2:
                out.append(cfg.with_(q_cutoff_hz=fc))
    return out


def _pct(a: float, b: float) -> str:
    return f"{100.0 * (a - b) / b:+.0f} %" if b > 0 and math.isfinite(a) else "-"


def _explained(res: WholeLoopResult, knowledge: PlantKnowledge) -> WholeLoopResult:
    """The result with its explanation, in an engineer's terms."""
    obj, t, sp, po = res.objective, res.targets, res.speed, res.position
    m = obj.metric
    lines = [
        f"plant: {res.plant_source}; gate evidence: {knowledge.describe()}",
        f"targets: speed loop GM >= {t.gain_margin_db:g} dB and PM >= "
        f"{t.phase_margin_deg:g} deg on every evidence, robust figure max|a T| <= "
        f"{t.robust_peak_max:g} for the stated bound; position loop {t.position_ratio:g}x "
        f"below it; integral corners 1/{t.corner_ratio:g} (speed) and "
        f"1/{t.position_corner_ratio:g} (position) of each crossover; then the position "
        f"loop refined on the twin down to PM {t.position_floor_pm_deg:g} deg and GM "
        f"{t.position_floor_gm_db:g} dB (the gate's 30 deg and 6 dB + 5 deg and 1 dB for the "
        f"twin's uncertainty; whole servo too) and a corner at 1/{t.position_corner_floor:g}; "
        f"every candidate's peak sensitivity <= {tune_limits(t).peak_sensitivity_max_db:g} dB "
        f"(the gate's {GateLimits().peak_sensitivity_max_db:g} dB - "
        f"{t.sensitivity_inside_db:g} dB for the twin's uncertainty)",
    ]
    worst = min(sp.figures, key=lambda fg: fg.margins.phase_margin_deg)
    res_hz = first_resonance_hz(knowledge, res.designed.config.rate_hz)
    lines.append(
        f"speed loop: crosses over at {sp.crossover_hz:.3g} Hz (Cv = {sp.kp:.3g} (1 + "
        f"{sp.ki_per_s:.3g}/s), integral corner {sp.corner_hz:.3g} Hz); worst evidence "
        f"{worst.name}: GM {worst.margins.gain_margin_db:.1f} dB, PM "
        f"{worst.margins.phase_margin_deg:.1f} deg; a higher crossover is limited by: "
        f"{sp.limit}"
        + (f"; the first measured resonance is at {res_hz:.3g} Hz (crossover at "
           f"{sp.crossover_hz / res_hz:.2f} of it; the field's rule: about half)"
           if res_hz else "; the measurements show no resonance"))
    filt = _filter_line(res, m, knowledge)
    if filt:
        lines.append(filt)
    pw = min(po.figures, key=lambda fg: fg.margins.phase_margin_deg)
    lines.append(
        f"position loop: crosses over at {po.crossover_hz:.3g} Hz ({po.ratio:.2g}x below the "
        f"speed loop; Cp = {po.kp_per_s:.3g} (1 + {po.ki_per_s:.3g}/s), corner "
        f"{po.corner_hz:.3g} Hz); worst evidence {pw.name}: GM "
        f"{pw.margins.gain_margin_db:.1f} dB, PM {pw.margins.phase_margin_deg:.1f} deg; set "
        f"by: {po.limit}")
    if res.backoff_steps:
        lines.append(f"the gate did not accept the design as placed: both loops' gains stepped "
                     f"down {res.backoff_steps} x 15 %")
    st = res.start
    lag_start = reference_lag(st.config, knowledge, obj.trajectory)
    sv, sp_hz = crossovers_hz(st.config, knowledge)
    lines.append(
        f"starting loop ({_describe(st.config)}; speed loop crossing at {sv:.3g} Hz, position "
        f"loop at {sp_hz:.3g} Hz): {m} {st.error_deg(m):.4g} deg, command noise "
        f"{st.command_noise_deg_s:.3g} deg/s ({st.verdict}); its reference lag alone (linear, "
        f"model): {lag_start:.4g} deg RMS"
        + (f" = {100 * (lag_start / st.rmse_deg) ** 2:.0f} % of its mean-square error"
           if obj.trajectory.kind == "sine" and st.rmse_deg > 0 else ""))
    d = res.designed
    lines.append(
        f"designed PIs{' + feedforward' if d.config.ff_on else ''}, DOB off: {m} "
        f"{d.error_deg(m):.4g} deg ({_pct(d.error_deg(m), st.error_deg(m))} against the "
        f"starting loop), command noise {d.command_noise_deg_s:.3g} deg/s ({d.verdict})"
        + (f"; feedforward gain {d.config.ff_gain:.3g} removes the velocity path's reference "
           f"lag (linear, model: {reference_lag(d.config, knowledge, obj.trajectory):.3g} deg "
           f"RMS left)" if d.config.ff_on else ""))
    b = res.best
    if b is None:
        reasons = judge(res.designed.config, knowledge, recommendation=False).rejections
        lines.append("no candidate the gate accepts was found: nothing to propose"
                     + (f"; the gate on the designed loop: {'; '.join(reasons[:2])}"
                        if reasons else ""))
        return _with(res, lines)
    dob_runs = [c for c in res.dob_curve if c.verdict == "accept" and math.isfinite(c.score)]
    if b.config.dob_on:
        ref = res.best_dob_off or res.designed
        lines.append(
            f"DOB: {b.config.q_type} at {b.config.q_cutoff_hz:.3g} Hz: {m} "
            f"{b.error_deg(m):.4g} deg against {ref.error_deg(m):.4g} with the DOB off "
            f"({_pct(b.error_deg(m), ref.error_deg(m))}); it rejects the rate disturbance "
            f"below about half its cut-off and costs above it (the waterbed) and in command "
            f"noise: {b.command_noise_deg_s:.3g} against {ref.command_noise_deg_s:.3g} deg/s "
            f"({_pct(b.command_noise_deg_s, ref.command_noise_deg_s)})")
    elif res.dob_dropped is not None:
        d = res.dob_dropped
        lines.append(
            f"DOB off: with it ({d.config.q_type} at {d.config.q_cutoff_hz:.3g} Hz) the same loop "
            f"scores {d.score:.4g} against {b.score:.4g} without it: within "
            f"{100 * SIGNIFICANT_REL:g} % (the prediction's accuracy), no gain worth its "
            f"command noise ({d.command_noise_deg_s:.3g} against "
            f"{b.command_noise_deg_s:.3g} deg/s) and waterbed")
    else:
        best_dob = min(dob_runs, key=lambda c: c.score) if dob_runs else None
        fragile_dob = any(c.config.dob_on for c in res.passed_over)
        lines.append(
            ("DOB off: the Q settings that beat it on the twin are fragile (below)"
             if fragile_dob else
             f"DOB off: no Q setting the gate accepts beats it by more than "
             f"{100 * SIGNIFICANT_REL:g} % (the prediction's accuracy) on this plant and "
             f"trajectory")
            + (f" (best DOB: {best_dob.config.q_type} at {best_dob.config.q_cutoff_hz:.3g} Hz,"
               f" {m} {best_dob.error_deg(m):.4g} deg, noise "
               f"{best_dob.command_noise_deg_s:.3g} deg/s)" if best_dob else ""))
    if b is not res.start:
        lines.append(_position_line(res, knowledge, m))
        if res.variants:
            lines.append(_robust_line(res, m))
    else:
        found = res.beaten
        lines.append(
            "the starting loop is proposed unchanged: nothing the tune found beats it on this "
            "plant" + (f" (its best, {_describe(found.config)}: {m} {found.error_deg(m):.4g} "
                       f"deg)" if found is not None else ""))
    lines.append(
        f"candidate ({_describe(b.config)}): {m} {b.error_deg(m):.4g} deg "
        f"({_pct(b.error_deg(m), st.error_deg(m))} against the starting loop), peak "
        f"{b.peak_error_deg:.4g} deg, command noise {b.command_noise_deg_s:.3g} deg/s; "
        f"accepted by the gate; {res.runs} runs in {res.elapsed_s:.1f} s")
    return _with(res, lines)


def position_figures(cfg: LoopConfig, knowledge: PlantKnowledge) -> tuple[float, str, float]:
    """The position loop of `cfg` on its worst evidence: (phase margin deg, the evidence's
    name, crossover / integral corner there)."""
    rate = cfg.rate_hz
    f = design_grid(rate, 800)
    ev = filtered(evidence_of(knowledge, rate, f), cfg.command_filter, f, rate)
    integ = (1.0 / rate) / (1.0 - np.exp(-2j * math.pi * f / rate))
    cp = pi_response(cfg.pos_kp_per_s, cfg.pos_ki_per_s, f, rate)
    worst = (math.inf, "", math.inf)
    for t, e in zip(speed_closed(ev, cfg.cv_kp, cfg.cv_ki_per_s, f, rate), ev, strict=True):
        m = loop_margins(cp * t * integ, f)
        if m.phase_margin_deg < worst[0]:
            ratio = (TWO_PI * m.crossover_hz / cfg.pos_ki_per_s if cfg.pos_ki_per_s > 0
                     else math.inf)
            worst = (m.phase_margin_deg, e.name, ratio)
    return worst


def _position_line(res: WholeLoopResult, knowledge: PlantKnowledge, metric: str) -> str:
    """Which phase margin the candidate's position loop has, and why (step 5b)."""
    b, u, t = res.best, res.unrefined, res.targets
    assert b is not None
    if res.dob_dropped is not None:  # the refinement's result is the loop with the DOB
        b = res.dob_dropped
    pm, name, ratio = position_figures(b.config, knowledge)
    have = (f"position loop of the candidate: PM {pm:.1f} deg on {name}, integral corner at "
            f"1/{ratio:.2g} of its crossover")
    if u is None or (not res.variants and b.config == u.config):
        return f"{have} (the design's {t.phase_margin_deg:g} deg target, not refined)"
    if b.config != u.config and b.score < u.score and u.config.with_(
            pos_kp_per_s=b.config.pos_kp_per_s, pos_ki_per_s=b.config.pos_ki_per_s,
            ff_gain=b.config.ff_gain) == b.config:
        upm = position_figures(u.config, knowledge)[0]
        return (f"{have}: refined on the twin from the design's PM {upm:.1f} deg (Cp "
                f"{u.config.pos_kp_per_s:.3g} (1 + {u.config.pos_ki_per_s:.3g}/s), FF "
                f"{u.config.ff_gain:.3g}), within the floors (PM {t.position_floor_pm_deg:g} "
                f"deg, GM {t.position_floor_gm_db:g} dB: the gate's limits + the twin's "
                f"uncertainty): {metric} {u.error_deg(metric):.4g} -> "
                f"{b.error_deg(metric):.4g} deg on the twin, not fragile on its variants, "
                f"accepted by the gate on every measured position")
    return (f"{have}: no refinement within the floors (PM {t.position_floor_pm_deg:g} deg, GM "
            f"{t.position_floor_gm_db:g} dB) scored better on the twin and held on its "
            f"variants, so it stays as designed")


def _robust_line(res: WholeLoopResult, metric: str) -> str:
    """The candidate against the twin's variants, in words."""
    b = res.best
    assert b is not None
    head = (f"robustness: the twin is an estimate, so the best candidates were also run on "
            f"its variants ({', '.join(res.variants)}); a candidate scoring worse than "
            f"{FRAGILE_RATIO:g}x its twin score on one of them is fragile")
    over = [c for c in res.passed_over if c is not b]
    if b in res.passed_over:
        return (f"{head}: every candidate checked was fragile; the twin's best is proposed, "
                f"and its prediction is not to be relied on")
    if not over:
        return f"{head}: the candidate is not"
    o = over[0]
    return (f"{head}: passed over {len(over)} the twin ranked higher (the best: "
            f"{_describe(o.config)}, {metric} {o.error_deg(metric):.4g} deg on the twin)")


def _describe(c: LoopConfig) -> str:
    dob = f"{c.q_type} {c.q_cutoff_hz:.3g} Hz" if c.dob_on else "DOB off"
    ff = f"FF {c.ff_gain:.3g}" if c.ff_on else "no FF"
    cf = c.command_filter
    filt = f", {_filter_words(cf)}" if cf.kind != "off" else ""
    return (f"Cv {c.cv_kp:.3g} (1 + {c.cv_ki_per_s:.3g}/s){filt}, Cp {c.pos_kp_per_s:.3g} (1 + "
            f"{c.pos_ki_per_s:.3g}/s), {ff}, {dob}")


def _filter_words(cf: CommandFilter) -> str:
    if cf.kind == "notch":
        return (f"a notch at {cf.notch_hz:.3g} Hz, -{cf.notch_depth_db:.3g} dB, width "
                f"{cf.notch_width:.3g}")
    return f"a low-pass at {cf.lowpass_hz:.3g} Hz (damping {cf.lowpass_damping:.3g})"


def _filter_line(res: WholeLoopResult, metric: str, knowledge: PlantKnowledge) -> str:
    """The speed-command filter, in an engineer's terms."""
    fd = res.filter_design
    if fd is None:
        if not res.filter_tried:
            return "speed-command filter: off (not designed: the tune was asked for none)"
        found = mode_band_hz(knowledge)
        if found is None or not mode_limits(res.speed, found[1]):
            return "speed-command filter: off (no measured resonance limits the speed loop)"
        return (f"speed-command filter: off; the mode at {min(found[0]):.3g} Hz limits the "
                f"speed loop, but no notch or low-pass raised its crossover "
                f"{100 * (MIN_RAISE - 1):.0f} %")
    modes = sorted(fd.modes_hz)
    where = (f"{modes[0]:.3g} Hz" if modes[-1] - modes[0] < 0.005 * modes[0]
             else f"{modes[0]:.3g}-{modes[-1]:.3g} Hz")
    why = (f"the mode at {where} measured at {len(modes)} position(s) limits the speed loop "
           f"(without a filter, {fd.plain.limit})")
    words = _filter_words(fd.command_filter)
    other = res.designed_other
    alone = plain_crossover_hz(fd.plain)
    instead = (f"{alone:.3g} Hz" if alone > 0 else
               "not at all (no speed crossover meets the targets without a filter)")
    tuned = res.other_best
    if fd.kept:
        tail = (f"; designed loop, DOB off: {metric} {res.designed.error_deg(metric):.4g} deg "
                f"against {other.error_deg(metric):.4g} without it" if other else "")
        if tuned is not None and res.best is not None:
            tail += (f"; tuned: {metric} {res.best.error_deg(metric):.4g} deg against "
                     f"{tuned.error_deg(metric):.4g} without it")
        return (f"speed-command filter: {why}: {words} lets the speed loop cross at "
                f"{res.speed.crossover_hz:.3g} Hz instead of {instead}{tail}")
    if tuned is not None and res.best is not None:
        tail = (f"the loop tuned with it did not do better: {metric} "
                f"{tuned.error_deg(metric):.4g} deg against {res.best.error_deg(metric):.4g} "
                f"without it (designed, DOB off: {other.error_deg(metric):.4g} "
                f"({other.verdict}) against {res.designed.error_deg(metric):.4g})"
                if other else "")
    else:
        tail = (f"the loop with it did not do better: {metric} {other.error_deg(metric):.4g} "
                f"deg ({other.verdict}) against {res.designed.error_deg(metric):.4g} without it"
                if other else "no position loop meets the targets around it")
    return (f"speed-command filter: off; {why}; {words} would let it cross at "
            f"{fd.speed.crossover_hz:.3g} Hz instead of {instead}, but {tail}")


def _with(res: WholeLoopResult, lines: list[str]) -> WholeLoopResult:
    return replace(res, explanation=tuple(lines))
