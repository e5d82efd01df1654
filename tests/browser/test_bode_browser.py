"""The Bode tab as a servo engineer reads it (issue 22 items 5 and 6), checked on what the
page draws: the loop's classic Bode (magnitude over phase on one frequency axis, a zoom of one
zooms both), the -180 deg line a horizontal line at -180 deg, the cursor read-out of both charts
at the hovered frequency against the dashboard's own data, the margin markers labelled with the
margins python-control finds, and the decision views (verdict, loop Bode, sensitivity,
rejection) inside a 1920 x 1080 screen.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import FIRST_LOAD_S, open_when_ready
from helpers import wait_for

from server import charts
from server.dashboard.app import Dashboard
from server.http_access import ESTOP_STRIP_PX

pytestmark = pytest.mark.browser

#: The loop's Bode charts, found by a series of their own.
MAG = "|L| candidate"
PHASE = "phase candidate"
#: Time for the page under load (a 2-core machine shared by several test runs).
SLOW_S = 60.0

#: JS: facts about the drawn chart that holds the series `label` (the page's own uPlot).
CHART_JS = """(label) => {
  const u = Object.values(window.__viserTestpoints?.uplots || {}).map(e => e.chart)
    .find(u => document.body.contains(u.root) && u.series.some(s => s.label === label));
  if (!u) return null;
  const o = u.over.getBoundingClientRect();
  return {
    over: [o.left, o.top, o.width, o.height],
    x: [u.scales.x.min, u.scales.x.max],
    axes: u.axes.map(a => a.scale),
    n: u.data[0].length,
    x0: u.data[0][0],
    idx: u.cursor.idx,
    k: u.ctx.canvas.width / u.width,
    plotLeft: u.bbox.left / (u.ctx.canvas.width / u.width),
    labels: u.root.dataset.marginLabels || null,
    title: u.root.querySelector('.u-title')?.textContent || '',
  };
}"""


def _chart(page: Any, label: str) -> dict[str, Any]:
    info = page.evaluate(CHART_JS, label)
    assert info is not None, f"no drawn chart with the series {label!r}"
    return dict(info)


def _text(page: Any, selector: str) -> str:
    return str(page.evaluate("(s) => document.querySelector(s)?.textContent || ''", selector))


def _scroll_to(page: Any, selector: str) -> None:
    page.evaluate("(s) => document.querySelector(s).scrollIntoView({block: 'start'})", selector)


def _panel(page: Any, dashboard: Dashboard) -> Any:
    """The page's candidate panel, once its charts show the controller's knowledge and the
    page holds the panel's loop Bode data."""
    # Polled from here (a wait for visibility needs the page's animation frames, which come
    # seconds apart on a loaded machine).
    wait_for(lambda: re.search(r"plant knowledge v[1-9]", _text(page, ".dt-verdict")),
             SLOW_S * 2, "the verdict never named the controller's plant knowledge")
    # a browser another test closed leaves when viser handles its disconnect (seconds at load)
    wait_for(lambda: len(dashboard.server.get_clients()) == 1, SLOW_S,
             "another browser's page is still connected")
    clients = list(dashboard.server.get_clients().values())
    assert len(clients) == 1
    panel = dashboard.panel_of(clients[0])
    assert panel is not None and panel.wait_idle(SLOW_S)
    data = panel._charts["loop_mag"].data

    def drawn() -> bool:
        c = page.evaluate(CHART_JS, MAG)
        return bool(c) and c["n"] == len(data[0]) and c["x0"] == data[0][0] and c["labels"]

    wait_for(drawn, SLOW_S, "the page never drew the panel's loop Bode")
    return panel


