"""Independent truth for the stability gate: the discrete closed loop the tick really runs.

Test code, not product code. Given a true continuous plant (u -> load rate w) and a
`LoopConfig`, build the sampled loop exactly as `controller.core.loop.ServoLoop.tick` runs it,
with python-control objects only, and report whether it is stable and with which margins:

    plant     ZOH of M P over one period (`control.c2d`), `delay_ticks` whole periods of
              transport delay on the command; w[k] = (theta[k] - theta[k-1]) / Ts (backward
              difference of the load encoder, as the rig and the simulator measure it) or the
              sampled rate w(k Ts)
    position  r = Cp(z) (theta_ref - theta),   Cp = kp (1 + ki Ts/2 (z + 1)/(z - 1))
    speed     v = Cv(z) (r - w),               Cv likewise (Tustin, as loop.py integrates)
    DOB       d_hat = F1(z) w - F2(z) z^-1 u,  F1, F2: the SOS of `design_dob` (the design is
              the product's, since that is what runs; nothing else is taken from it)
    command   u = v - d_hat

Nothing here comes from `controller.gate`: the plant discretisation, the loop algebra, the
poles and the margins are built from `control.c2d`, `control.ss`, series / parallel /
`control.feedback` and `poles()`. Margins follow `control.stability_margins` (its selection
rules; by default the crossings are refined on the exact response, which the tests check
against `control.stability_margins` itself, 50x slower). Every block is a state-space system, and
each block's states enter the closed loop exactly once (no transfer-function products: with
Q poles near z = 1 polynomial coefficients lose all precision, and a duplicated integrator
would add a spurious pole at z = 1).

Loops reported: the speed loop alone (position loop open, `ServoLoop.tick_speed`) and the
whole servo (position loop closed, `ServoLoop.tick`), each broken at the plant input, where
the DOB's own command feedback F2 z^-1 u stays inside the controller:

    L_speed = (Cv + F1) G_w / (1 - F2 z^-1)
    L_full  = (Cv (G_w + Cp G_theta) + F1 G_w) / (1 - F2 z^-1)

Public API (used by tests/bench/fuzz_gate.py and the gate's tests):
    Resonance, TruePlant              the true plant (errors relative to a NominalModel)
    truth(plant, cfg) -> Truth        stability, pole radii, margins of both loops
    loop_margins(loop) -> LoopMargins  margins of a discrete loop (python-control's rules)
    sampled_response(plant, rate_hz, freq_hz)   exact u[k] -> w[k] response (evidence)
    continuous_response(plant, rate_hz, freq_hz)  M P(j w) e^{-j w delay}
    open_loops(plant, cfg) -> (L_speed, L_full) as control.StateSpace
    disturbance_loop(plant, cfg, position=True) -> StateSpace from an input disturbance d
        (added to the command at the plant input) to [w, theta]
    discrete_plant(plant, rate_hz) -> DiscretePlant (the sampled plant as StateSpace)
    edge_plant(plant, cfg, radius, near_hz=None) -> (TruePlant, float) | None: the plant's
        gain scaled so the loop's largest pole radius is just past `radius` (loops built to
        sit at the stability boundary)
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Literal

import control as ct
import numpy as np
from numpy.typing import ArrayLike, NDArray

from controller.core.command_filter import continuous_tf
from controller.core.config import LoopConfig, NominalModel
from controller.core.dob import design_dob

__all__ = [
    "DiscretePlant",
    "LoopMargins",
    "Resonance",
    "TruePlant",
    "Truth",
    "continuous_response",
    "discrete_plant",
    "disturbance_loop",
    "edge_plant",
    "frequency_response",
    "loop_margins",
    "margin_grid",
    "open_loops",
    "sampled_response",
    "truth",
]

RateSource = Literal["difference", "sampled"]
ComplexArray = NDArray[np.complex128]
_TWO_PI = 2.0 * math.pi


# ------------------------------------------------------------------------------ the plant


@dataclass(frozen=True)
class Resonance:
    """An extra lightly damped mode: poles at `freq_hz`, zeros at `zero_ratio * freq_hz`,
    unit DC gain: (wp/wz)^2 (s^2 + 2 zz wz s + wz^2) / (s^2 + 2 zp wp s + wp^2)."""

    freq_hz: float
    damping: float
    zero_ratio: float = 1.0
    """Anti-resonance over resonance frequency (< 1: collocated-like; 1 with equal damping:
    no effect)."""
    zero_damping: float | None = None
    """Damping of the zeros (default: `damping`)."""


@dataclass(frozen=True)
class TruePlant:
    """True M P (u -> load rate) as errors on a nominal model: the DC gain times `gain`, the
    roots of pn_den (the belt/load mode) moved by `wn_scale` (natural frequency) and
    `damping_scale`, an optional extra resonance and a transport delay in whole ticks."""

    gain: float = 1.0
    wn_scale: float = 1.0
    damping_scale: float = 1.0
    resonance: Resonance | None = None
    delay_ticks: int = 0
    base: NominalModel = field(default_factory=NominalModel)

    def sections(self) -> list[tuple[list[float], list[float]]]:
        """(num, den) factors in s of at most second order whose product is M P, no delay."""
        b = self.base
        a2, a1, a0 = b.pn_den
        k, d = self.wn_scale, self.damping_scale
        # s -> s / k moves every root by k; scaling the s term scales the damping ratio.
        pn_den = [a2 / (k * k), d * a1 / k, a0]
        zeros = _roots(b.pn_num)
        poles = _roots(b.mn_den)
        # The article's Pn numerator is Mn's denominator: cancel equal roots exactly.
        for z in list(zeros):
            for i, p in enumerate(poles):
                if abs(z - p) <= 1e-9 * max(1.0, abs(p)):
                    zeros.remove(z)
                    del poles[i]
                    break
        num = np.real(np.poly(zeros)) if zeros else np.ones(1)
        den = np.real(np.poly(poles)) if poles else np.ones(1)
        out = [
            (_unit_dc(num), _unit_dc(den)),
            ([1.0], _unit_dc(np.trim_zeros(np.asarray(pn_den), "f"))),
        ]
        if self.resonance is not None:
            r = self.resonance
            wp = _TWO_PI * r.freq_hz
            wz = wp * r.zero_ratio
            zz = r.damping if r.zero_damping is None else r.zero_damping
            num_r = _unit_dc([1.0, 2 * zz * wz, wz * wz])
            out.append((num_r, _unit_dc([1.0, 2 * r.damping * wp, wp * wp])))
        gain = self.gain * b.dc_gain
        out[0] = ([gain * c for c in out[0][0]], out[0][1])
        return out

    def continuous(self) -> ct.StateSpace:
        """M P as a continuous state-space system (a series of low-order sections)."""
        sys = ct.ss([], [], [], [[1.0]])
        for num, den in self.sections():
            sys = ct.ss(ct.tf(num, den)) * sys
        return sys

    def transfer_function(self) -> ct.TransferFunction:
        """M P as a python-control TransferFunction (no delay; for display and checks)."""
        tf = ct.tf([1.0], [1.0])
        for num, den in self.sections():
            tf = tf * ct.tf(num, den)
        return tf


def _roots(p: tuple[float, float, float]) -> list[complex]:
    return [complex(r) for r in np.roots(np.trim_zeros(np.asarray(p, float), "f"))]


def _unit_dc(c: ArrayLike) -> list[float]:
    a = np.asarray(c, dtype=float)
    return [float(x) for x in a / a[-1]]


def continuous_response(plant: TruePlant, rate_hz: float, freq_hz: ArrayLike) -> ComplexArray:
    """M P(j w) e^{-j w delay_ticks / rate_hz}: the continuous plant with its delay."""
    f = np.asarray(freq_hz, dtype=float)
    s = 1j * _TWO_PI * f
    h = np.ones_like(s)
    for num, den in plant.sections():
        h = h * np.polyval(num, s) / np.polyval(den, s)
    return np.asarray(h * np.exp(-s * plant.delay_ticks / rate_hz), dtype=np.complex128)


# ------------------------------------------------------------------------------ sampling


@dataclass(frozen=True)
class DiscretePlant:
    """The sampled plant: `full` maps u[k] to [w[k], theta[k]], `speed` maps u[k] to w[k]
    only (same dynamics without the position integrator, which w does not see)."""

    full: ct.StateSpace
    speed: ct.StateSpace


def _delay(ticks: int, ts: float) -> ct.StateSpace:
    """z^-ticks as a shift register."""
    if ticks == 0:
        return ct.ss([], [], [], [[1.0]], ts)
    a = np.eye(ticks, k=-1)
    b = np.zeros((ticks, 1))
    b[0, 0] = 1.0
    c = np.zeros((1, ticks))
    c[0, -1] = 1.0
    return ct.ss(a, b, c, [[0.0]], ts)


@lru_cache(maxsize=16)
def discrete_plant(
    plant: TruePlant, rate_hz: float, rate_source: RateSource = "difference"
) -> DiscretePlant:
    """ZOH of [M P; M P / s] over Ts, then the rate the loop reads and the delay (cached:
    the systems are never modified in place)."""
    ts = 1.0 / rate_hz
    pc = plant.continuous()
    a, b, c, d = (np.atleast_2d(np.asarray(m, dtype=float)) for m in (pc.A, pc.B, pc.C, pc.D))
    n = a.shape[0]
    # Continuous states [x; theta], theta' = w = C x + D u.
    aa = np.zeros((n + 1, n + 1))
    aa[:n, :n] = a
    aa[n, :n] = c[0]
    ba = np.vstack([b, d])
    sd = ct.c2d(ct.ss(aa, ba, np.eye(n + 1), np.zeros((n + 1, 1))), ts, method="zoh")
    phi, gam = np.asarray(sd.A), np.asarray(sd.B)
    if rate_source == "difference":
        # States [x; q; theta] with q[k] = theta[k] - theta[k-1]: w = q / Ts.
        af = np.zeros((n + 2, n + 2))
        af[:n, :n] = phi[:n, :n]
        af[n, :n] = phi[n, :n]
        af[n + 1, :n] = phi[n, :n]
        af[n + 1, n + 1] = 1.0
        bf = np.vstack([gam[:n], gam[n:], gam[n:]])
        cf = np.zeros((2, n + 2))
        cf[0, n] = 1.0 / ts
        cf[1, n + 1] = 1.0
        full = ct.ss(af, bf, cf, np.zeros((2, 1)), ts)
        speed = ct.ss(af[: n + 1, : n + 1], bf[: n + 1], cf[:1, : n + 1], [[0.0]], ts)
    else:
        if np.any(d != 0.0):
            raise ValueError("sampled rate needs a strictly proper plant")
        cf = np.zeros((2, n + 1))
        cf[0, :n] = c[0]
        cf[1, n] = 1.0
        full = ct.ss(phi, gam, cf, np.zeros((2, 1)), ts)
        speed = ct.ss(phi[:n, :n], gam[:n], c, [[0.0]], ts)
    delay = _delay(plant.delay_ticks, ts)
    return DiscretePlant(full=full * delay, speed=speed * delay)


def frequency_response(sys: ct.StateSpace, freq_hz: ArrayLike) -> ComplexArray:
    """SISO response of a discrete state-space system at e^{j 2 pi f Ts} (batched solves)."""
    f = np.asarray(freq_hz, dtype=float)
    z = np.exp(1j * _TWO_PI * f * sys.dt)
    a, b, c, d = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C, sys.D))
    n = a.shape[0]
    if n == 0:
        return np.full(f.shape, d[0, 0], dtype=np.complex128)
    m = z[:, None, None] * np.eye(n) - a[None, :, :]
    x = np.linalg.solve(m, np.broadcast_to(b.astype(complex), (f.size, n, 1)))
    return np.asarray((c @ x)[:, 0, 0] + d[0, 0], dtype=np.complex128)


def sampled_response(
    plant: TruePlant,
    rate_hz: float,
    freq_hz: ArrayLike,
    rate_source: RateSource = "difference",
) -> ComplexArray:
    """Exact response of the sampled plant u[k] -> w[k] (what a test run by the loop sees)."""
    return frequency_response(discrete_plant(plant, rate_hz, rate_source).speed, freq_hz)


# ------------------------------------------------------------------------------ controller


@dataclass(frozen=True)
class _Controller:
    cv: ct.StateSpace
    cp: ct.StateSpace
    f1: ct.StateSpace | None
    dinv: ct.StateSpace
    """1 / (1 - F2 z^-1): the DOB's positive feedback of its own (delayed) command."""


