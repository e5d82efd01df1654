"""The implemented discrete loop as frequency responses and state space: the ZOH plant with
the backward-difference rate, Tustin PIs, the DOB's F1/F2 sections, the closed-loop matrix.

Pure; the analysis (`controller.gate.analysis`) builds on these blocks.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike

from controller.core.arrays import ComplexArray, FloatArray
from controller.core.command_filter import command_filter_response, command_filter_sos
from controller.core.config import LoopConfig, NominalModel
from controller.core.discrete import SosArray, sos_responses
from controller.core.dob import cancel_common_roots, design_dob, poly_roots_gain
from controller.core.lti import expm, ss2tf, zpk2ss
from controller.gate.knowledge import (
    TWO_PI,
    readonly,
)

DB_3 = 10.0 ** (-3.0 / 20.0)  # -3 dB, as python-control's bandwidth()


def default_grid(rate_hz: float, n: int = 500) -> FloatArray:
    """`n` log-spaced frequencies from 0.01 Hz to just below Nyquist."""
    return _default_grid(float(rate_hz), int(n))


@lru_cache(maxsize=32)
def _default_grid(rate_hz: float, n: int) -> FloatArray:
    return readonly(np.geomspace(0.01, 0.4999 * rate_hz, n))


def mp_zpk(nominal: NominalModel) -> tuple[list[complex], list[complex], float]:
    """Mn(s) Pn(s) as zeros, poles, gain; common roots cancelled."""
    zeros, kn = poly_roots_gain(nominal.pn_num)
    pm, km = poly_roots_gain(nominal.mn_den)
    pd, kd = poly_roots_gain(nominal.pn_den)
    poles = pm + pd
    cancel_common_roots(zeros, poles)
    return zeros, poles, kn / (km * kd)


def nominal_continuous_response(nominal: NominalModel, freq_hz: ArrayLike) -> ComplexArray:
    """Mn(jw) Pn(jw) (continuous, u -> load rate)."""
    s = 1j * TWO_PI * np.asarray(freq_hz, dtype=np.float64)
    num = np.polyval(nominal.pn_num, s)
    den = np.polyval(nominal.mn_den, s) * np.polyval(nominal.pn_den, s)
    return np.asarray(num / den, dtype=np.complex128)


def discrete_equivalent(response: ArrayLike, freq_hz: ArrayLike, rate_hz: float) -> ComplexArray:
    """G_c(jw) e^{-jwTs} sinc^2(w Ts/2): ZOH + backward-difference rate, aliasing neglected.

    The k = 0 term of the exact sampled response; accurate well below Nyquist.
    """
    return with_zoh(response, zoh_terms(freq_hz, rate_hz))


def zoh_terms(freq_hz: ArrayLike, rate_hz: float) -> tuple[ComplexArray, FloatArray]:
    """(e^{-jwTs}, sinc(w Ts/2)) at `freq_hz`: what `discrete_equivalent` multiplies by
    (`with_zoh`), for responses that share their frequencies."""
    x = np.pi * np.asarray(freq_hz, dtype=np.float64) / rate_hz  # w Ts / 2
    return np.exp(-2j * x), np.sinc(x / np.pi)


def with_zoh(response: ArrayLike, terms: tuple[ComplexArray, FloatArray]) -> ComplexArray:
    """`discrete_equivalent` of `response` given its frequencies' `zoh_terms`."""
    delay, sinc = terms
    return np.asarray(response, dtype=np.complex128) * delay * sinc * sinc


@dataclass(frozen=True, eq=False)
class DiscretePlant:
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
def discrete_plant(nominal: NominalModel, rate_hz: float) -> DiscretePlant:
    ts = 1.0 / rate_hz
    z, p, k = mp_zpk(nominal)
    a, b, c, d = zpk2ss(np.array(z), np.array(p), k)
    a, b, c, d = (np.real(np.atleast_2d(m)).astype(np.float64) for m in (a, b, c, d))
    n = a.shape[0]
    # Augment with theta' = C x + D u, then ZOH over one period (matrix exponential).
    big = np.zeros((n + 2, n + 2))
    big[:n, :n] = a
    big[:n, n + 1 :] = b
    big[n, :n] = c[0]
    big[n, n + 1] = d[0, 0]
    e = expm(big * ts)
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
    num, den = ss2tf(ag, bg[:, None], cg[None, :], np.zeros((1, 1)))
    # In z: num(z)/den(z) with equal lengths; as polynomials in z^-1 the same arrays apply.
    return DiscretePlant(
        a=readonly(ax),
        b=readonly(bx),
        cw=readonly(cw),
        ct=readonly(ct),
        ag=readonly(ag),
        bg=readonly(bg),
        num=readonly(np.asarray(num[0], dtype=np.float64)),
        den=readonly(np.asarray(den, dtype=np.float64)),
    )


