"""Second-order model fit to measured frequency responses (pure math).

Models, in the article's form (control.md eqs. 12-13, 33-34):

* ``unit_dc``:  ``Mn Pn = 1 / (a2 s^2 + a1 s + 1)`` (unit DC gain, load-side speeds);
* ``dc_gain``:  ``Mn Pn = k / (a2 s^2 + a1 s + 1)`` (the same with its DC gain fitted: a drive
  whose speed scaling or gain is not the article's);
* ``general``:  ``b / (s^2 + a1 s + a0)``, i.e. ``b / (a2 s^2 + a1 s + a0)`` normalised to
  ``a2 = 1`` (the four coefficients are only defined up to a common factor).

An optional known pure delay ``delay_s`` (not fitted) multiplies the model, e.g. half a sample
for the zero-order hold of data measured at the loop rate.

Method: frequency-domain weighted least squares on the relative complex error
``e = G_fit / G_meas - 1`` (about ``ln |G_fit / G_meas| + j dphase``: dB and degrees alike at
every frequency), weighted by coherence ``w = g^2 / (1 - g^2)`` (the inverse variance of the
relative error of an averaged estimate), inside ``[f_lo_hz, f_hi_hz]``. Start: Levy's linearised
problem with Sanathanan-Koerner re-weighting; then Levenberg-Marquardt on the complex error
(scipy.optimize.least_squares). Parameter standard uncertainties come from the Jacobian,
``cov = s^2 (J^T J)^-1`` with ``s^2`` the weighted residual variance, so they do not depend on
the scale of the weights, but they are only right if the weights are proportional to the inverse
variances. With few averages the estimated coherence is biased towards 1 and scattered, so for
an :class:`FrdEstimate` :func:`fit_frd` prefers the between-period variance (``frd_weights``);
with that, the reported uncertainties match Monte-Carlo spreads (see the tests and the bench).
Natural frequency and damping get their uncertainties by linear propagation.
Frequencies are normalised internally by the geometric mean of the band for conditioning.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from controller.core.arrays import ComplexArray, FloatArray
from controller.gate.frd_csv import FrdData, FrdLike
from controller.ident.estimate import FrdEstimate, shared_grid

__all__ = [
    "MODELS",
    "ModelKind",
    "ModelUncertainty",
    "SecondOrderFit",
    "coherence_weights",
    "fit_frd",
    "fit_second_order",
    "frd_weights",
    "relative_uncertainty",
    "uncertainty_bound",
]

ModelKind = Literal["unit_dc", "dc_gain", "general"]
MODELS: tuple[ModelKind, ...] = ("unit_dc", "dc_gain", "general")
_PARAM_NAMES: dict[ModelKind, tuple[str, ...]] = {
    "unit_dc": ("a2", "a1"),
    "dc_gain": ("k", "a2", "a1"),
    "general": ("b", "a1", "a0"),
}
_DB_PER_NEPER = 20.0 / math.log(10.0)


@dataclass(frozen=True, eq=False)
class SecondOrderFit:
    """A fitted second-order model with uncertainties and residuals."""

    model: ModelKind
    num: FloatArray
    """Numerator coefficients in s, highest power first (scipy / python-control order)."""
    den: FloatArray
    """Denominator coefficients in s, highest power first."""
    params: dict[str, float]
    """``a2, a1`` (unit_dc), ``k, a2, a1`` (dc_gain) or ``b, a1, a0`` (general)."""
    param_std: dict[str, float]
    """Standard uncertainty of each parameter."""
    covariance: FloatArray
    """Covariance of the parameters, in the order of ``params``."""
    wn_rad_s: float
    wn_std_rad_s: float
    zeta: float
    zeta_std: float
    dc_gain: float
    delay_s: float
    """Known delay included in :meth:`response` (not fitted)."""
    f_lo_hz: float
    f_hi_hz: float
    n_points: int
    """Frequencies used (inside the band, non-zero weight)."""
    residual_rms_db: float
    """RMS of 20 log10 |G_fit / G_meas| over the points used (unweighted)."""
    residual_rms_deg: float
    """RMS of the phase of G_fit / G_meas over the points used (unweighted)."""
    converged: bool

    @property
    def natural_freq_hz(self) -> float:
        return self.wn_rad_s / (2.0 * math.pi)

    @property
    def natural_freq_std_hz(self) -> float:
        return self.wn_std_rad_s / (2.0 * math.pi)

    def response(self, freq_hz: ArrayLike, include_delay: bool = True) -> ComplexArray:
        """Model response at ``freq_hz`` (with the known delay unless told otherwise)."""
        f = np.asarray(freq_hz, dtype=np.float64)
        s = 2j * np.pi * f
        g = np.polyval(self.num, s) / np.polyval(self.den, s)
        if include_delay and self.delay_s:
            g = g * np.exp(-s * self.delay_s)
        return np.asarray(g, dtype=np.complex128)

    def tf(self) -> Any:
        """The model (without the delay) as a ``control.TransferFunction``."""
        import control  # deferred: python-control is slow to import and only needed here

        return control.tf(self.num, self.den)


def coherence_weights(coherence: ArrayLike, max_weight: float = 1.0e4) -> FloatArray:
    """``g^2 / (1 - g^2)``, clipped to ``[0, max_weight]`` (coherence 1 would be infinite).

    Proportional to the inverse variance of the relative error of an estimate averaged over a
    fixed number of periods; multiply by ``n_averages`` when that number varies.
    """
    g2 = np.clip(np.asarray(coherence, dtype=np.float64), 0.0, 1.0)
    with np.errstate(divide="ignore"):
        w = g2 / (1.0 - g2)
    return np.clip(np.nan_to_num(w, nan=0.0, posinf=max_weight), 0.0, max_weight)


def frd_weights(frd: FrdEstimate | FrdData) -> FloatArray:
    """Inverse-variance weights of the relative error for one measured response.

    FrdEstimate: ``1 / (rel_mag_std^2 + phase_std_rad^2)`` from the between-period spread
    where it is finite, otherwise ``n_averages * g^2 / (1 - g^2)``. FrdData (CSV): coherence
    weights if the file has a coherence column, otherwise all ones.
    """
    if isinstance(frd, FrdEstimate):
        var = (frd.mag_std_db / _DB_PER_NEPER) ** 2 + np.radians(frd.phase_std_deg) ** 2
        fallback = coherence_weights(frd.coherence) * frd.n_averages
        with np.errstate(divide="ignore"):
            w = np.where(np.isfinite(var) & (var > 0), 1.0 / var, fallback)
        return np.asarray(w, dtype=np.float64)
    if frd.coherence is not None:
        return coherence_weights(frd.coherence)
    return np.ones(frd.freq_hz.size)


# --------------------------------------------------------------------------- model algebra
# theta holds normalised parameters (frequency scaled by w_ref, s_n = s / w_ref):
#   unit_dc: (alpha2, alpha1),       D = alpha2 s_n^2 + alpha1 s_n + 1, G = 1 / D
#   dc_gain: (k, alpha2, alpha1),    D = alpha2 s_n^2 + alpha1 s_n + 1, G = k / D
#   general: (beta, alpha1, alpha0), D = s_n^2 + alpha1 s_n + alpha0,   G = beta / D


def _model(kind: ModelKind, theta: FloatArray, sn: NDArray[Any]) -> tuple[Any, Any]:
    """Response and its derivative w.r.t. theta (shape (p, n))."""
    if kind == "unit_dc":
        d = theta[0] * sn**2 + theta[1] * sn + 1.0
        g = 1.0 / d
        dg = np.array([-(sn**2) * g / d, -sn * g / d])
    elif kind == "dc_gain":
        d = theta[1] * sn**2 + theta[2] * sn + 1.0
        g = theta[0] / d
        dg = np.array([1.0 / d, -(sn**2) * g / d, -sn * g / d])
    else:
        d = sn**2 + theta[1] * sn + theta[2]
        g = theta[0] / d
        dg = np.array([1.0 / d, -sn * g / d, -g / d])
    return g, dg


def _levy_sk(
    kind: ModelKind, sn: NDArray[Any], h: NDArray[Any], sw: NDArray[Any], iterations: int
) -> FloatArray:
    """Levy's linearised fit with Sanathanan-Koerner re-weighting by 1 / |H D_prev|."""
    d_prev = np.ones_like(h)
    theta = np.zeros(len(_PARAM_NAMES[kind]))
    for _ in range(max(1, iterations)):
        row_w = sw / np.abs(h * d_prev)
        if kind == "unit_dc":
            # H (alpha2 s^2 + alpha1 s) = 1 - H
            a = np.stack([h * sn**2, h * sn], axis=1)
            rhs = 1.0 - h
        elif kind == "dc_gain":
            # k - H (alpha2 s^2 + alpha1 s) = H
            a = np.stack([np.ones_like(h), -h * sn**2, -h * sn], axis=1)
            rhs = h
        else:
            # beta - H s alpha1 - H alpha0 = H s^2
            a = np.stack([np.ones_like(h), -h * sn, -h], axis=1)
            rhs = h * sn**2
        a = a * row_w[:, None]
        rhs = rhs * row_w
        a_real = np.concatenate([a.real, a.imag])
        rhs_real = np.concatenate([rhs.real, rhs.imag])
        new = np.linalg.lstsq(a_real, rhs_real, rcond=None)[0]
        if kind == "unit_dc":
            d_prev = new[0] * sn**2 + new[1] * sn + 1.0
        elif kind == "dc_gain":
            d_prev = new[1] * sn**2 + new[2] * sn + 1.0
        else:
            d_prev = sn**2 + new[1] * sn + new[2]
        converged = np.allclose(new, theta, rtol=1e-10, atol=1e-12)
        theta = new
        if converged:
            break
    return theta


