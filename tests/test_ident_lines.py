"""The odd random-phase multisine's estimator (`estimate_multisine_lines`): each line's variance
from its non-excited neighbours, checked against Monte-Carlo scatter on a discrete plant with
a known transfer function (scipy), and the detection lines against static nonlinearities.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal as sig
from article_plant import A_G, B_G, FS, odd_multisine_spec, plant_response

from controller.ident.estimate import (
    coherence_std,
    detection_lines,
    estimate_multisine,
    estimate_multisine_lines,
)
from controller.ident.excitation import Multisine, multisine


def _odd(n_periods: int = 1, **kw: object) -> Multisine:
    return multisine(odd_multisine_spec(f_min_hz=0.5, f_max_hz=40.0, period_samples=2000,
                                        n_periods=n_periods, amplitude_deg_s=5.0,
                                        tail_samples=100, **kw))


@pytest.mark.parametrize("n_periods", [1, 3])
def test_spread_from_the_lines_matches_the_scatter(n_periods: int) -> None:
    """Output noise (white): the reported standard deviation of each line is the scatter of
    the estimate over 300 noise records, from one measured period or three."""
    ms = _odd(n_periods)
    u = ms.signal
    y0 = sig.lfilter(B_G, A_G, u)
    g = plant_response(ms.freq_hz)
    rng = np.random.default_rng(3)
    errors, sigmas = [], []
    for _ in range(300):
        est = estimate_multisine(ms, u, y0 + 0.05 * rng.standard_normal(u.size))
        assert est.n_averages[0] == n_periods and est.method == "open_loop_h1"
        errors.append(est.response / g - 1.0)
        sigmas.append(np.sqrt(2.0) * np.log(10.0) / 20.0 * est.mag_std_db)  # complex, relative
    err = np.array(errors)
    sigma = np.array(sigmas)
    bias = np.abs(np.mean(err, axis=0))
    scatter = np.sqrt(np.mean(np.abs(err) ** 2, axis=0))
    reported = np.sqrt(np.mean(sigma**2, axis=0))
    assert np.all(bias < 0.25 * scatter)  # unbiased: the mean's own scatter is 0.06 x
    # per line within 15 % (300 records: the scatter's own uncertainty is about 4 %)
    np.testing.assert_allclose(reported, scatter, rtol=0.15)
    # the phase spread in degrees is the magnitude spread in nepers, converted
    est = estimate_multisine_lines(ms, u, y0 + 0.05 * rng.standard_normal(u.size))
    np.testing.assert_allclose(
        np.radians(est.phase_std_deg), est.mag_std_db * np.log(10.0) / 20.0, rtol=1e-12
    )


def test_coherence_gives_the_same_spread() -> None:
    """The coherence is the one whose random error (Bendat & Piersol, `coherence_std`) is the
    spread reported, so a CSV with only the coherence keeps the same allowance."""
    ms = _odd(2)
    y = sig.lfilter(B_G, A_G, ms.signal)
    y += 0.2 * np.random.default_rng(0).standard_normal(y.size)
    est = estimate_multisine_lines(ms, ms.signal, y)
    assert np.all((est.coherence > 0.0) & (est.coherence < 1.0))
    mag, phase = coherence_std(est.coherence, est.n_averages)
    np.testing.assert_allclose(mag, est.mag_std_db, rtol=1e-6)
    np.testing.assert_allclose(phase, est.phase_std_deg, rtol=1e-6)


def test_a_tooth_line_next_to_an_excited_line_does_not_inflate_its_spread() -> None:
    """A lone periodic disturbance on one detection line (a belt tooth's) is left out by the
    median: the spread of its neighbours stays that of the noise."""
    ms = _odd(1)
    y0 = sig.lfilter(B_G, A_G, ms.signal) + 0.05 * np.random.default_rng(1).standard_normal(
        ms.signal.size
    )
    clean = estimate_multisine_lines(ms, ms.signal, y0)
    k = int(ms.bins[4]) + 1  # a detection line next to the fifth excited line
    assert k in set(ms.spec.detection_bins().tolist())
    t = np.arange(ms.signal.size) - ms.measure_start
    tooth = 0.5 * np.cos(2 * np.pi * k * t / ms.spec.period_samples)
    est = estimate_multisine_lines(ms, ms.signal, y0 + tooth)
    np.testing.assert_allclose(est.response, clean.response, rtol=1e-12)  # orthogonal
    assert np.max(est.mag_std_db / clean.mag_std_db) < 1.6
    lines = detection_lines(ms, y0 + tooth)  # and the tooth line stands far above the noise
    at_k = lines.amplitude[np.argmin(np.abs(lines.freq_hz - k * FS / ms.spec.period_samples))]
    assert at_k > 100 * np.median(lines.amplitude[lines.kind != 0])


def test_detection_lines_separate_even_and_odd_distortion() -> None:
    """With only odd bins excited, a square term shows on the even lines only, a cube on the
    odd non-excited lines too (Pintelon & Schoukens); noise alone is far below both."""
    ms = _odd(1)
    y = sig.lfilter(B_G, A_G, ms.signal)
    noise = 1e-4 * np.random.default_rng(2).standard_normal(y.size)
    base = detection_lines(ms, y + noise)
    square = detection_lines(ms, y + 0.05 * y**2 + noise)
    cube = detection_lines(ms, y + 0.01 * y**3 + noise)
    odd, even = base.kind == 1, base.kind == 2
    excited = base.kind == 0
    np.testing.assert_allclose(base.freq_hz[excited], ms.freq_hz)
    floor = 10 * np.max(base.amplitude[~excited])
    assert np.max(square.amplitude[even]) > 100 * floor
    assert np.max(square.amplitude[odd]) < floor
    assert np.max(cube.amplitude[odd]) > 100 * floor
    assert np.max(cube.amplitude[even]) < floor


def test_closed_loop_signals_and_lengths() -> None:
    ms = _odd(1)
    y = sig.lfilter(B_G, A_G, ms.signal)
    est = estimate_multisine_lines(ms, ms.signal, y, ms.signal)
    assert est.method == "closed_loop_x"
    np.testing.assert_allclose(est.response, plant_response(ms.freq_hz), rtol=1e-3)
    with pytest.raises(ValueError, match=r"^w:"):
        estimate_multisine_lines(ms, ms.signal, y[: ms.measure_start + 10])
