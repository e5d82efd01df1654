"""Stability analysis of a candidate configuration and the apply gate (pure math, no I/O).

The loop analysed is exactly the one `controller.core.loop` runs at fs = cfg.rate_hz (Ts = 1/fs):

    w[k]  = (theta[k] - theta[k-1]) / Ts          backward difference of the load encoder
    r     = Cp(z) (theta_ref - theta) + ff        Cp = kp_pos (1 + ki_pos Ts/2 (z+1)/(z-1))
    u     = Cv(z) (r - w) - d_hat                 Cv = cv_kp (1 + cv_ki Ts/2 (z+1)/(z-1))
    d_hat = F1(z) w - F2(z) z^-1 u                F1, F2: the implemented SOS of `design_dob`

and u is held (ZOH) until the next tick. The nominal plant from u to w is therefore

    G(z) = (1 - z^-1)/Ts * ZOH{ Mn(s) Pn(s) / s }

(exact, built once per (nominal, rate) from a matrix exponential); it holds the one-sample
delay of a sampled loop. With C = Cv, and D = 1 - F2 z^-1 + G (Cv + F1) (DOB off: 1 + G Cv):

    speed closed loop   Gyw = G Cv / D                       (eq. 15; DOB off eq. 18)
    disturbance         Gdw = Pd (1 - F2 z^-1) / D           (eq. 16; DOB off Pd/(1 + G Cv))
    noise               Gzw = G (Cv + F1) / D                (eq. 17)
    loop at plant input L_u = G (Cv + F1) / (1 - F2 z^-1),   S = 1/(1 + L_u) = (1 - F2 z^-1)/D
    eq. 23              E_without / E_with = D / ((1 - F2 z^-1)(1 + G Cv))   (> 1: DOB helps)
    eq. 21              X = (G_m F1 - F2 z^-1) / (1 + G_m Cv)  for a measured plant G_m

Pd, the path of a load-side rate disturbance (d enters at the input of P), is taken as
G(z) / Mn(j w): the sampled plant without the drive's speed loop.

With the position loop closed the controller seen from w is C_tot = Cv (1 + Cp Ts/(1 - z^-1))
(theta = Ts/(1 - z^-1) w exactly). The gate checks the loop the controller really runs, so the
small-gain tests are evaluated twice: with the speed loop alone (the article's eq. 21, reported)
and with C_tot in place of Cv (what makes the verdict sound for the full three-loop servo).

Why the gate is sound, and what it assumes:
* nominal plant: exact closed-loop eigenvalues of the whole discrete loop (plant, w and theta,
  Cp, Cv, F1, F2 and the one-sample delay), all strictly inside the unit circle;
* measured plant G_m (no poles known): D_m = (1 + G_m C)(1 + X). If the loop without DOB,
  1 + G_m C, is stable (checked from the data by the argument principle: the phase of
  1 + G_m C must turn by m*90 deg from 0+ to Nyquist, m = integrators of C) and |X| < 1 on the
  whole unit circle, then D_m has no zero outside the circle (small-gain theorem, eq. 21-22);
* uncertainty bound |Delta| <= |W|: D_Delta = D (1 + Delta T), T = G (C + F1) / D, so
  ||W T||_inf < 1 is the exact robust-stability test for all such Delta. ||Delta Q|| < 1
  alone is not sufficient (control.md) and is only reported.
Measured continuous responses G_c(jw) become discrete by the ZOH + backward-difference
equivalent G_c(jw) e^{-jwTs} sinc^2(w Ts/2), valid well below Nyquist (aliasing neglected).
Measured data are interpolated as their ratio R = G_c / (Mn Pn) to the nominal model (log
magnitude and unwrapped phase, linear in log f), so a response equal to the model gives
Delta = 0 exactly; outside the measured band Delta is held at its value at the nearest end.
The argument-principle test assumes the grid starts where the integrators dominate and ends
where |L| << 1 (the default grid, 0.01 Hz to Nyquist, does); if not, it reports "not proven".
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import linalg, signal

from controller.core.config import LoopConfig, NominalModel
from controller.core.discrete import SosArray, sos_response
from controller.core.dob import design_dob
from controller.core.qfilter import Q_TYPES, QType, check_q_type
from controller.gate.knowledge import (
    MeasuredResponse,
    PlantKnowledge,
    readonly,
)

__all__ = [
    "Analysis",
    "GateLimits",
    "Margins",
    "SourceResult",
    "analyse",
    "default_grid",
    "discrete_equivalent",
    "nominal_continuous_response",
    "recommended_max_cutoff_hz",
]

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
Verdict = Literal["accept", "reject"]

_TWO_PI = 2.0 * math.pi
_DB_3 = 10.0 ** (-3.0 / 20.0)  # -3 dB, as python-control's bandwidth()


@dataclass(frozen=True)
class GateLimits:
    """Acceptance limits of the apply gate (validated on construction)."""

    phase_margin_min_deg: float = 30.0
    gain_margin_min_db: float = 6.0
    """Applies to |GM| in dB: an upper margin must exceed it, a gain-reduction margin too."""
    peak_sensitivity_max_db: float = 6.0
    small_gain_max: float = 0.8
    """Limit for eq. 21 (measured responses) and ||W T|| (uncertainty bound); < 1 is proof."""
    pole_radius_max: float = 1.0
    """Strict: every closed-loop pole radius must be < this."""
    check_measured_margins: bool = True
    """Also hold the margins of L_u computed with each measured response to the limits."""
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
        need(0.0 < self.noise_to_command_max_db <= 80.0, "noise_to_command_max_db in (0, 80]")


# --------------------------------------------------------------------------- result objects


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


@dataclass(frozen=True, eq=False)
class SourceResult:
    """Robustness figures for one source of plant knowledge (a measured response or a bound)."""

    name: str
    kind: Literal["measured", "bound"]
    small_gain_peak: float
    """Measured: max |X| of eq. 21 (speed loop); bound: ||W T||_inf with the speed loop."""
    small_gain_freq_hz: float
    small_gain_full_peak: float
    """The same with the position loop closed (C_tot in place of Cv)."""
    small_gain_full_freq_hz: float
    delta_q_peak: float
    """||Delta Q||_inf (display only; not a sufficient condition)."""
    delta_q_freq_hz: float
    base_loop_stable: bool
    """Measured: the loop without DOB, with and without the position loop, passes the
    argument-principle test (always True for a bound: the nominal poles cover it)."""
    full_loop_winding_ok: bool
    """Measured: the whole loop (DOB and position loop as configured) passes the argument-
    principle test on D_m = 1 - F2 z^-1 + G_m (C_tot + F1) itself. Exact where the grid is
    adequate, unlike the sufficient eq. 21; reported only, not part of the verdict."""
    margins: Margins | None
    """Margins of L_u computed with this response (None for a bound)."""
    inv_delta_db: FloatArray
    """20 log10 (1/|Delta|) on the analysis grid (for a bound: 1/|W|)."""


@dataclass(frozen=True, eq=False)
class Analysis:
    """Everything the dashboard plots and the gate decides on, for one candidate."""

    config: LoopConfig
    tau_s: float
    freq_hz: FloatArray
    open_loop: ComplexArray
    """L_u on the grid (nominal plant; DOB off: G Cv)."""
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
    bandwidth_hz: float
    """-3 dB bandwidth of the speed closed loop Gyw (configured DOB state)."""
    poles: ComplexArray
    """Closed-loop eigenvalues of the whole discrete loop with the nominal plant."""
    max_pole_radius: float
    sources: tuple[SourceResult, ...]
    small_gain_peak: float
    """Largest small-gain value over all sources and both loops (nan without sources)."""
    verdict: Verdict
    reasons: tuple[str, ...]
    noise_to_command_peak_db: float = math.nan
    """max |(Cv + F1)/D| in dB: how much speed-measurement noise reaches the command."""

    @property
    def accepted(self) -> bool:
        return self.verdict == "accept"

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


# --------------------------------------------------------------------------- building blocks


def default_grid(rate_hz: float, n: int = 500) -> FloatArray:
    """`n` log-spaced frequencies from 0.01 Hz to just below Nyquist."""
    return _default_grid(float(rate_hz), int(n))


@lru_cache(maxsize=32)
def _default_grid(rate_hz: float, n: int) -> FloatArray:
    return readonly(np.geomspace(0.01, 0.4999 * rate_hz, n))


def _poly_roots(p: tuple[float, float, float]) -> tuple[list[complex], float]:
    c = np.trim_zeros(np.asarray(p, dtype=np.float64), "f")
    return [complex(r) for r in np.roots(c)], float(c[0])


def _mp_zpk(nominal: NominalModel) -> tuple[list[complex], list[complex], float]:
    """Mn(s) Pn(s) as zeros, poles, gain; common roots cancelled."""
    zeros, kn = _poly_roots(nominal.pn_num)
    pm, km = _poly_roots(nominal.mn_den)
    pd, kd = _poly_roots(nominal.pn_den)
    poles = pm + pd
    for z in list(zeros):
        for i, p in enumerate(poles):
            if abs(z - p) <= 1e-9 * max(1.0, abs(p)):
                zeros.remove(z)
                del poles[i]
                break
    return zeros, poles, kn / (km * kd)


def nominal_continuous_response(nominal: NominalModel, freq_hz: ArrayLike) -> ComplexArray:
    """Mn(jw) Pn(jw) (continuous, u -> load rate)."""
    s = 1j * _TWO_PI * np.asarray(freq_hz, dtype=np.float64)
    num = np.polyval(nominal.pn_num, s)
    den = np.polyval(nominal.mn_den, s) * np.polyval(nominal.pn_den, s)
    return np.asarray(num / den, dtype=np.complex128)


def discrete_equivalent(response: ArrayLike, freq_hz: ArrayLike, rate_hz: float) -> ComplexArray:
    """G_c(jw) e^{-jwTs} sinc^2(w Ts/2): ZOH + backward-difference rate, aliasing neglected.

    The k = 0 term of the exact sampled response; accurate well below Nyquist.
    """
    x = np.pi * np.asarray(freq_hz, dtype=np.float64) / rate_hz  # w Ts / 2
    sinc = np.sinc(x / np.pi)
    return np.asarray(response, dtype=np.complex128) * np.exp(-2j * x) * sinc * sinc


@dataclass(frozen=True, eq=False)
class _Plant:
    """Exact sampled plant, states [x; w; theta]: A, B; w = cw @ X, theta = ct @ X."""

    a: FloatArray
    b: FloatArray
    cw: FloatArray
    ct: FloatArray
    ag: FloatArray  # states [x; w] only: G(z) = cg (zI - ag)^-1 bg
    bg: FloatArray
    num: FloatArray  # G(z) = num(z^-1) / den(z^-1), ascending powers of z^-1
    den: FloatArray


@lru_cache(maxsize=64)
def _plant(nominal: NominalModel, rate_hz: float) -> _Plant:
    ts = 1.0 / rate_hz
    z, p, k = _mp_zpk(nominal)
    a, b, c, d = signal.zpk2ss(np.array(z), np.array(p), k)
    a, b, c, d = (np.real(np.atleast_2d(m)).astype(np.float64) for m in (a, b, c, d))
    n = a.shape[0]
    # Augment with theta' = C x + D u, then ZOH over one period (matrix exponential).
    big = np.zeros((n + 2, n + 2))
    big[:n, :n] = a
    big[:n, n + 1 :] = b
    big[n, :n] = c[0]
    big[n, n + 1] = d[0, 0]
    e = linalg.expm(big * ts)
    phi, gam = e[:n, :n], e[:n, n + 1]
    dth_x, dth_u = e[n, :n], e[n, n + 1]
    # X = [x; w; theta]: w[k+1] = (theta[k+1] - theta[k]) / Ts.
    ax = np.zeros((n + 2, n + 2))
    ax[:n, :n] = phi
    ax[n, :n] = dth_x / ts
    ax[n + 1, :n] = dth_x
    ax[n + 1, n + 1] = 1.0
    bx = np.concatenate([gam, [dth_u / ts, dth_u]])
    cw = np.zeros(n + 2)
    cw[n] = 1.0
    ct = np.zeros(n + 2)
    ct[n + 1] = 1.0
    ag, bg = ax[: n + 1, : n + 1], bx[: n + 1]
    cg = cw[: n + 1]
    num, den = signal.ss2tf(ag, bg[:, None], cg[None, :], np.zeros((1, 1)))
    # In z: num(z)/den(z) with equal lengths; as polynomials in z^-1 the same arrays apply.
    return _Plant(
        a=readonly(ax),
        b=readonly(bx),
        cw=readonly(cw),
        ct=readonly(ct),
        ag=readonly(ag),
        bg=readonly(bg),
        num=readonly(np.asarray(num[0], dtype=np.float64)),
        den=readonly(np.asarray(den, dtype=np.float64)),
    )


def _poly_zinv(coeffs: FloatArray, zinv: ComplexArray) -> ComplexArray:
    """sum_k c_k z^-k by Horner (coeffs in ascending powers of z^-1)."""
    out = np.full(zinv.shape, coeffs[-1], dtype=np.complex128)
    for c in coeffs[-2::-1]:
        out = out * zinv + c
    return out


def _plant_response(pl: _Plant, zinv: ComplexArray) -> ComplexArray:
    return _poly_zinv(pl.num, zinv) / _poly_zinv(pl.den, zinv)


def _sos_ss(sos: SosArray) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """State space of the SOS cascade exactly as `SosFilter` runs it (TDF-II per section)."""
    a = np.zeros((0, 0))
    b = np.zeros(0)
    c = np.zeros(0)
    d = 1.0
    for b0, b1, b2, _a0, a1, a2 in np.asarray(sos, dtype=np.float64):
        ai = np.array([[-a1, 1.0], [-a2, 0.0]])
        bi = np.array([b1 - a1 * b0, b2 - a2 * b0])
        ci = np.array([1.0, 0.0])
        n = a.shape[0]
        an = np.zeros((n + 2, n + 2))
        an[:n, :n] = a
        an[n:, :n] = np.outer(bi, c)
        an[n:, n:] = ai
        b = np.concatenate([b, bi * d])
        c = np.concatenate([b0 * c, ci])
        a = an
        d = b0 * d
    return a, b, c, float(d)


@dataclass(frozen=True, eq=False)
class _Dob:
    tau_s: float
    f1_sos: SosArray
    f2_sos: SosArray
    f1_ss: tuple[FloatArray, FloatArray, FloatArray, float]
    f2_ss: tuple[FloatArray, FloatArray, FloatArray, float]


def _dob(cfg: LoopConfig) -> _Dob:
    """The implemented DOB filters, cached per (Q type, cut-off, rate, nominal model)."""
    return _dob_cached(cfg.q_type, cfg.q_cutoff_hz, cfg.rate_hz, cfg.nominal)


@lru_cache(maxsize=256)
def _dob_cached(q_type: str, cutoff_hz: float, rate_hz: float, nominal: NominalModel) -> _Dob:
    # lru_cache keeps its own lock (CPython), so concurrent analyse() calls from GUI thread
    # pools share the cache safely; two callers may both compute a missing entry, which is
    # harmless: the design is a pure function of the key.
    d = design_dob(LoopConfig(q_type=q_type, q_cutoff_hz=cutoff_hz, rate_hz=rate_hz,
                              nominal=nominal))
    return _Dob(d.q.tau_s, d.f1_sos, d.f2_sos, _sos_ss(d.f1_sos), _sos_ss(d.f2_sos))


def _pi(kp: float, ki: float, ts: float, zinv: ComplexArray) -> ComplexArray:
    """Tustin PI kp (1 + ki Ts/2 (1 + z^-1)/(1 - z^-1)), as loop.py integrates."""
    return kp * (1.0 + ki * ts * 0.5 * (1.0 + zinv) / (1.0 - zinv))


@dataclass(frozen=True, eq=False)
class _Blocks:
    """Frequency responses of the loop pieces at some frequencies."""

    zinv: ComplexArray
    g: ComplexArray
    cv: ComplexArray
    ctot: ComplexArray
    f1: ComplexArray
    f2d: ComplexArray  # F2 z^-1


def _blocks(cfg: LoopConfig, dob: _Dob | None, f: FloatArray) -> _Blocks:
    ts = cfg.period_s
    zinv = np.exp(-1j * _TWO_PI * ts * f)
    g = _plant_response(_plant(cfg.nominal, cfg.rate_hz), zinv)
    cv = _pi(cfg.cv_kp, cfg.cv_ki_per_s, ts, zinv)
    cp = _pi(cfg.pos_kp_per_s, cfg.pos_ki_per_s, ts, zinv)
    ctot = cv * (1.0 + cp * ts / (1.0 - zinv))
    if dob is None:
        zero = np.zeros_like(zinv)
        return _Blocks(zinv, g, cv, ctot, zero, zero)
    f1 = sos_response(dob.f1_sos, f, cfg.rate_hz)
    f2d = sos_response(dob.f2_sos, f, cfg.rate_hz) * zinv
    return _Blocks(zinv, g, cv, ctot, f1, f2d)


# --------------------------------------------------------------------------- closed-loop poles


def _closed_loop_matrix(cfg: LoopConfig, dob: _Dob | None) -> FloatArray:
    """State matrix of the whole loop (references and disturbances zero)."""
    ts = cfg.period_s
    pl = _plant(cfg.nominal, cfg.rate_hz)
    npl = pl.a.shape[0]
    if dob is not None:
        a1, b1, c1, d1 = dob.f1_ss
        a2, b2, c2, d2 = dob.f2_ss
        n1, n2 = a1.shape[0], a2.shape[0]
    else:
        n1 = n2 = 0
    # State layout: plant | Cp integrator | Cv integrator | F1 | F2 | u[k-1] (if DOB).
    ip, icp, icv = 0, npl, npl + 1
    i1 = npl + 2
    i2 = i1 + n1
    idu = i2 + n2
    n = idu + (1 if dob is not None else 0)
    hp = cfg.pos_kp_per_s * cfg.pos_ki_per_s * ts * 0.5
    hv = cfg.cv_kp * cfg.cv_ki_per_s * ts * 0.5
    # Outputs as rows over the state vector (the plant has no feedthrough).
    w = np.zeros(n)
    w[ip:npl] = pl.cw
    th = np.zeros(n)
    th[ip:npl] = pl.ct
    # r = xcp + (kp + hp) e_pos with e_pos = -theta;  xcp+ = xcp + 2 hp e_pos.
    e_pos = -th
    r = (cfg.pos_kp_per_s + hp) * e_pos
    r[icp] += 1.0
    e = r - w
    v = (cfg.cv_kp + hv) * e
    v[icv] += 1.0
    u = v.copy()
    if dob is not None:
        y1 = d1 * w
        y1[i1:i2] += c1
        y2 = np.zeros(n)
        y2[i2:idu] = c2
        y2[idu] += d2
        u = v - y1 + y2
    a = np.zeros((n, n))
    a[ip:npl, ip:npl] = pl.a
    a[ip:npl] += np.outer(pl.b, u)
    a[icp] = 2.0 * hp * e_pos
    a[icp, icp] += 1.0
    a[icv] = 2.0 * hv * e
    a[icv, icv] += 1.0
    if dob is not None:
        a[i1:i2, i1:i2] += a1
        a[i1:i2] += np.outer(b1, w)
        a[i2:idu, i2:idu] += a2
        a[i2:idu, idu] += b2
        a[idu] = u
    return a


# --------------------------------------------------------------------------- refinement

Outputs = dict[str, ComplexArray]
Evaluator = Callable[[FloatArray], Outputs]


@dataclass(eq=False)
class _Task:
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


def _solve(tasks: list[_Task], ev: Evaluator, n: int = 9, rounds: int = 2) -> None:
    """Refine all tasks together: each round evaluates n points per bracket in one batched
    call and shrinks every bracket n/2-fold; a final secant (roots) or parabola (extrema)
    step and one more batched evaluation give the values at the refined frequencies."""
    if not tasks:
        return
    for _ in range(rounds):
        pts = np.concatenate([np.linspace(t.lo, t.hi, n) for t in tasks])
        outs = ev(np.exp(pts))
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
    final = ev(np.exp(np.array([t.x for t in tasks])))
    for j, t in enumerate(tasks):
        t.out = complex(final[t.key][j])
        t.value = float(t.fn(final[t.key][j : j + 1])[0])
        if t.kind != 0 and not (-t.kind * t.value <= -t.kind * t.best_v):
            t.x, t.value = t.best_x, t.best_v


def _log_mag(h: ComplexArray) -> FloatArray:
    return np.log(np.abs(h))


def _neg_arg(h: ComplexArray) -> FloatArray:
    return np.angle(-h)


def _dist(h: ComplexArray) -> FloatArray:
    return np.abs(1.0 + h)


def _abs(h: ComplexArray) -> FloatArray:
    return np.abs(h)


def _bw_fn(h: ComplexArray) -> FloatArray:
    return np.log(np.abs(h) / _DB_3)


@dataclass(eq=False)
class _LoopTasks:
    gain: list[_Task]
    phase: list[_Task]
    ms: _Task

    def all(self) -> list[_Task]:
        return [*self.gain, *self.phase, self.ms]


def _loop_tasks(x: FloatArray, loop: ComplexArray, key: str) -> _LoopTasks:
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
    return _LoopTasks(
        gain=[_Task(key, 0, _log_mag, float(x[k]), float(x[k + 1])) for k in gi],
        phase=[_Task(key, 0, _neg_arg, float(x[k]), float(x[k + 1])) for k in pi_],
        ms=_Task(key, -1, _dist, float(x[max(i - 1, 0)]), float(x[min(i + 1, x.size - 1)])),
    )


def _margins(t: _LoopTasks) -> Margins:
    """python-control's choice: the PM of smallest |PM|, the GM closest to 0 dB."""
    pm_deg, gm_db = math.inf, math.inf
    wgc, wpc = math.nan, math.nan
    delay = math.inf
    for g in t.gain:
        pm = (math.degrees(np.angle(g.out)) % 360.0) - 180.0
        if abs(pm) < abs(pm_deg):
            pm_deg, wgc = pm, g.freq_hz
        delay = min(delay, math.radians(pm) / (_TWO_PI * g.freq_hz) if pm > 0 else 0.0)
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


