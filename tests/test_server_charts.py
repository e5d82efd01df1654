"""Chart data (pure): decimation keeps spikes, Bode data shapes, log axes."""

from __future__ import annotations

import numpy as np
import pytest

from controller.core.config import LoopConfig
from controller.gate.analysis import analyse
from server import charts
from server.engine import curves_from_analysis, freq_grid_hz


def test_minmax_decimate_keeps_extremes_and_bounds_size() -> None:
    t = np.arange(60_000) / 1000.0
    y = np.sin(t)
    y[31_234] = 5.0  # a one-sample spike
    y[12_345] = -4.0
    x, (yd,) = charts.minmax_decimate(t, [y], 1000)
    assert len(x) <= 1000
    assert len(x) == len(yd)
    assert yd.max() == 5.0
    assert yd.min() == -4.0
    assert np.all(np.diff(x) >= 0)
    assert x[-1] == t[-1]


def test_minmax_decimate_passes_short_series_through() -> None:
    t = np.arange(10.0)
    x, (y,) = charts.minmax_decimate(t, [t * 2], 1000)
    np.testing.assert_array_equal(x, t)
    np.testing.assert_array_equal(y, t * 2)


def test_bode_specs_use_log_frequency_axis() -> None:
    for spec in charts.BODE_CHARTS:
        assert spec.scales["x"]["distr"] == 3
        assert spec.scales["x"]["log"] == 10


@pytest.mark.parametrize("spec", charts.BODE_CHARTS, ids=lambda s: s.key)
def test_bode_data_matches_series(spec: charts.ChartSpec) -> None:
    cfg = LoopConfig()
    cand, _ = curves_from_analysis(analyse(cfg, freq_hz=freq_grid_hz()))
    act, _ = curves_from_analysis(analyse(cfg.with_(q_cutoff_hz=2.0), freq_hz=freq_grid_hz()))
    data = charts.bode_data(spec.key, cand, act)
    assert len(data) == len(spec.series)
    assert all(d.shape == cand.freq_hz.shape for d in data)
    assert np.all(np.isfinite(data[1]))


def test_disturbance_chart_shows_dob_rejection_at_low_frequency() -> None:
    cand, _ = curves_from_analysis(analyse(LoopConfig(), freq_hz=freq_grid_hz()))
    f, with_dob, without, _active = charts.bode_data("disturbance", cand, None)
    low = f < 0.05
    assert np.all(with_dob[low] < without[low] - 6.0)  # eq. 16 well below eq. 18


def test_live_data_is_relative_to_newest_sample() -> None:
    n = 5000
    t = np.arange(n) / 1000.0
    cols = {c: np.random.default_rng(0).normal(size=n) for cols in charts.LIVE_COLUMNS.values()
            for c in cols}
    version = np.where(t > 2.5, 2.0, 1.0)
    data = charts.live_data(t, cols, version, max_points=800)
    for spec in charts.LIVE_CHARTS:
        d = data[spec.key]
        assert len(d) == len(spec.series)
        assert d[0][-1] == 0.0
        assert len(d[0]) <= 800
    assert set(data["error"][-1]) == {1.0, 2.0}


def test_live_data_empty() -> None:
    data = charts.live_data(np.zeros(0), {}, np.zeros(0))
    assert all(len(d[0]) == 2 for d in data.values())


def test_margin_markers_sit_at_the_crossovers_python_control_finds() -> None:
    """The open-loop chart's markers cover the 0 dB crossing (phase margin) and the -180 deg
    crossing (gain margin) that python-control's stability_margins finds on the same
    frequency response."""
    import control

    from server.engine import TuningEngine

    eng = TuningEngine()
    checked = 0
    for cfg in (LoopConfig(), LoopConfig(cv_kp=1.2, pos_kp_per_s=20.0)):
        c = eng.evaluate(cfg).curves
        f = c.freq_hz
        a = analyse(cfg, eng.plant, freq_hz=f)
        _gm, _pm, _sm, wpc, wgc, _wms = control.stability_margins(
            control.frd(a.open_loop, 2 * np.pi * f))
        for marks, w in ((c.gain_crossover_marks, wgc), (c.phase_crossover_marks, wpc)):
            if not np.isfinite(w) or w <= 0:
                continue
            at = f[np.isfinite(marks)]
            assert at.min() <= w / (2 * np.pi) <= at.max(), (at, w / (2 * np.pi))
            checked += 1
    assert checked >= 3  # both crossings exist for these loops (else the test proves nothing)


def test_no_bode_column_starts_with_a_gap() -> None:
    """uPlot gives a series whose first value is NaN a NaN scale and draws nothing (the
    small-gain chart was empty without a measured response): every column starts finite,
    and a gap-only column adds no drawable segment."""
    from server.engine import TuningEngine

    eng = TuningEngine()
    cmp = eng.compare(LoopConfig(), LoopConfig(q_cutoff_hz=1.0))
    for key, data in cmp.chart_data.items():
        spec = {s.key: s for s in charts.BODE_CHARTS}[key]
        for i, col in enumerate(data):
            if i and spec.series[i].get("scale") == charts.MARK_SCALE:
                continue  # a fixed 0..1 scale: no auto range to upset
            assert np.isfinite(col[0]), (key, i)
    measured = cmp.chart_data["small_gain"][4]  # no measured response: nothing to draw
    assert np.isnan(measured[1:]).all()


def test_nyquist_is_the_open_loop_inside_the_window() -> None:
    """The Nyquist view's points are L itself (python-control's frequency response of the
    same loop is the reference through the gate's analysis), clipped to |L| <= the radius,
    and the critical point, the unit circle and both margin points are drawn."""
    from server.engine import TuningEngine

    eng = TuningEngine()
    cfg = LoopConfig()
    c = eng.evaluate(cfg).curves
    a = analyse(cfg, eng.plant, freq_hz=c.freq_hz)
    z = charts.open_loop_response(c)
    np.testing.assert_allclose(z, a.open_loop, rtol=1e-9)  # back from dB and degrees
    segments = charts.nyquist_segments(c)
    inside = np.abs(a.open_loop) <= charts.NYQUIST_RADIUS
    assert sum(len(s) for s in segments) == int(inside.sum()) > 20
    assert all(np.all(np.abs(s) <= charts.NYQUIST_RADIUS) for s in segments)
    svg = charts.nyquist_svg(c, c)
    assert svg.count("dt-nyq-cand") == len(segments) and "dt-nyq-critical" in svg
    assert "dt-nyq-pm" in svg  # |L| = 1 lies on the unit circle, inside the window
