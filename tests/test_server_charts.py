"""Chart data (pure): decimation keeps spikes, Bode data shapes, log axes."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from controller.core.config import LoopConfig
from controller.gate.analysis import analyse
from controller.gate.knowledge import PlantKnowledge
from server import charts
from server.engine import curves_from_analysis

MODEL_ONLY = PlantKnowledge()


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


@pytest.mark.parametrize("n", [1001, 2001, 2630, 2999, 60_000, 60_999])
def test_minmax_decimate_covers_the_whole_series(n: int) -> None:
    """All but fewer than one bucket's oldest samples are drawn (n = 2999 into 1000 points
    drew only its newest 2000 samples); every sample kept lies in the drawn envelope."""
    t = np.arange(n) / 1000.0
    y = np.cos(7.0 * t)
    x, (yd,) = charts.minmax_decimate(t, [y], 1000)
    assert len(x) <= 1000 and x[-1] == t[-1]
    size = int(np.ceil(n / 500))  # samples per bucket, at most 500 buckets
    assert x[0] - t[0] < size / 1000.0, (x[0], size)
    kept = t >= x[0]
    assert yd.max() == y[kept].max() and yd.min() == y[kept].min()


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
    cand = curves_from_analysis(analyse(cfg), MODEL_ONLY)
    act = curves_from_analysis(analyse(cfg.with_(q_cutoff_hz=2.0)), MODEL_ONLY)
    data = charts.bode_data(spec.key, cand, act)
    assert len(data) == len(spec.series) == len(spec.columns) + 1
    assert all(d.shape == data[0].shape for d in data)
    # Increasing; the loop's Bode holds each margin mark's frequency twice (its two points).
    steps = np.diff(data[0])
    assert np.all(steps >= 0)
    marks = [c for k in ("loop_mag", "loop_phase") for c in charts.bode_data(k, cand, act)[4:]]
    repeats = sum(int(np.isfinite(c).sum()) for c in marks) // 2
    assert int(np.sum(steps == 0)) == (repeats if spec.key in ("loop_mag", "loop_phase") else 0)
    assert np.all(np.isfinite(data[1]))


def test_disturbance_chart_shows_dob_rejection_at_low_frequency() -> None:
    cand = curves_from_analysis(analyse(LoopConfig()), MODEL_ONLY)
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


def test_the_config_version_axis_ticks_whole_versions() -> None:
    for spec in charts.LIVE_CHARTS:
        (axis,) = [a for a in spec.axes if a.get("scale") == "ver"]
        incrs = axis["incrs"]
        assert all(isinstance(i, int) and i >= 1 for i in incrs)
        assert list(incrs) == sorted(incrs) and incrs[-1] >= 2**53 - 1  # MAX_VERSION


def test_live_data_empty() -> None:
    data = charts.live_data(np.zeros(0), {}, np.zeros(0))
    assert all(len(d[0]) == 2 for d in data.values())


def test_margin_markers_are_the_margins_python_control_finds() -> None:
    """The loop's Bode marks the gain margin on the magnitude chart (a vertical segment from
    |L| up or down to 0 dB at the phase crossover) and the phase margin on the phase chart (from
    -180 deg to the phase at the gain crossover): their frequencies and lengths are what
    python-control's stability_margins finds on the same frequency response (to the grid's
    interpolation: 1 % in frequency, 0.2 dB, 0.5 deg), and both charts share one x grid."""
    import control

    from server.engine import TuningEngine

    eng = TuningEngine()
    checked = 0
    for cfg in (LoopConfig(), LoopConfig(cv_kp=1.2, pos_kp_per_s=20.0),
                LoopConfig(dob_on=False), LoopConfig(q_type="q20", q_cutoff_hz=15.0)):
        c = eng.evaluate(cfg).curves
        f = c.freq_hz
        a = analyse(cfg, eng.plant, freq_hz=f)
        gm, pm, _sm, wpc, wgc, _wms = control.stability_margins(
            control.frd(a.open_loop, 2 * np.pi * f))
        mag, phase = charts.loop_bode_data(c, None)
        np.testing.assert_array_equal(mag[0], phase[0])
        x = mag[0]

        def segment(col: np.ndarray, x: np.ndarray = x) -> tuple[float, float, float]:
            idx = np.flatnonzero(np.isfinite(col))
            assert len(idx) == 2 and idx[1] == idx[0] + 1 and x[idx[0]] == x[idx[1]]
            return float(x[idx[0]]), float(col[idx[0]]), float(col[idx[1]])

        # python-control's pick in the column named for it: "gain margin (up)" (4) where
        # |L| < 1 at the crossing, "gain-reduction margin (down)" (5) where |L| > 1.
        f_gm, at_curve, at_zero = segment(mag[4] if gm >= 1.0 else mag[5])
        assert at_zero == 0.0
        np.testing.assert_allclose(f_gm, wpc / (2 * np.pi), rtol=0.01)
        np.testing.assert_allclose(at_zero - at_curve, 20 * np.log10(gm), atol=0.2)
        # The mark starts on the drawn |L| curve.
        np.testing.assert_allclose(at_curve, mag[1][np.searchsorted(x, f_gm)], atol=0.2)
        f_pm, at_ref, at_phase = segment(phase[4])
        assert at_ref == -180.0
        np.testing.assert_allclose(f_pm, wgc / (2 * np.pi), rtol=0.01)
        np.testing.assert_allclose(at_phase - at_ref, pm, atol=0.5)
        np.testing.assert_allclose(at_phase, phase[1][np.searchsorted(x, f_pm)], atol=0.5)
        assert np.all(phase[3] == -180.0)  # the -180 deg line: one constant
        html = charts.loop_margins_html(c)
        g_db = 20 * np.log10(gm)  # python-control's pick, signed: shown positive, named
        said = (f"gain-reduction margin</b> {-g_db:.1f} dB down" if g_db < 0
                else f"gain margin</b> {g_db:.1f} dB")
        assert f"{said}" in html and f"at {wpc / (2 * np.pi):.3g} Hz" in html, html
        assert f"{g_db:.1f} dB" not in html or g_db >= 0, html
        assert f"{pm:.1f} deg at {wgc / (2 * np.pi):.3g} Hz" in html, html
        checked += 1
    assert checked == 4


def test_no_bode_column_holds_a_made_up_value() -> None:
    """Every value of a Bode chart is its curve's (NaN where the curve has none: no stand-in
    first value), and each chart's fixed y scales hold every finite value on whole steps."""
    from server.engine import TuningEngine

    eng = TuningEngine()
    cmp = eng.compare(LoopConfig(), LoopConfig(q_cutoff_hz=1.0))
    c = cmp.candidate.curves
    small_gain = cmp.chart_data["small_gain"]
    assert np.isnan(small_gain[4]).all()  # no measured response: nothing, not a point
    np.testing.assert_array_equal(small_gain[1], c.q_db)
    for key, data in cmp.chart_data.items():
        spec = {s.key: s for s in charts.BODE_CHARTS}[key]
        scales = charts.ranged_scales(spec, data, charts.Y_STEPS)
        for i, col in enumerate(data[1:], start=1):
            name = spec.series[i].get("scale", "y")
            if name == charts.MARK_SCALE:
                continue
            lo, hi = scales[name]["range"]
            assert scales[name]["auto"] is False
            step = (spec.y_step or charts.Y_STEPS[name]) if name == "y" else \
                charts.Y_STEPS[name]
            assert lo % step == 0 and hi % step == 0
            fin = col[np.isfinite(col)]
            # A chart held within a range (|S|, the rejection: `y_clip`) lets the rest run off.
            clo, chi = (spec.y_clip or (-np.inf, np.inf)) if name == "y" else \
                (-np.inf, np.inf)
            assert fin.size == 0 or (lo <= max(fin.min(), clo) and min(fin.max(), chi) <= hi), \
                (key, i)