def _peak_task(x: FloatArray, vals: FloatArray, key: str) -> _Task:
    i = int(np.argmax(np.where(np.isfinite(vals), vals, -np.inf)))
    t = _Task(key, 1, _abs, float(x[max(i - 1, 0)]), float(x[min(i + 1, x.size - 1)]))
    t.best_x, t.best_v = float(x[i]), float(vals[i])
    return t


def _winding_ok(one_plus_l: ComplexArray, m_integrators: int) -> bool:
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
    ph = ph - _TWO_PI * np.round((ph[0] - start) / _TWO_PI)
    if abs(ph[0] - start) > np.radians(60.0):
        return False
    return bool(abs(ph[-1]) < 0.5 * np.pi)


# --------------------------------------------------------------------------- analyse


class _MeasuredModel:
    """A measured response as a function of frequency: nominal x interpolated ratio R."""

    def __init__(self, m: MeasuredResponse, cfg: LoopConfig) -> None:
        self.sampled = m.sampled
        self.cfg = cfg
        if m.sampled:
            zinv = np.exp(-1j * _TWO_PI * m.freq_hz / cfg.rate_hz)
            nom = _plant_response(_plant(cfg.nominal, cfg.rate_hz), zinv)
        else:
            nom = nominal_continuous_response(cfg.nominal, m.freq_hz)
        ratio = m.response / nom
        self.xm = np.log(m.freq_hz)
        self.logmag = np.log(np.abs(ratio))
        self.phase = np.unwrap(np.angle(ratio))

    def ratio(self, f: FloatArray) -> ComplexArray:
        xf = np.log(f)
        return np.exp(np.interp(xf, self.xm, self.logmag) + 1j * np.interp(xf, self.xm, self.phase))

    def discrete(self, f: FloatArray, g_nominal: ComplexArray) -> tuple[ComplexArray, ComplexArray]:
        """(G_m, Delta) at f given the exact nominal G at f."""
        r = self.ratio(f)
        if self.sampled:
            return g_nominal * r, r - 1.0
        gc = nominal_continuous_response(self.cfg.nominal, f) * r
        return discrete_equivalent(gc, f, self.cfg.rate_hz), r - 1.0


