"""Stability analysis of a candidate configuration and the apply gate (pure math, no I/O).

The loop analysed is exactly the one `controller.core.loop` runs at fs = cfg.rate_hz (Ts = 1/fs):

    w[k]  = (theta[k] - theta[k-1]) / Ts          backward difference of the load encoder
    r     = Cp(z) (theta_ref - theta) + ff        Cp = kp_pos (1 + ki_pos Ts/2 (z+1)/(z-1))
    u     = Cv(z) (r - w) - d_hat                 Cv = cv_kp (1 + cv_ki Ts/2 (z+1)/(z-1))
    d_hat = F1(z) w - F2(z) z^-1 u                F1, F2: the implemented SOS of `design_dob`

and u is held (ZOH) until the next tick. F1 and F2 are designed from the candidate's
`nominal` (the DOB's internal model); the plant G they act on is never taken from the
candidate: it comes from the plant knowledge (`PlantKnowledge`), the evidence the controller
owns. With the model, G(z) = (1 - z^-1)/Ts * ZOH{ M(s) P(s) / s } (exact, matrix exponential;
it holds the one-sample delay of a sampled loop). With C = Cv (speed loop alone) or
C_tot = Cv (1 + Cp Ts/(1 - z^-1)) (the whole servo: theta = Ts/(1 - z^-1) w exactly):

    characteristic  D = 1 - F2 z^-1 + G (C + F1)          (DOB off: 1 + G C)
    loop at u       L = G (C + F1) / (1 - F2 z^-1),   T = G (C + F1) / D
    speed loop      Gyw = G Cv / D  (eq. 15; eq. 18 without DOB),  Gdw, Gzw: eqs. 16-17
    eq. 23          E_without / E_with = D / ((1 - F2 z^-1)(1 + G Cv))   (> 1: DOB helps)

Every loop (the speed loop alone, the whole servo, the DOB's inner loop inside D) is judged on
every piece of evidence:

* the plant model: exact closed-loop eigenvalues of the whole discrete loop (plant, w and
  theta, Cp, Cv, F1, F2, the one-sample delay; PIs with a zero integral gain are plain gains),
  speed loop alone and whole servo, all strictly inside the unit circle; without measured
  responses also robust stability over the stated bound |Delta| <= |W|: D_Delta = D (1 +
  Delta T), so max |W T| < 1 is the exact test for every such plant.
* each measured response G_m (one per position): interpolated as its ratio R = G_m / G_model
  (log magnitude and unwrapped phase, linear in log f; a response equal to the model gives
  R = 1). Stability of the loop with the interpolated response by the argument principle on
  D_m, on a grid refined until the phase of D_m moves less than 20 deg between neighbours.
  Then robust stability over the allowance a(f) around it, max |a T_m| < 1:
    - at a measured point a = max(spread, MIN_ALLOWANCE);
    - between two points a = the larger point allowance + |ln R_(i+1) - ln R_i| (the
      assumption: between two points the plant departs from the interpolation by no more than
      it changes across the interval); an interval across which R changes by more than
      UNRESOLVED_CHANGE, or turns much faster than its neighbours (SHARP_TURN), holds a mode
      the points do not resolve: a = UNRESOLVED_ALLOWANCE there, and a loop with gain there
      is rejected with "measure denser"; a rejection whose peak lies in an interval whose
      allowance comes mostly from the interpolation says so and names the interval too;
    - the test is the supremum of a |T| over every interval, ends included (at a measured
      point the larger allowance of the intervals meeting there), on a grid that holds every
      measured point, every interval's middle and is refined where the loop turns fast (the
      phase of D_m moves > 20 deg between neighbours);
    - beyond the band R is held at the edge and a = the edge allowance + |W| (the plant is
      known there only within the bound; unknown without one): a loop that needs more is
      rejected with "measure up to X Hz first".
  With measured responses the model is the interpolation's reference; its own instability is
  then a caution, not the verdict.
Measured continuous responses G_c(jw) become discrete by the ZOH + backward-difference
equivalent G_c(jw) e^{-jwTs} sinc^2(w Ts/2), valid well below Nyquist (aliasing neglected).

The margin from instability, on every loop and every deciding piece of evidence: model poles
with radius < exp(-Ts / pole_time_constant_max_s) (1 - 1e-5 at 1 kHz, 100 s), the Nyquist
curve at least stability_margin_min (0.1) from -1, and for measured responses the allowance
(>= 5 % at every frequency) a disk around each measured point the loop must not reach.

Verdicts: `reject` (unstable or not proven stable on some evidence, a robust-stability
figure >= 1, or no margin from instability as above), `caution` (stable on all evidence but
a gain margin < 6 dB, a phase margin < 30 deg, peak sensitivity > 6 dB in any loop on any
evidence, conditionally stable within
6 dB of gain reduction, a robust figure >= 0.8, noise to command > 20 dB: applied only with
confirmation), `accept` otherwise. The controller adds the nonlinear check and the recommended
cut-off (`controller.gate.verdict`).
"""

