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
from collections.abc import Callable, Generator
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from controller.core.arrays import ComplexArray, FloatArray
from controller.core.config import LoopConfig, NominalModel
from controller.core.verdict import VerdictKind
from controller.gate.knowledge import (
    MIN_ALLOWANCE,
    MeasuredResponse,
    PlantKnowledge,
    UncertaintyBound,
    readonly,
)
from controller.gate.loop_model import (
    DB_3,
    TWO_PI,
    DobFilters,
    GainBlocks,
    LoopBlocks,
    closed_loop_matrix,
    default_grid,
    discrete_plant,
    dob_filters,
    gain_blocks,
    loop_blocks,
    loop_blocks_groups,
    nominal_continuous_response,
    plant_response,
    with_zoh,
    zoh_terms,
)
from controller.gate.margins import (
    LoopCrossings,
    LoopTasks,
    Margins,
    Outputs,
    RefineTask,
    bandwidth_of,
    crossings_of,
    loop_tasks_rows,
    margins_of,
    peak_task,
    peak_tasks_rows,
    solve,
    solve_groups,
    winding_ok,
    windings_ok,
)

__all__ = [
    "UNRESOLVED_ALLOWANCE",
    "UNRESOLVED_CHANGE",
    "Analysis",
    "GateLimits",
    "SourceResult",
    "accepted",
    "accepted_cutoffs",
    "analyse",
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
#: Winding-number refinement: adjacent points whose phase differs by more than this are split.
_MAX_PHASE_STEP_RAD = math.radians(20.0)
_MAX_WINDING_POINTS = 40000


@dataclass(frozen=True)
class GateLimits:
    """Limits of the apply gate (validated on construction).

    Below a margin limit the verdict is `caution` (stable on all evidence, applied only with
    confirmation); instability on any evidence, or a robust-stability test at or above 1, is
    `reject`.
    """

    phase_margin_min_deg: float = 30.0
    gain_margin_min_db: float = 6.0
    """Applies to |GM| in dB: an upper margin must exceed it, a gain-reduction margin too."""
    peak_sensitivity_max_db: float = 6.0
    small_gain_max: float = 0.8
    """Caution at or above this robust-stability figure (max |a T| over the evidence's
    allowance a); at or above 1 the loop is not proven stable: reject."""
    pole_radius_max: float = 1.0
    """Strict: every closed-loop pole radius with the plant model must be < this."""
    pole_time_constant_max_s: float = 100.0
    """The margin from instability on the model's poles: every closed-loop mode must decay
    with a time constant below this, radius < exp(-Ts / this) (1 - 1e-5 at 1 kHz); a pole
    at radius 1 - 1e-6 is as good as unstable (a 0.0001 % plant change moves it out)."""
    stability_margin_min: float = 0.1
    """The margin from instability on every loop and every piece of evidence that decides:
    the Nyquist curve must keep this distance from -1 (min |1 + L| at the plant input, the
    inverse of the peak sensitivity: 0.1 is 20 dB; a loop closer is rejected, not cautioned)."""
    check_measured_margins: bool = True
    """Also hold the margins computed with each measured response to the limits."""
    noise_to_command_max_db: float = 20.0
    """Peak gain from speed-measurement noise to the command, |(Cv + F1) / D|: a high Q
    cut-off makes F1 ~ Q (Mn Pn)^-1 differentiate twice and floods the drive with noise."""

    def __post_init__(self) -> None:
        def need(ok: bool, what: str) -> None:
            if not ok:
                raise ValueError(f"GateLimits: {what}")

        need(0.0 <= self.phase_margin_min_deg < 90.0, "phase_margin_min_deg in [0, 90)")
        need(0.0 <= self.gain_margin_min_db < 60.0, "gain_margin_min_db in [0, 60)")
        need(0.0 < self.peak_sensitivity_max_db < 60.0, "peak_sensitivity_max_db in (0, 60)")
        need(0.0 < self.small_gain_max <= 1.0, "small_gain_max in (0, 1]")
        need(0.0 < self.pole_radius_max <= 1.0, "pole_radius_max in (0, 1]")
        need(0.0 < self.pole_time_constant_max_s <= 1e6, "pole_time_constant_max_s in (0, 1e6]")
        need(0.0 <= self.stability_margin_min < 1.0, "stability_margin_min in [0, 1)")
        need(0.0 < self.noise_to_command_max_db <= 80.0, "noise_to_command_max_db in (0, 80]")

    def pole_radius_limit(self, rate_hz: float) -> float:
        """Every closed-loop pole radius must be strictly below this at `rate_hz`."""
        tau = self.pole_time_constant_max_s
        return min(self.pole_radius_max, math.exp(-1.0 / (rate_hz * tau)))


# --------------------------------------------------------------------------- result objects


@dataclass(frozen=True, eq=False)
class SourceResult:
    """What one piece of evidence says about the candidate.

    kind "model": the plant model (exact closed-loop poles) with its stated bound as the
    allowance; "measured": a measured response (winding number on a refined grid) with the
    allowance between its points and the bound beyond its band.
    """

    name: str
    kind: Literal["model", "measured", "bound"]
    small_gain_peak: float
    """Robust-stability figure max |a T| with the speed loop alone (nan: no allowance)."""
    small_gain_freq_hz: float
    small_gain_full_peak: float
    """The same with the position loop closed."""
    small_gain_full_freq_hz: float
    delta_q_peak: float
    """max |a Q| (display only; not a sufficient condition)."""
    delta_q_freq_hz: float
    base_loop_stable: bool
    """The loop with this evidence's plant (model: exact poles; measured: the interpolated
    response, argument principle), speed loop alone and whole servo."""
    margins: Margins | None
    """Margins of the speed loop at the plant input with this evidence's plant."""
    inv_delta_db: FloatArray
    """20 log10 (1 / a) on the analysis grid: the plant change this evidence allows."""
    margins_full: Margins | None = None
    """Margins of the whole servo (position loop closed) at the plant input."""
    band_hz: tuple[float, float] | None = None
    """The measured band (measured responses only)."""


@dataclass(frozen=True, eq=False)
class Analysis:
    """Everything the dashboard plots and the gate decides on, for one candidate."""

    config: LoopConfig
    tau_s: float
    freq_hz: FloatArray
    open_loop: ComplexArray
    """L_u on the grid (plant model; DOB off: G Cv)."""
    open_loop_mag_db: FloatArray
    open_loop_phase_deg: FloatArray
    """Unwrapped."""
    closed_loop: ComplexArray
    """Gyw with the configured DOB state (eq. 15, or eq. 18 when the DOB is off)."""
    closed_loop_dob: ComplexArray
    """Gyw with the DOB on (eq. 15), whatever cfg.dob_on."""
    closed_loop_no_dob: ComplexArray
    """Gyw without the DOB (eq. 18)."""
    disturbance_dob: ComplexArray
    """Gdw with the DOB (eq. 16)."""
    disturbance_no_dob: ComplexArray
    """Gdw without the DOB (eq. 18)."""
    noise_dob: ComplexArray
    """Gzw with the DOB (eq. 17)."""
    noise_no_dob: ComplexArray
    q_mag_db: FloatArray
    """|F2| (the implemented Q) in dB."""
    rejection_db: FloatArray
    """eq. 23: 20 log10 |E_without / E_with|; > 0 where the DOB helps."""
    margins: Margins
    """Speed loop at the plant input, plant model."""
    bandwidth_hz: float
    """-3 dB bandwidth of the speed closed loop Gyw (configured DOB state)."""
    poles: ComplexArray
    """Closed-loop eigenvalues of the whole discrete servo with the plant model."""
    max_pole_radius: float
    """Over the whole servo and the speed loop alone."""
    sources: tuple[SourceResult, ...]
    small_gain_peak: float
    """Largest robust-stability figure over all evidence and both loops (nan without)."""
    verdict: VerdictKind
    reasons: tuple[str, ...]
    """Rejections first, then cautions."""
    noise_to_command_peak_db: float = math.nan
    """max |(Cv + F1)/D| in dB: how much speed-measurement noise reaches the command."""
    rejections: tuple[str, ...] = ()
    cautions: tuple[str, ...] = ()
    margins_full: Margins | None = None
    """The whole servo (position loop closed) at the plant input, plant model."""
    knowledge: str = ""
    """Which plant knowledge the verdict used (`PlantKnowledge.describe`)."""
    open_loop_full: ComplexArray | None = None
    """The whole servo's loop at the plant input, G (C_tot + F1) / (1 - F2 z^-1), plant model."""
    crossings: LoopCrossings | None = None
    """Where `margins` are read: the speed loop's refined crossings (plant model)."""

    @property
    def accepted(self) -> bool:
        """Accepted without reservation."""
        return self.verdict == "accept"

    @property
    def applicable(self) -> bool:
        """Accepted, or `caution` (applied only with confirmation)."""
        return self.verdict != "reject"

    @property
    def gain_margin_db(self) -> float:
        return self.margins.gain_margin_db

    @property
    def phase_margin_deg(self) -> float:
        return self.margins.phase_margin_deg

    @property
    def peak_sensitivity_db(self) -> float:
        return self.margins.peak_sensitivity_db

    @property
    def delay_margin_s(self) -> float:
        return self.margins.delay_margin_s


# --------------------------------------------------------------------------- evidence


_Intervals = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                   np.ndarray | None]