def _integrators(cfg: LoopConfig, with_position: bool) -> int:
    m = 1 if cfg.cv_ki_per_s > 0 else 0
    if with_position:
        m += 1 + (1 if cfg.pos_ki_per_s > 0 else 0)
    return m


def _fmt_hz(f: float) -> str:
    return f"{f:.3g} Hz"


def analyse(
    cfg: LoopConfig,
    plant: PlantKnowledge | None = None,
    limits: GateLimits | None = None,
    freq_hz: ArrayLike | None = None,
) -> Analysis:
    """Analyse a candidate configuration and decide whether it may be applied."""
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
    x = np.log(f)
    dob = _dob(cfg)
    on = cfg.dob_on
    used = dob if on else None
    bk = _blocks(cfg, dob, f)
    g, cv, ctot, f1, f2d = bk.g, bk.cv, bk.ctot, bk.f1, bk.f2d
    one_f2 = 1.0 - f2d
    gcv = g * cv
    d_on = one_f2 + g * (cv + f1)
    d_off = 1.0 + gcv
    mn = 1.0 / np.polyval(cfg.nominal.mn_den, 1j * _TWO_PI * f)
    pd = g / mn
    gyw_on = gcv / d_on
    gyw_off = gcv / d_off
    loop = g * (cv + f1) / one_f2 if on else gcv
    gyw = gyw_on if on else gyw_off
    bound = plant.bound

    def ev(ff: FloatArray) -> Outputs:
        b = _blocks(cfg, used, ff)
        k_speed = b.cv + b.f1
        one = 1.0 - b.f2d
        out = {"L": b.g * k_speed / one, "gyw": b.g * b.cv / (one + b.g * k_speed)}
        if bound is not None:
            w = bound.magnitude(ff)
            k_full = b.ctot + b.f1
            out["wts"] = w * b.g * k_speed / (one + b.g * k_speed)
            out["wtf"] = w * b.g * k_full / (one + b.g * k_full)
        return out

    lt = _loop_tasks(x, loop, "L")
    tasks = lt.all()
    below = np.nonzero(np.abs(gyw) < _DB_3)[0]
    bw_task = None
    if below.size and below[0] > 0:
        i = int(below[0])
        bw_task = _Task("gyw", 0, _bw_fn, float(x[i - 1]), float(x[i]))
        tasks.append(bw_task)
    bound_tasks: list[_Task] = []
    if bound is not None:
        wmag = bound.magnitude(f)
        d_full = one_f2 + g * (ctot + f1) if on else 1.0 + g * ctot
        t_speed = g * (cv + f1) / d_on if on else gyw_off
        t_full = g * (ctot + f1) / d_full
        bound_tasks = [
            _peak_task(x, wmag * np.abs(t_speed), "wts"),
            _peak_task(x, wmag * np.abs(t_full), "wtf"),
        ]
        tasks += bound_tasks
    _solve(tasks, ev)
    margins = _margins(lt)
    bandwidth = bw_task.freq_hz if bw_task is not None else math.nan

    poles = np.linalg.eigvals(_closed_loop_matrix(cfg, used))
    max_radius = float(np.max(np.abs(poles)))

    reasons: list[str] = []
    if not max_radius < limits.pole_radius_max:
        reasons.append(
            f"closed-loop pole radius {max_radius:.5f} >= {limits.pole_radius_max:g}"
            + (" (unstable)" if max_radius >= 1.0 else "")
        )
    _margin_reasons(margins, limits, "", reasons)
    noise_cmd = np.abs((cv + f1) / d_on) if on else np.abs(cv / d_off)
    k_noise = int(np.argmax(noise_cmd))
    noise_cmd_db = float(20.0 * np.log10(noise_cmd[k_noise]))
    if not noise_cmd_db <= limits.noise_to_command_max_db:
        reasons.append(
            f"noise to command gain {noise_cmd_db:.1f} dB > {limits.noise_to_command_max_db:g} dB"
            f" (at {_fmt_hz(float(f[k_noise]))})"
        )

    sources: list[SourceResult] = []
    for m in plant.measured:
        model = _MeasuredModel(m, cfg)
        sources.append(_measured_source(cfg, dob, on, model, m.name, f, bk, limits, reasons))
    if bound is not None:
        sp, fp = bound_tasks
        dq = wmag * np.abs(f2d) if on else np.zeros_like(wmag)
        j = int(np.argmax(dq))
        sources.append(
            SourceResult(
                name=bound.name,
                kind="bound",
                small_gain_peak=sp.value,
                small_gain_freq_hz=sp.freq_hz,
                small_gain_full_peak=fp.value,
                small_gain_full_freq_hz=fp.freq_hz,
                delta_q_peak=float(dq[j]),
                delta_q_freq_hz=float(f[j]),
                base_loop_stable=True,
                full_loop_winding_ok=True,
                margins=None,
                inv_delta_db=readonly(-20.0 * np.log10(wmag)),
            )
        )
        for t, which in ((sp, "speed loop"), (fp, "with position loop")):
            if not t.value < limits.small_gain_max:
                reasons.append(
                    f"||W T|| ({which}) peaks at {t.value:.3g} at {_fmt_hz(t.freq_hz)} for bound "
                    f"{bound.name!r} >= {limits.small_gain_max:g}"
                )

    peaks = [s.small_gain_peak for s in sources] + [s.small_gain_full_peak for s in sources]
    peaks = [p for p in peaks if math.isfinite(p)]
    with np.errstate(divide="ignore"):
        rejection = 20.0 * np.log10(np.abs(d_on / (one_f2 * d_off)))
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
        disturbance_dob=readonly(pd * one_f2 / d_on),
        disturbance_no_dob=readonly(pd / d_off),
        noise_dob=readonly(g * (cv + f1) / d_on),
        noise_no_dob=readonly(gyw_off),
        q_mag_db=readonly(20.0 * np.log10(np.abs(f2d))),
        rejection_db=readonly(rejection),
        margins=margins,
        bandwidth_hz=bandwidth,
        poles=readonly(poles),
        max_pole_radius=max_radius,
        sources=tuple(sources),
        small_gain_peak=max(peaks) if peaks else math.nan,
        verdict="accept" if not reasons else "reject",
        reasons=tuple(reasons),
        noise_to_command_peak_db=noise_cmd_db,
    )


