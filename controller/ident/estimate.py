"""Frequency-response estimation from periodic excitation (pure math plus a CSV codec).

All estimators work on per-period Fourier coefficients: the excitation repeats exactly (a
periodic multisine, or a stepped sine whose windows hold whole periods), so one DFT bin per
period and per frequency is exact and the spread between periods measures the noise.

* Open loop (H1): ``H = S_uw / S_uu``, coherence ``|S_uw|^2 / (S_uu S_ww)``.
* Closed loop (joint input-output, "indirect"): the known excitation ``x`` is added to the
  command; ``H = S_xw / S_xu``. Noise on the measured output feeds back into ``u``, so the
  naive ``S_uw / S_uu`` is biased towards ``-1 / C`` wherever the noise dominates ``u``, while
  ``x`` is uncorrelated with the noise. Coherence is ``gamma^2_xu * gamma^2_xw``.

Spectra are averages over the measured periods (``n_averages`` of them). The confidence band is
the standard deviation of the estimate from the spread between periods: with residuals
``e_p = W_p - H U_p`` and ``s^2 = sum |e_p|^2 / (P - 1)``, ``var H = s^2 / sum_p |U_p|^2`` (H1) or
``s^2 sum |X_p|^2 / |sum X_p^* U_p|^2`` (closed loop); a circular complex error splits evenly
into magnitude and phase, so ``mag_std_db = 20 log10(e) sigma / (sqrt 2 |H|)`` and
``phase_std_deg = deg(sigma / (sqrt 2 |H|))``. With one period they are NaN.

A multisine with ``spread_from="lines"`` (`estimate_multisine_lines`) takes the variance from
the non-excited lines instead (Pintelon & Schoukens' nonparametric noise analysis): on the
period-averaged spectra ``H_k = W_k / U_k`` (equal to H1 and to ``S_xw / S_xu``: the
excitation repeats exactly), and ``var H_k = s_k^2 / |U_k|^2`` with ``s_k^2`` the mean of
``|W_l - H_k U_l|^2`` over the `NOISE_LINES` non-excited lines ``l`` nearest to ``k``, taken as
a median (divided by its expectation for exponentially distributed powers) so that a lone
periodic disturbance on one line (a belt tooth) does not inflate its neighbours. Those lines
carry the noise and the nonlinear distortion (which repeats in every period and so never shows
between periods): the spread is that of the best linear approximation. With only odd bins
excited only the odd non-excited lines count: even-order distortion (and the first
intermodulation of a disturbance kept on an odd line) falls on the even lines, never on the
excited ones. The coherence is the
one that gives this spread in `coherence_std`: ``1 / (1 + P var H / |H|^2)``.

CSV format (the project's measured-response files): header ``freq_hz,mag_db,phase_deg`` plus an
optional ``coherence`` column; frequencies strictly increasing; phase unwrapped on write.
`controller.gate.frd_csv.parse_frd_csv` is the single parser (`controller.cli.frd_files` reads the
files); errors name the file and the line.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from controller.core.arrays import ComplexArray, FloatArray, IntArray
from controller.gate.frd_csv import FrdLike, mag_db_of, phase_deg_of
from controller.gate.knowledge import UNCERTAINTY_SIGMAS
from controller.ident.excitation import Multisine, SteppedSine

__all__ = [
    "NOISE_LINES",
    "Agreement",
    "DetectionLines",
    "FrdEstimate",
    "agreement",
    "coherence_std",
    "detection_lines",
    "estimate_from_coefficients",
    "estimate_multisine",
    "estimate_multisine_lines",
    "estimate_stepped_sine",
    "multisine_coefficients",
    "shared_grid",
    "stepped_sine_coefficients",
]

Method = Literal["open_loop_h1", "closed_loop_x"]

_DB_PER_NEPER = 20.0 / math.log(10.0)

#: Non-excited lines whose median power gives an excited line's noise (`estimate_multisine_lines`).
NOISE_LINES = 6


@dataclass(frozen=True, eq=False)
class FrdEstimate:
    """A measured frequency response with its quality figures (arrays share one grid)."""

    freq_hz: FloatArray
    """Frequencies, increasing."""
    response: ComplexArray
    """Complex response (output / input)."""
    coherence: FloatArray
    """Coherence in [0, 1] (see the module docstring for the closed-loop definition)."""
    mag_std_db: FloatArray
    """Standard deviation of the magnitude estimate (dB); NaN with one period."""
    phase_std_deg: FloatArray
    """Standard deviation of the phase estimate (deg); NaN with one period."""
    n_averages: IntArray
    """Periods averaged at each frequency."""
    method: Method
    """``open_loop_h1`` or ``closed_loop_x``."""

    @property
    def mag_db(self) -> FloatArray:
        return mag_db_of(self.response)

    @property
    def phase_deg(self) -> FloatArray:
        """Unwrapped phase (deg), starting in (-180, 180] at the lowest frequency."""
        return phase_deg_of(self.response)


# ----------------------------------------------------------------------------- estimators


def coherence_std(coherence: ArrayLike, n_averages: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Bendat & Piersol random error from coherence: ``(mag_std_db, phase_std_deg)``.

    Normalised error of ``|H|`` and standard deviation of the phase (rad):
    ``sqrt(1 - g^2) / (|g| sqrt(2 n))``. An alternative to the between-period spread when only
    the coherence is known (for instance after reading a CSV file).
    """
    g2 = np.clip(np.asarray(coherence, dtype=np.float64), 1e-12, 1.0)
    n = np.asarray(n_averages, dtype=np.float64)
    eps = np.sqrt(1.0 - g2) / np.sqrt(g2 * 2.0 * n)
    return _DB_PER_NEPER * eps, np.degrees(eps)