def test_nyquist_is_the_open_loop_inside_the_window() -> None:
    """The with-DOB panel's points are the gate's L itself (the analysis of a DOB-on
    candidate), clipped to |L| <= the radius, and the critical point, the unit circle and both
    margin points are drawn; the Bode chart's L comes back from dB and degrees unchanged."""
    from server.engine import TuningEngine

    eng = TuningEngine()
    cfg = LoopConfig()
    c = eng.evaluate(cfg).curves
    a = analyse(cfg, eng.plant, freq_hz=c.freq_hz)
    np.testing.assert_allclose(charts.open_loop_response(c), a.open_loop, rtol=1e-9)
    assert c.nyquist_dob is not None
    np.testing.assert_allclose(c.nyquist_dob.response, a.open_loop, rtol=1e-12)
    segments = charts.nyquist_segments(c.nyquist_dob.response)
    inside = np.abs(a.open_loop) <= charts.NYQUIST_RADIUS
    assert sum(len(s) for s in segments) == int(inside.sum()) > 20
    assert all(np.all(np.abs(s) <= charts.NYQUIST_RADIUS) for s in segments)
    dob, _nodob = _panels(charts.nyquist_svg(c, c))
    assert len(dob.findall(".//*[@class='dt-nyq-cand']")) == len(segments)
    assert len(dob.findall(".//*[@class='dt-nyq-critical']")) == 1
    assert dob.findall(".//*[@class='dt-nyq-pm']")  # |L| = 1: on the unit circle, in view