from __future__ import annotations

import math
from collections.abc import Generator
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from controller.core.arrays import ComplexArray, FloatArray
from controller.core.config import LoopConfig, NominalModel
from controller.core.verdict import VerdictKind
from controller.gate.knowledge import (
    PlantKnowledge,
    readonly,
)
from controller.gate.limits import GateLimits
from controller.gate.loop_model import (
    DB_3,
    TWO_PI,
    DobFilters,
    LoopBlocks,
    closed_loop_matrix,
    default_grid,
    dob_filters,
    loop_blocks,
    loop_blocks_groups,
)
from controller.gate.margins import (
    LoopCrossings,
    Margins,
    Outputs,
    RefineTask,
    bandwidth_of,
    crossings_of,
    loop_tasks_rows,
    margins_of,
    peak_task,
    solve,
    solve_groups,
)
from controller.gate.measured_evidence import (
    BlocksMemo,
    GainMemo,
    MeasuredPasses,
    Refinement,
    controller_parts,
    measured_evidence,
    refined_winding_ok,
)
from controller.gate.measured_model import (
    UNRESOLVED_ALLOWANCE,
    UNRESOLVED_CHANGE,
    Points,
)
from controller.gate.reasons import (
    distance_reasons,
    fmt_hz,
    margin_reasons,
    on_grid,
    robust_reasons,
)
from controller.gate.results import Analysis, SourceResult

# (GateLimits, Analysis, SourceResult, UNRESOLVED_*, refined_winding_ok: imported from here
# by callers; defined in limits.py, results.py, measured_model.py, measured_evidence.py.)
__all__ = [
    "UNRESOLVED_ALLOWANCE",
    "UNRESOLVED_CHANGE",
    "Analysis",
    "GateLimits",
    "SourceResult",
    "accepted",
    "accepted_cutoffs",
    "analyse",
    "refined_winding_ok",
]


_T = TypeVar("_T")


def _concluded(part: Generator[Refinement, None, _T]) -> _T:
    """What an evidence concludes once its refinement is solved (it yields nothing more)."""
    try:
        next(part)
    except StopIteration as done:
        return done.value  # type: ignore[no-any-return]
    raise AssertionError("an evidence yields its refinement once")


# --------------------------------------------------------------------------- analyse