def estimate_from_coefficients(
    freq_hz: ArrayLike,
    u: ArrayLike,
    w: ArrayLike,
    x: ArrayLike | None = None,
) -> FrdEstimate:
    """Estimate from per-period Fourier coefficients, arrays of shape (periods, frequencies).

    ``x is None``: open-loop H1 from input ``u`` to output ``w``. Otherwise the closed-loop
    estimate ``S_xw / S_xu`` with ``x`` the known excitation.
    """
    f = np.asarray(freq_hz, dtype=np.float64)
    U = np.atleast_2d(np.asarray(u, dtype=np.complex128))
    W = np.atleast_2d(np.asarray(w, dtype=np.complex128))
    if U.shape != W.shape or U.shape[1] != f.size:
        raise ValueError(f"shape mismatch: freq {f.shape}, u {U.shape}, w {W.shape}")
    n = U.shape[0]
    s_uu = np.mean(np.abs(U) ** 2, axis=0)
    s_ww = np.mean(np.abs(W) ** 2, axis=0)
    if x is None:
        s_uw = np.mean(np.conj(U) * W, axis=0)
        h = s_uw / s_uu
        coh = np.abs(s_uw) ** 2 / (s_uu * s_ww)
        gain_den = n * s_uu  # sum_p |U_p|^2
        method: Method = "open_loop_h1"
    else:
        X = np.atleast_2d(np.asarray(x, dtype=np.complex128))
        if X.shape != U.shape:
            raise ValueError(f"shape mismatch: x {X.shape}, u {U.shape}")
        s_xx = np.mean(np.abs(X) ** 2, axis=0)
        s_xu = np.mean(np.conj(X) * U, axis=0)
        s_xw = np.mean(np.conj(X) * W, axis=0)
        h = s_xw / s_xu
        coh = (np.abs(s_xu) ** 2 / (s_xx * s_uu)) * (np.abs(s_xw) ** 2 / (s_xx * s_ww))
        gain_den = n * np.abs(s_xu) ** 2 / s_xx  # |sum X* U|^2 / sum |X|^2
        method = "closed_loop_x"
    if n >= 2:
        resid = W - h[None, :] * U
        s2 = np.sum(np.abs(resid) ** 2, axis=0) / (n - 1)
        rel = np.sqrt(s2 / gain_den) / (math.sqrt(2.0) * np.abs(h))
        mag_std = _DB_PER_NEPER * rel
        phase_std = np.degrees(rel)
    else:
        mag_std = np.full(f.size, np.nan)
        phase_std = np.full(f.size, np.nan)
    return FrdEstimate(
        freq_hz=f,
        response=h,
        coherence=np.clip(coh, 0.0, 1.0),
        mag_std_db=mag_std,
        phase_std_deg=phase_std,
        n_averages=np.full(f.size, n, dtype=np.int64),
        method=method,
    )