def _panels(html: str) -> tuple[ET.Element, ET.Element]:
    """The two SVG panels of the Nyquist view (the HTML is well-formed XML)."""
    root = ET.fromstring(html)
    svgs = root.findall(".//svg")
    assert len(svgs) == 2
    return svgs[0], svgs[1]


def _svg_point(panel: ET.Element, el: ET.Element) -> complex:
    """An element's centre back in the complex plane of its panel."""
    cx, cy = (float(v) for v in panel.attrib["data-origin"].split())
    k = float(panel.attrib["data-px-per-unit"])
    return complex((float(el.attrib["cx"]) - cx) / k, (cy - float(el.attrib["cy"])) / k)


def test_nyquist_has_ticks_and_its_legend_keeps_off_the_plot() -> None:
    """Each panel has a tick with its value at every whole unit of both axes (-3..3, at the
    pixel of that value), every curve point lies inside the plot's frame, and the title,
    formula and legend lie outside it (the curve ran through the legend)."""
    from server.engine import TuningEngine

    eng = TuningEngine()
    c = eng.evaluate(LoopConfig()).curves
    for panel in _panels(charts.nyquist_svg(c, c)):
        cx, cy = (float(v) for v in panel.attrib["data-origin"].split())
        k = float(panel.attrib["data-px-per-unit"])
        frame = panel.find(".//*[@class='dt-nyq-plot']")
        assert frame is not None
        x0, y0 = float(frame.attrib["x"]), float(frame.attrib["y"])
        x1, y1 = x0 + float(frame.attrib["width"]), y0 + float(frame.attrib["height"])
        units = range(-3, 4)
        re_ticks = panel.findall(".//*[@class='dt-nyq-tick-re']")
        im_ticks = panel.findall(".//*[@class='dt-nyq-tick-im']")
        assert [int(t.text or "") for t in re_ticks] == list(units)
        assert [int(t.text or "") for t in im_ticks] == list(units)
        for t, v in zip(re_ticks, units, strict=True):
            assert abs(float(t.attrib["x"]) - (cx + k * v)) < 0.1 and float(t.attrib["y"]) > y1
        for t, v in zip(im_ticks, units, strict=True):
            assert abs(float(t.attrib["y"]) - (cy - k * v)) < 0.1 and float(t.attrib["x"]) < x0
        for line in panel.findall(".//polyline"):
            pts = np.array([[float(v) for v in p.split(",")] for p in
                            line.attrib["points"].split()])
            assert (pts[:, 0] >= x0 - 0.1).all() and (pts[:, 0] <= x1 + 0.1).all()
            assert (pts[:, 1] >= y0 - 0.1).all() and (pts[:, 1] <= y1 + 0.1).all()
        for text in (*panel.findall(".//*[@class='dt-nyq-foot']"),
                     *panel.findall(".//*[@class='dt-nyq-title']/*")):
            y = float(text.attrib["y"])
            assert y > y1 + 15 or y < y0, ("".join(text.itertext()), y, y0, y1)


