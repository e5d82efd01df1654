"""What the user sees on the dashboard (issue 22), in headless Chromium against a real
controller: live traces that draw over the window after tab round trips and reloads.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
from conftest import ARTIFACTS, FIRST_LOAD_S, _wait_until, set_number

from server.app import Dashboard
from server.charts import LIVE_WINDOW_S

pytestmark = pytest.mark.browser

#: JS: per live chart (the ones with a "config v" series), what uPlot DRAWS: its x scale's
#: min/max, the drawn width in CSS px, the oldest and newest x of its data and how many of its
#: samples fall inside the drawn x range.
LIVE_DRAWN_JS = """() => {
  const ups = Object.values(window.__viserTestpoints?.uplots || {});
  return ups.filter(u => u.chart.series.some(s => s.label === 'config v')).map(u => {
    const c = u.chart, x = Array.from(c.data[0]), sx = c.scales.x;
    const inside = x.filter(v => v >= sx.min && v <= sx.max).length;
    return {title: c.root.querySelector('.u-title')?.textContent || '', min: sx.min,
            max: sx.max, width: c.bbox.width / devicePixelRatio, first: x[0], last: x.at(-1),
            n: x.length, inside: inside,
            shown: c.root.getBoundingClientRect().width > 0};
  });
}"""


def _live_ok(page: Any, window_s: float) -> list[dict[str, Any]]:
    """Wait until every live chart draws the window: x from -window to the newest sample (0),
    with (almost) all of its samples on the drawn axis; returns what was read."""
    deadline = time.monotonic() + 60.0
    last: list[dict[str, Any]] = []
    while time.monotonic() < deadline:
        last = page.evaluate(LIVE_DRAWN_JS)
        if len(last) == 4 and all(_draws_window(c, window_s) for c in last):
            return last
        time.sleep(0.2)
    page.screenshot(path=str(ARTIFACTS / "ui_live_failed.png"))
    raise AssertionError(f"live charts do not draw the {window_s} s window: {last}")


def _draws_window(c: dict[str, Any], window_s: float) -> bool:
    return bool(
        c["shown"] and c["width"] > 100 and c["n"] > 100
        and abs(c["last"]) < 1e-9  # the newest sample is at t = 0
        and c["first"] < -0.8 * window_s
        and abs(c["max"] - c["last"]) <= 0.02 * window_s
        and abs(c["min"] + window_s) <= 0.02 * window_s
        and c["inside"] >= 0.98 * c["n"]
    )


def test_live_traces_draw_the_window_after_a_tab_round_trip_and_a_reload(
    page: Any, dashboard: Dashboard, artifacts: Path
) -> None:
    page.get_by_role("tab", name="Live traces").click()
    first = _live_ok(page, LIVE_WINDOW_S)
    page.screenshot(path=str(artifacts / "ui_live_first.png"))
    page.get_by_role("tab", name="Bode").click()
    page.wait_for_function("() => [...document.querySelectorAll('.u-title')].some("
                           "t => t.textContent.startsWith('Open loop') && "
                           "t.getBoundingClientRect().width > 0)", timeout=20_000)
    page.get_by_role("tab", name="Live traces").click()
    trip = _live_ok(page, LIVE_WINDOW_S)
    page.screenshot(path=str(artifacts / "ui_live_round_trip.png"))
    # A reload straight onto the live traces.
    # A reload (F5) of the page showing the live traces: its URL says so (#plot=Live+traces).
    assert "plot=Live+traces" in page.url
    before = set(dashboard.server.get_clients())
    page.reload(wait_until="domcontentloaded")
    _wait_until(lambda: set(dashboard.server.get_clients()) - before, FIRST_LOAD_S,
                "the reloaded page never connected")
    reload = _live_ok(page, LIVE_WINDOW_S)
    page.screenshot(path=str(artifacts / "ui_live_reload.png"))
    # Another window: the time axis follows it.
    page.get_by_role("tab", name="Live", exact=True).click()
    set_number(page, "Window (s)", 20)
    wider = _live_ok(page, 20.0)
    page.screenshot(path=str(artifacts / "ui_live_window20.png"))
    page.get_by_role("tab", name="Tune").click()
    for name, got in (("first", first), ("round trip", trip), ("reload", reload),
                      ("window 20 s", wider)):
        c = got[0]
        print(f"live x range {name}: drawn {c['min']:.2f}..{c['max']:.2f} s, data "
              f"{c['first']:.2f}..{c['last']:.2f} s, {c['inside']}/{c['n']} samples drawn")
