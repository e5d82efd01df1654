"""A DOB in the position loop (Fig. 10's comparison), for the simulation only.

The runtime's loop (`controller.core.loop`) has the DOB in the rate loop. The classic
alternative puts it around the closed rate loop: the position controller's output r (the speed
reference) is corrected by an estimate of the disturbance seen at that point,

    d_hat = Q(z) Tn^-1(z) theta[k] - Q(z) r[k-1],   r = Cp e_pos (+ ff) - d_hat,
    Tn(s) = Cv Mn Pn / (1 + Cv Mn Pn) / s       (the nominal closed rate loop, r -> theta)

Tn^-1 has relative degree -3, so Q needs relative degree >= 3: we use Q41 = (4 tau s + 1) /
(tau s + 1)^4 (eq. 30 with binomial coefficients, N = 4, r = 3) at the configuration's -3 dB
cut-off (its tau solved here). Filters: Tustin prewarped at the cut-off into second-order
sections, as the runtime's DOB. The rate loop inside is the plain Cv (no rate DOB); gains,
limits and anti-windup are the runtime's. Our construction: control.md names the comparison,
not the article's position-loop DOB design.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from controller.core.config import LoopConfig
from controller.core.discrete import SosFilter, tustin_zpk, zpk_to_sos
from controller.core.dob import cancel_common_roots, poly_roots_gain
from controller.core.loop import tick_gains

__all__ = ["PositionDobLoop", "position_dob_zpk", "q41_tau_s"]


def q41_tau_s(cutoff_hz: float) -> float:
    """tau of Q41 whose -3 dB frequency is `cutoff_hz`."""

    def excess(x: float) -> float:  # |Q41(j x)|^2 - 1/2, x = omega tau
        return (1.0 + 16.0 * x * x) / (1.0 + x * x) ** 4 - 0.5

    x = optimize.brentq(excess, 0.1, 10.0, xtol=1e-14)
    return float(x / (2.0 * math.pi * cutoff_hz))


def position_dob_zpk(cfg: LoopConfig) -> tuple[list[complex], list[complex], float]:
    """F1(s) = Q41(s) Tn^-1(s) as zeros, poles, gain."""
    nom = cfg.nominal
    zg, kn = poly_roots_gain(nom.pn_num)
    pm, km = poly_roots_gain(nom.mn_den)
    pd, kd = poly_roots_gain(nom.pn_den)
    pg = pm + pd
    cancel_common_roots(zg, pg, rtol=1e-7)
    kg = kn / (km * kd)
    num_g = kg * np.real(np.poly(zg)) if zg else np.array([kg])
    den_g = np.real(np.poly(pg))
    kp, ki = cfg.cv_kp, cfg.cv_ki_per_s
    # Tn^-1 = s (s den_G + kp (s + ki) num_G) / (kp (s + ki) num_G)
    char = np.polyadd(np.polymul([1.0, 0.0], den_g), kp * np.polymul([1.0, ki], num_g))
    tau = q41_tau_s(cfg.q_cutoff_hz)
    zeros = [0j, *np.roots(char).astype(complex), complex(-1.0 / (4.0 * tau))]
    poles = [complex(-ki), *[complex(z) for z in zg], *[complex(-1.0 / tau)] * 4]
    if ki == 0.0:
        zeros.remove(0j)
        poles.remove(0j)
    gain = float(char[0]) / (kp * kg) * 4.0 / tau**3
    return zeros, poles, gain


class PositionDobLoop:
    """`tick(ref, ref_rate, pos, w) -> u` like `ServoLoop.tick`, with the DOB on the speed
    reference (see the module docstring). `d_hat` and `speed_ref_deg_s` as ServoLoop's."""

    __slots__ = (
        "_cv_half", "_cv_kp", "_f1", "_f2", "_ff", "_limit", "_pos_half", "_pos_kp",
        "_started", "cv_int", "d_hat", "e_pos_prev", "e_speed_prev", "pos_int", "r_prev",
        "speed_ref_deg_s",
    )

    def __init__(self, cfg: LoopConfig) -> None:
        gains = tick_gains(cfg)  # the runtime's
        self._pos_kp, self._pos_half, self._cv_kp, self._cv_half, self._ff, self._limit = gains
        z, p, k = position_dob_zpk(cfg)
        self._f1 = SosFilter(zpk_to_sos(*tustin_zpk(z, p, k, cfg.rate_hz, cfg.q_cutoff_hz)))
        tau = q41_tau_s(cfg.q_cutoff_hz)
        qz, qp = [complex(-1.0 / (4.0 * tau))], [complex(-1.0 / tau)] * 4
        self._f2 = SosFilter(
            zpk_to_sos(*tustin_zpk(qz, qp, 4.0 / tau**3, cfg.rate_hz, cfg.q_cutoff_hz))
        )
        self._started = False
        self.pos_int = self.cv_int = self.e_pos_prev = self.e_speed_prev = 0.0
        self.r_prev = self.d_hat = self.speed_ref_deg_s = 0.0

    def tick(
        self, ref_deg: float, ref_rate_deg_s: float, pos_deg: float, speed_deg_s: float
    ) -> float:
        if not self._started:  # the filters start as if the turntable had rested here
            self._f1.set_steady(pos_deg)
            self._f2.set_steady(0.0)
            self._started = True
        e_pos = ref_deg - pos_deg
        pos_int_new = self.pos_int + self._pos_half * (e_pos + self.e_pos_prev)
        r0 = self._pos_kp * e_pos + pos_int_new + self._ff * ref_rate_deg_s
        d_hat = self._f1.step(pos_deg) - self._f2.step(self.r_prev)
        r = r0 - d_hat
        e = r - speed_deg_s
        cv_int_new = self.cv_int + self._cv_half * (e + self.e_speed_prev)
        u = self._cv_kp * e + cv_int_new
        lim = self._limit
        if u > lim:
            u = lim
            cv_int_new = min(cv_int_new, self.cv_int)
            pos_int_new = min(pos_int_new, self.pos_int)
        elif u < -lim:
            u = -lim
            cv_int_new = max(cv_int_new, self.cv_int)
            pos_int_new = max(pos_int_new, self.pos_int)
        self.cv_int = cv_int_new
        self.pos_int = pos_int_new
        self.e_speed_prev = e
        self.e_pos_prev = e_pos
        self.r_prev = r
        self.d_hat = d_hat
        self.speed_ref_deg_s = r
        return u