def poly_zinv(coeffs: FloatArray, zinv: ComplexArray) -> ComplexArray:
    """sum_k c_k z^-k by Horner (coeffs in ascending powers of z^-1)."""
    out = np.full(zinv.shape, coeffs[-1], dtype=np.complex128)
    for c in coeffs[-2::-1]:
        out = out * zinv + c
    return out


def plant_response(pl: DiscretePlant, zinv: ComplexArray) -> ComplexArray:
    return poly_zinv(pl.num, zinv) / poly_zinv(pl.den, zinv)


def sos_state_space(sos: SosArray) -> tuple[FloatArray, FloatArray, FloatArray, float]:
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
class DobFilters:
    tau_s: float
    f1_sos: SosArray
    f2_sos: SosArray
    f1_ss: tuple[FloatArray, FloatArray, FloatArray, float]
    f2_ss: tuple[FloatArray, FloatArray, FloatArray, float]


def dob_filters(cfg: LoopConfig) -> DobFilters:
    """The implemented DOB filters, cached per (Q type, cut-off, rate, nominal model)."""
    return _dob_cached(cfg.q_type, cfg.q_cutoff_hz, cfg.rate_hz, cfg.nominal)


@lru_cache(maxsize=256)
def _dob_cached(q_type: str, cutoff_hz: float, rate_hz: float, nominal: NominalModel) -> DobFilters:
    # lru_cache keeps its own lock (CPython), so concurrent analyse() calls from GUI thread
    # pools share the cache safely; two callers may both compute a missing entry, which is
    # harmless: the design is a pure function of the key.
    d = design_dob(LoopConfig(q_type=q_type, q_cutoff_hz=cutoff_hz, rate_hz=rate_hz,
                              nominal=nominal))
    f1, f2 = d.f1_sos, d.f2_sos
    return DobFilters(d.q.tau_s, f1, f2, sos_state_space(f1), sos_state_space(f2))


def tustin_pi(kp: float, ki: float, ts: float, zinv: ComplexArray) -> ComplexArray:
    """Tustin PI kp (1 + ki Ts/2 (1 + z^-1)/(1 - z^-1)), as loop.py integrates."""
    return kp * (1.0 + ki * ts * 0.5 * (1.0 + zinv) / (1.0 - zinv))


@dataclass(frozen=True, eq=False)
class LoopBlocks:
    """Frequency responses of the loop pieces at some frequencies."""

    zinv: ComplexArray
    g: ComplexArray
    cv: ComplexArray
    ctot: ComplexArray
    f1: ComplexArray
    f2d: ComplexArray  # F2 z^-1


def loop_blocks(
    cfg: LoopConfig, dob: DobFilters | None, f: FloatArray, plant: NominalModel,
    gains: GainBlocks | None = None,
) -> LoopBlocks:
    """The blocks at `f` with `plant` (the plant model: never the candidate's own `nominal`,
    which is only the DOB's internal model) as G (`gains`: `gain_blocks` at f, given)."""
    zinv, g, cv, ctot = gains if gains is not None else gain_blocks(cfg, f, plant)
    if dob is None:
        zero = np.zeros_like(zinv)
        return LoopBlocks(zinv, g, cv, ctot, zero, zero)
    f1, f2d = _dob_blocks(dob, f, cfg.rate_hz, zinv)
    return LoopBlocks(zinv, g, cv, ctot, f1, f2d)