def test_loop_bode_is_magnitude_over_phase_on_one_frequency_axis(
        page: Any, dashboard: Dashboard, artifacts: Path) -> None:
    """Two charts, magnitude above phase, their plot areas aligned, each with its own y axis
    (no phase on a second axis of the magnitude chart), the same x range; a drag-zoom on the
    magnitude chart zooms the phase chart to the same range."""
    _panel(page, dashboard)
    mag, phase = _chart(page, MAG), _chart(page, PHASE)
    assert mag["axes"] == ["x", "y"] and phase["axes"] == ["x", "deg"]
    assert mag["over"][1] + mag["over"][3] <= phase["over"][1]  # magnitude above phase
    assert abs(mag["over"][0] - phase["over"][0]) <= 1.0
    assert abs(mag["over"][2] - phase["over"][2]) <= 1.0
    assert mag["x"] == phase["x"]
    _scroll_to(page, ".dt-loop-readout")
    mag = _chart(page, MAG)
    left, top, width, height = mag["over"]
    page.mouse.move(left + 0.3 * width, top + height / 2)
    page.mouse.down()
    page.mouse.move(left + 0.6 * width, top + height / 2, steps=8)
    page.mouse.up()

    def zoomed() -> bool:
        m, p = _chart(page, MAG), _chart(page, PHASE)
        return m["x"] == p["x"] and m["x"][1] / m["x"][0] < 0.5 * mag["x"][1] / mag["x"][0]

    wait_for(zoomed, SLOW_S, "a zoom of the magnitude chart did not zoom both charts alike")
    m = _chart(page, MAG)
    # The range dragged over: 30 % to 60 % of the log axis.
    lo, hi = (math.log10(v) for v in mag["x"])
    assert math.isclose(math.log10(m["x"][0]), lo + 0.3 * (hi - lo), abs_tol=0.05)
    assert math.isclose(math.log10(m["x"][1]), lo + 0.6 * (hi - lo), abs_tol=0.05)
    page.mouse.dblclick(left + 0.5 * width, top + height / 2)  # back to the whole range

    def whole() -> bool:
        m, p = _chart(page, MAG), _chart(page, PHASE)
        return m["x"] == p["x"] == mag["x"]

    wait_for(whole, SLOW_S, "a double click did not bring both charts back to the whole range")


#: JS: red (the -180 deg line's #d62728) pixels of the phase chart's canvas, per row.
RED_ROWS_JS = """(label) => {
  const u = Object.values(window.__viserTestpoints?.uplots || {}).map(e => e.chart)
    .find(u => document.body.contains(u.root) && u.series.some(s => s.label === label));
  const {left, top, width, height} = u.bbox;
  const d = u.ctx.getImageData(left, top, width, height).data;
  const rows = [];
  for (let y = 0; y < height; y++) {
    let n = 0;
    for (let x = 0; x < width; x++) {
      const i = 4 * (y * width + x);
      if (d[i] > 170 && d[i + 1] < 110 && d[i + 2] < 110) n++;
    }
    rows.push(n / width);
  }
  return {rows, top: top / (u.ctx.canvas.width / u.width), k: u.ctx.canvas.width / u.width};
}"""


#: JS: set the magnitude chart's x scale to a range neither chart maps onto itself (NaN) and
#: count the setScale hooks of both charts until the page runs its next task. A hook past the
#: 1000th throws, which ends uPlot's commit: a bounce between the charts is counted, not hung.
BOUNCE_JS = """async ([mag, phase]) => {
  const charts = Object.values(window.__viserTestpoints?.uplots || {}).map(e => e.chart)
    .filter(u => document.body.contains(u.root));
  const m = charts.find(u => u.series.some(s => s.label === mag));
  const p = charts.find(u => u.series.some(s => s.label === phase));
  const before = [m.scales.x.min, m.scales.x.max];
  let hooks = 0;
  const count = () => { if (++hooks > 1000) throw new Error("setScale bounced"); };
  m.hooks.setScale.push(count);
  p.hooks.setScale.push(count);
  try {
    m.setScale("x", {min: NaN, max: NaN});
    await new Promise(r => setTimeout(r, 0));
  } catch (err) {
    console.warn(err);
  }
  m.hooks.setScale.splice(m.hooks.setScale.indexOf(count), 1);
  p.hooks.setScale.splice(p.hooks.setScale.indexOf(count), 1);
  m.setScale("x", {min: before[0], max: before[1]});
  return hooks;
}"""