def analyse(
    cfg: LoopConfig,
    plant: PlantKnowledge | None = None,
    limits: GateLimits | None = None,
    freq_hz: ArrayLike | None = None,
) -> Analysis:
    """Judge a candidate on all the plant knowledge: accept, caution or reject."""
    plant = plant if plant is not None else PlantKnowledge()
    limits = limits if limits is not None else GateLimits()
    if freq_hz is None:
        f = default_grid(cfg.rate_hz)
    else:
        f = np.asarray(freq_hz, dtype=np.float64)
        if f.ndim != 1 or f.size < 8 or np.any(np.diff(f) <= 0) or f[0] <= 0:
            raise ValueError("freq_hz: need >= 8 increasing positive frequencies")
        if f[-1] >= cfg.rate_hz / 2:
            raise ValueError(f"freq_hz: must stay below Nyquist {cfg.rate_hz / 2} Hz")
    model = plant.model
    x = np.log(f)
    dob = dob_filters(cfg)
    on = cfg.dob_on
    used = dob if on else None
    bk = loop_blocks(cfg, used, f, model)
    bk_on = bk if on else loop_blocks(cfg, dob, f, model)
    g, cv = bk.g, bk.cv
    one_on = 1.0 - bk_on.f2d
    gcv = g * cv
    d_on = one_on + g * (cv + bk_on.f1)
    d_off = 1.0 + gcv
    mn = 1.0 / np.polyval(cfg.nominal.mn_den, 1j * TWO_PI * f)
    pd = g / mn
    gyw_on = gcv / d_on
    gyw_off = gcv / d_off
    one, ks, kf = controller_parts(bk, on)
    loop = g * ks / one
    loop_full = g * kf / one
    gyw = gyw_on if on else gyw_off
    rejections: list[str] = []
    cautions: list[str] = []

    # -- the plant model: exact poles, margins, the bound as allowance (decisive only
    # -- without measurements: measured responses supersede the model in their band).
    poles, max_radius = _poles(cfg, used, model)
    judged = _evidence(cfg, plant, f, x, bk, limits, max_radius, gyw, used)
    assert judged is not None  # (None only with decisive_only)
    model_concluded, measured, reasons = judged
    assert model_concluded is not None and None not in measured
    model_src, margins, margins_full, bw, crossings = model_concluded
    sources: list[SourceResult] = [model_src, *(m for m in measured if m is not None)]
    for rej, cau in reasons:
        rejections += rej
        cautions += cau

    noise_cmd_db, k_noise = _noise_to_command(g, ks, one)
    if not noise_cmd_db <= limits.noise_to_command_max_db:
        cautions.append(
            f"noise to command gain {noise_cmd_db:.1f} dB > {limits.noise_to_command_max_db:g} dB"
            f" (at {fmt_hz(float(f[k_noise]))}; plant model)"
        )

    peaks = [s.small_gain_peak for s in sources] + [s.small_gain_full_peak for s in sources]
    peaks = [p for p in peaks if math.isfinite(p)]
    with np.errstate(divide="ignore"):
        rejection = 20.0 * np.log10(np.abs(d_on / (one_on * d_off)))
    verdict: VerdictKind = "reject" if rejections else ("caution" if cautions else "accept")
    return Analysis(
        config=cfg,
        tau_s=dob.tau_s,
        freq_hz=f,
        open_loop=readonly(loop),
        open_loop_mag_db=readonly(20.0 * np.log10(np.abs(loop))),
        open_loop_phase_deg=readonly(np.degrees(np.unwrap(np.angle(loop)))),
        closed_loop=readonly(gyw),
        closed_loop_dob=readonly(gyw_on),
        closed_loop_no_dob=readonly(gyw_off),
        disturbance_dob=readonly(pd * one_on / d_on),
        disturbance_no_dob=readonly(pd / d_off),
        noise_dob=readonly(g * (cv + bk_on.f1) / d_on),
        noise_no_dob=readonly(gyw_off),
        q_mag_db=readonly(20.0 * np.log10(np.abs(bk_on.f2d))),
        rejection_db=readonly(rejection),
        margins=margins,
        bandwidth_hz=bw,
        poles=readonly(poles),
        max_pole_radius=max_radius,
        sources=tuple(sources),
        small_gain_peak=max(peaks) if peaks else math.nan,
        verdict=verdict,
        reasons=tuple(rejections + cautions),
        noise_to_command_peak_db=noise_cmd_db,
        rejections=tuple(rejections),
        cautions=tuple(cautions),
        margins_full=margins_full,
        knowledge=plant.describe(),
        open_loop_full=readonly(loop_full),
        crossings=crossings,
    )


def accepted(cfg: LoopConfig, plant: PlantKnowledge | None = None,
             limits: GateLimits | None = None) -> bool:
    """`analyse(cfg, plant, limits).accepted` (the gate's grid), computing only what can
    give a reason and stopping at the first: what the recommended cut-off's search asks of
    each cut-off (the charts, the bandwidth, the figures shown and the bound's peaks where
    measured responses decide are left out)."""
    return accepted_cutoffs(cfg, [cfg.q_cutoff_hz], plant, limits)[0]