def _margin_reasons(m: Margins, limits: GateLimits, suffix: str, reasons: list[str]) -> None:
    if not m.phase_margin_deg >= limits.phase_margin_min_deg:
        reasons.append(
            f"phase margin {m.phase_margin_deg:.1f} deg < {limits.phase_margin_min_deg:g} deg"
            f" (at {_fmt_hz(m.gain_crossover_hz)}){suffix}"
        )
    if not abs(m.gain_margin_db) >= limits.gain_margin_min_db:
        reasons.append(
            f"gain margin {m.gain_margin_db:.1f} dB, |GM| < {limits.gain_margin_min_db:g} dB"
            f" (at {_fmt_hz(m.phase_crossover_hz)}){suffix}"
        )
    if not m.peak_sensitivity_db <= limits.peak_sensitivity_max_db:
        reasons.append(
            f"peak sensitivity {m.peak_sensitivity_db:.1f} dB > "
            f"{limits.peak_sensitivity_max_db:g} dB (at {_fmt_hz(m.peak_sensitivity_hz)}){suffix}"
        )


def _measured_source(
    cfg: LoopConfig,
    dob: _Dob,
    on: bool,
    model: _MeasuredModel,
    name: str,
    f: FloatArray,
    bk: _Blocks,
    limits: GateLimits,
    reasons: list[str],
) -> SourceResult:
    x = np.log(f)
    gm, delta = model.discrete(f, bk.g)
    suffix = f" for response {name!r}"
    used = dob if on else None

    # The loops without DOB must be stable with this plant (base of the small-gain test).
    base_ok = _winding_ok(1.0 + gm * bk.cv, _integrators(cfg, False)) and _winding_ok(
        1.0 + gm * bk.ctot, _integrators(cfg, True)
    )
    if not base_ok:
        reasons.append(
            f"the loop without DOB is not proven stable{suffix} (argument principle on 1 + G C)"
        )

    d_full = 1.0 - bk.f2d + gm * (bk.ctot + bk.f1) if on else 1.0 + gm * bk.ctot
    full_ok = _winding_ok(d_full, _integrators(cfg, True))

    def ev(ff: FloatArray) -> Outputs:
        b = _blocks(cfg, used, ff)
        g2 = model.discrete(ff, b.g)[0]
        num = g2 * b.f1 - b.f2d
        return {
            "L": g2 * (b.cv + b.f1) / (1.0 - b.f2d),
            "xs": num / (1.0 + g2 * b.cv),
            "xf": num / (1.0 + g2 * b.ctot),
        }

    loop = gm * (bk.cv + bk.f1) / (1.0 - bk.f2d) if on else gm * bk.cv
    lt = _loop_tasks(x, loop, "L")
    tasks = lt.all()
    num = gm * bk.f1 - bk.f2d
    if on:
        sg = [
            _peak_task(x, np.abs(num / (1.0 + gm * bk.cv)), "xs"),
            _peak_task(x, np.abs(num / (1.0 + gm * bk.ctot)), "xf"),
        ]
        tasks += sg
    _solve(tasks, ev)
    if on:
        sp, fp = sg
        dq = np.abs(delta * bk.f2d)
        j = int(np.argmax(dq))
        dq_peak, dq_f = float(dq[j]), float(f[j])
        for t, which in ((sp, ""), (fp, " (with position loop)")):
            if not t.value < limits.small_gain_max:
                reasons.append(
                    f"eq. 21{which} peaks at {t.value:.3g} at {_fmt_hz(t.freq_hz)}{suffix} "
                    f">= {limits.small_gain_max:g}"
                )
        peaks = (sp.value, sp.freq_hz, fp.value, fp.freq_hz)
    else:
        dq_peak = dq_f = math.nan
        peaks = (math.nan,) * 4
    margins = _margins(lt)
    if limits.check_measured_margins:
        _margin_reasons(margins, limits, suffix, reasons)
    with np.errstate(divide="ignore"):
        inv_delta = -20.0 * np.log10(np.abs(delta))
    return SourceResult(
        name=name,
        kind="measured",
        small_gain_peak=peaks[0],
        small_gain_freq_hz=peaks[1],
        small_gain_full_peak=peaks[2],
        small_gain_full_freq_hz=peaks[3],
        delta_q_peak=dq_peak,
        delta_q_freq_hz=dq_f,
        base_loop_stable=base_ok,
        full_loop_winding_ok=full_ok,
        margins=margins,
        inv_delta_db=readonly(inv_delta),
    )