def test_a_zoom_the_other_chart_cannot_take_does_not_bounce_between_them(
        page: Any, dashboard: Dashboard) -> None:
    """The magnitude and phase charts keep one frequency axis: a zoom of one sets the other's.
    A range that does not map onto itself (NaN here) bounced between the two forever, one
    microtask each: the page ran no task again (seen as a frozen page after a caution apply
    and a watchdog rollback). Now the other chart's answer goes no further; a chart left with
    a NaN range gets its data's back."""
    _panel(page, dashboard)
    hooks = page.evaluate(BOUNCE_JS, [MAG, PHASE])
    assert hooks <= 4, f"{hooks} setScale hooks: the zoom bounced between the charts"
    before = _chart(page, MAG)["x"]
    wait_for(lambda: _chart(page, MAG)["x"] == _chart(page, PHASE)["x"] == before, SLOW_S,
             "the charts did not come back to one range")
    # The state a chart was left in (viser's zoom keeper, new data while its tab was hidden):
    # the page's script gives it its data's range back.
    page.evaluate("""(phase) => Object.values(window.__viserTestpoints.uplots).map(e => e.chart)
      .find(u => document.body.contains(u.root) && u.series.some(s => s.label === phase))
      .setScale("x", {min: NaN, max: 1})""", PHASE)
    wait_for(lambda: _chart(page, PHASE)["x"] == before, SLOW_S,
             "a NaN range of the phase chart was not repaired")


def test_the_minus_180_line_is_a_horizontal_line_at_minus_180_deg(
        page: Any, dashboard: Dashboard) -> None:
    """The phase chart's -180 deg marker is one horizontal line across the plot at the pixel
    row of -180 deg on the chart's scale (the scale the dashboard set: computed here from its
    range), and no other red is drawn (it was a dotted rectangle between the two phase
    crossovers)."""
    panel = _panel(page, dashboard)
    lo, hi = panel._charts["loop_phase"].scales["deg"]["range"]
    assert lo < -180.0 < hi
    got = page.evaluate(RED_ROWS_JS, PHASE)
    rows = np.array(got["rows"])
    expected_row = (hi - (-180.0)) / (hi - lo) * (len(rows) - 1)
    line = int(np.argmax(rows))
    assert abs(line - expected_row) <= 1.5 * got["k"], (line, expected_row)
    band = slice(max(0, line - 2 * math.ceil(got["k"])), line + 2 * math.ceil(got["k"]) + 1)
    assert rows[band].max() > 0.6  # across the plot (the curve crosses it in places)
    outside = np.delete(rows, np.arange(len(rows))[band])
    assert outside.max() < 0.02, outside.max()  # no other line, no rectangle


def test_cursor_readout_shows_both_charts_at_the_hovered_frequency(
        page: Any, dashboard: Dashboard) -> None:
    """Hovering the magnitude chart at 2 Hz, then the phase chart at 20 Hz: the read-out gives
    the frequency under the cursor and |L| and phase there, as the dashboard computed them
    (its chart data, to the read-out's 0.1), and both charts' cursors sit on that frequency."""
    panel = _panel(page, dashboard)
    mag_data = panel._charts["loop_mag"].data
    phase_data = panel._charts["loop_phase"].data
    x = np.asarray(mag_data[0])
    _scroll_to(page, ".dt-loop-readout")
    pattern = re.compile(r"f (\S+) Hz \| \|L\| (\S+) dB \| phase (\S+) deg \| active: \|L\| "
                         r"(\S+) dB, phase (\S+) deg")
    for label, f_hz in ((MAG, 2.0), (PHASE, 20.0)):
        c = _chart(page, label)
        left, top, width, height = c["over"]
        lo, hi = (math.log10(v) for v in c["x"])
        page.mouse.move(left + (math.log10(f_hz) - lo) / (hi - lo) * width, top + height / 3)

        def reading(f_hz: float = f_hz) -> re.Match[str] | None:
            m = pattern.search(_text(page, ".dt-loop-readout"))
            return m if m and abs(math.log10(float(m.group(1)) / f_hz)) < 0.02 else None

        wait_for(reading, SLOW_S, f"no read-out near {f_hz} Hz")
        m = reading()
        assert m is not None
        f = float(m.group(1))
        i = int(np.argmin(np.abs(np.log(x / f))))
        assert abs(np.log10(x[i] / f_hz)) < 0.02  # a grid point within 5 % of the cursor
        expect = (mag_data[1][i], phase_data[1][i], mag_data[2][i], phase_data[2][i])
        for text, value in zip(m.groups()[1:], expect, strict=True):
            assert abs(float(text) - value) <= 0.051, (m.group(0), expect)
        mag, phase = _chart(page, MAG), _chart(page, PHASE)
        assert mag["idx"] == phase["idx"] and mag["idx"] is not None  # one cursor on both
        assert math.isclose(x[mag["idx"]], f, rel_tol=5e-3)