def _static(k: float | list[list[float]], ts: float) -> ct.StateSpace:
    return ct.ss([], [], [], np.atleast_2d(np.asarray(k, dtype=float)), ts)


def _pi(kp: float, ki: float, ts: float) -> ct.StateSpace:
    """kp (1 + ki Ts/2 (z + 1)/(z - 1)) as loop.py integrates it: with h = kp ki Ts/2,
    I[k] = I[k-1] + h (e[k] + e[k-1]), v = kp e + I; state s = I[k-1] + h e[k-1].
    A plain gain when ki = 0 (no pole at z = 1: the tick has no integrator state then)."""
    if ki == 0.0:
        return _static(kp, ts)
    h = 0.5 * kp * ki * ts
    return ct.ss([[1.0]], [[2.0 * h]], [[1.0]], [[kp + h]], ts)


def _sos(sos: np.ndarray, ts: float) -> ct.StateSpace:
    """The cascade of second-order sections as `SosFilter` runs them (transposed direct
    form II per section: y = b0 x + s1, s1' = b1 x - a1 y + s2, s2' = b2 x - a2 y)."""
    sys = _static(1.0, ts)
    for b0, b1, b2, _a0, a1, a2 in np.asarray(sos, dtype=float):
        sec = ct.ss(
            [[-a1, 1.0], [-a2, 0.0]], [[b1 - a1 * b0], [b2 - a2 * b0]], [[1.0, 0.0]], [[b0]], ts
        )
        sys = sec * sys
    return sys


