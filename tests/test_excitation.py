"""Excitation signals: exact bins, whole periods, position window, validation."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from article_plant import FS, odd_multisine_spec

from controller.core.errors import ConfigError
from controller.ident.excitation import (
    MultisineSpec,
    SteppedSineSpec,
    cap_speed_amplitude,
    crest_factor,
    multisine,
    schroeder_phases,
    stepped_sine,
)

# ------------------------------------------------------------------------------- multisine


@pytest.mark.parametrize("ppd", [None, 10])
def test_multisine_has_exactly_the_requested_bins(ppd: int | None) -> None:
    spec = MultisineSpec(
        f_min_hz=0.5, f_max_hz=40.0, period_samples=2000, n_periods=3, points_per_decade=ppd
    )
    ms = multisine(spec)
    bins = spec.bins()
    res = FS / 2000
    assert np.all(bins * res >= 0.5 - 1e-12)
    assert np.all(bins * res <= 40.0 + 1e-12)
    if ppd is None:
        np.testing.assert_array_equal(bins, np.arange(1, 81))
    X = np.fft.rfft(ms.period) * (2.0 / spec.period_samples)
    mag = np.abs(X)
    excited = np.zeros(mag.size, dtype=bool)
    excited[bins] = True
    # requested bins carry the reported amplitude, every other bin (and DC) is numerically zero
    np.testing.assert_allclose(mag[bins], ms.amplitudes_deg_s, rtol=1e-9)
    assert np.max(mag[~excited]) < 1e-9 * np.max(mag)
    np.testing.assert_allclose(ms.freq_hz, bins * res)
    # the signal is the period repeated transient + measured times
    assert ms.signal.size == (1 + 3) * 2000
    np.testing.assert_array_equal(ms.signal[2000:4000], ms.period)


def test_classical_schroeder_formula() -> None:
    k = np.arange(1, 12)
    phases = schroeder_phases(k, np.ones(k.size))
    expected = np.mod(-np.pi * k * (k - 1) / k.size, 2 * np.pi)
    np.testing.assert_allclose(np.exp(1j * phases), np.exp(1j * expected), atol=1e-12)


@pytest.mark.parametrize(("f_max_hz", "n_comp"), [(5.0, 10), (20.0, 40), (100.0, 200)])
def test_schroeder_crest_factor_below_2(f_max_hz: float, n_comp: int) -> None:
    spec = MultisineSpec(f_min_hz=0.5, f_max_hz=f_max_hz, period_samples=2000, crest_iterations=0)
    ms = multisine(spec)
    assert ms.bins.size == n_comp >= 10
    assert ms.crest_factor < 2.0
    assert ms.crest_factor == pytest.approx(crest_factor(ms.signal))
    # random phases, for contrast, are typically well above
    rng = np.random.default_rng(1)
    x = np.zeros(2000)
    t = np.arange(2000)
    for k in ms.bins:
        x += np.cos(2 * np.pi * k * t / 2000 + rng.uniform(0, 2 * np.pi))
    assert crest_factor(x) > ms.crest_factor


def test_crest_iterations_do_not_make_it_worse() -> None:
    base = MultisineSpec(f_min_hz=0.1, f_max_hz=20.0, points_per_decade=10, crest_iterations=0)
    better = MultisineSpec(f_min_hz=0.1, f_max_hz=20.0, points_per_decade=10)
    assert multisine(better).crest_factor <= multisine(base).crest_factor


@pytest.mark.parametrize("knee", [None, 2.0])
def test_multisine_peak_speed_and_window(knee: float | None) -> None:
    spec = MultisineSpec(
        f_min_hz=0.1, f_max_hz=10.0, amplitude_deg_s=20.0, window_deg=1.0, position_knee_hz=knee
    )
    ms = multisine(spec)
    position = np.cumsum(ms.signal) / FS  # what the loop integrates from the start
    assert np.max(np.abs(ms.signal)) <= 20.0 + 1e-9
    # the exact integral is bounded by the window; the sampled sum differs by O(1/fs)
    assert ms.max_excursion_deg <= 1.0 + 1e-9
    assert np.max(np.abs(position)) <= 1.0 * 1.01
    # one of the two limits is active
    assert ms.max_excursion_deg == pytest.approx(1.0) or ms.peak_speed_deg_s == pytest.approx(20)
    if knee is not None:
        low = ms.freq_hz < knee
        # below the knee the position amplitudes a / (2 pi f) are equal
        pos_amp = ms.amplitudes_deg_s[low] / (2 * np.pi * ms.freq_hz[low])
        np.testing.assert_allclose(pos_amp, pos_amp[0], rtol=1e-12)


# ------------------------------------------------------------- odd random-phase multisine

ODD = odd_multisine_spec(f_min_hz=0.1, f_max_hz=20.0, period_samples=10000, n_periods=2, seed=0,
                         tail_samples=200)


def test_odd_multisine_has_lines_only_at_odd_excited_bins() -> None:
    """Over the measured periods (a whole number of them after the lead-in) the spectrum holds
    exactly the excited odd bins with their amplitudes and nothing between them."""
    ms = multisine(ODD)
    n = ODD.period_samples
    assert np.all(ms.bins % 2 == 1) and np.all(np.diff(ms.bins) > 0)
    assert ms.freq_hz[0] == pytest.approx(0.1) and ms.freq_hz[-1] <= 20.0
    # log-spaced: about 10 per decade, fewer where the odd grid is coarser (below 1 Hz)
    assert 15 <= ms.bins.size <= 24
    measured = ms.signal[ms.measure_start : ms.measure_start + ms.measure_len]
    assert measured.size == ODD.n_periods * n
    X = np.fft.rfft(measured) * (2.0 / measured.size)
    on = ms.bins * ODD.n_periods  # the bins of the two-period record
    np.testing.assert_allclose(np.abs(X[on]), ms.amplitudes_deg_s, rtol=1e-9)
    np.testing.assert_allclose(np.angle(X[on] / np.exp(1j * ms.phases_rad)), 0.0, atol=1e-9)
    off = np.ones(X.size, dtype=bool)
    off[on] = False
    assert np.max(np.abs(X[off])) < 1e-9 * np.max(np.abs(X))  # DC and every other line
    # the detection lines are every other bin up to twice the highest excited one
    det = ODD.detection_bins()
    assert not set(det.tolist()) & set(ms.bins.tolist())
    assert det[0] == 2 and det[-1] == 2 * ms.bins[-1] + 1
    assert set(det.tolist()) | set(ms.bins.tolist()) == set(range(1, det[-1] + 1))
    # the spread comes from the odd ones only (even-order distortion stays on even lines)
    np.testing.assert_array_equal(ODD.noise_bins(), det[det % 2 == 1])


def test_odd_multisine_is_periodic_with_a_faded_lead_in_and_tail() -> None:
    ms = multisine(ODD)
    n, lead, tail = ODD.period_samples, ODD.lead_samples, ODD.tail_samples
    assert ms.signal.size == lead + ODD.n_periods * n + tail
    assert ms.measure_start == lead
    np.testing.assert_array_equal(ms.signal[lead : lead + n], ms.period)
    np.testing.assert_array_equal(ms.signal[lead + n : lead + 2 * n], ms.period)
    # the lead-in is the end of a period, faded in over its first half (raised cosine), the
    # tail its start, faded out
    half = lead // 2
    rise = np.sin(0.5 * np.pi * np.arange(1, half + 1) / (half + 1)) ** 2
    np.testing.assert_allclose(ms.signal[:half], ms.period[n - lead : n - half] * rise,
                               atol=1e-12)
    np.testing.assert_array_equal(ms.signal[half:lead], ms.period[n - half :])
    fall = np.cos(0.5 * np.pi * np.arange(1, tail + 1) / (tail + 1)) ** 2
    np.testing.assert_allclose(ms.signal[lead + 2 * n :], ms.period[:tail] * fall, atol=1e-12)
    assert abs(ms.signal[0]) < 1e-5 * ms.peak_speed_deg_s
    assert abs(ms.signal[-1]) < 1e-3 * ms.peak_speed_deg_s
    assert np.max(np.abs(ms.signal)) <= ms.peak_speed_deg_s * (1 + 1e-12)


def test_odd_multisine_crest_factor() -> None:
    """Random phases, then clipping: well below the random phases' own crest factor and below
    2.2 (a single sine has sqrt 2; Schroeder phases on the same sparse bins give about 2.3)."""
    ms = multisine(ODD)
    raw = multisine(dataclasses.replace(ODD, crest_iterations=0))
    np.testing.assert_array_equal(raw.bins, ms.bins)
    assert ms.crest_factor == pytest.approx(crest_factor(ms.period))
    assert ms.crest_factor < 2.2
    assert ms.crest_factor < raw.crest_factor
    # the same seed gives the same signal, another seed another one
    np.testing.assert_array_equal(multisine(ODD).signal, ms.signal)
    assert not np.allclose(multisine(dataclasses.replace(ODD, seed=1)).period, ms.period)


# ---------------------------------------------------------------------------- stepped sine


def test_stepped_sine_windows_hold_whole_periods() -> None:
    spec = SteppedSineSpec(f_min_hz=0.2, f_max_hz=50.0, points_per_decade=8, min_periods=4)
    ss = stepped_sine(spec)
    assert ss.signal.size == ss.points[-1].stop
    f = ss.freq_hz
    assert np.all(np.diff(f) > 0)
    assert f[0] == pytest.approx(0.2, rel=0.01)
    assert f[-1] == pytest.approx(50.0, rel=0.01)
    # about 8 points per decade (snapping may merge a few at the top)
    assert abs(f.size - (8 * math.log10(250) + 1)) <= 1
    previous_stop = 0
    for p in ss.points:
        assert p.start == previous_stop
        previous_stop = p.stop
        assert p.freq_hz * p.period_samples == pytest.approx(FS, rel=1e-12)
        assert p.n_periods >= 4
        assert p.measure_len == p.n_periods * p.period_samples
        assert p.measure_len >= spec.min_measure_s * FS - p.period_samples
        assert (p.measure_start - p.start) / FS >= spec.settle_s - 1.0 / p.freq_hz
        seg = ss.signal[p.measure_start : p.measure_start + p.measure_len]
        # constant amplitude, whole periods: single-bin DFT gives the amplitude, no leakage
        n = np.arange(seg.size)
        c = 2.0 / seg.size * np.sum(seg * np.exp(-2j * np.pi * p.freq_hz * n / FS))
        assert abs(c) == pytest.approx(p.amplitude_deg_s, rel=1e-12)
        spectrum = np.abs(np.fft.rfft(seg)) * 2.0 / seg.size
        spectrum[p.n_periods] = 0.0
        assert np.max(spectrum) < 1e-9 * p.amplitude_deg_s
        # every point starts at zero speed and ends one sample before it: the jump into the
        # next point is no larger than the largest sample-to-sample change inside the point
        assert ss.signal[p.start] == 0.0
        largest_step = np.max(np.abs(np.diff(ss.signal[p.start : p.stop])))
        assert abs(ss.signal[p.stop - 1]) <= largest_step


def test_stepped_sine_amplitude_respects_window() -> None:
    window = 0.5
    spec = SteppedSineSpec(f_min_hz=0.1, f_max_hz=20.0, amplitude_deg_s=10.0, window_deg=window)
    ss = stepped_sine(spec)
    position = np.cumsum(ss.signal) / FS
    for p in ss.points:
        cap = window * 2 * np.pi * p.freq_hz
        assert p.amplitude_deg_s <= min(10.0, cap) * (1 + 1e-12)
        start_pos = position[p.start - 1] if p.start > 0 else 0.0
        excursion = np.max(np.abs(position[p.start : p.stop] - start_pos))
        assert excursion <= window * (1 + 1e-9)
        assert excursion == pytest.approx(p.max_excursion_deg)
        # no net drift: each point returns to its starting position
        assert abs(position[p.stop - 1] - start_pos) < 1e-9
    # the cap is what limits the low frequencies, and it is barely reduced further
    low = ss.points[0]
    assert low.amplitude_deg_s == pytest.approx(window * 2 * np.pi * low.freq_hz, rel=1e-3)
    # without a window, the amplitude is the requested one
    free = stepped_sine(SteppedSineSpec(f_min_hz=0.1, f_max_hz=20.0, amplitude_deg_s=10.0))
    assert all(p.amplitude_deg_s == 10.0 for p in free.points)


def test_cap_speed_amplitude() -> None:
    f = np.array([0.1, 1.0, 10.0])
    np.testing.assert_allclose(cap_speed_amplitude(5.0, f, 2.0), [0.4 * np.pi, 5.0, 5.0])
    np.testing.assert_allclose(cap_speed_amplitude(5.0, f, None), [5.0, 5.0, 5.0])


# ------------------------------------------------------------------------------ validation


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"f_min_hz": 10.0, "f_max_hz": 5.0}, "f_min_hz"),
        ({"f_min_hz": 5.0, "f_max_hz": 5.0}, "f_min_hz"),
        ({"f_min_hz": 0.0}, "f_min_hz"),
        ({"f_min_hz": -1.0}, "f_min_hz"),
        ({"f_min_hz": math.nan}, "f_min_hz"),
        ({"f_max_hz": 600.0}, "f_max_hz"),
        ({"f_max_hz": 500.0}, "f_max_hz"),
        ({"f_max_hz": math.inf}, "f_max_hz"),
        ({"amplitude_deg_s": 0.0}, "amplitude_deg_s"),
        ({"amplitude_deg_s": math.nan}, "amplitude_deg_s"),
        ({"window_deg": -1.0}, "window_deg"),
        ({"min_periods": 2.5}, "min_periods"),
        ({"min_periods": 0}, "min_periods"),
        ({"min_periods": math.nan}, "min_periods"),
        ({"settle_periods": 1.5}, "settle_periods"),
        ({"ramp_periods": -1}, "ramp_periods"),
        ({"points_per_decade": 0}, "points_per_decade"),
        ({"points_per_decade": 10**9}, "points_per_decade"),  # a billion frequencies built
        ({"settle_s": -1.0}, "settle_s"),
        ({"sample_rate_hz": 0.0}, "sample_rate_hz"),
        ({"f_min_hz": "1"}, "f_min_hz"),
    ],
)
def test_stepped_sine_errors_name_the_field(kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field}:") as info:
        SteppedSineSpec(**kwargs)  # type: ignore[arg-type]
    assert isinstance(info.value, ConfigError)
    assert info.value.field == field


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"f_min_hz": 10.0, "f_max_hz": 5.0}, "f_min_hz"),
        ({"f_min_hz": 0.01}, "f_min_hz"),  # below the resolution 1000 / 10000
        ({"f_max_hz": 501.0}, "f_max_hz"),
        ({"f_max_hz": math.nan}, "f_max_hz"),
        ({"period_samples": 1000.5}, "period_samples"),
        ({"period_samples": 10**10}, "period_samples"),
        ({"points_per_decade": 10**9}, "points_per_decade"),
        ({"n_periods": 2.5}, "n_periods"),
        ({"n_periods": 0}, "n_periods"),
        ({"transient_periods": -1}, "transient_periods"),
        ({"amplitude_deg_s": -1.0}, "amplitude_deg_s"),
        ({"window_deg": 0.0}, "window_deg"),
        ({"position_knee_hz": math.nan}, "position_knee_hz"),
        ({"crest_iterations": 0.5}, "crest_iterations"),
        ({"harmonics": "even"}, "harmonics"),
        ({"phases": "zero"}, "phases"),
        ({"spread_from": "guess"}, "spread_from"),
        ({"seed": -1}, "seed"),
        ({"lead_samples": 1.5}, "lead_samples"),
        ({"lead_samples": 20000}, "lead_samples"),
        ({"tail_samples": -1}, "tail_samples"),
    ],
)
def test_multisine_errors_name_the_field(kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field}:"):
        MultisineSpec(**kwargs)  # type: ignore[arg-type]


def test_integral_floats_are_accepted() -> None:
    spec = SteppedSineSpec(min_periods=3.0, points_per_decade=5.0)  # type: ignore[arg-type]
    assert spec.min_periods == 3
    assert isinstance(spec.min_periods, int)