class _Points:
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


#: `_MeasuredModel`s by (response object, rate, model, bound object): every candidate judged
#: on the same knowledge shares them, with the grids they were asked for (the analysis grid
#: with the measured points is the same for every candidate). Bounded.
_MEASURED: dict[tuple[MeasuredResponse, float, NominalModel, UncertaintyBound | None],
                _MeasuredModel] = {}
_MEASURED_MAX = 32


def _measured_model(
    m: MeasuredResponse, rate_hz: float, model: NominalModel, bound: UncertaintyBound | None
) -> _MeasuredModel:
    key = (m, rate_hz, model, bound)
    mm = _MEASURED.get(key)
    if mm is None:
        mm = _MeasuredModel(m, rate_hz, model, bound)
        if len(_MEASURED) >= _MEASURED_MAX:
            _MEASURED.clear()
        _MEASURED[key] = mm
    return mm


class _MeasuredModel:
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
        if not keep or f.size < _GainMemo.MIN_POINTS:
            return make(f)
        key = (what, f.tobytes())
        got = self._kept.get(key)
        if got is None:
            got = readonly(make(f))
            if len(self._kept) >= self._GRIDS_MAX:
                self._kept.clear()
            self._kept[key] = got
        return got

    def points(self, f: FloatArray) -> _Points:
        """`f` with what depends on it alone, for this response's model, rate and bound."""
        return _Points(f, self.rate_hz, self.model, self.bound)

    def _ratio(self, pts: _Points) -> ComplexArray:
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

    def plant_at(self, pts: _Points, g_model: ComplexArray) -> ComplexArray:
        """`plant` at points shared with other responses of the same model, rate and bound
        (not kept)."""
        if self.sampled:
            return g_model * self._ratio(pts)
        return self._continuous_plant(pts)

    def _continuous_plant(self, pts: _Points) -> ComplexArray:
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

    def allowance_at(self, pts: _Points) -> FloatArray:
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