#: JS: pixels of colour `rgb` (within 40) in a box of the chart `label`'s canvas (CSS px).
INK_JS = """([label, box, rgb]) => {
  const u = Object.values(window.__viserTestpoints?.uplots || {}).map(e => e.chart)
    .find(u => document.body.contains(u.root) && u.series.some(s => s.label === label));
  const k = u.ctx.canvas.width / u.width;
  const [x, y, w, h] = box.map(v => Math.round(v * k));
  const d = u.ctx.getImageData(x, y, w, h).data;
  let n = 0;
  for (let i = 0; i < d.length; i += 4) {
    if (Math.abs(d[i] - rgb[0]) < 40 && Math.abs(d[i + 1] - rgb[1]) < 40
        && Math.abs(d[i + 2] - rgb[2]) < 40) n++;
  }
  return n;
}"""


def _rgb(hex_color: str) -> list[int]:
    return [int(hex_color[i:i + 2], 16) for i in (1, 3, 5)]


def test_margin_markers_are_labelled_with_their_values_and_frequencies(
        page: Any, dashboard: Dashboard) -> None:
    """Each margin marker carries its label on the chart ("gain margin 26.0 dB up at 36.3 Hz",
    "gain-reduction margin 25.8 dB down at 0.183 Hz", "PM 74.8
    deg at 6.86 Hz": the margins of the verdict, from the gate's refined crossings), drawn in
    the marker's colour at the marker's frequency; the line above the charts says the same."""
    panel = _panel(page, dashboard)
    curves = panel.last_evaluation.curves
    gm, pm = charts.margin_marks(curves)
    assert gm and pm is not None
    margins_text = _text(page, ".dt-loop-margins")
    for label, marks, unit, color in ((MAG, gm, "dB", charts.GM_COLOR),
                                      (PHASE, (pm,), "deg", charts.PM_COLOR)):
        c = _chart(page, label)
        drawn = json.loads(c["labels"])
        want = [(f"PM {m.value:.1f} deg" if unit == "deg"
                 else f"gain-reduction margin {-m.value:.1f} dB down" if m.value < 0
                 else f"gain margin {m.value:.1f} dB up")
                + f" at {float(f'{m.freq_hz:.3g}'):g} Hz" for m in marks]
        assert [d["text"] for d in drawn] == want
        lo, hi = (math.log10(v) for v in c["x"])
        for d, m in zip(drawn, marks, strict=True):
            # At the marker's frequency on the chart's log axis (canvas CSS px).
            x_expected = c["plotLeft"] + (math.log10(m.freq_hz) - lo) / (hi - lo) * c["over"][2]
            assert abs(d["x"] - x_expected) <= 1.0, (d, x_expected)
            # The text is drawn in the marker's colour beside the marker.
            box = [d["x"] - 220, d["y"] - 7, 440, 14]
            assert page.evaluate(INK_JS, [label, box, _rgb(color)]) >= 30
            # Placed where it covers no curve (the GM label covered |L| from 0.2 to 1.3 Hz).
            assert d["covers"] == 0, d
            # The line above: each gain margin positive and named (issue 33: "gain-reduction
            # margin 25.8 dB down", never "-25.8 dB").
            at = f"at {float(f'{m.freq_hz:.3g}'):g} Hz"
            value = (f"{-m.value:.1f} dB down {at}" if unit == "dB" and m.value < 0
                     else f"{m.value:.1f} {unit}")
            assert value in margins_text and at in margins_text, (value, margins_text)
    assert "-" + f"{abs(min(m.value for m in gm)):.1f}" not in margins_text, margins_text