def _signal(name: str, y: ArrayLike, needed: int) -> FloatArray:
    arr = np.asarray(y, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D signal (got shape {arr.shape})")
    if arr.size < needed:
        raise ValueError(f"{name}: {arr.size} samples, the excitation needs {needed}")
    return arr


def multisine_coefficients(
    excitation: Multisine, y: ArrayLike, name: str = "y", bins: IntArray | None = None
) -> ComplexArray:
    """Per-period coefficients of ``y`` at the excited bins (or at `bins`), shape
    (n_periods, n_bins).

    ``y`` is aligned with ``excitation.signal`` (same sample 0); the lead-in and the transient
    periods are dropped. Coefficients are amplitudes: a cos(2 pi f t + phi) gives a e^{j phi}.
    """
    spec = excitation.spec
    n = spec.period_samples
    start = excitation.measure_start
    arr = _signal(name, y, start + spec.n_periods * n)
    periods = arr[start : start + spec.n_periods * n].reshape(spec.n_periods, n)
    at = excitation.bins if bins is None else bins
    return np.fft.rfft(periods, axis=1)[:, at] * (2.0 / n)


def estimate_multisine(
    excitation: Multisine, u: ArrayLike, w: ArrayLike, x: ArrayLike | None = None
) -> FrdEstimate:
    """Response from command ``u`` to output ``w`` under a periodic multisine.

    Pass the excitation samples as ``x`` (usually ``excitation.signal``) when the loop is
    closed; then the estimate is ``S_xw / S_xu``. With ``spread_from="lines"`` this is
    `estimate_multisine_lines`.
    """
    if excitation.spec.spread_from == "lines":
        return estimate_multisine_lines(excitation, u, w, x)
    U = multisine_coefficients(excitation, u, "u")
    W = multisine_coefficients(excitation, w, "w")
    X = None if x is None else multisine_coefficients(excitation, x, "x")
    return estimate_from_coefficients(excitation.freq_hz, U, W, X)


def _expected_median(n: int) -> float:
    """Expected sample median of `n` exponential variables of mean 1 (order statistics)."""

    def order(i: int) -> float:  # E[X_(i)], i-th smallest of n
        return sum(1.0 / m for m in range(n - i + 1, n + 1))

    if n % 2:
        return order((n + 1) // 2)
    return 0.5 * (order(n // 2) + order(n // 2 + 1))


def _nearest(bins: IntArray, candidates: IntArray, count: int) -> IntArray:
    """For each of `bins`, the `count` nearest `candidates` (shape (bins, count))."""
    dist = np.abs(candidates[None, :] - bins[:, None])
    order = np.argsort(dist, axis=1, kind="stable")[:, :count]
    return np.asarray(candidates[order], dtype=np.int64)


def estimate_multisine_lines(
    excitation: Multisine, u: ArrayLike, w: ArrayLike, x: ArrayLike | None = None
) -> FrdEstimate:
    """Response from ``u`` to ``w`` with each line's variance from its non-excited neighbours
    (see the module docstring); works from one measured period. ``x`` (closed loop) only
    selects the method's name: with an exactly repeating excitation ``S_xw / S_xu`` is the
    ratio of the period-averaged spectra, as H1 is."""
    bins = excitation.bins
    det = excitation.spec.noise_bins()
    if det.size == 0:
        raise ValueError("excitation: no non-excited line to take the spread from")
    near = _nearest(bins, det, min(NOISE_LINES, det.size))
    at = np.union1d(bins, det)  # sorted; the two sets are disjoint
    U = np.mean(multisine_coefficients(excitation, u, "u", at), axis=0)
    W = np.mean(multisine_coefficients(excitation, w, "w", at), axis=0)
    if x is not None:
        multisine_coefficients(excitation, x, "x")  # same length checks as the other signals
    exc_i = np.searchsorted(at, bins)
    u_k, w_k = U[exc_i], W[exc_i]
    h = w_k / u_k
    idx = np.searchsorted(at, near)
    resid = W[idx] - h[:, None] * U[idx]
    s2 = np.median(np.abs(resid) ** 2, axis=1) / _expected_median(near.shape[1])
    var_h = s2 / np.abs(u_k) ** 2
    rel = np.sqrt(var_h) / (math.sqrt(2.0) * np.abs(h))
    n = excitation.spec.n_periods
    return FrdEstimate(
        freq_hz=excitation.freq_hz,
        response=h,
        coherence=1.0 / (1.0 + n * var_h / np.abs(h) ** 2),
        mag_std_db=_DB_PER_NEPER * rel,
        phase_std_deg=np.degrees(rel),
        n_averages=np.full(bins.size, n, dtype=np.int64),
        method="open_loop_h1" if x is None else "closed_loop_x",
    )


@dataclass(frozen=True, eq=False)
class DetectionLines:
    """The output spectrum of a multisine run split by lines (period-averaged amplitudes)."""

    freq_hz: FloatArray
    """Every bin from 1 to twice the highest excited one."""
    amplitude: FloatArray
    """|Y| at each of them."""
    kind: NDArray[np.int8]
    """0: excited, 1: odd non-excited (odd-order distortion + noise), 2: even non-excited
    (even-order distortion + noise)."""


def detection_lines(excitation: Multisine, y: ArrayLike) -> DetectionLines:
    """The spectrum of ``y`` at the excited lines and at the detection lines: how far the
    nonlinear distortion and the noise lie below the response (odd and even orders apart when
    only odd bins are excited)."""
    det = excitation.spec.detection_bins()
    at = np.union1d(excitation.bins, det)
    amp = np.abs(np.mean(multisine_coefficients(excitation, y, "y", at), axis=0))
    kind = np.where(np.isin(at, excitation.bins), 0, np.where(at % 2 == 1, 1, 2))
    res = excitation.spec.sample_rate_hz / excitation.spec.period_samples
    return DetectionLines(
        freq_hz=at.astype(np.float64) * res, amplitude=amp, kind=kind.astype(np.int8)
    )


def stepped_sine_coefficients(
    excitation: SteppedSine, y: ArrayLike, name: str = "y"
) -> list[ComplexArray]:
    """Per point, the single-bin DFT of each measured period of ``y`` (length n_periods)."""
    last = max((p.measure_start + p.measure_len for p in excitation.points), default=0)
    arr = _signal(name, y, last)
    out: list[ComplexArray] = []
    for p in excitation.points:
        big_l = p.period_samples
        seg = arr[p.measure_start : p.measure_start + p.measure_len].reshape(p.n_periods, big_l)
        kernel = np.exp(-2j * np.pi * np.arange(big_l) / big_l) * (2.0 / big_l)
        out.append(seg @ kernel)
    return out


def estimate_stepped_sine(
    excitation: SteppedSine, u: ArrayLike, w: ArrayLike, x: ArrayLike | None = None
) -> FrdEstimate:
    """Response from ``u`` to ``w`` under a stepped sine, one frequency per point.

    Signals are aligned with ``excitation.signal``. Each point's measurement window is split
    into whole periods; the per-period single-bin DFTs are averaged as in
    :func:`estimate_from_coefficients` (``n_averages`` is each point's period count).
    """
    cu = stepped_sine_coefficients(excitation, u, "u")
    cw = stepped_sine_coefficients(excitation, w, "w")
    cx = None if x is None else stepped_sine_coefficients(excitation, x, "x")
    parts = [
        estimate_from_coefficients(
            [p.freq_hz], cu[i][:, None], cw[i][:, None], None if cx is None else cx[i][:, None]
        )
        for i, p in enumerate(excitation.points)
    ]
    return FrdEstimate(
        freq_hz=excitation.freq_hz,
        response=np.concatenate([e.response for e in parts]),
        coherence=np.concatenate([e.coherence for e in parts]),
        mag_std_db=np.concatenate([e.mag_std_db for e in parts]),
        phase_std_deg=np.concatenate([e.phase_std_deg for e in parts]),
        n_averages=np.array([p.n_periods for p in excitation.points], dtype=np.int64),
        method="open_loop_h1" if x is None else "closed_loop_x",
    )


# ---------------------------------------------------------------------------- agreement


@dataclass(frozen=True, eq=False)
class Agreement:
    """How far several responses on one grid agree (e.g. measured at different positions),
    judged against the measurement's own uncertainty: a difference within `UNCERTAINTY_SIGMAS`
    of the responses' standard deviations is not counted against them."""

    freq_hz: FloatArray
    spread_db: FloatArray
    """max - min of the magnitudes (dB) at each frequency."""
    spread_deg: FloatArray
    """max - min of the phases (deg), phases taken relative to the first response."""
    tol_db: float
    tol_deg: float
    agree_below_hz: float
    """Highest grid frequency up to which every point is within both tolerances (plus the
    uncertainty); 0.0 if the lowest point already differs (`differs_at_lowest`)."""
    first_disagree_hz: float | None
    """Lowest frequency out of tolerance beyond the uncertainty, None if all agree."""
    uncertainty_db: FloatArray | None = None
    """k x the largest magnitude standard deviation at each frequency (None: not known)."""
    uncertainty_deg: FloatArray | None = None
    unresolved_hz: tuple[float, ...] = ()
    """Frequencies whose difference exceeds the tolerances but not the uncertainty: the
    measurement cannot tell there whether the responses agree."""

    @property
    def differs_at_lowest(self) -> bool:
        return self.first_disagree_hz is not None and self.first_disagree_hz <= self.freq_hz[0]

    def describe(self) -> str:
        """One sentence that agrees with the numbers."""
        tol = f"{self.tol_db:g} dB / {self.tol_deg:g} deg"
        if self.first_disagree_hz is None:
            text = f"curves agree within {tol} on the whole band"
        elif self.differs_at_lowest:
            text = (f"curves differ by more than {tol} already at the lowest frequency "
                    f"({self.first_disagree_hz:.3g} Hz)")
        else:
            text = (f"curves agree within {tol} up to {self.agree_below_hz:.3g} Hz "
                    f"(differ from {self.first_disagree_hz:.3g} Hz)")
        if self.unresolved_hz:
            at = ", ".join(f"{f:.3g}" for f in self.unresolved_hz)
            text += (f"; at {at} Hz the difference is within the measurement's uncertainty "
                     f"({UNCERTAINTY_SIGMAS:g} sigma): not counted")
        return text


def shared_grid(responses: Sequence[FrdLike]) -> FloatArray:
    """The frequency grid of responses[0], which every response must share (rtol 1e-9);
    ValueError naming the first response on another grid."""
    f = np.asarray(responses[0].freq_hz, dtype=np.float64)
    for i, r in enumerate(responses[1:], start=1):
        fi = np.asarray(r.freq_hz, dtype=np.float64)
        if fi.shape != f.shape or not np.allclose(fi, f, rtol=1e-9, atol=0.0):
            raise ValueError(f"responses[{i}]: frequency grid differs from responses[0]")
    return f


def agreement(
    responses: Sequence[FrdLike], tol_db: float = 1.0, tol_deg: float = 10.0
) -> Agreement:
    """Frequency up to which the responses agree within ``tol_db`` and ``tol_deg`` (beyond
    `UNCERTAINTY_SIGMAS` standard deviations of the estimates when they carry them).

    This is the article's "the curves agree below about 1 Hz": the model is trusted below
    ``agree_below_hz`` and not above.
    """
    if len(responses) < 2:
        raise ValueError("responses: need at least two responses to compare")
    if not (tol_db > 0 and tol_deg > 0):
        raise ValueError(f"tol_db, tol_deg: must be > 0 (got {tol_db}, {tol_deg})")
    f = shared_grid(responses)
    h = np.array([np.asarray(r.response, dtype=np.complex128) for r in responses])
    mag = mag_db_of(h)
    rel_phase = np.degrees(np.angle(h / h[0][None, :]))
    spread_db = np.max(mag, axis=0) - np.min(mag, axis=0)
    spread_deg = np.max(rel_phase, axis=0) - np.min(rel_phase, axis=0)
    unc_db = unc_deg = None
    over = (spread_db > tol_db) | (spread_deg > tol_deg)
    bad_mask = over
    if all(isinstance(r, FrdEstimate) for r in responses):
        ests = [r for r in responses if isinstance(r, FrdEstimate)]
        sd_db = np.nan_to_num(np.array([e.mag_std_db for e in ests]), nan=0.0)
        sd_deg = np.nan_to_num(np.array([e.phase_std_deg for e in ests]), nan=0.0)
        unc_db = UNCERTAINTY_SIGMAS * np.max(sd_db, axis=0)
        unc_deg = UNCERTAINTY_SIGMAS * np.max(sd_deg, axis=0)
        bad_mask = (spread_db > tol_db + unc_db) | (spread_deg > tol_deg + unc_deg)
    bad = np.flatnonzero(bad_mask)
    unresolved = tuple(float(x) for x in f[over & ~bad_mask])
    if bad.size == 0:
        below, first = float(f[-1]), None
    else:
        i0 = int(bad[0])
        below, first = (float(f[i0 - 1]) if i0 > 0 else 0.0), float(f[i0])
    return Agreement(
        freq_hz=f,
        spread_db=spread_db,
        spread_deg=spread_deg,
        tol_db=float(tol_db),
        tol_deg=float(tol_deg),
        agree_below_hz=below,
        first_disagree_hz=first,
        uncertainty_db=unc_db,
        uncertainty_deg=unc_deg,
        unresolved_hz=unresolved,
    )


