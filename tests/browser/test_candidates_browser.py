"""Per-browser candidates (issue 13 item 4), in two headless Chromium pages of one dashboard.

Each browser edits a candidate of its own; the active configuration and the live data are
shared. A candidate made against a version that someone else has since replaced says so, and
its Apply carries that version: the controller refuses it (compare-and-set) and the active
configuration stays. What is checked is what each page shows, and what the controller runs
(through a separate Zenoh client).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from conftest import (
    FINITE_JS,
    FIRST_LOAD_S,
    cutoff_box,
    open_when_ready,
    set_number,
    wait_shown_text,
)
from helpers import wait_for

from controller.client import ControllerClient
from server.dashboard.app import Dashboard

pytestmark = pytest.mark.browser




def _stale(page: Any) -> str:
    return str(page.locator(".dt-stale").first.inner_text()).strip()


def _panels(dashboard: Dashboard, first: Any, second: Any) -> tuple[Any, Any]:
    """The candidate panels of two pages, told apart by the cut-off each shows."""
    shown = {id(p): float(cutoff_box(p).input_value()) for p in (first, second)}
    panels = list(dashboard.panels.values())
    assert len(panels) == 2
    a = [t for t in panels if t.cutoff_hz == shown[id(first)]]
    b = [t for t in panels if t.cutoff_hz == shown[id(second)]]
    assert len(a) == len(b) == 1 and a[0] is not b[0], (shown, [t.cutoff_hz for t in panels])
    return a[0], b[0]


def test_each_browser_edits_its_own_candidate(
    page: Any, dashboard: Dashboard, probe: ControllerClient, artifacts: Path
) -> None:
    other = page.context.browser.new_context(viewport={"width": 1600, "height": 1000}).new_page()
    try:
        open_when_ready(other, dashboard, FIRST_LOAD_S)
        wait_for(lambda: len(dashboard.panels) == 2, 10.0, "the second browser has no candidate")
        start = probe.get_config()
        hz0 = start.config.q_cutoff_hz
        assert hz0 != 0.8
        other.wait_for_selector(f".dt-cutoff >> text={hz0:.3f} Hz", timeout=15_000)

        # A types 0.8 Hz: A's candidate changes, B's does not.
        set_number(page, "Q cut-off (Hz)", 0.8)
        page.wait_for_selector(".dt-cutoff >> text=0.800 Hz", timeout=15_000)
        page.wait_for_selector(".dt-diff >> text=q_cutoff_hz", timeout=15_000)
        assert float(cutoff_box(other).input_value()) == hz0
        assert "same as active" in other.locator(".dt-diff").first.inner_text()

        # A applies: the controller runs 0.8 Hz; B's candidate is now based on an old version.
        page.wait_for_selector(".dt-verdict.dt-accept", timeout=15_000)
        page.get_by_role("button", name="Apply candidate").click()
        wait_shown_text(page, ".dt-apply", "Accepted", 60_000)
        v2 = probe.get_config()
        assert v2.version == start.version + 1 and v2.config.q_cutoff_hz == 0.8
        other.wait_for_selector(f".dt-stale >> text=Based on v{start.version}", timeout=15_000)
        assert f"now v{v2.version}" in _stale(other)
        assert _stale(page) == ""  # A's own apply: A is up to date
        assert float(cutoff_box(other).input_value()) == hz0  # B's candidate is still its own
        other.screenshot(path=str(artifacts / "candidates_1_stale.png"))

        # B's candidate is based on an old version: its Apply is disabled (issue 22: it would
        # be refused) ...
        set_number(other, "Q cut-off (Hz)", 0.6)
        other.wait_for_selector(".dt-cutoff >> text=0.600 Hz", timeout=15_000)
        other.wait_for_selector(".dt-verdict.dt-accept", timeout=15_000)
        other.wait_for_selector(".dt-computing-on", state="detached", timeout=30_000)
        assert other.get_by_role("button", name="Apply candidate").is_disabled()
        # ... and sent anyway (what a forged press does), it carries the version it was made
        # against: refused, A's config stays.
        _, b_panel = _panels(dashboard, page, other)
        b_panel.apply()
        other.wait_for_selector(".dt-apply-rejected", timeout=15_000)
        refusal = other.locator(".dt-apply-rejected").first.inner_text()
        assert f"based on version {start.version}" in refusal, refusal
        after = probe.get_config()
        assert after.version == v2.version and after.config == v2.config
        other.screenshot(path=str(artifacts / "candidates_2_refused.png"))

        # Revert: B's candidate is the active v2, nothing stale.
        other.get_by_role("button", name="Revert to active").click()
        other.wait_for_selector(".dt-cutoff >> text=0.800 Hz", timeout=15_000)
        wait_for(lambda: _stale(other) == "", 10.0, "the stale note stayed after Revert")
        assert float(cutoff_box(other).input_value()) == 0.8

        # Suggest in B: the search's curve is drawn in B and its result is B's candidate;
        # A's candidate and the controller's configuration stay.
        set_number(page, "Q cut-off (Hz)", 0.7)  # A's and B's candidates differ
        page.wait_for_selector(".dt-cutoff >> text=0.700 Hz", timeout=15_000)
        a_panel, b_panel = _panels(dashboard, page, other)
        a_before = a_panel.candidate()
        other.get_by_role("button", name="Suggest Q cut-off").click()
        other.wait_for_selector(".dt-suggest-done", timeout=120_000)
        assert b_panel.wait_idle(10.0)
        res = b_panel.suggest.last
        assert res is not None
        want = "DOB off" if not res.dob_helps else f"{res.best.q_cutoff_hz:.3g} Hz"
        assert want in other.locator(".dt-suggest").first.inner_text()
        # The search's chart is drawn in the Bode tab's Suggest sub-tab, mounted while shown.
        other.get_by_role("tab", name="Bode", exact=True).click()
        other.get_by_role("tab", name="Suggest", exact=True).click()
        other.wait_for_function(f"() => ({FINITE_JS})('Q31 score (deg)') >= 4", timeout=60_000)
        assert b_panel.candidate().dob_on == res.dob_helps
        assert a_panel.candidate() == a_before
        assert probe.get_config().version == v2.version
        other.screenshot(path=str(artifacts / "candidates_3_suggest.png"))
    finally:
        other.context.close()
    wait_for(lambda: len(dashboard.panels) == 1, 15.0, "the closed browser's candidate stayed")