#: JS: the y ticks uPlot drew on the chart whose title starts with `title`: their values and
#: the CSS px between two neighbours (uPlot's computed splits of the first y axis).
Y_TICKS_JS = """(title) => {
  const u = Object.values(window.__viserTestpoints?.uplots || {}).map(e => e.chart)
    .find(u => document.body.contains(u.root)
          && (u.root.querySelector('.u-title')?.textContent || '').startsWith(title));
  if (!u) return null;
  const ax = u.axes.find(a => a.scale !== 'x' && a.show !== false);
  const splits = (ax._splits || []).filter(v => v !== null && isFinite(v));
  const k = u.ctx.canvas.width / u.width;
  const px = splits.map(v => u.valToPos(v, ax.scale, true) / k);
  const gaps = px.slice(1).map((p, i) => Math.abs(p - px[i]));
  return {splits, minGapPx: gaps.length ? Math.min(...gaps) : 0,
          range: [u.scales[ax.scale].min, u.scales[ax.scale].max]};
}"""


@pytest.mark.parametrize("title", ["Open loop L (speed loop): magnitude", "DOB rejection gain",
                                   "Sensitivity |S|"])
def test_the_short_dB_charts_have_readable_y_ticks(page: Any, dashboard: Dashboard,
                                                   title: str) -> None:
    """The loop magnitude (was -60, 0, 60 only), the DOB rejection (was 0, 10, 20) and |S|
    (crowded at 5 dB steps) each have at least 4 y ticks within their range, at least 14 CSS px
    apart (a 10 px label then stays clear of the next), on whole dB steps."""
    _panel(page, dashboard)
    got: dict[str, Any] = {}

    def drawn() -> bool:
        got.update(page.evaluate(Y_TICKS_JS, title) or {})
        return bool(got.get("splits"))

    wait_for(drawn, SLOW_S, f"no drawn chart titled {title!r}")
    splits, lo, hi = got["splits"], *got["range"]
    print(title, got)
    inside = [v for v in splits if lo - 1e-9 <= v <= hi + 1e-9]
    assert len(inside) >= 4, got
    assert got["minGapPx"] >= 14.0, got
    assert all(abs(v - round(v)) < 1e-9 for v in splits), got


def test_the_decision_views_fit_a_1920_by_1080_screen(
        page: Any, dashboard: Dashboard, artifacts: Path) -> None:
    """On a 1920 x 1080 screen the Bode tab opens on Decide, and the verdict, the margins, the
    read-out, the loop's magnitude and phase, sensitivity and rejection are all on the screen
    at once, unscrolled and not covered (the tab was ~3,850 px of 11 charts)."""
    other = page.context.browser.new_context(viewport={"width": 1920, "height": 1080})
    try:
        fresh = other.new_page()
        open_when_ready(fresh, dashboard, FIRST_LOAD_S)  # a second page: 120 s ran out at load ~12
        wait_for(lambda: "phase margin" in _text(fresh, ".dt-loop-margins")
                 and fresh.evaluate(CHART_JS, "|S| candidate"), SLOW_S * 2,
                 "the Decide view never drew")
        specs = {s.key: s for s in charts.BODE_CHARTS}
        titles = [specs[k].title for k in ("loop_mag", "loop_phase", "sensitivity",
                                           "rejection")]
        boxes = fresh.evaluate("""(titles) => {
          const seen = (el) => {
            const r = el.getBoundingClientRect();
            const hit = document.elementFromPoint(r.left + r.width / 2, r.top + r.height / 2);
            return {top: r.top, bottom: r.bottom, width: r.width,
                    covered: !(hit && (el === hit || el.contains(hit)))};
          };
          const out = {};
          for (const sel of ['.dt-decide', '.dt-loop-margins', '.dt-loop-readout'])
            out[sel] = seen(document.querySelector(sel));
          for (const t of titles) {
            const title = [...document.querySelectorAll('.u-title')]
              .find(e => e.textContent === t && e.getBoundingClientRect().width > 0);
            out[t] = title ? seen(title.closest('.uplot-container')) : null;
          }
          return out;
        }""", titles)
        fresh.screenshot(path=str(artifacts / "bode_decide_1080.png"), timeout=SLOW_S * 3000)
        for name, b in boxes.items():
            assert b is not None, f"{name}: not shown"
            # Above the E-STOP's strip (the E-STOP covered the bottom chart's axis).
            assert b["width"] > 500 and b["top"] >= 0 and b["bottom"] <= 1080 - ESTOP_STRIP_PX, \
                (name, b)
            assert not b["covered"], (name, b)
    finally:
        other.close()