# --------------------------------------------------------------------------- recommendation


def recommended_max_cutoff_hz(
    cfg: LoopConfig,
    plant: PlantKnowledge | None = None,
    limits: GateLimits | None = None,
    q_type: str | None = None,
    *,
    lowest_hz: float = 0.02,
    highest_hz: float | None = None,
    coarse_points: int = 16,
    rel_tol: float = 0.01,
) -> float | None:
    """Largest Q cut-off (Hz) the gate accepts for `q_type` (default cfg.q_type), DOB on.

    Acceptance is assumed to hold on an interval from low cut-offs up to a limit (robustness
    and margins degrade as the Q bandwidth grows), though not strictly monotone. Guard: scan
    `coarse_points` log-spaced cut-offs from `lowest_hz` to `highest_hz` (default: a tenth of
    the loop rate), take the first accept -> reject transition from below, then bisect it in
    log cut-off to `rel_tol`. None if `lowest_hz` is already rejected.
    """
    qt: QType = check_q_type(q_type if q_type is not None else cfg.q_type)
    assert qt in Q_TYPES
    top = highest_hz if highest_hz is not None else 0.1 * cfg.rate_hz
    top = min(top, 0.45 * cfg.rate_hz)
    base = cfg.with_(dob_on=True, q_type=qt)

    def ok(fc: float) -> bool:
        return analyse(base.with_(q_cutoff_hz=fc), plant, limits).accepted

    grid = np.geomspace(lowest_hz, top, coarse_points)
    if not ok(float(grid[0])):
        return None
    lo = float(grid[0])
    hi: float | None = None
    for fc in grid[1:]:
        if ok(float(fc)):
            lo = float(fc)
        else:
            hi = float(fc)
            break
    if hi is None:
        return lo
    while hi / lo > 1.0 + rel_tol:
        mid = math.sqrt(lo * hi)
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return lo
