"""Two recorded runs compared in the wide plots panel (issue 22: "wide space for verdict
details and comparisons"), checked on what the page shows.

The dashboard's recordings directory holds two real MCAP files of a known sine run (B started
3.7 s later along the trajectory, its error half of A's, its Q cut-off 0.8 Hz against 0.5 Hz).
A user picks them in the plots panel's Compare runs tab and presses Compare; the page must show
the overlay charts there, in the wide panel and wide (measured on the page, against the
controls' sidebar), both runs' names, their numbers (numpy's peak and RMSE on the files' own
samples) and the configuration difference, and the drawn curves must be the runs' (B's peak
error half of A's, B's reference on A's after the shift).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import ARTIFACTS
from helpers import free_port, wait_for
from sine_recordings import write_sine_recording

from controller.client import ControllerClient
from controller.core.config import LoopConfig
from controller.recording.mcap_io import read_recording
from server.dashboard.app import PLOTS_WIDTH_PX, Dashboard, DashboardOptions
from server.panels.recordings import COMPARE_TAB, OVERLAY_CHART, REFERENCE_CHART

pytestmark = pytest.mark.browser

RIG = "browsertest"
A_NAME, B_NAME = "1-before.mcap", "2-after.mcap"
#: Time for the page under load (a 2-core machine shared by several test runs).
SLOW_S = 90.0

#: JS: the drawn uPlot titled `title`: its box on the page, its series' labels and data, and
#: the box of the controls' sidebar (the panel that holds the E-STOP button).
CHART_JS = """(title) => {
  const u = Object.values(window.__viserTestpoints?.uplots || {}).map(e => e.chart)
    .find(c => document.body.contains(c.root)
               && (c.root.querySelector('.u-title')?.textContent || '') === title);
  if (!u) return null;
  const r = u.root.getBoundingClientRect();
  return {
    box: [r.left, r.top, r.width, r.height],
    labels: u.series.map(s => s.label),
    data: u.data.map(col => Array.from(col, v => (v === null || !isFinite(v)) ? null : v)),
  };
}"""


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("recordings")
    write_sine_recording(d / A_NAME, LoopConfig(), 0.0, 1.0)
    write_sine_recording(d / B_NAME, LoopConfig().with_(q_cutoff_hz=0.8), 3.7, 0.5)
    return d


@pytest.fixture(scope="module")
def dashboard(controller_endpoint: str, probe: ControllerClient,
              recordings: Path) -> Iterator[Dashboard]:
    """The browser harness's dashboard with the two recordings in its directory."""
    opts = DashboardOptions(connect=(controller_endpoint,), rig_name=RIG, port=free_port(),
                            verbose=False, recordings_dir=recordings)
    with Dashboard(opts) as d:
        yield d


def _pick(page: Any, label: str, name: str) -> None:
    """Choose `name` in the dropdown labelled `label`, as a user does: open it, click it."""
    page.get_by_label(label, exact=True).click()
    page.get_by_role("option", name=name, exact=True).click()


def _numbers(path: Path) -> tuple[float, float]:
    """Peak |error| and RMSE of a recording's samples (numpy, not the dashboard's metrics)."""
    e = read_recording(path).state["error_deg"]
    return float(np.max(np.abs(e))), float(np.sqrt(np.mean(e**2)))


def test_two_runs_are_compared_in_the_wide_plots_panel(
    page: Any, dashboard: Dashboard, recordings: Path
) -> None:
    page.get_by_role("tab", name=COMPARE_TAB, exact=True).click()
    # The list is read in a thread: the pickers offer the files once it is done.
    _pick(page, "A (before)", A_NAME)
    _pick(page, "B (after)", B_NAME)
    page.get_by_role("button", name="Compare", exact=True).click()
    shown = page.locator(".dt-compare")
    wait_for(lambda: B_NAME in shown.inner_text(), SLOW_S, "the comparison never showed")
    text = shown.inner_text()
    page.screenshot(path=str(ARTIFACTS / "compare_runs.png"))

    # Both runs named, with their numbers and the configuration difference.
    assert f"A (before) {A_NAME}" in text and f"B (after) {B_NAME}" in text, text
    for name in (A_NAME, B_NAME):
        peak, rmse = _numbers(recordings / name)
        assert f"{peak:.4g} deg" in text and f"{rmse:.4g} deg" in text, (name, text)
    assert "q_cutoff_hz" in text and "0.8" in text, text
    assert "-3.70 s" in text, text  # B shifted onto A by the lag the runs were made with

    # The charts: in the plots panel, as wide as it is, far wider than the controls' sidebar.
    sidebar = page.get_by_role("tab", name="Tune", exact=True).bounding_box()
    viewport = page.viewport_size
    for spec in (OVERLAY_CHART, REFERENCE_CHART):
        chart: dict[str, Any] = {}

        def drawn(spec: Any = spec) -> bool:
            nonlocal chart
            chart = page.evaluate(CHART_JS, spec.title) or {}
            return bool(chart) and len(chart["data"][0]) > 100
        wait_for(drawn, SLOW_S, f"{spec.title!r}: not drawn with the runs' data: {chart}")
        left, _top, width, _height = chart["box"]
        assert left > sidebar["x"] + sidebar["width"], (spec.title, chart["box"], sidebar)
        assert left + width <= viewport["width"] + 1, (spec.title, chart["box"])
        assert width >= 0.8 * PLOTS_WIDTH_PX, (spec.title, chart["box"])
        assert chart["labels"][1:] == ["A", "B"], chart["labels"]
        a = np.array([v for v in chart["data"][1] if v is not None])
        b = np.array([v for v in chart["data"][2] if v is not None])
        assert a.size > 100 and b.size > 100, spec.title
        # The whole overlap drawn: B began 3.7 s into A's trajectory, both end at 30 s.
        x = chart["data"][0]
        assert x[0] < 3.7 + 0.1 and x[-1] > 29.9, (spec.title, x[0], x[-1])
        if spec is OVERLAY_CHART:
            # B's error is half of A's at every point of the trajectory (made so).
            assert np.max(np.abs(b)) == pytest.approx(0.5 * np.max(np.abs(a)), rel=0.05)
        else:
            # B's reference, shifted by the lag, lies on A's.
            assert np.max(np.abs(a - b)) < 0.05, np.max(np.abs(a - b))
            assert np.ptp(a) == pytest.approx(10.0, abs=0.1)  # 5 sin(0.5 t): -5 .. 5 deg
