"""Second-order fit: recovery of M(s)P(s) = 1935 / (s^2 + 62.2 s + 1935), uncertainty, band."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal as sig

from controller.gate.frd_csv import FrdData
from controller.ident.estimate import estimate_stepped_sine
from controller.ident.excitation import SteppedSineSpec, stepped_sine
from controller.ident.model_fit import (
    coherence_weights,
    fit_frd,
    fit_second_order,
    frd_weights,
    relative_uncertainty,
    uncertainty_bound,
)

FS = 1000.0
WN = math.sqrt(1935.0)  # 43.99 rad/s = 7.0 Hz
ZETA = 62.2 / (2.0 * WN)  # 0.707
F = np.logspace(math.log10(0.3), math.log10(30.0), 40)


def mp(freq_hz: np.ndarray) -> np.ndarray:
    s = 2j * np.pi * freq_hz
    return 1935.0 / (s**2 + 62.2 * s + 1935.0)


def noisy(h: np.ndarray, rel: float, rng: np.random.Generator) -> np.ndarray:
    """Circular complex relative noise of standard deviation ``rel``."""
    e = (rng.standard_normal(h.size) + 1j * rng.standard_normal(h.size)) / math.sqrt(2.0)
    return h * (1.0 + rel * e)


@pytest.mark.parametrize("model", ["unit_dc", "dc_gain", "general"])
def test_exact_data_gives_exact_model(model: str) -> None:
    fit = fit_second_order(F, mp(F), model=model)  # type: ignore[arg-type]
    assert fit.converged
    assert fit.wn_rad_s == pytest.approx(WN, rel=1e-9)
    assert fit.zeta == pytest.approx(ZETA, rel=1e-9)
    assert fit.dc_gain == pytest.approx(1.0, rel=1e-9)
    assert fit.residual_rms_db < 1e-9
    assert fit.residual_rms_deg < 1e-9
    if model == "unit_dc":
        # the article's eq. (33)-(34) product: 5.169e-4 s^2 + 0.03215 s + 1
        assert fit.params["a2"] == pytest.approx(1 / 1935, rel=1e-9)
        assert fit.params["a1"] == pytest.approx(62.2 / 1935, rel=1e-9)
        np.testing.assert_allclose(fit.den, [1 / 1935, 62.2 / 1935, 1.0], rtol=1e-9)
    elif model == "dc_gain":
        assert fit.params["k"] == pytest.approx(1.0, rel=1e-9)
        np.testing.assert_allclose(fit.num, [1.0], rtol=1e-9)
        np.testing.assert_allclose(fit.den, [1 / 1935, 62.2 / 1935, 1.0], rtol=1e-9)
    else:
        np.testing.assert_allclose(fit.num, [1935.0], rtol=1e-9)
        np.testing.assert_allclose(fit.den, [1.0, 62.2, 1935.0], rtol=1e-9)
    np.testing.assert_allclose(fit.response(F), mp(F), rtol=1e-9)


@pytest.mark.parametrize("model", ["unit_dc", "dc_gain", "general"])
def test_recovers_wn_and_zeta_from_noisy_data(model: str) -> None:
    rng = np.random.default_rng(0)
    fit = fit_second_order(F, noisy(mp(F), 0.03, rng), np.full(F.size, 0.99), model=model)  # type: ignore[arg-type]
    assert fit.natural_freq_hz == pytest.approx(WN / (2 * math.pi), rel=0.02)
    assert fit.zeta == pytest.approx(ZETA, rel=0.02)
    # the reported uncertainty is consistent with the actual error
    assert abs(fit.wn_rad_s - WN) < 4 * fit.wn_std_rad_s
    assert abs(fit.zeta - ZETA) < 4 * fit.zeta_std
    # residual of 3 % circular noise: 8.686 * 0.03 / sqrt 2 = 0.18 dB, 1.2 deg rms
    assert 0.12 < fit.residual_rms_db < 0.25
    assert 0.8 < fit.residual_rms_deg < 1.6


@pytest.mark.parametrize("k", [0.55, 1.0, 1.9])
def test_dc_gain_model_recovers_the_gain_as_the_general_model_does(k: float) -> None:
    """k / (a2 s^2 + a1 s + 1): on exact data k, a2, a1 exactly (against the generating
    coefficients and the general model's b / a0, 1 / a0, a1 / a0); on noisy data k within its
    reported uncertainty, which matches a Monte-Carlo spread. The unit-DC model cannot follow
    k != 1 (its residual says so)."""
    exact = k * mp(F)
    fit = fit_second_order(F, exact, model="dc_gain")
    gen = fit_second_order(F, exact, model="general")
    b, a1, a0 = gen.params["b"], gen.params["a1"], gen.params["a0"]
    assert fit.params["k"] == pytest.approx(k, rel=1e-9) == pytest.approx(b / a0, rel=1e-9)
    assert fit.params["a2"] == pytest.approx(1 / 1935, rel=1e-9) == pytest.approx(1 / a0, rel=1e-9)
    assert fit.params["a1"] == pytest.approx(62.2 / 1935, rel=1e-9)
    assert fit.params["a1"] == pytest.approx(a1 / a0, rel=1e-9)
    assert fit.dc_gain == pytest.approx(k, rel=1e-9)
    unit = fit_second_order(F, exact, model="unit_dc")
    if k != 1.0:
        assert unit.residual_rms_db > 1.0 and fit.residual_rms_db < 1e-9
    rng = np.random.default_rng(5)
    fits = [fit_second_order(F, noisy(exact, 0.03, rng), model="dc_gain") for _ in range(60)]
    ks = np.array([f.params["k"] for f in fits])
    k_std = np.mean([f.param_std["k"] for f in fits])
    assert 0.7 < np.std(ks) / k_std < 1.35
    assert abs(np.mean(ks) - k) < 4 * np.std(ks) / math.sqrt(ks.size)


def test_reported_uncertainty_matches_monte_carlo() -> None:
    rng = np.random.default_rng(1)
    fits = [fit_second_order(F, noisy(mp(F), 0.03, rng)) for _ in range(100)]
    wn = np.array([f.wn_rad_s for f in fits])
    zeta = np.array([f.zeta for f in fits])
    wn_std = np.mean([f.wn_std_rad_s for f in fits])
    zeta_std = np.mean([f.zeta_std for f in fits])
    assert 0.75 < np.std(wn) / wn_std < 1.3
    assert 0.75 < np.std(zeta) / zeta_std < 1.3
    assert abs(np.mean(wn) - WN) < 3 * np.std(wn) / math.sqrt(wn.size)


def test_uncertainty_shrinks_with_more_data() -> None:
    rng = np.random.default_rng(2)
    few = np.logspace(math.log10(0.3), math.log10(30.0), 20)
    many = np.logspace(math.log10(0.3), math.log10(30.0), 320)
    fit_few = fit_second_order(few, noisy(mp(few), 0.03, rng))
    fit_many = fit_second_order(many, noisy(mp(many), 0.03, rng))
    # 16x the points: about 4x smaller
    assert fit_many.wn_std_rad_s < 0.4 * fit_few.wn_std_rad_s
    assert fit_many.zeta_std < 0.4 * fit_few.zeta_std
    # less noise, same points: proportionally smaller
    fit_quiet = fit_second_order(few, noisy(mp(few), 0.003, rng))
    assert fit_quiet.zeta_std < 0.2 * fit_few.zeta_std


def test_band_restriction_ignores_outside_points() -> None:
    rng = np.random.default_rng(3)
    h = noisy(mp(F), 0.01, rng)
    inside = (F >= 0.5) & (F <= 12.0)
    fit = fit_second_order(F, h, model="unit_dc", f_lo_hz=0.5, f_hi_hz=12.0)
    assert fit.n_points == np.count_nonzero(inside)
    assert (fit.f_lo_hz, fit.f_hi_hz) == (0.5, 12.0)
    # garbage outside the band changes nothing
    corrupted = h.copy()
    corrupted[~inside] *= 3.0 * np.exp(1j * 1.0)
    fit_c = fit_second_order(F, corrupted, model="unit_dc", f_lo_hz=0.5, f_hi_hz=12.0)
    assert fit_c.params == fit.params
    assert fit.zeta == pytest.approx(ZETA, rel=0.02)
    # ... while fitting the whole corrupted range is far off
    fit_all = fit_second_order(F, corrupted, model="unit_dc")
    assert abs(fit_all.zeta / ZETA - 1) > 0.1 or abs(fit_all.wn_rad_s / WN - 1) > 0.1


def test_weights_from_coherence() -> None:
    w = coherence_weights([0.0, 0.5, 0.9, 1.0])
    np.testing.assert_allclose(w, [0.0, 1.0, 9.0, 1.0e4])
    # low-coherence points with a gross error barely move the fit
    h = mp(F).copy()
    coh = np.full(F.size, 0.999)
    h[::7] *= 2.0
    coh[::7] = 0.01
    fit = fit_second_order(F, h, coh)
    assert fit.zeta == pytest.approx(ZETA, rel=0.02)
    assert fit.wn_rad_s == pytest.approx(WN, rel=0.02)


def test_fit_through_the_estimation_chain_with_zoh_delay() -> None:
    """Stepped sine on the ZOH-discretised plant, estimate, fit with half a sample of delay."""
    num, den, _ = sig.cont2discrete(([1935.0], [1.0, 62.2, 1935.0]), 1.0 / FS, method="zoh")
    ss = stepped_sine(SteppedSineSpec(f_min_hz=0.3, f_max_hz=30.0, settle_s=0.3))
    rng = np.random.default_rng(4)
    w = sig.lfilter(np.ravel(num), np.ravel(den), ss.signal)
    est = estimate_stepped_sine(ss, ss.signal, w + 0.05 * rng.standard_normal(w.size))
    fit = fit_second_order(est.freq_hz, est.response, est.coherence, delay_s=0.5 / FS)
    assert fit.wn_rad_s == pytest.approx(WN, rel=0.02)
    assert fit.zeta == pytest.approx(ZETA, rel=0.02)
    # without the half-sample delay the damping comes out about 3 % low
    no_delay = fit_second_order(est.freq_hz, est.response, est.coherence)
    assert abs(no_delay.zeta / ZETA - 1) > abs(fit.zeta / ZETA - 1)


def test_fit_frd_uncertainty_matches_monte_carlo_on_stepped_sine() -> None:
    """Estimate + fit repeated on fresh noise: the reported std matches the actual spread."""
    num, den, _ = sig.cont2discrete(([1935.0], [1.0, 62.2, 1935.0]), 1.0 / FS, method="zoh")
    ss = stepped_sine(SteppedSineSpec(f_min_hz=0.5, f_max_hz=20.0, min_measure_s=1.0, settle_s=0.2))
    w0 = sig.lfilter(np.ravel(num), np.ravel(den), ss.signal)
    rng = np.random.default_rng(5)
    fits = []
    for _ in range(40):
        est = estimate_stepped_sine(ss, ss.signal, w0 + 0.5 * rng.standard_normal(w0.size))
        fits.append(fit_frd(est, delay_s=0.5 / FS))
    wn = np.array([f.wn_rad_s for f in fits])
    zeta = np.array([f.zeta for f in fits])
    assert 0.7 < np.std(wn) / np.mean([f.wn_std_rad_s for f in fits]) < 1.4
    assert 0.7 < np.std(zeta) / np.mean([f.zeta_std for f in fits]) < 1.4
    assert np.mean(wn) == pytest.approx(WN, rel=0.005)
    assert np.mean(zeta) == pytest.approx(ZETA, rel=0.005)
    # several positions at once: the concatenated fit uses every point
    joint = fit_frd([est, est], delay_s=0.5 / FS)
    assert joint.n_points == 2 * est.freq_hz.size
    weights = frd_weights(est)
    assert np.all(np.isfinite(weights))
    assert np.all(weights > 0)


def test_frd_weights_for_csv_data() -> None:
    data = FrdData(freq_hz=F, mag_db=np.zeros(F.size), phase_deg=np.zeros(F.size), coherence=None)
    np.testing.assert_array_equal(frd_weights(data), np.ones(F.size))
    coh = np.full(F.size, 0.9)
    with_coh = FrdData(
        freq_hz=F, mag_db=np.zeros(F.size), phase_deg=np.zeros(F.size), coherence=coh
    )
    np.testing.assert_allclose(frd_weights(with_coh), 9.0)


def test_relative_uncertainty_and_bound() -> None:
    fit = fit_second_order(F, mp(F))
    s = 2j * np.pi * F
    deltas = [0.2 * np.ones(F.size), -0.3 * s / (s + 2 * np.pi * 5.0)]
    responses = [
        FrdData(
            freq_hz=F,
            mag_db=20 * np.log10(np.abs(mp(F) * (1 + d))),
            phase_deg=np.degrees(np.unwrap(np.angle(mp(F) * (1 + d)))),
            coherence=None,
        )
        for d in deltas
    ]
    np.testing.assert_allclose(
        relative_uncertainty(fit, F, responses[1].response), deltas[1], atol=1e-9
    )
    u = uncertainty_bound(fit, responses)
    assert u.delta.shape == (2, F.size)
    np.testing.assert_allclose(u.bound, np.maximum(0.2, np.abs(deltas[1])), atol=1e-9)


def test_tf_matches_response() -> None:
    fit = fit_second_order(F, mp(F), model="general")
    sys = fit.tf()
    np.testing.assert_allclose(sys(2j * np.pi * F), mp(F), rtol=1e-9)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"model": "third"}, "model"),
        ({"f_lo_hz": 50.0, "f_hi_hz": 60.0}, "f_lo_hz"),
        ({"f_lo_hz": 10.0, "f_hi_hz": 1.0}, "f_lo_hz"),
        ({"delay_s": -1.0}, "delay_s"),
        ({"weights": np.full(F.size, -1.0)}, "weights"),
        ({"coherence": np.ones(3)}, "coherence"),
    ],
)
def test_bad_arguments_name_the_field(kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field}"):
        fit_second_order(F, mp(F), **kwargs)  # type: ignore[arg-type]


def test_bad_data_is_rejected() -> None:
    h = mp(F)
    h[3] = np.nan
    with pytest.raises(ValueError, match=r"^response"):
        fit_second_order(F, h)
    with pytest.raises(ValueError, match=r"^freq_hz"):
        fit_second_order(-F, mp(F))
