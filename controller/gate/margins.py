"""Margins and the refinement of crossings, peaks and the winding number on the analysis grid
(python-control's selection rules; checked against it in tests/test_analysis.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from controller.gate.loop_model import (
    DB_3,
    TWO_PI,
    ComplexArray,
    FloatArray,
)


@dataclass(frozen=True)
class Margins:
    """Classical margins of a loop transfer function (python-control's selection rules)."""

    gain_margin_db: float
    """At the phase crossover whose |L| is closest to 1 (negative: a gain-reduction margin);
    inf when the phase never crosses -180 deg."""
    phase_crossover_hz: float
    phase_margin_deg: float
    """Smallest |PM| over the gain crossovers, in (-180, 180]; inf without a crossover."""
    gain_crossover_hz: float
    delay_margin_s: float
    """Smallest PM/omega over the gain crossovers (0 if a PM is <= 0)."""
    peak_sensitivity_db: float
    """max |1/(1 + L)| in dB (-20 log10 of python-control's stability margin sm)."""
    peak_sensitivity_hz: float
    gain_margin_up_db: float = math.inf
    """How far the loop gain may rise before instability: the least -20 log10 |L| over the
    phase crossovers where |L| < 1 (>= 0; inf: none). The number an engineer reads as "the"
    gain margin; `gain_margin_db` is python-control's pick of the two."""
    gain_margin_up_hz: float = math.nan
    gain_reduction_margin_db: float = math.inf
    """How far the loop gain may fall before instability (a conditionally stable loop): the
    least 20 log10 |L| over the phase crossovers where |L| > 1 (> 0; inf: none)."""
    gain_reduction_margin_hz: float = math.nan

    @property
    def conditionally_stable(self) -> bool:
        """A phase crossover with |L| > 1: a gain reduction destabilises the loop."""
        return math.isfinite(self.gain_reduction_margin_db)



Outputs = dict[str, ComplexArray]
Evaluator = Callable[[FloatArray], Outputs]


@dataclass(eq=False)
class RefineTask:
    """One feature to refine in log frequency: a root (kind 0), a minimum (-1), a maximum (+1)
    of fn(outputs[key]) inside [lo, hi]."""

    key: str
    kind: int
    fn: Callable[[ComplexArray], FloatArray]
    lo: float
    hi: float
    x: float = math.nan
    best_x: float = math.nan
    best_v: float = math.nan
    out: complex = complex(math.nan)
    value: float = math.nan

    @property
    def freq_hz(self) -> float:
        return math.exp(self.x)


def solve(tasks: list[RefineTask], ev: Evaluator, n: int = 9, rounds: int = 2) -> None:
    """Refine all tasks together: each round evaluates n points per bracket in one batched
    call and shrinks every bracket n/2-fold; a final secant (roots) or parabola (extrema)
    step and one more batched evaluation give the values at the refined frequencies."""
    if tasks:
        solve_groups([tasks], lambda fs: [ev(fs[0])], n, rounds)


GroupEvaluator = Callable[[list[FloatArray]], list[Outputs]]


def solve_groups(groups: list[list[RefineTask]], ev: GroupEvaluator, n: int = 9,
                 rounds: int = 2) -> None:
    """`solve` for several groups of tasks at once (each group's outputs its own: one loop
    per group), every round one call of `ev` with each group's points (as `solve` hands
    them to its evaluator). Every group holds a task."""
    assert all(groups) and n > 1
    plan = _Plan(groups)
    tasks = [t for g in groups for t in g]
    ends = np.cumsum([len(g) for g in groups])[:-1]
    for _ in range(rounds):
        pts = _brackets(tasks, n)
        outs = ev([np.exp(p) for p in np.split(pts, ends * n)])
        _round(tasks, plan, pts, plan.outputs(outs, n), n)
    finals = ev([np.exp(np.array([t.x for t in g])) for g in groups])
    out = plan.outputs(finals, 1)
    value = plan.values(out)[:, 0]
    for t, o, v in zip(tasks, out[:, 0].tolist(), value.tolist(), strict=True):
        t.out, t.value = o, v
        if t.kind != 0 and not (-t.kind * t.value <= -t.kind * t.best_v):
            t.x, t.value = t.best_x, t.best_v


class _Plan:
    """Every group's tasks, one group after the other, as `_round` takes them by array: the
    rows of each function, the roots' rows and the extrema's rows with their sign (-kind),
    and in each group the key each task reads."""

    def __init__(self, groups: list[list[RefineTask]]) -> None:
        self.keys: list[tuple[list[str], np.ndarray]] = []
        for g in groups:
            keys: dict[str, int] = {}
            for t in g:
                keys.setdefault(t.key, len(keys))
            self.keys.append((list(keys), np.array([keys[t.key] for t in g])))
        by: dict[Callable[[ComplexArray], FloatArray], list[int]] = {}
        for j, t in enumerate(t for g in groups for t in g):
            by.setdefault(t.fn, []).append(j)
        self.fns = [(fn, np.array(rows)) for fn, rows in by.items()]
        kinds = np.array([t.kind for g in groups for t in g])
        self.roots = np.nonzero(kinds == 0)[0]
        self.extrema = np.nonzero(kinds != 0)[0]
        self.sign = (-kinds[self.extrema]).astype(np.float64)

    def outputs(self, outs: list[Outputs], n: int) -> ComplexArray:
        """Each task's own output at its n points (a row per task) from each group's `outs`
        (n points per task, every key)."""
        rows = []
        for (keys, key_of), o in zip(self.keys, outs, strict=True):
            m = key_of.size
            stacked = np.stack([o[k] for k in keys]).reshape(len(keys), m, n)
            rows.append(stacked[key_of, np.arange(m)])
        return rows[0] if len(rows) == 1 else np.concatenate(rows)

    def values(self, h: ComplexArray) -> FloatArray:
        """Each task's function of its own outputs `h` (a row per task)."""
        v = np.empty(h.shape)
        for fn, rows in self.fns:
            v[rows] = fn(h[rows])
        return v


def _brackets(tasks: list[RefineTask], n: int) -> FloatArray:
    """np.linspace(t.lo, t.hi, n) of every task, one after the other, computed for all at
    once as np.linspace computes each (k * step + lo, the last point hi; k / (n - 1) * delta
    where the step is 0)."""
    lo = np.array([t.lo for t in tasks])
    hi = np.array([t.hi for t in tasks])
    delta = hi - lo
    step = delta / (n - 1)
    k = np.arange(n, dtype=np.float64)
    y = k * step[:, None]
    zero = step == 0
    if np.any(zero):
        y[zero] = (k / (n - 1)) * delta[zero, None]
    y += lo[:, None]
    y[:, -1] = hi
    return y.ravel()


def _round(tasks: list[RefineTask], plan: _Plan, pts: FloatArray, h: ComplexArray, n: int
           ) -> None:
    """One round of `solve` for `tasks` given their own outputs `h` at `pts` (n points each,
    a row per task), all tasks' values and steps as arrays (each row as the task alone
    computes it: roots, the first sign change's secant, else the point of least |value|;
    extrema, the best point kept and a parabola through the best point and its neighbours)."""
    m = len(tasks)
    p = pts.reshape(m, n)
    v = plan.values(h)
    if plan.roots.size:
        rows = plan.roots
        vr, pr = v[rows], p[rows]
        s = np.sign(vr)
        change = s[:, :-1] != s[:, 1:]
        has = change.any(axis=1)
        i = np.where(has, change.argmax(axis=1), np.argmin(np.abs(vr), axis=1))
        r = np.arange(rows.size)
        j = np.minimum(i + 1, n - 1)
        lo, hi = pr[r, i], pr[r, j]
        a, b = vr[r, i], vr[r, j]
        with np.errstate(all="ignore"):  # (rows where a == b, or without a change: unused)
            secant = (lo * b - hi * a) / (b - a)
        x = np.where(has, np.where(a == b, lo, secant), lo)
        for t, h, lo_, hi_, x_ in zip([tasks[k] for k in rows.tolist()], has.tolist(),
                                      lo.tolist(), hi.tolist(), x.tolist(), strict=True):
            if h:
                t.lo, t.hi = lo_, hi_
            t.x = x_
    if plan.extrema.size:
        rows = plan.extrema
        ve, pe = v[rows], p[rows]
        sg = plan.sign
        sv = np.where(np.isfinite(ve), sg[:, None] * ve, np.inf)
        i = np.argmin(sv, axis=1)
        r = np.arange(rows.size)
        i0, i1 = np.maximum(i - 1, 0), np.minimum(i + 1, n - 1)
        svi, pi = sv[r, i], pe[r, i]
        with np.errstate(all="ignore"):  # (inf - inf at the edges or odd values: unused)
            den = sv[r, i0] - 2.0 * sv[r, i] + sv[r, i1]
            step = pi + 0.5 * (pe[:, 1] - pe[:, 0]) * (sv[r, i0] - sv[r, i1]) / den
        x = np.where((i > 0) & (i < n - 1) & (den > 0), step, pi)
        for t, sgn, s_, bx, bv, lo_, hi_, x_ in zip(
            [tasks[k] for k in rows.tolist()], sg.tolist(), svi.tolist(), pi.tolist(),
            ve[r, i].tolist(), pe[r, i0].tolist(), pe[r, i1].tolist(), x.tolist(), strict=True,
        ):
            if not s_ >= sgn * t.best_v:  # also true while best_v is nan
                t.best_x, t.best_v = bx, bv
            t.lo, t.hi, t.x = lo_, hi_, x_


def log_mag(h: ComplexArray) -> FloatArray:
    return np.log(np.abs(h))


def neg_arg(h: ComplexArray) -> FloatArray:
    return np.angle(-h)


def dist_of(h: ComplexArray) -> FloatArray:
    return np.abs(1.0 + h)


def abs_of(h: ComplexArray) -> FloatArray:
    return np.abs(h)


def bandwidth_of(h: ComplexArray) -> FloatArray:
    return np.log(np.abs(h) / DB_3)


@dataclass(eq=False)
class LoopTasks:
    gain: list[RefineTask]
    phase: list[RefineTask]
    ms: RefineTask

    def all(self) -> list[RefineTask]:
        return [*self.gain, *self.phase, self.ms]


def loop_tasks(x: FloatArray, loop: ComplexArray, key: str) -> LoopTasks:
    """Brackets of every gain crossover, every negative-real-axis crossing and min |1 + L|."""
    return loop_tasks_rows(x, loop[None], [key])[0]


def loop_tasks_rows(x: FloatArray, loops: ComplexArray, keys: list[str]) -> list[LoopTasks]:
    """`loop_tasks` of each row of `loops` (one loop per row, on the same points x), computed
    for all rows at once (every value per point, as for each row alone)."""
    logm = np.log(np.abs(loops))
    ok = np.isfinite(logm[:, :-1]) & np.isfinite(logm[:, 1:])
    gain = ok & (np.sign(logm[:, :-1]) != np.sign(logm[:, 1:]))
    arg = np.angle(-loops)
    phase = (
        (np.sign(arg[:, :-1]) != np.sign(arg[:, 1:]))
        & (np.abs(arg[:, :-1]) < 0.5 * np.pi)
        & (np.abs(arg[:, 1:]) < 0.5 * np.pi)
    )
    dist = np.abs(1.0 + loops)
    least = np.argmin(np.where(np.isfinite(dist), dist, np.inf), axis=1).tolist()
    xs = x.tolist()
    last = len(xs) - 1
    gains: list[list[RefineTask]] = [[] for _ in keys]
    phases: list[list[RefineTask]] = [[] for _ in keys]
    for r, k in zip(*(v.tolist() for v in np.nonzero(gain)), strict=True):
        gains[r].append(RefineTask(keys[r], 0, log_mag, xs[k], xs[k + 1]))
    for r, k in zip(*(v.tolist() for v in np.nonzero(phase)), strict=True):
        phases[r].append(RefineTask(keys[r], 0, neg_arg, xs[k], xs[k + 1]))
    return [
        LoopTasks(gain=gains[r], phase=phases[r],
                  ms=RefineTask(key, -1, dist_of, xs[max(i - 1, 0)], xs[min(i + 1, last)]))
        for r, (key, i) in enumerate(zip(keys, least, strict=True))
    ]


def margins_of(t: LoopTasks) -> Margins:
    """python-control's choice: the PM of smallest |PM|, the GM closest to 0 dB."""
    pm_deg, gm_db = math.inf, math.inf
    up_db, down_db = math.inf, math.inf
    wgc, wpc, w_up, w_down = math.nan, math.nan, math.nan, math.nan
    delay = math.inf
    for g in t.gain:
        pm = (math.degrees(np.angle(g.out)) % 360.0) - 180.0
        if abs(pm) < abs(pm_deg):
            pm_deg, wgc = pm, g.freq_hz
        delay = min(delay, math.radians(pm) / (TWO_PI * g.freq_hz) if pm > 0 else 0.0)
    for p in t.phase:
        if p.out.real <= 0 and abs(p.out) > 0:
            gm = -20.0 * math.log10(abs(p.out))
            if abs(gm) < abs(gm_db):
                gm_db, wpc = gm, p.freq_hz
            if gm >= 0.0 and gm < up_db:
                up_db, w_up = gm, p.freq_hz
            elif gm < 0.0 and -gm < down_db:
                down_db, w_down = -gm, p.freq_hz
    sm = t.ms.value
    return Margins(
        gain_margin_db=gm_db,
        phase_crossover_hz=wpc,
        phase_margin_deg=pm_deg,
        gain_crossover_hz=wgc,
        delay_margin_s=delay,
        peak_sensitivity_db=-20.0 * math.log10(sm) if sm > 0 else math.inf,
        peak_sensitivity_hz=t.ms.freq_hz,
        gain_margin_up_db=up_db,
        gain_margin_up_hz=w_up,
        gain_reduction_margin_db=down_db,
        gain_reduction_margin_hz=w_down,
    )


@dataclass(frozen=True)
class LoopCrossings:
    """Where a loop's margins are read (the refined points): its gain crossovers (|L| = 1)
    and its crossings of the negative real axis (the ones `margins_of` counts)."""

    gain_crossover_hz: tuple[float, ...]
    gain_crossings: tuple[complex, ...]
    """L at each gain crossover."""
    phase_crossover_hz: tuple[float, ...]
    phase_crossings: tuple[complex, ...]
    """L at each negative-real-axis crossing."""


def crossings_of(t: LoopTasks) -> LoopCrossings:
    """The refined crossings of `t` (after `solve`), with `margins_of`'s own filter on the
    phase crossings (on the negative real axis)."""
    phase = [p for p in t.phase if p.out.real <= 0.0]
    return LoopCrossings(
        gain_crossover_hz=tuple(g.freq_hz for g in t.gain),
        gain_crossings=tuple(g.out for g in t.gain),
        phase_crossover_hz=tuple(p.freq_hz for p in phase),
        phase_crossings=tuple(p.out for p in phase),
    )


def peak_task(x: FloatArray, vals: FloatArray, key: str) -> RefineTask:
    return peak_tasks_rows(x, vals[None], [key])[0]


def peak_tasks_rows(x: FloatArray, vals: FloatArray, keys: list[str]) -> list[RefineTask]:
    """`peak_task` of each row of `vals` (on the same points x), for all rows at once."""
    best = np.argmax(np.where(np.isfinite(vals), vals, -np.inf), axis=1)
    xs = x.tolist()
    last = len(xs) - 1
    tasks = []
    for key, i, v in zip(keys, best.tolist(), vals[np.arange(len(keys)), best].tolist(),
                         strict=True):
        t = RefineTask(key, 1, abs_of, xs[max(i - 1, 0)], xs[min(i + 1, last)])
        t.best_x, t.best_v = xs[i], v
        tasks.append(t)
    return tasks


def winding_ok(one_plus_l: ComplexArray, m_integrators: int) -> bool:
    """Argument principle for 1 + L with L = (stable) x (m poles at z = 1) x (k > 0).

    Stable iff arg(1 + L) turns by m*90 deg from 0+ (where it is -m*90 deg) to Nyquist (0).
    The grid must start where the integrators dominate (|L| >> 1) and end where |L| << 1;
    otherwise the loop is reported as not proven stable.
    """
    return windings_ok(one_plus_l[None], [m_integrators])[0]


def windings_ok(one_plus_l: ComplexArray, m_integrators: list[int]) -> list[bool]:
    """`winding_ok` of each row of `one_plus_l` (on the same points) with its number of
    integrators, all rows at once (each row's numbers as `winding_ok` computes them alone)."""
    fine = np.all(np.isfinite(one_plus_l), axis=1) & ~np.any(one_plus_l == 0, axis=1)
    m = np.array(m_integrators)
    # (|1 + L| at the ends of each row as numpy's scalar abs gives it, as `winding_ok` did.)
    first_abs = np.array([abs(z) for z in one_plus_l[:, 0]])
    last_abs = np.array([abs(z - 1.0) for z in one_plus_l[:, -1]])
    with np.errstate(invalid="ignore"):  # (rows not finite: not fine)
        ends = fine & ~((m > 0) & (first_abs < 2.0)) & ~(last_abs > 0.5)
    if not np.any(ends):
        return [False] * m.size
    with np.errstate(invalid="ignore"):  # (rows not finite: not `ends`)
        ph = np.unwrap(np.angle(one_plus_l), axis=1)
        start = -0.5 * np.pi * m
        turns = TWO_PI * np.round((ph[:, 0] - start) / TWO_PI)
        first, final = ph[:, 0] - turns, ph[:, -1] - turns
        ok = ends & ~(np.abs(first - start) > np.radians(60.0)) & (np.abs(final) < 0.5 * np.pi)
    return [bool(v) for v in ok.tolist()]