def accepted_cutoffs(cfg: LoopConfig, cutoffs_hz: list[float],
                     plant: PlantKnowledge | None = None,
                     limits: GateLimits | None = None) -> list[bool]:
    """`accepted` of cfg with each Q cut-off in `cutoffs_hz`, the cut-offs judged together:
    the measured responses' first passes of every cut-off as rows of one array
    (`MeasuredPasses`), then one refinement for all of them, each round evaluating the loop,
    the plant model and every measured response once for every cut-off's points (only the
    DOB's filters are evaluated per cut-off). Each answer is `accepted`'s for that cut-off
    alone (every output is per frequency point)."""
    plant = plant if plant is not None else PlantKnowledge()
    limits = limits if limits is not None else GateLimits()
    f = default_grid(cfg.rate_hz)
    x = np.log(f)
    model = plant.model
    on = cfg.dob_on
    answers = [False] * len(cutoffs_hz)
    started: list[tuple[int, DobFilters | None, _Started]] = []
    gains = GainMemo(cfg, model)
    survivors: list[tuple[int, LoopConfig, DobFilters | None, LoopBlocks, float]] = []
    for i, fc in enumerate(cutoffs_hz):
        c = cfg.with_(q_cutoff_hz=fc)
        used = dob_filters(c) if on else None
        bk = loop_blocks(c, used, f, model, gains(f))
        one, ks, _ = controller_parts(bk, on)
        if not _noise_to_command(bk.g, ks, one)[0] <= limits.noise_to_command_max_db:
            continue  # a caution
        _, max_radius = _poles(c, used, model)
        if not max_radius < limits.pole_radius_limit(c.rate_hz):
            continue  # a rejection, or a caution with measured responses
        survivors.append((i, c, used, bk, max_radius))
    if survivors:
        passes = MeasuredPasses(plant, f, [(c, BlocksMemo(c, used, model, gains))
                                            for _, c, used, _, _ in survivors])
    for case, (i, c, used, bk, max_radius) in enumerate(survivors):
        st = _evidence_start(c, plant, f, x, bk, limits, max_radius, None, used,
                             decisive_only=True, batch=(passes, case))
        if st is not None:
            started.append((i, used, st))
    if not started:
        return answers
    # Every cut-off's evidence gives the same outputs of the blocks (its output functions
    # hold the evidence, the DOB switch and the keys, the same for every cut-off): the first
    # one's serve every cut-off's points.
    first = started[0][2]
    assert all(len(st.refinements) == len(first.refinements) for _, _, st in started)

    def ev(fs: list[FloatArray]) -> list[Outputs]:
        ff = np.concatenate(fs)
        b = loop_blocks_groups(cfg, [u for _, u, _ in started], fs, model)
        out = first.outputs(ff, b, Points(ff, cfg.rate_hz, model, plant.bound))
        split: list[Outputs] = []
        start = 0
        for ff in fs:
            split.append({k: v[start : start + ff.size] for k, v in out.items()})
            start += ff.size
        return split

    solve_groups([st.tasks for _, _, st in started], ev)
    for i, _, st in started:
        answers[i] = st.conclude() is not None
    return answers


def _poles(cfg: LoopConfig, used: DobFilters | None, model: NominalModel
           ) -> tuple[np.ndarray, float]:
    """The whole servo's closed-loop eigenvalues with the plant model, and the largest
    radius of them and of the speed loop's alone."""
    poles = np.linalg.eigvals(closed_loop_matrix(cfg, used, model))
    poles_speed = np.linalg.eigvals(closed_loop_matrix(cfg, used, model, position=False))
    return poles, float(max(np.max(np.abs(poles)), np.max(np.abs(poles_speed))))


def _noise_to_command(g: ComplexArray, ks: ComplexArray, one: ComplexArray
                      ) -> tuple[float, int]:
    """max |(Cv + F1) / D| in dB and where (its index on the grid)."""
    noise_cmd = np.abs(ks / (one + g * ks))
    k_noise = int(np.argmax(noise_cmd))
    return float(20.0 * np.log10(noise_cmd[k_noise])), k_noise


def _evidence(
    cfg: LoopConfig, plant: PlantKnowledge, f: FloatArray, x: FloatArray, bk: LoopBlocks,
    limits: GateLimits, max_radius: float, gyw: ComplexArray | None,
    used: DobFilters | None,
) -> tuple[ModelConclusion | None, list[SourceResult | None],
           list[tuple[list[str], list[str]]]]:
    """Every piece of evidence up to its crossings and peaks, refined together (one
    evaluation of the loop's blocks per round for all), then each concluded in turn: (the
    plant model's conclusion and each measured response's, the rejections and cautions of
    each)."""
    st = _evidence_start(cfg, plant, f, x, bk, limits, max_radius, gyw, used)
    assert st is not None  # (None only with decisive_only)
    model = plant.model

    def ev(ff: FloatArray) -> Outputs:
        b = loop_blocks(cfg, used, ff, model)  # (points asked for once)
        return st.outputs(ff, b, Points(ff, cfg.rate_hz, model, plant.bound))

    solve(st.tasks, ev)
    got = st.conclude()
    assert got is not None
    return got


