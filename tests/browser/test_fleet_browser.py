"""The Fleet tab in headless Chromium (issue 16): a router with two simulated rigs
(`dobtune demo --rigs 2`'s processes) and a dashboard with the fleet overview. What a user
sees: a row per rig with its state and a live error trace that moves; E-STOP of one rig from
the overview stops that rig (its row says so), the other runs on.
"""

from __future__ import annotations

import contextlib
import re
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import CONTROLLER_START_S, FIRST_LOAD_S, VIEWPORT, free_port
from helpers import wait_for

from server.dashboard.app import Dashboard, DashboardOptions
from server.dashboard.demo import DemoOptions, fleet_processes

pytestmark = pytest.mark.browser

#: Each step's wait on the page (conditions, not sleeps): generous for a loaded machine.
WAIT_MS = 60_000
ROWS_JS = """() => Array.from(document.querySelectorAll('.dt-fleet-row')).map(r => [
  r.dataset.rig, r.querySelector('.dt-fleet-mode').innerText,
  r.querySelector('.dt-spark')?.getAttribute('points') || ''])"""


def _free_run(n: int) -> int:
    """A port p with p .. p+n free."""
    while True:
        p = free_port()
        if p + n >= 65000:
            continue
        ok = True
        for i in range(1, n + 1):
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", p + i))
                except OSError:
                    ok = False
                    break
        if ok:
            return p




@pytest.fixture(scope="module")
def fleet() -> Iterator[Dashboard]:
    base = _free_run(2)
    with tempfile.TemporaryDirectory() as root, fleet_processes(
            DemoOptions(zenoh_port=base, rigs=2, log_level="warning"), Path(root)):
        opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{base}",), rig_name="rig1",
                                port=free_port(), verbose=False, fleet=True)
        with Dashboard(opts) as dash:
            mon = dash._fleet_monitor
            assert mon is not None
            wait_for(lambda: [(r.rig, r.mode) for r in mon.rows()]
                  == [("rig1", "running"), ("rig2", "running")],
                  CONTROLLER_START_S, "the two rigs did not come up")
            yield dash


def test_the_fleet_tab_shows_every_rig_and_stops_one(fleet: Dashboard, artifacts: Path,
                                                     chromium_browser: Any) -> None:
    with contextlib.closing(chromium_browser.new_context(viewport=VIEWPORT)) as context:
        page = context.new_page()
        # Clicks wait for a stable element: at load ~12 the page drew too few frames for the
        # default 30 s (a clean-clone run with two busy loops). Waits are on conditions.
        page.set_default_timeout(WAIT_MS)
        page.goto(fleet.url, wait_until="domcontentloaded", timeout=FIRST_LOAD_S * 1000)
        page.wait_for_selector(".dt-banner", timeout=FIRST_LOAD_S * 1000)
        page.get_by_role("tab", name="Fleet").click()
        page.wait_for_function(f"() => ({ROWS_JS})().length === 2", timeout=WAIT_MS)
        rows = page.evaluate(ROWS_JS)
        assert [(r[0], r[1]) for r in rows] == [("rig1", "running"), ("rig2", "running")]
        assert all(r[2].count(",") > 100 for r in rows)  # a trace of >100 points each
        # The traces move (what is drawn changes, not only what was sent).
        page.wait_for_function(
            f"(a) => JSON.stringify(({ROWS_JS})()) !== JSON.stringify(a)", arg=rows,
            timeout=WAIT_MS)
        page.screenshot(path=str(artifacts / "fleet_1_overview.png"))
        # Choose rig1 as a user does (the default is whichever rig appeared first).
        label = page.locator("label").filter(has_text=re.compile(r"^Rig$")).first
        box = page.locator(f"[id='{label.get_attribute('for')}']")
        (box if box.evaluate("e => e.tagName") == "INPUT" else box.locator("input")).first \
            .click()
        page.get_by_role("option", name="rig1", exact=True).click()
        panel = fleet.fleet
        assert panel is not None
        wait_for(lambda: str(panel.pick.value) == "rig1", WAIT_MS / 1000,
                 "the choice never arrived")
        page.get_by_role("button", name="E-STOP this rig").click()
        page.wait_for_function(
            f"() => ({ROWS_JS})().map(r => r[1]).join() === 'estop,running'",
            timeout=WAIT_MS)
        page.wait_for_selector(".dt-fleet-result >> text=E-STOP sent to rig1",
                               timeout=WAIT_MS)
        page.screenshot(path=str(artifacts / "fleet_2_estop_one.png"))