def _controller(cfg: LoopConfig) -> _Controller:
    ts = cfg.period_s
    cv = _pi(cfg.cv_kp, cfg.cv_ki_per_s, ts)
    cf = cfg.command_filter
    if cf.kind != "off":
        # The speed-command filter on Cv's output: its continuous prototype, discretised
        # here by python-control (Tustin prewarped at the filter's frequency).
        num, den = continuous_tf(cf)
        n_cont = ct.tf(list(np.trim_zeros(np.asarray(num), "f")), list(den))
        n_disc = ct.c2d(n_cont, ts, method="tustin",
                        prewarp_frequency=2.0 * math.pi * cf.frequency_hz)
        cv = ct.ss(n_disc) * cv
    cp = _pi(cfg.pos_kp_per_s, cfg.pos_ki_per_s, ts)
    if not cfg.dob_on:
        return _Controller(cv=cv, cp=cp, f1=None, dinv=_static(1.0, ts))
    dob = design_dob(cfg)
    f1 = _sos(dob.f1_sos, ts)
    f2_delayed = _delay(1, ts) * _sos(dob.f2_sos, ts)
    dinv = ct.feedback(_static(1.0, ts), f2_delayed, sign=1)
    return _Controller(cv=cv, cp=cp, f1=f1, dinv=dinv)