class _Started:
    """Every piece of evidence up to its refinement (`_evidence_start`): the tasks to refine
    together, their outputs, then the conclusions."""

    def __init__(self, parts: list[Generator[Refinement, None, Any]],
                 refinements: list[Refinement], reasons: list[tuple[list[str], list[str]]],
                 decisive_only: bool) -> None:
        self.parts, self.refinements, self.reasons = parts, refinements, reasons
        self.decisive_only = decisive_only
        self.tasks = [t for tasks, _ in refinements for t in tasks]

    def outputs(self, ff: FloatArray, b: LoopBlocks, pts: Points) -> Outputs:
        """Every evidence's outputs at `ff` (the blocks `b` and `pts` there)."""
        out: Outputs = {}
        for _, outputs in self.refinements:
            out.update(outputs(ff, b, pts))
        return out

    def conclude(self) -> tuple[ModelConclusion | None, list[SourceResult | None],
                                list[tuple[list[str], list[str]]]] | None:
        """Once the tasks are refined: (the plant model's conclusion and each measured
        response's, the rejections and cautions of each); with `decisive_only`, None on any
        reason."""
        model_part, *measured_parts = self.parts
        model_concluded = _concluded(model_part)
        measured = [_concluded(p) for p in measured_parts]
        if self.decisive_only and any(rej or cau for rej, cau in self.reasons):
            return None
        return model_concluded, measured, self.reasons


def _evidence_start(
    cfg: LoopConfig, plant: PlantKnowledge, f: FloatArray, x: FloatArray, bk: LoopBlocks,
    limits: GateLimits, max_radius: float, gyw: ComplexArray | None, used: DobFilters | None,
    *, decisive_only: bool = False, batch: tuple[MeasuredPasses, int] | None = None,
) -> _Started | None:
    """Every piece of evidence up to its refinement (with `decisive_only`, None at the first
    reason: the candidate is not accepted; `batch`: the measured responses' first passes,
    shared with other cut-offs, and this candidate's place among them)."""
    on = cfg.dob_on
    if batch is None:
        batch = (MeasuredPasses(plant, f, [(cfg, BlocksMemo(cfg, used, plant.model))]), 0)
    passes, case = batch
    reasons: list[tuple[list[str], list[str]]] = [([], []) for _ in range(len(plant.measured) + 1)]
    model_part = _model_evidence(
        cfg, plant, f, x, bk, limits, max_radius, on, gyw, *reasons[0], decisive_only)
    measured_parts = [
        measured_evidence(cfg, passes, case, i, f, limits, *reasons[i + 1], decisive_only)
        for i in range(len(passes.mms))
    ]
    parts: list[Generator[Refinement, None, Any]] = [model_part, *measured_parts]
    refinements: list[Refinement] = []
    for part, (rej, cau) in zip(parts, reasons, strict=True):
        try:
            refinements.append(next(part))
        except StopIteration:
            if not decisive_only:
                raise
            return None  # (it stopped at a rejection)
        if decisive_only and (rej or cau):
            return None
    return _Started(parts, refinements, reasons, decisive_only)


ModelConclusion = tuple[SourceResult, Margins, Margins, float, LoopCrossings]


