"""A measured response as the gate judges it: the model times the interpolated ratio, the
allowance around it between and beyond the measured points (`MeasuredModel`), and the points
shared by the responses of one analysis (`Points`). The assumptions are stated in
`controller.gate.analysis`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cached_property

import numpy as np

from controller.core.arrays import ComplexArray, FloatArray
from controller.core.config import NominalModel
from controller.gate.knowledge import (
    MIN_ALLOWANCE,
    MeasuredResponse,
    UncertaintyBound,
    readonly,
)
from controller.gate.loop_model import (
    TWO_PI,
    discrete_plant,
    nominal_continuous_response,
    plant_response,
    with_zoh,
    zoh_terms,
)

__all__ = [
    "KEEP_MIN_POINTS",
    "SHARP_TURN",
    "UNRESOLVED_ALLOWANCE",
    "UNRESOLVED_CHANGE",
    "MeasuredModel",
    "Points",
    "measured_model",
]


#: Between two measured points the plant's ratio to the model is assumed to change by no more
#: than it changes across the interval. When it changes by more than this (natural log units:
#: a factor e in magnitude, or 57 deg), the interval does not resolve the plant (a mode sits
#: in it) and the plant there is taken as unknown up to `UNRESOLVED_ALLOWANCE`.
UNRESOLVED_CHANGE = 1.0
UNRESOLVED_ALLOWANCE = 100.0
#: An interval across which the response turns fast compared with its neighbours holds a
#: feature the points do not resolve either: a lightly damped pole-zero pair between two
#: points shows at the points only as a kink (a 4.3 Hz mode of damping 0.014 with its zeros at
#: 4.5 Hz, between points at 4.0 and 5.0 Hz, 36x at its peak: changes of 0.12, 0.75, 1.2, 0.7,
#: 0.05 across successive intervals). The measure is the interval's departure from the mean of
#: its neighbours' changes, |d_i - (d_(i-1) + d_(i+1)) / 2| of d = diff(ln R) (complex); above
#: SHARP_TURN the interval is unresolved like one that changes by more than UNRESOLVED_CHANGE.
#: (Resolved modes turn less: the belt mode at 0.3x its damping, 0.5-2x its frequency, on 10
#: points per decade, up to 0.54.)
SHARP_TURN = 0.75
#: Grids of fewer points than this are computed every time (not worth a key).
KEEP_MIN_POINTS = 64


_Intervals = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                   np.ndarray | None]


class Points:
    """Frequencies with what depends on them alone (log f, the model's continuous response,
    the ZOH terms, the bound's magnitude), each computed when first asked: the measured
    responses of one analysis share their model, rate and bound, so one refinement round
    computes these once for all of them."""

    def __init__(self, f: FloatArray, rate_hz: float, model: NominalModel,
                 bound: UncertaintyBound | None) -> None:
        self.f, self.rate_hz, self.model, self.bound = f, rate_hz, model, bound
        self._intervals: dict[bytes, _Intervals] = {}

    @cached_property
    def log_f(self) -> FloatArray:
        return np.log(self.f)

    @cached_property
    def nominal(self) -> ComplexArray:
        return nominal_continuous_response(self.model, self.f)

    @cached_property
    def zoh(self) -> tuple[ComplexArray, FloatArray]:
        return zoh_terms(self.f, self.rate_hz)

    def intervals(self, fm: FloatArray) -> _Intervals:
        """Where the points fall among measured points `fm` (strictly increasing): inside
        the band (and the index of the interval of each point inside), below it, above it,
        exactly at a measured point (and its index; None: at none). Kept per `fm`: the
        responses measured at the same frequencies share it."""
        key = fm.tobytes()
        got = self._intervals.get(key)
        if got is None:
            f = self.f
            i = np.searchsorted(fm, f, side="right") - 1
            inside = (i >= 0) & (i < fm.size - 1)
            segment = np.clip(i, 0, fm.size - 2)[inside]
            # At a measured point (the points are strictly increasing: i is its index).
            exact = (i >= 0) & (fm[np.maximum(i, 0)] == f)
            j = np.searchsorted(fm, f[exact]) if np.any(exact) else None
            got = self._intervals[key] = (inside, segment, f < fm[0], f > fm[-1], exact, j)
        return got

    @cached_property
    def bound_magnitude(self) -> FloatArray:
        """|W| (without a bound: `UNRESOLVED_ALLOWANCE`, the plant unknown)."""
        if self.bound is not None:
            return self.bound.magnitude(self.f)
        return np.full_like(self.f, UNRESOLVED_ALLOWANCE)


#: `MeasuredModel`s by (response object, rate, model, bound object): every candidate judged
#: on the same knowledge shares them, with the grids they were asked for (the analysis grid
#: with the measured points is the same for every candidate). Bounded.
_MEASURED: dict[tuple[MeasuredResponse, float, NominalModel, UncertaintyBound | None],
                MeasuredModel] = {}
_MEASURED_MAX = 32


def measured_model(
    m: MeasuredResponse, rate_hz: float, model: NominalModel, bound: UncertaintyBound | None
) -> MeasuredModel:
    key = (m, rate_hz, model, bound)
    mm = _MEASURED.get(key)
    if mm is None:
        mm = MeasuredModel(m, rate_hz, model, bound)
        if len(_MEASURED) >= _MEASURED_MAX:
            _MEASURED.clear()
        _MEASURED[key] = mm
    return mm


class MeasuredModel:
    """A measured response as a function of frequency: model x interpolated ratio R, and the
    allowance a(f) the gate grants around it (relative plant error |G/G_c - 1| <= a).

    What it gives for a grid of many points is kept (read-only arrays, a few grids: they
    depend on the grid alone); a thread that finds a grid missing computes it again."""

    _GRIDS_MAX = 8

    def __init__(
        self, m: MeasuredResponse, rate_hz: float, model: NominalModel,
        bound: UncertaintyBound | None,
    ) -> None:
        self.name = m.name
        self.sampled = m.sampled
        self.rate_hz = rate_hz
        self.model = model
        self.bound = bound
        self._kept: dict[tuple[str, bytes], np.ndarray] = {}
        if m.sampled:
            zinv = np.exp(-1j * TWO_PI * m.freq_hz / rate_hz)
            nom = plant_response(discrete_plant(model, rate_hz), zinv)
        else:
            nom = nominal_continuous_response(model, m.freq_hz)
        ratio = m.response / nom
        self.fm = m.freq_hz
        self.xm = np.log(m.freq_hz)
        self.logmag = np.log(np.abs(ratio))
        self.phase = np.unwrap(np.angle(ratio))
        spread = m.spread if m.spread is not None else np.zeros_like(self.fm)
        self.point = np.maximum(spread, MIN_ALLOWANCE)
        change = np.abs(np.diff(self.logmag + 1j * self.phase))
        seg = np.maximum(self.point[:-1], self.point[1:]) + change
        d = np.diff(self.logmag + 1j * self.phase)
        sharp = np.zeros(change.shape, dtype=bool)
        if d.size > 2:
            sharp[1:-1] = np.abs(d[1:-1] - 0.5 * (d[:-2] + d[2:])) > SHARP_TURN
        bad = (change > UNRESOLVED_CHANGE) | sharp
        self.segment = np.where(bad, UNRESOLVED_ALLOWANCE, seg)
        self.change = change
        self.unresolved = [
            (float(self.fm[i]), float(self.fm[i + 1]), float(change[i]))
            for i in np.nonzero(bad)[0]
        ]

    @property
    def band_hz(self) -> tuple[float, float]:
        return float(self.fm[0]), float(self.fm[-1])

    def _kept_or(self, what: str, f: FloatArray, make: Callable[[FloatArray], np.ndarray],
                 keep: bool = True) -> np.ndarray:
        if not keep or f.size < KEEP_MIN_POINTS:
            return make(f)
        key = (what, f.tobytes())
        got = self._kept.get(key)
        if got is None:
            got = readonly(make(f))
            if len(self._kept) >= self._GRIDS_MAX:
                self._kept.clear()
            self._kept[key] = got
        return got

    def points(self, f: FloatArray) -> Points:
        """`f` with what depends on it alone, for this response's model, rate and bound."""
        return Points(f, self.rate_hz, self.model, self.bound)

    def _ratio(self, pts: Points) -> ComplexArray:
        xf = pts.log_f
        return np.exp(np.interp(xf, self.xm, self.logmag) + 1j * np.interp(xf, self.xm, self.phase))

    def grid(self, f0: FloatArray) -> FloatArray:
        """The analysis grid `f0` with every measured point inside it and the middle of every
        measured interval (kept: the same for every candidate)."""
        return self._kept_or("grid", f0, self._grid)

    def _grid(self, f0: FloatArray) -> FloatArray:
        inner = (self.fm > f0[0]) & (self.fm < f0[-1])
        mid = np.sqrt(self.fm[:-1] * self.fm[1:])
        return np.union1d(f0, np.concatenate([self.fm[inner], mid[(mid > f0[0]) & (mid < f0[-1])]]))

    def plant(self, f: FloatArray, g_model: ComplexArray, keep: bool = True) -> ComplexArray:
        """G_m at f (discrete), given the exact model G at f (`keep` false: a grid asked for
        once, not worth keeping)."""
        if self.sampled:
            return g_model * self._kept_or("ratio", f, lambda ff: self._ratio(self.points(ff)),
                                           keep)
        return self._kept_or("plant", f, lambda ff: self._continuous_plant(self.points(ff)),
                             keep)

    def plant_at(self, pts: Points, g_model: ComplexArray) -> ComplexArray:
        """`plant` at points shared with other responses of the same model, rate and bound
        (not kept)."""
        if self.sampled:
            return g_model * self._ratio(pts)
        return self._continuous_plant(pts)

    def _continuous_plant(self, pts: Points) -> ComplexArray:
        gc = pts.nominal * self._ratio(pts)
        return with_zoh(gc, pts.zoh)

    def allowance(self, f: FloatArray, keep: bool = True) -> FloatArray:
        """a(f): the segment's allowance between measured points, beyond the band the edge's
        allowance plus the bound (unknown without a bound), and at a measured point the
        largest allowance of the intervals meeting there: the robust test takes the supremum
        of a |T| over each interval, and |T| is continuous, so an interval's allowance holds
        up to its ends (with the point's own allowance there, a segment's peak at a measured
        point was sampled at the point's smaller allowance only and missed)."""
        f = np.asarray(f, dtype=np.float64)
        return self._kept_or("allowance", f, lambda ff: self.allowance_at(self.points(ff)), keep)

    def allowance_at(self, pts: Points) -> FloatArray:
        """`allowance` at points shared with other responses (not kept)."""
        f = pts.f
        inside, segment, below, above, exact, j = pts.intervals(self.fm)
        a = np.empty_like(f)
        a[inside] = self.segment[segment]
        w = pts.bound_magnitude
        a[below] = self.point[0] + w[below]
        a[above] = self.point[-1] + w[above]
        if j is not None:
            # (The band's edges keep their point allowance: beyond them the analysis grid
            # samples the allowance of the outside, which starts there.)
            seg = np.concatenate([[0.0], self.segment, [0.0]])
            left, right = seg[j], seg[j + 1]
            a[exact] = np.maximum(self.point[j], np.maximum(left, right))
        return a

    def sparse_segment(self, freq_hz: float) -> tuple[float, float, float] | None:
        """(lo, hi, change) of the measured interval at `freq_hz` when its allowance comes
        mostly from the interpolation (the response changes across it by more than the
        points' own allowance: the points do not resolve it), else None."""
        i = int(np.searchsorted(self.fm, freq_hz, side="right")) - 1
        if freq_hz == self.fm[min(max(i, 0), self.fm.size - 1)] and i > 0:
            # At a point the interval with the larger allowance holds the supremum.
            i = i if i < self.fm.size - 1 and self.segment[i] >= self.segment[i - 1] else i - 1
        if not 0 <= i < self.fm.size - 1:
            return None
        point = max(float(self.point[i]), float(self.point[i + 1]))
        if not self.change[i] > point:
            return None
        return float(self.fm[i]), float(self.fm[i + 1]), float(self.change[i])