def _feedback_gains(cfg: LoopConfig, k: _Controller, position: bool) -> ct.StateSpace:
    """N = Cv (w + Cp theta) + F1 w from [w, theta] (position) or from w; u = -Dinv N."""
    ts = cfg.period_s
    if position:
        sel_w, sel_t = _static([[1.0, 0.0]], ts), _static([[0.0, 1.0]], ts)
        inner = ct.parallel(sel_w, k.cp * sel_t)
        n = k.cv * inner
        if k.f1 is not None:
            n = ct.parallel(n, k.f1 * sel_w)
        return n
    return k.cv if k.f1 is None else ct.parallel(k.cv, k.f1)


def open_loops(
    plant: TruePlant, cfg: LoopConfig, rate_source: RateSource = "difference"
) -> tuple[ct.StateSpace, ct.StateSpace]:
    """(L_speed, L_full): loop transfer at the plant input, negative-feedback convention
    (closed loop = feedback(L, 1)); every block's states appear once."""
    g = discrete_plant(plant, cfg.rate_hz, rate_source)
    k = _controller(cfg)
    l_speed = k.dinv * _feedback_gains(cfg, k, False) * g.speed
    l_full = k.dinv * _feedback_gains(cfg, k, True) * g.full
    return l_speed, l_full


def disturbance_loop(
    plant: TruePlant,
    cfg: LoopConfig,
    position: bool = True,
    rate_source: RateSource = "difference",
) -> ct.StateSpace:
    """Closed loop from a disturbance d added to the command at the plant input to the
    measurements: [w, theta] (position loop closed) or w (speed loop alone)."""
    g = discrete_plant(plant, cfg.rate_hz, rate_source)
    k = _controller(cfg)
    return ct.feedback(
        g.full if position else g.speed, k.dinv * _feedback_gains(cfg, k, position), sign=-1
    )


# ------------------------------------------------------------------------------ the truth


@dataclass(frozen=True)
class LoopMargins:
    """Margins of a loop with `control.stability_margins`' selection rules, from 1 mHz to
    Nyquist: the gain margin closest to 0 dB (negative: a gain-reduction margin), the phase
    margin of smallest magnitude, the stability margin min |1 + L|; inf where nothing
    crosses, frequencies nan then."""

    gain_margin_db: float
    phase_crossover_hz: float
    phase_margin_deg: float
    gain_crossover_hz: float
    stability_margin: float

    def comfortable(self, gm_min_db: float = 6.0, pm_min_deg: float = 30.0) -> bool:
        return abs(self.gain_margin_db) >= gm_min_db and self.phase_margin_deg >= pm_min_deg