def _wn_zeta(kind: ModelKind, p: FloatArray) -> tuple[float, float, FloatArray, FloatArray]:
    """wn, zeta and their gradients w.r.t. the physical parameters."""
    if kind == "dc_gain":  # k does not enter them
        wn, zeta, g_wn, g_zeta = _wn_zeta("unit_dc", p[1:])
        return wn, zeta, np.concatenate([[0.0], g_wn]), np.concatenate([[0.0], g_zeta])
    if kind == "unit_dc":
        a2, a1 = p
        if a2 <= 0:
            nan = np.full(2, np.nan)
            return math.nan, math.nan, nan, nan
        wn = 1.0 / math.sqrt(a2)
        zeta = a1 / (2.0 * math.sqrt(a2))
        g_wn = np.array([-0.5 * a2**-1.5, 0.0])
        g_zeta = np.array([-0.25 * a1 * a2**-1.5, 0.5 / math.sqrt(a2)])
    else:
        _, a1, a0 = p
        if a0 <= 0:
            nan = np.full(3, np.nan)
            return math.nan, math.nan, nan, nan
        wn = math.sqrt(a0)
        zeta = a1 / (2.0 * math.sqrt(a0))
        g_wn = np.array([0.0, 0.0, 0.5 / math.sqrt(a0)])
        g_zeta = np.array([0.0, 0.5 / math.sqrt(a0), -0.25 * a1 * a0**-1.5])
    return wn, zeta, g_wn, g_zeta


