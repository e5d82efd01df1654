"""Tustin + prewarp discretisation and the scalar SOS runtime, against scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from controller.core.config import LoopConfig, NominalModel
from controller.core.discrete import SosFilter, prewarped_fs, sos_dc_gain, sos_response, tustin_zpk
from controller.core.dob import design_dob, f1_continuous_zpk


def test_sos_filter_step_matches_scipy_sosfilt() -> None:
    dob = design_dob(LoopConfig(q_cutoff_hz=3.0))
    x = np.random.default_rng(1).standard_normal(2000)
    for sos in (dob.f1_sos, dob.f2_sos):
        f = SosFilter(sos)
        y = np.array([f.step(float(v)) for v in x])
        np.testing.assert_allclose(y, signal.sosfilt(np.array(sos), x), rtol=1e-10, atol=1e-12)


def test_set_steady_holds_a_constant_input() -> None:
    f = SosFilter(design_dob(LoopConfig(q_cutoff_hz=1.0)).f1_sos)
    y0 = f.set_steady(3.5)
    assert y0 == pytest.approx(3.5 * f.dc_gain())
    ys = [f.step(3.5) for _ in range(500)]
    np.testing.assert_allclose(ys, y0, rtol=1e-9)


def test_tustin_prewarp_matches_continuous_at_the_prewarp_frequency() -> None:
    z, p, k = [-2.0], [-1.0, -5.0 + 30j, -5.0 - 30j], 900.0
    for f0 in (0.5, 7.0, 40.0):
        zd, pd, kd = tustin_zpk(z, p, k, 1000.0, f0)
        _, hd = signal.freqz_zpk(zd, pd, kd, worN=[f0], fs=1000.0)
        _, hc = signal.freqs_zpk(z, p, k, worN=[2 * math.pi * f0])
        assert abs(hd[0] - hc[0]) <= 1e-9 * abs(hc[0])
    # Without prewarp: exactly scipy's bilinear of the polynomial form.
    zd, pd, kd = tustin_zpk(z, p, k, 1000.0, None)
    b, a = signal.zpk2tf(z, p, k)
    bd, ad = signal.bilinear(b, a, fs=1000.0)
    _, h1 = signal.freqz_zpk(zd, pd, kd, worN=[1.0, 10.0, 100.0], fs=1000.0)
    _, h2 = signal.freqz(bd, ad, worN=[1.0, 10.0, 100.0], fs=1000.0)
    np.testing.assert_allclose(h1, h2, rtol=1e-9)
    assert prewarped_fs(1000.0, 1.0) == pytest.approx(1000.0, rel=1e-5)


@pytest.mark.parametrize("cutoff_hz", [0.02, 0.5, 10.0])
def test_sections_keep_unit_dc_gain_even_with_poles_near_one(cutoff_hz: float) -> None:
    """control.md mistake 3: a direct-form Q31 near z = 1 loses its DC gain; SOS must not."""
    dob = design_dob(LoopConfig(q_cutoff_hz=cutoff_hz))
    # (a float32 direct form loses ~88 % here; float64 sections are within rounding)
    assert sos_dc_gain(dob.f2_sos) == pytest.approx(1.0, abs=1e-6)
    assert sos_dc_gain(dob.f1_sos) == pytest.approx(1.0, abs=1e-6)
    # And the step response of the runtime settles at 1 (float64 arithmetic end to end).
    f = SosFilter(dob.f2_sos)
    n = int(40 * 1000 / cutoff_hz) if cutoff_hz < 1 else 20000
    y = 0.0
    for _ in range(n):
        y = f.step(1.0)
    assert y == pytest.approx(1.0, abs=1e-3)


def test_f1_is_q_times_inverse_nominal_product() -> None:
    cfg = LoopConfig(q_type="q20", q_cutoff_hz=2.0)
    q = design_dob(cfg).q
    z, p, k = f1_continuous_zpk(q, cfg.nominal)
    f = np.array([0.1, 1.0, 5.0, 20.0])
    s = 2j * np.pi * f
    _, h = signal.freqs_zpk(z, p, k, worN=2 * np.pi * f)
    qn, qd = q.tf()
    n = cfg.nominal
    mnpn = np.polyval(n.pn_num, s) / (np.polyval(n.mn_den, s) * np.polyval(n.pn_den, s))
    expected = np.polyval(qn, s) / np.polyval(qd, s) / mnpn
    np.testing.assert_allclose(h, expected, rtol=1e-9)
    # A nominal model where Pn's numerator does not cancel Mn: F1 is 4th/4th order, still exact.
    other = NominalModel(mn_den=(1e-5, 0.004, 1.0), pn_num=(2e-5, 0.006, 1.0))
    z2, p2, k2 = f1_continuous_zpk(q, other)
    assert len(z2) == 4 and len(p2) == 4
    dob = design_dob(LoopConfig(nominal=other, q_type="q20", q_cutoff_hz=2.0))
    hd = sos_response(dob.f1_sos, np.array([0.1]), 1000.0)
    _, hc = signal.freqs_zpk(z2, p2, k2, worN=[2 * np.pi * 0.1])
    assert abs(hd[0] - hc[0]) < 1e-3 * abs(hc[0])


def test_sos_filter_rejects_bad_arrays() -> None:
    with pytest.raises(ValueError, match="sos"):
        SosFilter(np.zeros((2, 5)))
    with pytest.raises(ValueError, match="sos"):
        SosFilter(np.array([[1.0, 0, 0, 1.0, float("nan"), 0]]))