@dataclass(frozen=True)
class Truth:
    """Stability and margins of the discrete loop the tick runs, for one plant and config."""

    stable_speed: bool
    stable_full: bool
    radius_speed: float
    """Largest closed-loop pole radius, speed loop alone."""
    radius_full: float
    """Largest closed-loop pole radius, position loop closed."""
    margins_speed: LoopMargins | None
    margins_full: LoopMargins | None

    @property
    def stable(self) -> bool:
        """All poles strictly inside the unit circle, with and without the position loop."""
        return self.stable_speed and self.stable_full

    @property
    def max_pole_radius(self) -> float:
        return max(self.radius_speed, self.radius_full)

    def comfortable(self, gm_min_db: float = 6.0, pm_min_deg: float = 30.0) -> bool:
        """Stable with |GM| >= gm_min_db and PM >= pm_min_deg in both loops."""
        return (
            self.stable
            and self.margins_speed is not None
            and self.margins_full is not None
            and self.margins_speed.comfortable(gm_min_db, pm_min_deg)
            and self.margins_full.comfortable(gm_min_db, pm_min_deg)
        )


def margin_grid(rate_hz: float, n: int = 1000) -> NDArray[np.float64]:
    """Frequencies for the margins: 1 mHz to just below Nyquist."""
    return np.geomspace(1e-3, 0.49999 * rate_hz, n)


def loop_margins(
    loop: ct.StateSpace,
    freq_hz: ArrayLike | None = None,
    method: Literal["exact", "control"] = "exact",
) -> LoopMargins:
    """Margins of a discrete SISO loop, with python-control's selection rules.

    "control": `control.stability_margins` on an FRD of the exact response (spline
    interpolation between grid points; slow: ~0.2 s per loop). "exact" (default): the same
    crossings bracketed on the grid and refined by bisection on the exact state-space
    response, ~50x faster; tests/test_fuzz_truth.py checks the two agree.
    """
    f = margin_grid(1.0 / loop.dt) if freq_hz is None else np.asarray(freq_hz, dtype=float)
    resp = frequency_response(loop, f)
    if method == "control":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gm, pm, sm, wpc, wgc, _ = ct.stability_margins(ct.frd(resp, _TWO_PI * f))
        return _margins(float(gm), float(wpc) / _TWO_PI, float(pm), float(wgc) / _TWO_PI, sm)

    def at(x: NDArray[np.float64]) -> ComplexArray:
        return frequency_response(loop, x)

    mag = np.log(np.abs(resp))
    k = np.nonzero(np.isfinite(mag[:-1]) & (np.sign(mag[:-1]) != np.sign(mag[1:])))[0]
    wgc = _bisect(lambda x: np.log(np.abs(at(x))), f[k], f[k + 1])
    arg = np.angle(-resp)
    k = np.nonzero(
        (np.sign(arg[:-1]) != np.sign(arg[1:])) & (resp.real[:-1] <= 0) & (resp.real[1:] <= 0)
    )[0]
    wpc = _bisect(lambda x: np.angle(-at(x)), f[k], f[k + 1])
    gm_all = 1.0 / np.abs(at(wpc)) if wpc.size else np.zeros(0)
    pm_all = np.remainder(np.angle(at(wgc), deg=True), 360.0) - 180.0 if wgc.size else wgc
    gm, f_gm = math.inf, math.nan
    if gm_all.size and np.any(np.isfinite(gm_all)):
        i = int(np.argmin(np.abs(np.log(gm_all))))
        gm, f_gm = float(gm_all[i]), float(wpc[i])
    pm, f_pm = math.inf, math.nan
    if pm_all.size:
        i = int(np.argmin(np.abs(pm_all)))
        pm, f_pm = float(pm_all[i]), float(wgc[i])
    i = int(np.argmin(np.abs(1.0 + resp)))
    lo, hi = f[max(i - 1, 0)], f[min(i + 1, f.size - 1)]
    xs = np.geomspace(lo, hi, 65)
    sm = min(float(np.min(np.abs(1.0 + at(xs)))), float(np.abs(1.0 + resp[i])))
    return _margins(gm, f_gm, pm, f_pm, sm)


