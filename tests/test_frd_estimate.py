"""Frequency-response estimators against a discrete plant with a known transfer function."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import scipy.signal as sig
from article_plant import A_G, B_G, FS, plant_response

from controller.cli.frd_files import measured_from_csv, read_frd_csv, write_frd_csv
from controller.gate.frd_csv import FrdData
from controller.ident.estimate import (
    FrdEstimate,
    agreement,
    coherence_std,
    estimate_from_coefficients,
    estimate_multisine,
    estimate_stepped_sine,
)
from controller.ident.excitation import MultisineSpec, SteppedSineSpec, multisine, stepped_sine

# speed controller Cv = 0.5 (1 + 55 / s), Tustin
B_C, A_C = sig.bilinear([0.5, 0.5 * 55.0], [1.0, 0.0], fs=FS)


def errors(h: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ratio = h / ref
    return 20 * np.log10(np.abs(ratio)), np.degrees(np.angle(ratio))


def open_loop(u: np.ndarray, noise_std: float, seed: int) -> np.ndarray:
    """w = G u + white noise of `noise_std` on the output (numpy generator `seed`)."""
    rng = np.random.default_rng(seed)
    return np.asarray(sig.lfilter(B_G, A_G, u) + noise_std * rng.standard_normal(u.size))


def good_bins_within(
    est: FrdEstimate, max_db: float, max_deg: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Asserts the estimate's error against the plant is under `max_db` and `max_deg` at every
    bin of coherence > 0.95; returns those bins (a mask) and the errors at every bin."""
    good = est.coherence > 0.95
    err_db, err_deg = errors(est.response, plant_response(est.freq_hz))
    assert np.max(np.abs(err_db[good])) < max_db
    assert np.max(np.abs(err_deg[good])) < max_deg
    return good, err_db, err_deg