def _integrators(cfg: LoopConfig, with_position: bool) -> int:
    m = 1 if cfg.cv_ki_per_s > 0 else 0
    if with_position:
        m += 1 + (1 if cfg.pos_ki_per_s > 0 else 0)
    return m


def _fmt_hz(f: float) -> str:
    return f"{f:.3g} Hz"


def _controller_parts(b: LoopBlocks, on: bool) -> tuple[ComplexArray, ComplexArray, ComplexArray]:
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
        bad = np.nonzero(step > _MAX_PHASE_STEP_RAD)[0]
        if bad.size == 0:
            return f, d
        if f.size + bad.size > _MAX_WINDING_POINTS:
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
    one, ks, kf = _controller_parts(bk, on)
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
            f" (at {_fmt_hz(float(f[k_noise]))}; plant model)"
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
    (`_MeasuredPasses`), then one refinement for all of them, each round evaluating the loop,
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
    gains = _GainMemo(cfg, model)
    survivors: list[tuple[int, LoopConfig, DobFilters | None, LoopBlocks, float]] = []
    for i, fc in enumerate(cutoffs_hz):
        c = cfg.with_(q_cutoff_hz=fc)
        used = dob_filters(c) if on else None
        bk = loop_blocks(c, used, f, model, gains(f))
        one, ks, _ = _controller_parts(bk, on)
        if not _noise_to_command(bk.g, ks, one)[0] <= limits.noise_to_command_max_db:
            continue  # a caution
        _, max_radius = _poles(c, used, model)
        if not max_radius < limits.pole_radius_limit(c.rate_hz):
            continue  # a rejection, or a caution with measured responses
        survivors.append((i, c, used, bk, max_radius))
    if survivors:
        passes = _MeasuredPasses(plant, f, [(c, _BlocksMemo(c, used, model, gains))
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
        out = first.outputs(ff, b, _Points(ff, cfg.rate_hz, model, plant.bound))
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
        return st.outputs(ff, b, _Points(ff, cfg.rate_hz, model, plant.bound))

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

    def outputs(self, ff: FloatArray, b: LoopBlocks, pts: _Points) -> Outputs:
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
    *, decisive_only: bool = False, batch: tuple[_MeasuredPasses, int] | None = None,
) -> _Started | None:
    """Every piece of evidence up to its refinement (with `decisive_only`, None at the first
    reason: the candidate is not accepted; `batch`: the measured responses' first passes,
    shared with other cut-offs, and this candidate's place among them)."""
    on = cfg.dob_on
    if batch is None:
        batch = (_MeasuredPasses(plant, f, [(cfg, _BlocksMemo(cfg, used, plant.model))]), 0)
    passes, case = batch
    reasons: list[tuple[list[str], list[str]]] = [([], []) for _ in range(len(plant.measured) + 1)]
    model_part = _model_evidence(
        cfg, plant, f, x, bk, limits, max_radius, on, gyw, *reasons[0], decisive_only)
    measured_parts = [
        _measured_evidence(cfg, passes, case, i, f, limits, *reasons[i + 1], decisive_only)
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


def _margin_reasons(m: Margins, limits: GateLimits, where: str, out: list[str]) -> None:
    """Cautions for margins below the limits (`where` names the loop and the evidence)."""
    if not m.phase_margin_deg >= limits.phase_margin_min_deg:
        out.append(
            f"phase margin {m.phase_margin_deg:.1f} deg < {limits.phase_margin_min_deg:g} deg"
            f" (at {_fmt_hz(m.gain_crossover_hz)}; {where})"
        )
    if not abs(m.gain_margin_db) >= limits.gain_margin_min_db:
        if m.gain_margin_db < 0:
            out.append(
                f"conditionally stable: a gain reduction of {-m.gain_margin_db:.1f} dB "
                f"(< {limits.gain_margin_min_db:g} dB, as a saturating command gives) "
                f"destabilises it (at {_fmt_hz(m.phase_crossover_hz)}; {where})"
            )
        else:
            out.append(
                f"gain margin {m.gain_margin_db:.1f} dB < {limits.gain_margin_min_db:g} dB"
                f" (at {_fmt_hz(m.phase_crossover_hz)}; {where})"
            )
    if not m.peak_sensitivity_db <= limits.peak_sensitivity_max_db:
        out.append(
            f"peak sensitivity {m.peak_sensitivity_db:.1f} dB > "
            f"{limits.peak_sensitivity_max_db:g} dB (at {_fmt_hz(m.peak_sensitivity_hz)}; {where})"
        )


def _distance_reasons(m: Margins, limits: GateLimits, where: str, out: list[str]) -> None:
    """A rejection when the Nyquist curve passes closer to -1 than the stated margin."""
    sm = 10.0 ** (-m.peak_sensitivity_db / 20.0)
    if not sm >= limits.stability_margin_min:
        out.append(
            f"no margin from instability: the Nyquist curve passes within {sm:.3g} of -1"
            f" (< {limits.stability_margin_min:g}; peak sensitivity"
            f" {m.peak_sensitivity_db:.1f} dB at {_fmt_hz(m.peak_sensitivity_hz)}; {where})"
        )


def _robust_reasons(
    task: RefineTask, which: str, evidence: str, limits: GateLimits,
    band_top_hz: float | None, a_of: Callable[[FloatArray], FloatArray],
    t_of: Callable[[FloatArray], FloatArray], f: FloatArray,
    rejections: list[str], cautions: list[str], symbol: str = "|a T|",
    sparse: tuple[float, float, float] | None = None,
) -> None:
    """Reject when max |a T| >= 1 (not proven stable for every plant the evidence allows),
    caution at >= small_gain_max. Beyond a measured band the reason says how far to measure;
    inside it, where the allowance comes from the interpolation between two measured points
    (`sparse`: the interval and the change across it), that the points do not resolve the
    response there and where to measure denser."""
    v = task.value
    if v < limits.small_gain_max:
        return
    text = (
        f"robust stability ({which}): {symbol} peaks at {v:.3g} at {_fmt_hz(task.freq_hz)}"
        f" for {evidence}"
    )
    if v < 1.0:
        cautions.append(text + f" (>= {limits.small_gain_max:g}: little room for plant error)")
        return
    if band_top_hz is not None and task.freq_hz > band_top_hz:
        # Where does the loop stop depending on the unmeasured plant?
        fine = np.geomspace(band_top_hz, f[-1], 400)
        over = fine[a_of(fine) * t_of(fine) >= 1.0]
        top = float(over[-1]) if over.size else task.freq_hz
        rejections.append(
            text + f": the loop depends on the plant above the measured band "
            f"({_fmt_hz(band_top_hz)}), known there only within the bound; "
            f"measure up to {_round_up(top)} Hz first"
        )
        return
    if sparse is not None:
        lo, hi, change = sparse
        rejections.append(
            text + f" >= 1: the measured points do not resolve the response there (it changes"
            f" by a factor {math.exp(change):.3g} between {_fmt_hz(lo)} and {_fmt_hz(hi)},"
            f" a sharp mode may sit between them): measure denser between {_fmt_hz(lo)} and"
            f" {_fmt_hz(hi)} first"
        )
        return
    rejections.append(text + " >= 1: not proven stable for every plant this evidence allows")


def _on_grid(x: FloatArray, vals: FloatArray) -> Callable[[FloatArray], FloatArray]:
    """vals (given at log frequencies x) as a function of frequency, linear in log f."""

    def at(ff: FloatArray) -> FloatArray:
        return np.asarray(np.interp(np.log(ff), x, vals), dtype=np.float64)

    return at


def _round_up(f: float) -> str:
    """A frequency rounded up to two significant digits."""
    e = 10.0 ** (math.floor(math.log10(f)) - 1)
    return f"{math.ceil(f / e) * e:.3g}"


#: What an evidence hands to the analysis's one refinement (`solve`) of every evidence's
#: crossings and peaks: its tasks, and its outputs at any frequencies given the loop's blocks
#: there and what depends on the points alone (`_Points`; keys prefixed per evidence). Results
#: are per frequency point, so refining every evidence's tasks together gives each task what
#: refining it alone gives.
Refinement = tuple[list[RefineTask], Callable[[FloatArray, LoopBlocks, _Points], Outputs]]


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
    one, ks, kf = _controller_parts(bk, on)
    g = bk.g

    with_bound = bound is not None and not (decisive_only and has_measured)  # (else display)

    def ev(ff: FloatArray, b: LoopBlocks, pts: _Points) -> Outputs:
        o, s_, f_ = _controller_parts(b, on)
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
        _margin_reasons(margins, limits, f"speed loop, {where}", cautions)
        _margin_reasons(margins_full, limits, f"whole servo, {where}", cautions)
        if not has_measured:
            _distance_reasons(margins, limits, f"speed loop, {where}", rejections)
            _distance_reasons(margins_full, limits, f"whole servo, {where}", rejections)
    if bound is not None and not has_measured:
        evidence = f"the {where} within {bound.name!r}"
        for t, which, tt in zip(bound_tasks, ("speed loop", "whole servo"),
                                (t_speed, t_full), strict=True):
            _robust_reasons(
                t, which, evidence, limits, None, bound.magnitude,
                _on_grid(x, np.abs(tt)), f, rejections, cautions, "||W T||",
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


class _GainMemo:
    """`gain_blocks` of one loop's gains per frequency grid (by its values), shared by the
    cut-offs judged together (`accepted_cutoffs`). Grids of a few refinement points are
    computed every time (not worth a key)."""

    MIN_POINTS = 64

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


class _BlocksMemo:
    """`loop_blocks` of one analysis's loop per frequency grid (by its values): the measured
    responses share their grids, and each asks for the same grid several times (`gains`:
    the gains' blocks, shared with other cut-offs)."""

    MIN_POINTS = _GainMemo.MIN_POINTS

    def __init__(self, cfg: LoopConfig, used: DobFilters | None, model: NominalModel,
                 gains: _GainMemo | None = None) -> None:
        self._cfg, self._used, self._model = cfg, used, model
        self._gains = gains if gains is not None else _GainMemo(cfg, model)
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
class _FirstPass:
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


class _MeasuredPasses:
    """Every measured response's `_FirstPass` for one or more candidates that differ only in
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
                 cases: list[tuple[LoopConfig, _BlocksMemo]]) -> None:
        rate_hz = cases[0][0].rate_hz
        self.mms = [_measured_model(m, rate_hz, plant.model, plant.bound)
                    for m in plant.measured]
        self.tags = [f"{i}:" for i in range(len(self.mms))]
        self._f0, self._cases = f0, cases
        self._passes: dict[tuple[int, int], _FirstPass] | None = None

    def blocks(self, case: int) -> _BlocksMemo:
        return self._cases[case][1]

    def get(self, case: int, i: int) -> _FirstPass:
        """Response i's pass with candidate `case`."""
        if self._passes is None:
            self._passes = self._compute()
        return self._passes[case, i]

    def _compute(self) -> dict[tuple[int, int], _FirstPass]:
        mms = self.mms
        grids = [mm.grid(self._f0) for mm in mms]
        by_grid: dict[bytes, list[int]] = {}
        for i, g in enumerate(grids):
            by_grid.setdefault(g.tobytes(), []).append(i)
        passes: dict[tuple[int, int], _FirstPass] = {}
        for rows in by_grid.values():
            f = grids[rows[0]]
            k = len(rows)
            gk_parts: list[ComplexArray] = []
            d_parts: list[ComplexArray] = []
            ones: list[ComplexArray] = []
            for cfg, lb in self._cases:
                b = lb(f)
                one, ks, kf = _controller_parts(b, cfg.dob_on)
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
                turns = np.any(np.abs(np.angle(d[:, 1:] / d[:, :-1])) > _MAX_PHASE_STEP_RAD,
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
                ms = [_integrators(self._cases[c][0], False) for c, _ in together]
                mf = [_integrators(self._cases[c][0], True) for c, _ in together]
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
               loops: list[tuple[ComplexArray, bool, bool]]) -> _FirstPass:
        """Response i's pass with candidate `case` on its own, given (1 - F2 z^-1 + G_m (C +
        F1) on f, finite and non-zero, turning slowly enough) of its speed loop and its whole
        servo: a loop that turns too fast is refined (`refine_by_phase`)."""
        mm = self.mms[i]
        cfg, lb = self._cases[case]
        on = cfg.dob_on

        def d_of(full: bool) -> Callable[[FloatArray], ComplexArray]:
            def d(ff: FloatArray) -> ComplexArray:
                b = lb(ff)
                o, s_, f_ = _controller_parts(b, on)
                return o + mm.plant(ff, b.g) * (f_ if full else s_)
            return d

        r_speed, r_full = (
            None if not fine else (f, d) if clean else refine_by_phase(d_of(full), f)
            for full, (d, fine, clean) in zip((False, True), loops, strict=True)
        )
        stable = (
            r_speed is not None and r_full is not None
            and winding_ok(r_speed[1], _integrators(cfg, False))
            and winding_ok(r_full[1], _integrators(cfg, True))
        )
        if r_speed is not None and r_full is not None:
            f = np.union1d(r_speed[0], r_full[0])
        b = lb(f)
        one, ks, kf = _controller_parts(b, on)
        gm = mm.plant(f, b.g)
        gk = np.stack([gm * ks, gm * kf])
        return self._tasks(f, gk, one + gk, one, [(case, i)], [stable])[case, i]

    def _tasks(self, f: FloatArray, gk: ComplexArray, d: ComplexArray, one: ComplexArray,
               which: list[tuple[int, int]], stable: list[bool]
               ) -> dict[tuple[int, int], _FirstPass]:
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
            w: _FirstPass(f, x, stable[j], t[j], t[n + j], a[j], lts[j], lts[n + j], peaks[j],
                          peaks[n + j])
            for j, w in enumerate(which)
        }


def _measured_evidence(
    cfg: LoopConfig, passes: _MeasuredPasses, case: int, i: int, f0: FloatArray,
    limits: GateLimits, rejections: list[str], cautions: list[str],
    decisive_only: bool = False,
) -> Generator[Refinement, None, SourceResult | None]:
    """A measured response's evidence (`decisive_only`: only what can give a reason, None for
    the conclusion, and no refinement after a rejection by the argument principle), from its
    first pass (`_MeasuredPasses`: the grid, the argument principle, the tasks)."""
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

    def ev(ff: FloatArray, b: LoopBlocks, pts: _Points) -> Outputs:
        o, s_, f_ = _controller_parts(b, on)
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
            _margin_reasons(margins, limits, f"speed loop, {where}", cautions)
            _margin_reasons(margins_full, limits, f"whole servo, {where}", cautions)
        _distance_reasons(margins, limits, f"speed loop, {where}", rejections)
        _distance_reasons(margins_full, limits, f"whole servo, {where}", rejections)
        hi = mm.band_hz[1]
        for t, which, tt in ((sp, "speed loop", t_speed), (fp, "whole servo", t_full)):
            unresolved = [u for u in mm.unresolved if u[0] <= t.freq_hz <= u[1]]
            if unresolved and t.value >= 1.0:
                u = unresolved[0]
                rejections.append(
                    f"robust stability ({which}): the {where} changes by a factor "
                    f"{math.exp(u[2]):.3g} between {_fmt_hz(u[0])} and {_fmt_hz(u[1])} (a mode "
                    f"between the points) where the loop has gain |T| = "
                    f"{t.value / UNRESOLVED_ALLOWANCE:.3g}:"
                    f" measure denser between {_fmt_hz(u[0])} and {_fmt_hz(u[1])} first"
                )
                continue
            _robust_reasons(
                t, which, where, limits, hi, mm.allowance,
                _on_grid(x, tt), f, rejections, cautions,
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