#: JS: the left edge and width of the plots panel (the dock column holding the "Bode" tab).
PLOTS_BOX_JS = """() => {
  const tab = [...document.querySelectorAll('[data-dock-strip] [role=tab]')]
    .find(t => (t.getAttribute('title') || '') === 'Bode');
  let el = tab;
  while (el && el.getBoundingClientRect().height < 0.8 * window.innerHeight) el = el.parentElement;
  const r = (el || tab).getBoundingClientRect();
  return [r.left, r.width];
}"""


#: JS: the controls' panel (the one holding the "Hide / show the 3-D view" button... or any
#: of the Tune / Live tabs): [left, width] of its dock column.
CONTROLS_BOX_JS = """() => {
  const tab = [...document.querySelectorAll('[role=tab]')]
    .find(t => t.textContent.trim() === 'Tune');
  let el = tab;
  while (el && el.getBoundingClientRect().height < 0.8 * window.innerHeight) el = el.parentElement;
  const r = (el || tab).getBoundingClientRect();
  return [r.left, r.width];
}"""

#: JS: the 3-D view's canvas width (CSS px; 0: none drawn).
SCENE_WIDTH_JS = """() => Math.max(0, ...[...document.querySelectorAll('canvas')]
  .filter(c => !c.closest('.uplot')).map(c => c.getBoundingClientRect().width))"""


def test_the_3d_view_hides_and_comes_back_in_this_browser_only(
        page: Any, dashboard: Dashboard) -> None:
    """"Hide / show the 3-D view" (Live tab) widens the plots panel over the 3-D view in the
    browser that pressed it (the Decide charts get wider), and gives the space back on a
    second press; another browser's layout does not move."""
    _panel(page, dashboard)
    other = page.context.browser.new_context(viewport={"width": 1600, "height": 1000})
    try:
        fresh = other.new_page()
        open_when_ready(fresh, dashboard, FIRST_LOAD_S)  # a second page: 120 s ran out at load ~12
        before = page.evaluate(PLOTS_BOX_JS)
        controls_before = page.evaluate(CONTROLS_BOX_JS)
        other_before = fresh.evaluate(PLOTS_BOX_JS)
        mag_before = _chart(page, MAG)["over"][2]
        page.get_by_role("tab", name="Live", exact=True).click(timeout=SLOW_S * 1000)
        page.get_by_role("button", name="Hide / show the 3-D view").click(timeout=SLOW_S * 1000)
        # In 1600 px: controls 384, plots 900, scene 316; hidden, the scene keeps viser's
        # 120 px minimum, so the plots gain ~190 px (the 4000 px of before gained more by
        # squeezing the controls to ~110 px).
        wait_for(lambda: page.evaluate(PLOTS_BOX_JS)[1] > before[1] + 150, SLOW_S,
                 "the plots panel did not widen over the 3-D view")
        wide = page.evaluate(PLOTS_BOX_JS)
        # The controls keep their width (they were squeezed to ~110 px) and the 3-D view is
        # gone but for viser's minimum strip: the plots take the rest of the window.
        controls = page.evaluate(CONTROLS_BOX_JS)
        viewport = page.evaluate("() => window.innerWidth")
        print("controls", controls_before, "->", controls, "plots", before, "->", wide,
              "scene", page.evaluate(SCENE_WIDTH_JS), "viewport", viewport)
        assert controls[1] >= 0.95 * controls_before[1] and controls[1] >= 300, controls
        assert wide[1] + controls[1] >= viewport - 140, (wide, controls, viewport)
        wait_for(lambda: _chart(page, MAG)["over"][2] > mag_before + 150, SLOW_S,
                 "the Decide charts did not widen")
        assert fresh.evaluate(PLOTS_BOX_JS) == other_before  # the other browser: unchanged
        page.get_by_role("button", name="Hide / show the 3-D view").click(timeout=SLOW_S * 1000)
        wait_for(lambda: abs(page.evaluate(PLOTS_BOX_JS)[1] - before[1]) <= 2, SLOW_S,
                 "the 3-D view did not come back")
        assert wide[0] < before[0]
    finally:
        other.close()
        page.get_by_role("tab", name="Tune", exact=True).click(timeout=SLOW_S * 1000)


