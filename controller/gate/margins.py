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
    for _ in range(rounds):
        pts = [_brackets(g, n) for g in groups]
        outs = ev([np.exp(p) for p in pts])
        for g, gp, go in zip(groups, pts, outs, strict=True):
            _round(g, gp, go, n)
    finals = ev([np.exp(np.array([t.x for t in g])) for g in groups])
    for g, final in zip(groups, finals, strict=True):
        for j, t in enumerate(g):
            t.out = complex(final[t.key][j])
            t.value = float(t.fn(final[t.key][j : j + 1])[0])
            if t.kind != 0 and not (-t.kind * t.value <= -t.kind * t.best_v):
                t.x, t.value = t.best_x, t.best_v


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


def _round(tasks: list[RefineTask], pts: FloatArray, outs: Outputs, n: int) -> None:
    """One round of `solve` for `tasks` given their outputs at `pts` (n points each)."""
    for j, t in enumerate(tasks):
        p = pts[j * n : (j + 1) * n]
        v = t.fn(outs[t.key][j * n : (j + 1) * n])
        if t.kind == 0:
            s = np.sign(v)
            k = np.nonzero(s[:-1] != s[1:])[0]
            if k.size:
                i = int(k[0])
                t.lo, t.hi = float(p[i]), float(p[i + 1])
                a, b = float(v[i]), float(v[i + 1])
                t.x = t.lo if a == b else (t.lo * b - t.hi * a) / (b - a)
            else:
                t.x = float(p[int(np.argmin(np.abs(v)))])
            continue
        sv = np.where(np.isfinite(v), -t.kind * v, np.inf)
        i = int(np.argmin(sv))
        if not sv[i] >= -t.kind * t.best_v:  # also true while best_v is nan
            t.best_x, t.best_v = float(p[i]), float(v[i])
        i0, i1 = max(i - 1, 0), min(i + 1, n - 1)
        t.lo, t.hi = float(p[i0]), float(p[i1])
        t.x = float(p[i])
        if 0 < i < n - 1:
            den = sv[i - 1] - 2.0 * sv[i] + sv[i + 1]
            if den > 0:
                t.x = float(p[i] + 0.5 * (p[1] - p[0]) * (sv[i - 1] - sv[i + 1]) / den)


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
    logm = np.log(np.abs(loop))
    ok = np.isfinite(logm[:-1]) & np.isfinite(logm[1:])
    gi = np.nonzero(ok & (np.sign(logm[:-1]) != np.sign(logm[1:])))[0]
    arg = np.angle(-loop)
    pi_ = np.nonzero(
        (np.sign(arg[:-1]) != np.sign(arg[1:]))
        & (np.abs(arg[:-1]) < 0.5 * np.pi)
        & (np.abs(arg[1:]) < 0.5 * np.pi)
    )[0]
    dist = np.abs(1.0 + loop)
    i = int(np.argmin(np.where(np.isfinite(dist), dist, np.inf)))
    return LoopTasks(
        gain=[RefineTask(key, 0, log_mag, float(x[k]), float(x[k + 1])) for k in gi],
        phase=[RefineTask(key, 0, neg_arg, float(x[k]), float(x[k + 1])) for k in pi_],
        ms=RefineTask(key, -1, dist_of, float(x[max(i - 1, 0)]), float(x[min(i + 1, x.size - 1)])),
    )


def margins_of(t: LoopTasks) -> Margins:
    """python-control's choice: the PM of smallest |PM|, the GM closest to 0 dB."""
    pm_deg, gm_db = math.inf, math.inf
    wgc, wpc = math.nan, math.nan
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
    sm = t.ms.value
    return Margins(
        gain_margin_db=gm_db,
        phase_crossover_hz=wpc,
        phase_margin_deg=pm_deg,
        gain_crossover_hz=wgc,
        delay_margin_s=delay,
        peak_sensitivity_db=-20.0 * math.log10(sm) if sm > 0 else math.inf,
        peak_sensitivity_hz=t.ms.freq_hz,
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
    i = int(np.argmax(np.where(np.isfinite(vals), vals, -np.inf)))
    t = RefineTask(key, 1, abs_of, float(x[max(i - 1, 0)]), float(x[min(i + 1, x.size - 1)]))
    t.best_x, t.best_v = float(x[i]), float(vals[i])
    return t


def winding_ok(one_plus_l: ComplexArray, m_integrators: int) -> bool:
    """Argument principle for 1 + L with L = (stable) x (m poles at z = 1) x (k > 0).

    Stable iff arg(1 + L) turns by m*90 deg from 0+ (where it is -m*90 deg) to Nyquist (0).
    The grid must start where the integrators dominate (|L| >> 1) and end where |L| << 1;
    otherwise the loop is reported as not proven stable.
    """
    if not np.all(np.isfinite(one_plus_l)) or np.any(one_plus_l == 0):
        return False
    if m_integrators > 0 and abs(one_plus_l[0]) < 2.0:
        return False
    if abs(one_plus_l[-1] - 1.0) > 0.5:
        return False
    ph = np.unwrap(np.angle(one_plus_l))
    start = -0.5 * np.pi * m_integrators
    ph = ph - TWO_PI * np.round((ph[0] - start) / TWO_PI)
    if abs(ph[0] - start) > np.radians(60.0):
        return False
    return bool(abs(ph[-1]) < 0.5 * np.pi)