@pytest.mark.parametrize("dob_on", [True, False])
def test_nyquist_shows_the_loop_with_and_without_the_dob(dob_on: bool) -> None:
    """Two panels side by side, "with DOB" (class dt-nyquist: what the browser test finds)
    and "without DOB" (dt-nyquist-nodob), whatever the candidate's DOB switch: each draws
    its own loop, the active one dashed, its own critical point, and its own PM and GM
    points where the refined crossings lie (|L| = 1 on the unit circle, L real and
    negative), to the drawing's 0.1 px rounding."""
    from server.engine import TuningEngine

    eng = TuningEngine()
    cand = eng.evaluate(LoopConfig(q_cutoff_hz=2.0, dob_on=dob_on)).curves
    act = eng.evaluate(LoopConfig()).curves
    dob, nodob = _panels(charts.nyquist_svg(cand, act))
    assert "dt-nyquist" in dob.attrib["class"].split() and dob.attrib["data-loop"] == "dob"
    assert "dt-nyquist" not in nodob.attrib["class"].split()
    assert "dt-nyquist-nodob" in nodob.attrib["class"].split()
    assert nodob.attrib["data-loop"] == "nodob"
    px = 1.0 / float(dob.attrib["data-px-per-unit"])  # one px, in units
    for panel, loop, title in ((dob, cand.nyquist_dob, "with DOB"),
                               (nodob, cand.nyquist_nodob, "without DOB")):
        assert loop is not None
        text = "".join(panel.find(".//*[@class='dt-nyq-title']").itertext())  # type: ignore[union-attr]
        assert text.startswith(f"{title}: PM {loop.phase_margin_deg:.1f} deg")
        if dob_on and title == "with DOB":  # the gate's own loop: its margins, both positive
            m = analyse(LoopConfig(q_cutoff_hz=2.0)).margins
            assert f"GM {m.gain_margin_up_db:.1f} dB" in text, text
            assert m.conditionally_stable and (
                f"gain-reduction margin {m.gain_reduction_margin_db:.1f} dB down" in text), text
        assert len(panel.findall(".//*[@class='dt-nyq-critical']")) == 1
        cand_lines = panel.findall(".//*[@class='dt-nyq-cand']")
        assert len(cand_lines) == len(charts.nyquist_segments(loop.response)) >= 1
        assert panel.findall(".//*[@class='dt-nyq-active']")
        pms = panel.findall(".//*[@class='dt-nyq-pm']")
        assert len(pms) == int(np.sum(np.abs(loop.gain_crossings) <= charts.NYQUIST_RADIUS)) >= 1
        for el in pms:
            assert abs(abs(_svg_point(panel, el)) - 1.0) <= px
        for el in panel.findall(".//*[@class='dt-nyq-gm']"):
            z = _svg_point(panel, el)
            assert abs(z.imag) <= px and z.real < 0
    # The two loops differ (the DOB changes L), and each panel draws its own.
    assert cand.nyquist_dob is not None and cand.nyquist_nodob is not None
    assert not np.allclose(cand.nyquist_dob.response, cand.nyquist_nodob.response)
    assert ET.tostring(dob) != ET.tostring(nodob)


def test_spread_band_is_the_relative_band_in_db() -> None:
    """20 log10(|H| (1 +- spread)), the lower edge clipped at SPREAD_FLOOR |H| (a spread of 1
    or more has no lower edge)."""
    h = np.array([2.0, 1j, -0.5, 3.0 + 4.0j])
    sp = np.array([0.0, 0.5, 0.95, 2.0])
    hi, lo = charts.spread_band_db(h, sp)
    mag = np.array([2.0, 1.0, 0.5, 5.0])
    np.testing.assert_allclose(hi, 20 * np.log10(mag * (1 + sp)), rtol=1e-12)
    np.testing.assert_allclose(lo[:2], 20 * np.log10(mag[:2] * (1 - sp[:2])), rtol=1e-12)
    np.testing.assert_allclose(lo[2:], 20 * np.log10(mag[2:]) - 20.0, rtol=1e-12)


def test_plant_chart_without_plant_curves_names_the_field() -> None:
    """Curves built without the plant (not the engine's way) are an error naming it, not an
    empty chart."""
    import dataclasses

    cand = curves_from_analysis(analyse(LoopConfig()), MODEL_ONLY)
    with pytest.raises(ValueError, match=r"BodeCurves\.plant"):
        charts.bode_data("plant", dataclasses.replace(cand, plant=None), None)