def loop_blocks_groups(
    cfg: LoopConfig, dobs: list[DobFilters | None], fs: list[FloatArray], plant: NominalModel
) -> LoopBlocks:
    """`loop_blocks` at the points of every group in `fs`, one after the other, with group
    i's DOB filters `dobs[i]` (the same loop but for the DOB's cut-off): each point's blocks
    as `loop_blocks` gives them for its group alone (the filters are evaluated per group)."""
    f = np.concatenate(fs)
    zinv, g, cv, ctot = gain_blocks(cfg, f, plant)
    f1s, f2ds = [], []
    start = 0
    for dob, ff in zip(dobs, fs, strict=True):
        if dob is None:
            f1 = f2d = np.zeros(ff.size, dtype=np.complex128)
        else:
            f1, f2d = _dob_blocks(dob, ff, cfg.rate_hz, zinv[start : start + ff.size])
        f1s.append(f1)
        f2ds.append(f2d)
        start += ff.size
    return LoopBlocks(zinv, g, cv, ctot, np.concatenate(f1s), np.concatenate(f2ds))


GainBlocks = tuple[ComplexArray, ComplexArray, ComplexArray, ComplexArray]


def gain_blocks(cfg: LoopConfig, f: FloatArray, plant: NominalModel) -> GainBlocks:
    """(z^-1, G, Cv, C_tot) at `f`: the blocks that do not depend on the DOB. Cv includes the
    speed-command filter N (Cv's output goes through it before the DOB): Cv here is N Cv."""
    ts = cfg.period_s
    zinv = np.exp(-1j * TWO_PI * ts * f)
    g = plant_response(discrete_plant(plant, cfg.rate_hz), zinv)
    cv = tustin_pi(cfg.cv_kp, cfg.cv_ki_per_s, ts, zinv)
    if cfg.command_filter.kind != "off":
        cv = cv * command_filter_response(cfg.command_filter, f, cfg.rate_hz)
    cp = tustin_pi(cfg.pos_kp_per_s, cfg.pos_ki_per_s, ts, zinv)
    ctot = cv * (1.0 + cp * ts / (1.0 - zinv))
    return zinv, g, cv, ctot


def _dob_blocks(dob: DobFilters, f: FloatArray, rate_hz: float, zinv: ComplexArray
                ) -> tuple[ComplexArray, ComplexArray]:
    """(F1, F2 z^-1) at `f` (z^-1 given there)."""
    f1, f2 = sos_responses((dob.f1_sos, dob.f2_sos), f, rate_hz)
    return f1, f2 * zinv


# --------------------------------------------------------------------------- closed-loop poles


def closed_loop_matrix(
    cfg: LoopConfig, dob: DobFilters | None, plant: NominalModel, *, position: bool = True
) -> FloatArray:
    """State matrix of the loop with plant model `plant` (references and disturbances zero):
    the whole servo, or with `position` false the speed loop alone (`ServoLoop.tick_speed`).

    A PI with a zero integral gain is a plain gain: its integrator state is left out (the tick
    integrates nothing then), so it adds no spurious pole at z = 1.
    """
    ts = cfg.period_s
    pl = discrete_plant(plant, cfg.rate_hz)
    npl = pl.a.shape[0]
    if dob is not None:
        a1, b1, c1, d1 = dob.f1_ss
        a2, b2, c2, d2 = dob.f2_ss
        n1, n2 = a1.shape[0], a2.shape[0]
    else:
        n1 = n2 = 0
    # The speed-command filter's states (none when it is off).
    acf, bcf, ccf, dcf = sos_state_space(command_filter_sos(cfg.command_filter, cfg.rate_hz))
    ncf = acf.shape[0]
    # State layout: plant | Cp integrator | Cv integrator | F1 | F2 | u[k-1] (if DOB) | N.
    ip, icp, icv = 0, npl, npl + 1
    i1 = npl + 2
    i2 = i1 + n1
    idu = i2 + n2
    icf = idu + (1 if dob is not None else 0)
    n = icf + ncf
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
    u = dcf * v
    u[icf:n] += ccf
    if dob is not None:
        y1 = d1 * w
        y1[i1:i2] += c1
        y2 = np.zeros(n)
        y2[i2:idu] = c2
        y2[idu] += d2
        u = u - y1 + y2
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
    if ncf:
        a[icf:n, icf:n] += acf
        a[icf:n] += np.outer(bcf, v)
    # Without the position loop theta is fed back nowhere and r = 0; states that are not
    # integrators of the running loop are removed (rows and columns: they feed nothing).
    drop = []
    if not position:
        drop += [npl - 1, icp]  # theta (the last plant state) and Cp's integrator
    else:
        if hp == 0.0:
            drop.append(icp)
    if hv == 0.0:
        drop.append(icv)
    if drop:
        keep = np.array([i for i in range(n) if i not in drop])
        a = a[keep][:, keep]
    return a