def simulate_closed_loop(x: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """u = x - C y, y = G u + noise (noise on the measured output, which feeds back)."""
    den = np.polyadd(np.polymul(A_C, A_G), np.polymul(B_C, B_G))
    assert np.all(np.abs(np.roots(den)) < 1.0)
    u = sig.lfilter(np.polymul(A_C, A_G), den, x) - sig.lfilter(np.polymul(B_C, A_G), den, noise)
    y = sig.lfilter(B_G, A_G, u) + noise
    return u, y


# ------------------------------------------------------------------------------- open loop


def test_open_loop_multisine_recovers_plant() -> None:
    # 200 periods of 0.5 s: at coherence 0.95 the relative error is about
    # sqrt((1 - 0.95) / (2 * 0.95 * 200)) = 0.011, i.e. 0.10 dB and 0.66 deg (1 sigma)
    ms = multisine(
        MultisineSpec(
            f_min_hz=2.0, f_max_hz=100.0, period_samples=500, n_periods=200, amplitude_deg_s=10
        )
    )
    est = estimate_multisine(ms, ms.signal, open_loop(ms.signal, 0.15, seed=0))
    assert est.method == "open_loop_h1"
    assert np.all(est.n_averages == 200)
    good, err_db, err_deg = good_bins_within(est, 0.3, 2.0)
    assert np.all(good[est.freq_hz <= 30.0])  # the useful band, not a handful of points
    assert not np.all(good)  # and the test does reach low-coherence bins
    # everywhere, including low coherence, the error is within the reported band
    assert np.all(np.abs(err_db) < 4 * est.mag_std_db)
    assert np.all(np.abs(err_deg) < 4 * est.phase_std_deg)


def test_open_loop_stepped_sine_recovers_plant() -> None:
    ss = stepped_sine(
        SteppedSineSpec(
            f_min_hz=0.2, f_max_hz=50.0, points_per_decade=10, min_measure_s=10.0, settle_s=0.3
        )
    )
    est = estimate_stepped_sine(ss, ss.signal, open_loop(ss.signal, 0.2, seed=1))
    np.testing.assert_array_equal(est.freq_hz, ss.freq_hz)
    np.testing.assert_array_equal(est.n_averages, [p.n_periods for p in ss.points])
    good, _, _ = good_bins_within(est, 0.3, 2.0)
    assert good.sum() >= 0.8 * est.freq_hz.size


def test_noise_free_estimates_are_exact() -> None:
    """Whole periods and a settled plant: the single-bin DFT ratio is the plant response."""
    ss = stepped_sine(SteppedSineSpec(f_min_hz=0.5, f_max_hz=100.0, settle_s=0.5))
    w = sig.lfilter(B_G, A_G, ss.signal)
    est = estimate_stepped_sine(ss, ss.signal, w)
    np.testing.assert_allclose(est.response, plant_response(est.freq_hz), rtol=1e-6)
    assert np.all(est.coherence > 1 - 1e-9)


def test_confidence_band_is_calibrated() -> None:
    """Reported std vs actual error over repeated experiments (Monte Carlo)."""
    ms = multisine(MultisineSpec(f_min_hz=2.0, f_max_hz=40.0, period_samples=500, n_periods=8))
    g = plant_response(ms.freq_hz)
    w0 = sig.lfilter(B_G, A_G, ms.signal)
    rng = np.random.default_rng(2)
    z_mag, z_ph = [], []
    for _ in range(60):
        est = estimate_multisine(ms, ms.signal, w0 + 0.3 * rng.standard_normal(w0.size))
        e_db, e_deg = errors(est.response, g)
        z_mag.append(e_db / est.mag_std_db)
        z_ph.append(e_deg / est.phase_std_deg)
    # std estimated from 8 periods: t-distributed, rms about sqrt(14 / 12) = 1.08
    assert 0.85 < np.sqrt(np.mean(np.square(z_mag))) < 1.35
    assert 0.85 < np.sqrt(np.mean(np.square(z_ph))) < 1.35


def test_coherence_std_formula() -> None:
    mag_db, ph_deg = coherence_std([0.5, 0.99], [1, 100])
    eps = np.array([np.sqrt(0.5 / 0.5 / 2), np.sqrt(0.01 / 0.99 / 200)])
    np.testing.assert_allclose(mag_db, 20 / np.log(10) * eps)
    np.testing.assert_allclose(ph_deg, np.degrees(eps))


def test_single_period_has_no_variance() -> None:
    est = estimate_from_coefficients([1.0, 2.0], [[1.0, 2.0]], [[0.5, 1j]])
    np.testing.assert_allclose(est.response, [0.5, 0.5j])
    assert np.all(np.isnan(est.mag_std_db))
    assert np.all(np.isnan(est.phase_std_deg))


def test_short_signal_is_rejected() -> None:
    ms = multisine(MultisineSpec(f_min_hz=1.0, f_max_hz=10.0, period_samples=1000, n_periods=2))
    with pytest.raises(ValueError, match=r"^w: "):
        estimate_multisine(ms, ms.signal, ms.signal[:-1])


# ----------------------------------------------------------------------------- closed loop


def test_closed_loop_x_estimator_is_unbiased_and_h1_is_not() -> None:
    ms = multisine(
        MultisineSpec(
            f_min_hz=0.5, f_max_hz=20.0, period_samples=2000, n_periods=256, amplitude_deg_s=10
        )
    )
    rng = np.random.default_rng(3)
    x = ms.signal
    u, y = simulate_closed_loop(x, 2.0 * rng.standard_normal(x.size))
    good = estimate_multisine(ms, u, y, x)
    naive = estimate_multisine(ms, u, y)
    assert good.method == "closed_loop_x"
    g = plant_response(ms.freq_hz)
    good_db, good_deg = errors(good.response, g)
    naive_db, _ = errors(naive.response, g)
    assert np.max(np.abs(good_db)) < 0.5
    assert np.max(np.abs(good_deg)) < 4.0
    # at 0.5 Hz the controller's integrator feeds the noise back into u: q = |C|^2 S_nn / S_xx
    # ~ 0.7, so H1 ~ G / (1 + q) is about 2.3 dB low, well outside the good estimate's error
    assert ms.freq_hz[0] == pytest.approx(0.5)
    assert naive_db[0] < -1.5
    assert abs(good_db[0]) < 0.5
    assert abs(naive_db[0]) > 3 * abs(good_db[0])
    # coherence with respect to x is lowest where the noise dominates u
    assert good.coherence[0] < good.coherence[5]


def test_closed_loop_stepped_sine_noise_free_is_exact() -> None:
    ss = stepped_sine(SteppedSineSpec(f_min_hz=0.5, f_max_hz=30.0, settle_s=1.0))
    u, y = simulate_closed_loop(ss.signal, np.zeros(ss.signal.size))
    est = estimate_stepped_sine(ss, u, y, ss.signal)
    np.testing.assert_allclose(est.response, plant_response(est.freq_hz), rtol=1e-5)


# ------------------------------------------------------------------------------ agreement


def _frd(freq: np.ndarray, h: np.ndarray) -> FrdData:
    return FrdData(
        freq_hz=freq,
        mag_db=20 * np.log10(np.abs(h)),
        phase_deg=np.degrees(np.unwrap(np.angle(h))),
        coherence=None,
    )


def test_agreement_finds_the_frequency_where_curves_split() -> None:
    f = np.logspace(-1, 1.3, 40)
    s = 2j * np.pi * f
    base = 1935 / (s**2 + 62.2 * s + 1935)
    # two "positions" with a different belt mode at 3 Hz and 4 Hz: equal at low frequency
    responses = [_frd(f, base)]
    for fm in (3.0, 4.0):
        wm = 2 * np.pi * fm
        responses.append(_frd(f, base * (s**2 + 0.2 * wm * s + wm**2) / (wm**2 + 0 * s)))
    ag = agreement(responses, tol_db=1.0, tol_deg=10.0)
    assert ag.first_disagree_hz is not None
    assert 0.5 < ag.agree_below_hz < ag.first_disagree_hz < 3.0
    assert np.all(ag.spread_db[f <= ag.agree_below_hz] <= 1.0)
    assert np.all(ag.spread_deg[f <= ag.agree_below_hz] <= 10.0)
    # identical responses agree everywhere
    same = agreement([responses[0], responses[0]])
    assert same.first_disagree_hz is None
    assert same.agree_below_hz == f[-1]


def test_agreement_phase_wrap_is_not_a_disagreement() -> None:
    f = np.array([1.0, 2.0])
    a = _frd(f, np.exp(1j * np.radians(np.array([179.0, 179.0]))))
    b = _frd(f, np.exp(1j * np.radians(np.array([-179.0, -179.0]))))
    ag = agreement([a, b], tol_deg=5.0)
    np.testing.assert_allclose(ag.spread_deg, [2.0, 2.0], atol=1e-9)


def test_agreement_rejects_different_grids() -> None:
    a = _frd(np.array([1.0, 2.0]), np.ones(2, complex))
    b = _frd(np.array([1.0, 2.5]), np.ones(2, complex))
    with pytest.raises(ValueError, match=r"responses\[1\]"):
        agreement([a, b])


# ------------------------------------------------------------------------------------ CSV


def test_csv_round_trip_unwraps_phase(tmp_path: Path) -> None:
    f = np.logspace(-1, 2, 30)
    s = 2j * np.pi * f
    h = 1935 / (s**2 + 62.2 * s + 1935) * np.exp(-s * 0.004)  # phase well past -180
    coh = np.linspace(1.0, 0.5, f.size)
    path = tmp_path / "pos1.csv"
    write_frd_csv(path, f, h, coh)
    assert path.read_text().splitlines()[0] == "freq_hz,mag_db,phase_deg,coherence"
    data = read_frd_csv(path)
    np.testing.assert_allclose(data.freq_hz, f, rtol=1e-9)
    np.testing.assert_allclose(data.response, h, rtol=1e-8)
    assert data.coherence is not None
    np.testing.assert_allclose(data.coherence, coh, rtol=1e-9)
    assert data.phase_deg[-1] < -180.0  # unwrapped, not folded back
    assert np.all(np.abs(np.diff(data.phase_deg)) < 180.0)
    assert data.source == str(path)
    # without coherence
    write_frd_csv(path, f, h)
    assert read_frd_csv(path).coherence is None


def test_csv_reader_accepts_comments_extra_columns_and_order(tmp_path: Path) -> None:
    path = tmp_path / "hand.csv"
    path.write_text(
        "# measured at 40 deg\n\nphase_deg, freq_hz ,mag_db,note\n-10,0.5,0.1,a\n-20,1.0,-0.2,b\n"
    )
    data = read_frd_csv(path)
    np.testing.assert_allclose(data.freq_hz, [0.5, 1.0])
    np.testing.assert_allclose(data.mag_db, [0.1, -0.2])
    np.testing.assert_allclose(data.phase_deg, [-10.0, -20.0])


@pytest.mark.parametrize(
    ("content", "line", "what"),
    [
        ("", 1, "empty file"),
        ("freq_hz,mag_db\n1,0\n", 1, "missing column 'phase_deg'"),
        ("freq_hz,mag_db,phase_deg\n", 1, "no data rows"),
        ("freq_hz,mag_db,phase_deg\n1,0,0\n2,abc,0\n", 3, "mag_db: not a number"),
        ("freq_hz,mag_db,phase_deg\n1,0,0\n2,0,nan\n", 3, "phase_deg: not finite"),
        ("freq_hz,mag_db,phase_deg\n1,0,0\n2,0,0\n2,0,0\n", 4, "freq_hz: not increasing"),
        ("freq_hz,mag_db,phase_deg\n1,0,0\n0.5,0,0\n", 3, "freq_hz: not increasing"),
        ("freq_hz,mag_db,phase_deg\n0,0,0\n", 2, "freq_hz: must be > 0"),
        ("freq_hz,mag_db,phase_deg\n1,0\n", 2, "expected 3 fields"),
        ("freq_hz,mag_db,phase_deg,coherence\n1,0,0,1.5\n", 2, "coherence: must be in"),
        ("# c\nfreq_hz,mag_db,phase_deg\n\n1,0,0\n2,0,x\n", 5, "phase_deg: not a number"),
        ("freq_hz,mag_db,mag_db,phase_deg\n", 1, "duplicate column"),
        ("# comment\nfreq_hz,mag_db,phase_deg\n1,0,0\n2,x,0\n", 4, "mag_db: not a number"),
        ("freq_hz,mag_db,phase_deg\n1,0,0\n2,nan,0\n", 3, "mag_db: not finite"),
        ("freq_hz,mag_db,phase_deg\n1,0,0\n3,0,0\n\n2,0,0\n", 5, "freq_hz: not increasing"),
        ("freq_hz,mag_db,phase_deg\n1,0,0\n1,0,0\n", 3, "freq_hz: not increasing"),
    ],
)
@pytest.mark.parametrize("read", [read_frd_csv, measured_from_csv], ids=lambda f: f.__name__)
def test_csv_bad_files_name_file_and_line(
    tmp_path: Path, content: str, line: int, what: str, read: Callable[[Path], object]
) -> None:
    """The reader, and the gate's measured response from a file (read through it), name the
    file, the line and what is wrong there."""
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(ValueError) as info:
        read(path)
    message = str(info.value)
    assert message.startswith(f"{path}:{line}: "), message
    assert what in message


def test_csv_writer_rejects_bad_data(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="freq_hz"):
        write_frd_csv(tmp_path / "x.csv", [2.0, 1.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="response"):
        write_frd_csv(tmp_path / "x.csv", [1.0, 2.0], [1.0, 0.0])
    with pytest.raises(ValueError, match="coherence"):
        write_frd_csv(tmp_path / "x.csv", [1.0, 2.0], [1.0, 1.0], [0.5, 1.2])