def _margins(gm: float, f_gm: float, pm: float, f_pm: float, sm: float) -> LoopMargins:
    return LoopMargins(
        gain_margin_db=20.0 * math.log10(gm) if 0.0 < gm < math.inf else math.inf,
        phase_crossover_hz=f_gm,
        phase_margin_deg=pm,
        gain_crossover_hz=f_pm,
        stability_margin=float(sm),
    )


def _bisect(
    fn: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    iterations: int = 24,
) -> NDArray[np.float64]:
    """Sign changes of fn in [lo, hi] (vectorised over brackets), bisection in log f."""
    lo, hi = np.array(lo, dtype=float), np.array(hi, dtype=float)
    if lo.size == 0:
        return lo
    f_lo = fn(lo)
    for _ in range(iterations):
        mid = np.sqrt(lo * hi)
        f_mid = fn(mid)
        left = np.sign(f_mid) == np.sign(f_lo)
        lo = np.where(left, mid, lo)
        f_lo = np.where(left, f_mid, f_lo)
        hi = np.where(left, hi, mid)
    return np.sqrt(lo * hi)


def _radius(loop: ct.StateSpace) -> float:
    p = ct.feedback(loop, 1).poles()
    return float(np.max(np.abs(p))) if p.size else 0.0


def truth(
    plant: TruePlant,
    cfg: LoopConfig,
    *,
    margins: Literal["always", "if_stable", "never"] = "always",
    rate_source: RateSource = "difference",
) -> Truth:
    """The truth for one case; margins (the costly part, ~40 ms) as `margins` says."""
    l_speed, l_full = open_loops(plant, cfg, rate_source)
    r_speed, r_full = _radius(l_speed), _radius(l_full)
    want = margins == "always" or (margins == "if_stable" and max(r_speed, r_full) < 1.0)
    return Truth(
        stable_speed=r_speed < 1.0,
        stable_full=r_full < 1.0,
        radius_speed=r_speed,
        radius_full=r_full,
        margins_speed=loop_margins(l_speed) if want else None,
        margins_full=loop_margins(l_full) if want else None,
    )


def _pole_radius_and_hz(plant: TruePlant, cfg: LoopConfig) -> tuple[float, float]:
    """Largest closed-loop pole radius over both loops and that pole's frequency."""
    poles = np.concatenate([ct.feedback(lp, 1).poles() for lp in open_loops(plant, cfg)])
    k = int(np.argmax(np.abs(poles)))
    return float(np.abs(poles[k])), abs(float(np.angle(poles[k]))) * cfg.rate_hz / _TWO_PI


def edge_plant(
    plant: TruePlant,
    cfg: LoopConfig,
    radius: float,
    near_hz: float | None = None,
    span: float = 30.0,
) -> tuple[TruePlant, float] | None:
    """`plant` with its gain scaled (within x1/span..x span) so that the largest closed-loop
    pole radius of `cfg`'s loops is in [radius, radius + 1e-9 * radius]: a loop just past the
    boundary when radius > 1. Of the boundary crossings found, the one whose critical pole
    lies nearest `near_hz` (e.g. a resonance) is taken, else the one nearest the original
    gain. Returns (plant, its radius), or None when no gain in the range crosses `radius`."""
    gains = np.geomspace(1.0 / span, span, 49) * plant.gain

    def rad(g: float) -> tuple[float, float]:
        return _pole_radius_and_hz(replace(plant, gain=float(g)), cfg)

    scan = [rad(float(g)) for g in gains]
    crossings = [
        i for i in range(len(gains) - 1) if (scan[i][0] < radius) != (scan[i + 1][0] < radius)
    ]
    if not crossings:
        return None

    def score(i: int) -> float:
        hz = scan[i][1] if scan[i][0] >= radius else scan[i + 1][1]
        if near_hz is not None:
            return abs(math.log(max(hz, 1e-3) / near_hz))
        return abs(math.log(math.sqrt(gains[i] * gains[i + 1]) / plant.gain))

    i = min(crossings, key=score)
    lo, hi = float(gains[i]), float(gains[i + 1])
    lo_stable = scan[i][0] < radius
    best: tuple[TruePlant, float] | None = None
    for _ in range(200):
        mid = math.sqrt(lo * hi)
        if not lo < mid < hi:
            break
        r = rad(mid)[0]
        if r >= radius:
            best = (replace(plant, gain=mid), r)
            if r <= radius * (1.0 + 1e-9):
                break
        if (r < radius) == lo_stable:
            lo = mid
        else:
            hi = mid
    return best