def _model_evidence(
    cfg: LoopConfig, plant: PlantKnowledge, f: FloatArray, x: FloatArray,
    bk: LoopBlocks, limits: GateLimits, max_radius: float, on: bool, gyw: ComplexArray | None,
    rejections: list[str], cautions: list[str], decisive_only: bool = False,
) -> Generator[Refinement, None, ModelConclusion | None]:
    """The plant model's evidence (`decisive_only`: only what can give a reason, None for
    the conclusion; `gyw` None: no bandwidth)."""
    bound = plant.bound
    has_measured = bool(plant.measured)
    one, ks, kf = controller_parts(bk, on)
    g = bk.g

    with_bound = bound is not None and not (decisive_only and has_measured)  # (else display)

    def ev(ff: FloatArray, b: LoopBlocks, pts: Points) -> Outputs:
        o, s_, f_ = controller_parts(b, on)
        out = {"L": b.g * s_ / o, "Lf": b.g * f_ / o}
        if gyw is not None:
            out["gyw"] = b.g * b.cv / (o + b.g * s_)
        if with_bound:
            w = pts.bound_magnitude
            out["wts"] = w * b.g * s_ / (o + b.g * s_)
            out["wtf"] = w * b.g * f_ / (o + b.g * f_)
        return out

    lt, ltf = loop_tasks_rows(x, g * np.stack([ks, kf]) / one, ["L", "Lf"])
    tasks = lt.all() + ltf.all()
    below = np.nonzero(np.abs(gyw) < DB_3)[0] if gyw is not None else np.zeros(0, dtype=int)
    bw_task = None
    if below.size and below[0] > 0:
        i = int(below[0])
        bw_task = RefineTask("gyw", 0, bandwidth_of, float(x[i - 1]), float(x[i]))
        tasks.append(bw_task)
    bound_tasks: list[RefineTask] = []
    t_speed = g * ks / (one + g * ks)
    t_full = g * kf / (one + g * kf)
    if with_bound:
        assert bound is not None
        wmag = bound.magnitude(f)
        bound_tasks = [
            peak_task(x, wmag * np.abs(t_speed), "wts"),
            peak_task(x, wmag * np.abs(t_full), "wtf"),
        ]
        tasks += bound_tasks
    yield tasks, ev
    margins, margins_full = margins_of(lt), margins_of(ltf)
    bw = bw_task.freq_hz if bw_task is not None else math.nan
    where = f"plant model ({plant.source})"
    limit = limits.pole_radius_limit(cfg.rate_hz)
    unstable = not max_radius < limit
    if unstable:
        text = (
            f"closed-loop pole radius {max_radius:.6f} >= {limit:.6g}"
            + (
                " (unstable)"
                if max_radius >= 1.0
                else f" (a mode decaying slower than {limits.pole_time_constant_max_s:g} s:"
                " no margin from instability)"
            )
            + f" with the {where}"
        )
        # Measured responses supersede the model in their band: then the model's own
        # instability is a caution (the model is wrong), not the verdict.
        (cautions if has_measured else rejections).append(text)
    else:
        margin_reasons(margins, limits, f"speed loop, {where}", cautions)
        margin_reasons(margins_full, limits, f"whole servo, {where}", cautions)
        if not has_measured:
            distance_reasons(margins, limits, f"speed loop, {where}", rejections)
            distance_reasons(margins_full, limits, f"whole servo, {where}", rejections)
    if bound is not None and not has_measured:
        evidence = f"the {where} within {bound.name!r}"
        for t, which, tt in zip(bound_tasks, ("speed loop", "whole servo"),
                                (t_speed, t_full), strict=True):
            robust_reasons(
                t, which, evidence, limits, None, bound.magnitude,
                on_grid(x, np.abs(tt)), f, rejections, cautions, "||W T||",
            )
    if decisive_only:
        return None
    nan = math.nan
    sg = (nan, nan, nan, nan)
    dq_peak = dq_f = nan
    if bound is not None:
        sp, fp = bound_tasks
        sg = (sp.value, sp.freq_hz, fp.value, fp.freq_hz)
        dq = wmag * np.abs(bk.f2d) if on else np.zeros_like(wmag)
        j = int(np.argmax(dq))
        dq_peak, dq_f = float(dq[j]), float(f[j])
        inv = -20.0 * np.log10(wmag)
    else:
        inv = np.full_like(f, np.inf)
    src = SourceResult(
        name=bound.name if bound is not None else "plant model",
        kind="bound" if bound is not None else "model",
        small_gain_peak=sg[0],
        small_gain_freq_hz=sg[1],
        small_gain_full_peak=sg[2],
        small_gain_full_freq_hz=sg[3],
        delta_q_peak=dq_peak,
        delta_q_freq_hz=dq_f,
        base_loop_stable=not unstable,
        margins=margins,
        inv_delta_db=readonly(inv),
        margins_full=margins_full,
    )
    return src, margins, margins_full, bw, crossings_of(lt)