#: JS: the selected tab of the Bode tab's sub-tabs (null: not drawn).
BODE_SUBTAB_JS = """() => {
  for (const list of document.querySelectorAll('[role=tablist]')) {
    const tabs = [...list.querySelectorAll('[role=tab]')];
    if (!tabs.some(t => t.textContent.trim() === 'Decide')) continue;
    const on = tabs.find(t => t.getAttribute('aria-selected') === 'true');
    return on ? on.textContent.trim() : null;
  }
  return null;
}"""
#: JS: whether the Nyquist view is drawn with a size (shown).
NYQUIST_SHOWN_JS = """() => [...document.querySelectorAll('.dt-nyquist-box svg')].some(
  s => s.getBoundingClientRect().width > 0)"""
#: JS: a live chart is drawn on screen (the Live traces plots tab is shown).
LIVE_TRACES_SHOWN_JS = """() => [...document.querySelectorAll('.u-title')].some(
  t => t.textContent === 'Position error' && t.getBoundingClientRect().width > 0)"""


#: A link to the dashboard opened on the Live traces tab, asking for Nyquist in the Bode tab.
DEEP_LINK = "tab=Live&plot=Live+traces&bode=Nyquist"


def _open_with_view(page: Any, dashboard: Dashboard, view: str) -> None:
    """This page's URL with `view` as its fragment opened in a new document, as a link or a
    bookmark opens it, once its websocket is connected. (The tests set the fragment on the
    live page with history.replaceState and reloaded: the page's own URL upkeep, which runs
    every second and on every change, could write the tabs it showed back into the fragment
    before the reload began, and the reloaded page opened on Tune, Bode, Decide: the CI
    failures under load, the page not at fault.)"""
    assert dashboard.server is not None
    url = str(page.evaluate("() => location.origin + location.pathname + location.search"))
    before = set(dashboard.server.get_clients())
    page.goto("about:blank", timeout=SLOW_S * 1000)
    wait_for(lambda: not (before & set(dashboard.server.get_clients())), SLOW_S * 2,
             "the page's old websocket never closed")
    page.goto(f"{url}#{view}", wait_until="domcontentloaded", timeout=SLOW_S * 2000)
    wait_for(lambda: set(dashboard.server.get_clients()) - before, SLOW_S * 2,
             "the page opened on the link never connected")