def _as_1d(name: str, value: ArrayLike, dtype: type, size: int | None = None) -> NDArray[Any]:
    arr: NDArray[Any] = np.asarray(value, dtype=dtype)
    if arr.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D array (got shape {arr.shape})")
    if size is not None and arr.size != size:
        raise ValueError(f"{name}: {arr.size} values, expected {size}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return arr


def fit_second_order(
    freq_hz: ArrayLike,
    response: ArrayLike,
    coherence: ArrayLike | None = None,
    *,
    model: ModelKind = "unit_dc",
    f_lo_hz: float | None = None,
    f_hi_hz: float | None = None,
    weights: ArrayLike | None = None,
    delay_s: float = 0.0,
    sk_iterations: int = 20,
) -> SecondOrderFit:
    """Fit ``model`` to a measured response (see the module docstring for the method).

    Frequencies need not be sorted, so responses from several positions may be concatenated
    and fitted together. ``weights`` (inverse variance of the relative error) override the
    coherence weights; with neither, all points weigh the same.
    """
    if model not in MODELS:
        raise ValueError(f"model: unknown model {model!r}; expected one of {', '.join(MODELS)}")
    f = _as_1d("freq_hz", freq_hz, np.float64)
    h = _as_1d("response", response, np.complex128, f.size)
    if np.any(f <= 0):
        raise ValueError("freq_hz: must be > 0")
    if np.any(h == 0):
        raise ValueError("response: must be non-zero")
    if weights is not None:
        w = _as_1d("weights", weights, np.float64, f.size)
        if np.any(w < 0):
            raise ValueError("weights: must be >= 0")
    elif coherence is not None:
        w = coherence_weights(_as_1d("coherence", coherence, np.float64, f.size))
    else:
        w = np.ones(f.size)
    if not math.isfinite(delay_s) or delay_s < 0:
        raise ValueError(f"delay_s: must be finite and >= 0 (got {delay_s})")
    lo = float(np.min(f)) if f_lo_hz is None else float(f_lo_hz)
    hi = float(np.max(f)) if f_hi_hz is None else float(f_hi_hz)
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        raise ValueError(f"f_lo_hz: must be <= f_hi_hz (got {lo} > {hi})")
    use = (f >= lo) & (f <= hi) & (w > 0)
    n_params = len(_PARAM_NAMES[model])
    if np.count_nonzero(use) < n_params:
        raise ValueError(
            f"f_lo_hz, f_hi_hz: only {np.count_nonzero(use)} weighted points in "
            f"[{lo}, {hi}] Hz, need at least {n_params}"
        )
    f_u, w_u = f[use], w[use]
    omega = 2.0 * np.pi * f_u
    h_u = h[use] * np.exp(1j * omega * delay_s)  # remove the known delay
    w_ref = float(np.exp(np.mean(np.log(omega))))
    sn = 1j * omega / w_ref
    sw = np.sqrt(w_u)

    theta0 = _levy_sk(model, sn, h_u, sw, sk_iterations)

    def residual(theta: FloatArray) -> FloatArray:
        g, _ = _model(model, theta, sn)
        e = sw * (g / h_u - 1.0)
        return np.concatenate([e.real, e.imag])

    def jacobian(theta: FloatArray) -> FloatArray:
        _, dg = _model(model, theta, sn)
        de = sw * dg / h_u
        return np.concatenate([de.real, de.imag], axis=1).T

    sol = least_squares(residual, theta0, jac=jacobian, method="lm", xtol=1e-12, ftol=1e-12)
    theta = sol.x
    m = 2 * f_u.size
    jac = jacobian(theta)
    dof = m - n_params
    s2 = float(np.sum(sol.fun**2)) / dof if dof > 0 else math.nan
    cov_n = s2 * np.linalg.pinv(jac.T @ jac)

    if model == "unit_dc":
        scale = np.array([1.0 / w_ref**2, 1.0 / w_ref])
    elif model == "dc_gain":
        scale = np.array([1.0, 1.0 / w_ref**2, 1.0 / w_ref])
    else:
        scale = np.array([w_ref**2, w_ref, w_ref**2])
    p = theta * scale
    cov = cov_n * np.outer(scale, scale)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    wn, zeta, g_wn, g_zeta = _wn_zeta(model, p)
    if model == "unit_dc":
        num, den = np.array([1.0]), np.array([p[0], p[1], 1.0])
    elif model == "dc_gain":
        num, den = np.array([p[0]]), np.array([p[1], p[2], 1.0])
    else:
        num, den = np.array([p[0]]), np.array([1.0, p[1], p[2]])

    g_fit, _ = _model(model, theta, sn)
    ratio = g_fit / h_u
    names = _PARAM_NAMES[model]
    return SecondOrderFit(
        model=model,
        num=num,
        den=den,
        params={k: float(v) for k, v in zip(names, p, strict=True)},
        param_std={k: float(v) for k, v in zip(names, std, strict=True)},
        covariance=np.asarray(cov, dtype=np.float64),
        wn_rad_s=wn,
        wn_std_rad_s=math.sqrt(max(0.0, float(g_wn @ cov @ g_wn))),
        zeta=zeta,
        zeta_std=math.sqrt(max(0.0, float(g_zeta @ cov @ g_zeta))),
        dc_gain=float(num[-1] / den[-1]),
        delay_s=float(delay_s),
        f_lo_hz=lo,
        f_hi_hz=hi,
        n_points=int(f_u.size),
        residual_rms_db=float(np.sqrt(np.mean((_DB_PER_NEPER * np.log(np.abs(ratio))) ** 2))),
        residual_rms_deg=float(np.sqrt(np.mean(np.degrees(np.angle(ratio)) ** 2))),
        converged=bool(sol.success),
    )


def fit_frd(
    frds: FrdEstimate | FrdData | Sequence[FrdEstimate | FrdData],
    *,
    model: ModelKind = "unit_dc",
    f_lo_hz: float | None = None,
    f_hi_hz: float | None = None,
    delay_s: float = 0.0,
) -> SecondOrderFit:
    """Fit one model to one or several measured responses, weighted by :func:`frd_weights`."""
    items = [frds] if isinstance(frds, (FrdEstimate, FrdData)) else list(frds)
    if not items:
        raise ValueError("frds: need at least one response")
    return fit_second_order(
        np.concatenate([r.freq_hz for r in items]),
        np.concatenate([r.response for r in items]),
        model=model,
        f_lo_hz=f_lo_hz,
        f_hi_hz=f_hi_hz,
        weights=np.concatenate([frd_weights(r) for r in items]),
        delay_s=delay_s,
    )


# ---------------------------------------------------------------------------- uncertainty


def relative_uncertainty(
    fit: SecondOrderFit, freq_hz: ArrayLike, response: ArrayLike, include_delay: bool = True
) -> ComplexArray:
    """Multiplicative model error ``Delta = G_meas / G_fit - 1`` (so ``G = G_fit (1 + Delta)``)."""
    f = _as_1d("freq_hz", freq_hz, np.float64)
    h = _as_1d("response", response, np.complex128, f.size)
    return np.asarray(h / fit.response(f, include_delay) - 1.0, dtype=np.complex128)


@dataclass(frozen=True, eq=False)
class ModelUncertainty:
    """Delta of several measured responses against one model, on a common grid."""

    freq_hz: FloatArray
    delta: ComplexArray
    """Shape (responses, frequencies)."""
    bound: FloatArray
    """max over responses of |Delta|, per frequency."""


def uncertainty_bound(
    fit: SecondOrderFit, responses: Sequence[FrdLike], include_delay: bool = True
) -> ModelUncertainty:
    """Delta of every response against ``fit`` and their envelope (same grid required)."""
    if not responses:
        raise ValueError("responses: need at least one response")
    f = shared_grid(responses)
    delta = np.array([relative_uncertainty(fit, f, r.response, include_delay) for r in responses])
    return ModelUncertainty(freq_hz=f, delta=delta, bound=np.max(np.abs(delta), axis=0))