def test_crossover_marks_follow_their_definition_at_every_crossing() -> None:
    """The marks (vectorised: on every slider move, candidate and active) against their
    definition walked point by point from low to high frequency: 0/1 on the two points around
    each sign change of less than 180, alternately up and down, a later crossing overwriting
    a shared point; random sequences with zeros, wraps, NaN and inf."""
    def walked(c: np.ndarray) -> np.ndarray:
        out = np.full(len(c), np.nan)
        up = True
        for i in range(len(c) - 1):
            a, b = c[i], c[i + 1]
            if (np.isfinite(a) and np.isfinite(b) and (a <= 0.0 < b or b <= 0.0 < a)
                    and abs(b - a) < 180.0):
                out[i], out[i + 1] = (0.0, 1.0) if up else (1.0, 0.0)
                up = not up
        return out

    rng = np.random.default_rng(3)
    values = np.array([-1.0, 0.0, 1.0, -200.0, 200.0, np.nan, np.inf, 0.5, -0.5])
    crossings = 0
    for _ in range(2000):
        n = int(rng.integers(1, 40))
        c = rng.choice(values, size=n) * rng.uniform(0.5, 2.0, size=n)
        want = walked(c)
        np.testing.assert_array_equal(charts.crossing_marks(c), want)
        crossings += int(np.count_nonzero(want == 0.0))
    assert crossings > 1000  # the sequences did cross


def test_the_small_db_charts_show_what_they_are_read_for() -> None:
    """Issue 33: |S| had ticks at 0 and -100 only (its ~3 dB peak unreadable) and the DOB
    rejection chart spanned 0-50 dB (its -2 dB waterbed hidden). Their ranges now hold the peak
    and the waterbed on 10 dB steps within -20..20 dB (4 ticks or more, every 10 dB, 14 px
    apart: 5 dB ticks 10 px apart were crowded)."""
    curves = curves_from_analysis(analyse(LoopConfig()), MODEL_ONLY)
    for key, column in (("sensitivity", "cand.s_db"), ("rejection", "cand.rejection_db")):
        spec = next(s for s in charts.BODE_CHARTS if s.key == key)
        assert spec.axes[1]["space"] == 14 and spec.axes[1]["incrs"][0] == 10
        data = charts.bode_data(key, curves, curves)
        lo, hi = charts.ranged_scales(spec, data, charts.Y_STEPS)["y"]["range"]
        y = np.asarray(data[1 + spec.columns.index(column)])
        assert -20.0 <= lo < 0.0 < hi <= 20.0 and lo % 10 == 0 and hi % 10 == 0, (key, lo, hi)
        assert (hi - lo) / 10 + 1 >= 4, (key, lo, hi)  # 4 ticks or more
        if key == "sensitivity":
            assert 0.0 < np.nanmax(y) < hi  # the peak |S| inside the range
        else:
            assert lo < np.nanmin(y) < 0.0  # the waterbed inside the range


def test_the_preview_scale_is_that_of_the_settled_run() -> None:
    """A start-up transient of 0.23 deg over a 0.05 deg steady error: the scale is the steady
    error's (5 % margin), and the start-up's end and peak are said."""
    t = np.linspace(0.0, 12.0, 1201)
    e = 0.05 * np.sin(t) + 0.23 * np.exp(-t / 0.2)
    data = charts.preview_data(t, e, 0.5 * e)
    scales, t_end, peak = charts.settled_scales(charts.PREVIEW_CHART, data, 0.15)
    lo, hi = scales["y"]["range"]
    assert t_end == pytest.approx(1.8)
    steady = e[t >= 1.8]
    assert lo == pytest.approx(steady.min() - 0.05 * (steady.max() - steady.min()))
    assert peak == pytest.approx(0.23 + 0.0, abs=0.01) and hi < 0.1
    # Nothing runs off: no note.
    calm = charts.preview_data(t, 0.05 * np.sin(t), 0.05 * np.sin(t))
    assert np.isnan(charts.settled_scales(charts.PREVIEW_CHART, calm, 0.15)[2])