def test_the_url_keeps_the_bode_sub_tab_over_a_reload(dashboard: Dashboard, page: Any) -> None:
    """The selected Bode sub-tab is in the URL (#...&bode=Nyquist): a reload shows that
    sub-tab (not Decide, the one a page opens on); while another plots tab is shown, the URL
    keeps it and it is still selected on coming back. (Last in this module: the reload gives
    the page a new candidate panel.)"""
    page.get_by_role("tab", name="Bode", exact=True).click(timeout=SLOW_S * 1000)
    page.get_by_role("tab", name="Nyquist", exact=True).click(timeout=SLOW_S * 1000)
    page.wait_for_function("() => location.hash.includes('bode=Nyquist')",
                           timeout=SLOW_S * 1000)
    before = set(dashboard.server.get_clients())
    page.reload(wait_until="domcontentloaded", timeout=SLOW_S * 2000)
    wait_for(lambda: set(dashboard.server.get_clients()) - before, SLOW_S * 2,
             "the reloaded page never connected")
    page.wait_for_function(f"() => ({BODE_SUBTAB_JS})() === 'Nyquist'", timeout=SLOW_S * 2000)
    page.wait_for_function(NYQUIST_SHOWN_JS, timeout=SLOW_S * 1000)
    assert "bode=Nyquist" in page.url
    # Another plots tab: the Nyquist view is hidden, the URL keeps the Bode sub-tab; back on
    # Bode, it is there.
    page.get_by_role("tab", name="Live traces", exact=True).click(timeout=SLOW_S * 1000)
    page.wait_for_function("() => location.hash.includes('plot=Live+traces')",
                           timeout=SLOW_S * 1000)
    page.wait_for_function(f"() => !({NYQUIST_SHOWN_JS})()", timeout=SLOW_S * 1000)
    assert "bode=Nyquist" in page.url
    page.get_by_role("tab", name="Bode", exact=True).click(timeout=SLOW_S * 1000)
    page.wait_for_function(NYQUIST_SHOWN_JS, timeout=SLOW_S * 1000)
    page.get_by_role("tab", name="Decide", exact=True).click(timeout=SLOW_S * 1000)
    page.wait_for_function("() => location.hash.includes('bode=Decide')", timeout=SLOW_S * 1000)
    # A page opened on another plots tab with a Bode sub-tab in its URL (a link, a bookmark):
    # the Bode tab opens on that sub-tab.
    _open_with_view(page, dashboard, DEEP_LINK)
    page.wait_for_function(LIVE_TRACES_SHOWN_JS, timeout=SLOW_S * 2000)
    page.get_by_role("tab", name="Bode", exact=True).click(timeout=SLOW_S * 1000)
    page.wait_for_function(NYQUIST_SHOWN_JS, timeout=SLOW_S * 1000)
    assert "bode=Nyquist" in page.url, page.url


def test_a_bode_sub_tab_from_the_url_drawn_after_the_rest_is_restored(
        dashboard: Dashboard, page: Any) -> None:
    """The CI failure at load 5-7 made certain: a page opened on
    #tab=Live&plot=Live+traces&bode=Nyquist whose candidate charts (the Bode sub-tabs) come
    only after the Live traces tab is shown (the dashboard builds them when the page connects,
    held back here) still opens the Bode tab on Nyquist when Bode is clicked. (The page
    script's restore finds the sub-tabs only once drawn; it then activated them with a click
    the dock's tabs ignore: Decide stayed.)"""
    before = set(dashboard.server.get_clients())
    with dashboard.candidates._build_lock:  # the page's candidate charts wait
        _open_with_view(page, dashboard, DEEP_LINK)
        page.wait_for_function(LIVE_TRACES_SHOWN_JS, timeout=SLOW_S * 2000)
        assert page.evaluate(BODE_SUBTAB_JS) is None  # not drawn yet
    new = set(dashboard.server.get_clients()) - before
    wait_for(lambda: any(dashboard.panel_of(dashboard.server.get_clients()[c]) is not None
                         for c in new if c in dashboard.server.get_clients()),
             SLOW_S * 2, "the reloaded page's candidate panel was never built")
    page.get_by_role("tab", name="Bode", exact=True).click(timeout=SLOW_S * 1000)
    page.wait_for_function(f"() => ({BODE_SUBTAB_JS})() === 'Nyquist'", timeout=SLOW_S * 1000)
    page.wait_for_function(NYQUIST_SHOWN_JS, timeout=SLOW_S * 1000)
    assert "bode=Nyquist" in page.url, page.url
