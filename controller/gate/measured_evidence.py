"""The measured responses' evidence: each response's first pass (the grid refined where the loop
turns fast, the argument principle, |T| and its allowance) for one or more cut-offs together
(`MeasuredPasses`), then each response's conclusion (`measured_evidence`). The refinement
and the assumptions are `controller.gate.analysis`'s.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator
from dataclasses import dataclass

import numpy as np

from controller.core.arrays import ComplexArray, FloatArray
from controller.core.config import LoopConfig, NominalModel
from controller.gate.knowledge import (
    PlantKnowledge,
    readonly,
)
from controller.gate.limits import GateLimits
from controller.gate.loop_model import (
    DobFilters,
    GainBlocks,
    LoopBlocks,
    gain_blocks,
    loop_blocks,
)
from controller.gate.margins import (
    LoopCrossings,
    LoopTasks,
    Margins,
    Outputs,
    RefineTask,
    loop_tasks_rows,
    margins_of,
    peak_tasks_rows,
    winding_ok,
    windings_ok,
)
from controller.gate.measured_model import (
    KEEP_MIN_POINTS,
    UNRESOLVED_ALLOWANCE,
    Points,
    measured_model,
)
from controller.gate.reasons import (
    distance_reasons,
    fmt_hz,
    margin_reasons,
    on_grid,
    robust_reasons,
)
from controller.gate.results import SourceResult

__all__ = [
    "MAX_PHASE_STEP_RAD",
    "MAX_WINDING_POINTS",
    "BlocksMemo",
    "FirstPass",
    "GainMemo",
    "MeasuredPasses",
    "Refinement",
    "controller_parts",
    "integrators",
    "measured_evidence",
    "refine_by_phase",
    "refined_winding_ok",
]


#: Winding-number refinement: adjacent points whose phase differs by more than this are split.
MAX_PHASE_STEP_RAD = math.radians(20.0)
MAX_WINDING_POINTS = 40000


def integrators(cfg: LoopConfig, with_position: bool) -> int:
    m = 1 if cfg.cv_ki_per_s > 0 else 0
    if with_position:
        m += 1 + (1 if cfg.pos_ki_per_s > 0 else 0)
    return m




def controller_parts(b: LoopBlocks, on: bool) -> tuple[ComplexArray, ComplexArray, ComplexArray]:
    """(1 - F2 z^-1, Cv + F1, C_tot + F1) (DOB off: 1, Cv, C_tot)."""
    return 1.0 - b.f2d, b.cv + b.f1, b.ctot + b.f1


def refine_by_phase(
    d_of: Callable[[FloatArray], ComplexArray], f: FloatArray
) -> tuple[FloatArray, ComplexArray] | None:
    """(f, D(f)) on `f` refined until the phase of D moves less than 20 deg between
    neighbours: where the loop turns fast (a sharp resonance, a pass close to -1) the grid
    follows it. None if D is not finite and non-zero everywhere or the refinement takes more
    than a bounded number of points."""
    f = np.asarray(f, dtype=np.float64)
    d = d_of(f)
    while True:
        if not np.all(np.isfinite(d)) or np.any(d == 0):
            return None
        step = np.abs(np.angle(d[1:] / d[:-1]))
        bad = np.nonzero(step > MAX_PHASE_STEP_RAD)[0]
        if bad.size == 0:
            return f, d
        if f.size + bad.size > MAX_WINDING_POINTS:
            return None
        fm = np.sqrt(f[bad] * f[bad + 1])
        if np.any(fm <= f[bad]) or np.any(fm >= f[bad + 1]):
            return None  # no resolution left between two floats
        f = np.insert(f, bad + 1, fm)
        d = np.insert(d, bad + 1, d_of(fm))


def refined_winding_ok(
    d_of: Callable[[FloatArray], ComplexArray], f: FloatArray, m_integrators: int
) -> bool:
    """The argument-principle test (`winding_ok`) on a grid refined until the phase of D moves
    less than 20 deg between neighbours (a curve passing close to 0 is resolved, not stepped
    over); False (not proven) if that takes more than a bounded number of points."""
    r = refine_by_phase(d_of, f)
    return r is not None and winding_ok(r[1], m_integrators)


#: What an evidence hands to the analysis's one refinement (`solve`) of every evidence's
#: crossings and peaks: its tasks, and its outputs at any frequencies given the loop's blocks
#: there and what depends on the points alone (`Points`; keys prefixed per evidence). Results
#: are per frequency point, so refining every evidence's tasks together gives each task what
#: refining it alone gives.
Refinement = tuple[list[RefineTask], Callable[[FloatArray, LoopBlocks, Points], Outputs]]


ModelConclusion = tuple[SourceResult, Margins, Margins, float, LoopCrossings]


class GainMemo:
    """`gain_blocks` of one loop's gains per frequency grid (by its values), shared by the
    cut-offs judged together (`accepted_cutoffs`). Grids of a few refinement points are
    computed every time (not worth a key)."""

    MIN_POINTS = KEEP_MIN_POINTS

    def __init__(self, cfg: LoopConfig, model: NominalModel) -> None:
        self._cfg, self._model = cfg, model
        self._memo: dict[bytes, GainBlocks] = {}

    def __call__(self, f: FloatArray) -> GainBlocks:
        if f.size < self.MIN_POINTS:
            return gain_blocks(self._cfg, f, self._model)
        key = f.tobytes()
        b = self._memo.get(key)
        if b is None:
            b = self._memo[key] = gain_blocks(self._cfg, f, self._model)
        return b


class BlocksMemo:
    """`loop_blocks` of one analysis's loop per frequency grid (by its values): the measured
    responses share their grids, and each asks for the same grid several times (`gains`:
    the gains' blocks, shared with other cut-offs)."""

    MIN_POINTS = GainMemo.MIN_POINTS

    def __init__(self, cfg: LoopConfig, used: DobFilters | None, model: NominalModel,
                 gains: GainMemo | None = None) -> None:
        self._cfg, self._used, self._model = cfg, used, model
        self._gains = gains if gains is not None else GainMemo(cfg, model)
        self._memo: dict[bytes, LoopBlocks] = {}

    def __call__(self, f: FloatArray) -> LoopBlocks:
        if f.size < self.MIN_POINTS:
            return loop_blocks(self._cfg, self._used, f, self._model, self._gains(f))
        key = f.tobytes()
        b = self._memo.get(key)
        if b is None:
            b = self._memo[key] = loop_blocks(self._cfg, self._used, f, self._model,
                                              self._gains(f))
        return b


@dataclass(frozen=True, eq=False)
class FirstPass:
    """A measured response's evidence up to its refinement: the grid (the analysis grid with
    the measured points, refined where the loop turns fast), the argument principle's answer,
    |T| of both loops there, its allowance, and the tasks to refine."""

    f: FloatArray
    x: FloatArray
    stable: bool
    t_speed: FloatArray
    t_full: FloatArray
    allowance: FloatArray
    lt: LoopTasks
    ltf: LoopTasks
    sp: RefineTask
    fp: RefineTask


class MeasuredPasses:
    """Every measured response's `FirstPass` for one or more candidates that differ only in
    the DOB's cut-off (`cases`: each one's configuration and loop blocks), computed together
    when the first is asked for.

    The grid: the analysis grid, every measured point (the allowance jumps there) and the
    middle of every measured interval (each interval's allowance sampled inside it, also when
    the points coincide with the analysis grid), refined where the loop turns fast (the phase
    of 1 + L moves more than 20 deg between neighbours: a sharp resonance or a pass close to
    -1 between grid points is followed, not stepped over). The responses that share a grid
    (measured at the same frequencies) share it for every candidate, and their loops with
    every candidate are judged as rows of one array, each row as the response alone gives it
    with that candidate alone (every value is per point); a response whose loop turns too
    fast on that grid is refined alone."""

    def __init__(self, plant: PlantKnowledge, f0: FloatArray,
                 cases: list[tuple[LoopConfig, BlocksMemo]]) -> None:
        rate_hz = cases[0][0].rate_hz
        self.mms = [measured_model(m, rate_hz, plant.model, plant.bound)
                    for m in plant.measured]
        self.tags = [f"{i}:" for i in range(len(self.mms))]
        self._f0, self._cases = f0, cases
        self._passes: dict[tuple[int, int], FirstPass] | None = None

    def blocks(self, case: int) -> BlocksMemo:
        return self._cases[case][1]

    def get(self, case: int, i: int) -> FirstPass:
        """Response i's pass with candidate `case`."""
        if self._passes is None:
            self._passes = self._compute()
        return self._passes[case, i]

    def _compute(self) -> dict[tuple[int, int], FirstPass]:
        mms = self.mms
        grids = [mm.grid(self._f0) for mm in mms]
        by_grid: dict[bytes, list[int]] = {}
        for i, g in enumerate(grids):
            by_grid.setdefault(g.tobytes(), []).append(i)
        passes: dict[tuple[int, int], FirstPass] = {}
        for rows in by_grid.values():
            f = grids[rows[0]]
            k = len(rows)
            gk_parts: list[ComplexArray] = []
            d_parts: list[ComplexArray] = []
            ones: list[ComplexArray] = []
            for cfg, lb in self._cases:
                b = lb(f)
                one, ks, kf = controller_parts(b, cfg.dob_on)
                gm = np.stack([mms[i].plant(f, b.g) for i in rows])
                gk = np.concatenate([gm * ks, gm * kf])  # (the speed loops, then the whole's)
                gk_parts.append(gk)
                d_parts.append(one + gk)
                ones.append(one)
            # Row (c, loop, j): candidate c's speed loop (0) or whole servo (1) with rows[j].
            gk_all = np.concatenate(gk_parts)
            d = np.concatenate(d_parts)
            fine = np.all(np.isfinite(d), axis=1) & ~np.any(d == 0, axis=1)
            with np.errstate(all="ignore"):  # (rows not finite or through 0: not fine)
                turns = np.any(np.abs(np.angle(d[:, 1:] / d[:, :-1])) > MAX_PHASE_STEP_RAD,
                               axis=1)
            clean = (fine & ~turns).tolist()
            together: list[tuple[int, int]] = []  # (case, j)
            for c in range(len(self._cases)):
                for j in range(k):
                    r = 2 * k * c + j
                    if clean[r] and clean[r + k]:
                        together.append((c, j))
                    else:
                        passes[c, rows[j]] = self._alone(
                            c, rows[j], f, [(d[r], fine[r], clean[r]),
                                            (d[r + k], fine[r + k], clean[r + k])])
            if together:
                # (On an unrefined grid the union of both loops' grids is the grid itself.)
                speed = [2 * k * c + j for c, j in together]
                both = speed + [r + k for r in speed]
                ms = [integrators(self._cases[c][0], False) for c, _ in together]
                mf = [integrators(self._cases[c][0], True) for c, _ in together]
                stable = windings_ok(d[both], ms + mf)
                n = len(together)
                one_rows = np.stack([ones[c] for c, _ in together] * 2)
                made = self._tasks(f, gk_all[both], d[both], one_rows,
                                   [(c, rows[j]) for c, j in together],
                                   [s1 and s2 for s1, s2 in zip(stable[:n], stable[n:],
                                                                strict=True)])
                passes.update(made)
        return passes

    def _alone(self, case: int, i: int, f: FloatArray,
               loops: list[tuple[ComplexArray, bool, bool]]) -> FirstPass:
        """Response i's pass with candidate `case` on its own, given (1 - F2 z^-1 + G_m (C +
        F1) on f, finite and non-zero, turning slowly enough) of its speed loop and its whole
        servo: a loop that turns too fast is refined (`refine_by_phase`)."""
        mm = self.mms[i]
        cfg, lb = self._cases[case]
        on = cfg.dob_on

        def d_of(full: bool) -> Callable[[FloatArray], ComplexArray]:
            def d(ff: FloatArray) -> ComplexArray:
                b = lb(ff)
                o, s_, f_ = controller_parts(b, on)
                return o + mm.plant(ff, b.g) * (f_ if full else s_)
            return d

        r_speed, r_full = (
            None if not fine else (f, d) if clean else refine_by_phase(d_of(full), f)
            for full, (d, fine, clean) in zip((False, True), loops, strict=True)
        )
        stable = (
            r_speed is not None and r_full is not None
            and winding_ok(r_speed[1], integrators(cfg, False))
            and winding_ok(r_full[1], integrators(cfg, True))
        )
        if r_speed is not None and r_full is not None:
            f = np.union1d(r_speed[0], r_full[0])
        b = lb(f)
        one, ks, kf = controller_parts(b, on)
        gm = mm.plant(f, b.g)
        gk = np.stack([gm * ks, gm * kf])
        return self._tasks(f, gk, one + gk, one, [(case, i)], [stable])[case, i]

    def _tasks(self, f: FloatArray, gk: ComplexArray, d: ComplexArray, one: ComplexArray,
               which: list[tuple[int, int]], stable: list[bool]
               ) -> dict[tuple[int, int], FirstPass]:
        """The passes of (candidate, response) pairs `which` on the grid f, given G_m (Cv +
        F1) and G_m (C_tot + F1) of each (rows: every pair's speed loop, then every pair's
        whole servo), 1 - F2 z^-1 + those (the loops' denominators) and 1 - F2 z^-1 (one row,
        or a row per row)."""
        x = np.log(f)
        tags = [self.tags[i] for _, i in which]
        t = np.abs(gk / d)
        kept = {i: self.mms[i].allowance(f) for i in {i for _, i in which}}
        a = np.stack([kept[i] for _, i in which])
        lts = loop_tasks_rows(x, gk / one, [tg + "L" for tg in tags] + [tg + "Lf" for tg in tags])
        peaks = peak_tasks_rows(x, np.concatenate([a, a]) * t,
                                [tg + "ts" for tg in tags] + [tg + "tf" for tg in tags])
        n = len(which)
        return {
            w: FirstPass(f, x, stable[j], t[j], t[n + j], a[j], lts[j], lts[n + j], peaks[j],
                          peaks[n + j])
            for j, w in enumerate(which)
        }


def measured_evidence(
    cfg: LoopConfig, passes: MeasuredPasses, case: int, i: int, f0: FloatArray,
    limits: GateLimits, rejections: list[str], cautions: list[str],
    decisive_only: bool = False,
) -> Generator[Refinement, None, SourceResult | None]:
    """A measured response's evidence (`decisive_only`: only what can give a reason, None for
    the conclusion, and no refinement after a rejection by the argument principle), from its
    first pass (`MeasuredPasses`: the grid, the argument principle, the tasks)."""
    on = cfg.dob_on
    mm, tag, lb = passes.mms[i], passes.tags[i], passes.blocks(case)
    where = f"measured response {mm.name!r}"
    first = passes.get(case, i)
    stable = first.stable
    if not stable:
        rejections.append(f"unstable or not proven stable with the {where} (argument principle)")
        if decisive_only:
            return None
    f, x = first.f, first.x

    def ev(ff: FloatArray, b: LoopBlocks, pts: Points) -> Outputs:
        o, s_, f_ = controller_parts(b, on)
        g2 = mm.plant_at(pts, b.g)
        a = mm.allowance_at(pts)
        return {
            tag + "L": g2 * s_ / o,
            tag + "Lf": g2 * f_ / o,
            tag + "ts": a * g2 * s_ / (o + g2 * s_),
            tag + "tf": a * g2 * f_ / (o + g2 * f_),
        }

    a, t_speed, t_full = first.allowance, first.t_speed, first.t_full
    lt, ltf, sp, fp = first.lt, first.ltf, first.sp, first.fp
    yield [*lt.all(), *ltf.all(), sp, fp], ev
    margins, margins_full = margins_of(lt), margins_of(ltf)
    if stable:
        if limits.check_measured_margins:
            margin_reasons(margins, limits, f"speed loop, {where}", cautions)
            margin_reasons(margins_full, limits, f"whole servo, {where}", cautions)
        distance_reasons(margins, limits, f"speed loop, {where}", rejections)
        distance_reasons(margins_full, limits, f"whole servo, {where}", rejections)
        hi = mm.band_hz[1]
        for t, which, tt in ((sp, "speed loop", t_speed), (fp, "whole servo", t_full)):
            unresolved = [u for u in mm.unresolved if u[0] <= t.freq_hz <= u[1]]
            if unresolved and t.value >= 1.0:
                u = unresolved[0]
                rejections.append(
                    f"robust stability ({which}): the {where} changes by a factor "
                    f"{math.exp(u[2]):.3g} between {fmt_hz(u[0])} and {fmt_hz(u[1])} (a mode "
                    f"between the points) where the loop has gain |T| = "
                    f"{t.value / UNRESOLVED_ALLOWANCE:.3g}:"
                    f" measure denser between {fmt_hz(u[0])} and {fmt_hz(u[1])} first"
                )
                continue
            robust_reasons(
                t, which, where, limits, hi, mm.allowance,
                on_grid(x, tt), f, rejections, cautions,
                sparse=mm.sparse_segment(t.freq_hz),
            )
    if decisive_only:
        return None
    dq = a * np.abs(lb(f).f2d)
    j = int(np.argmax(dq))
    with np.errstate(divide="ignore"):
        inv = -20.0 * np.log10(np.interp(np.log(f0), x, a))
    return SourceResult(
        name=mm.name,
        kind="measured",
        small_gain_peak=sp.value,
        small_gain_freq_hz=sp.freq_hz,
        small_gain_full_peak=fp.value,
        small_gain_full_freq_hz=fp.freq_hz,
        delta_q_peak=float(dq[j]) if on else math.nan,
        delta_q_freq_hz=float(f[j]) if on else math.nan,
        base_loop_stable=stable,
        margins=margins,
        inv_delta_db=readonly(inv),
        margins_full=margins_full,
        band_hz=mm.band_hz,
    )
