"""The Identify panel in headless Chromium: open the tab, set a short run (multisine, one
position) on the controller (the excitation runs in its loop), start it, wait for completion on
the page, check the charts and the fit, use the fit as the nominal model (the Tune verdict
re-evaluates; nothing is applied). Screenshots go to test-artifacts/identify_*.png.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
from conftest import FINITE_JS, only_panel, set_number

from controller.client import ControllerClient
from server.dashboard.app import Dashboard

pytestmark = pytest.mark.browser

def _input(page: Any, label: str) -> Any:
    fid = page.locator("label", has_text=label).first.get_attribute("for")
    el = page.locator(f"[id='{fid}']")
    return el if el.evaluate("e => e.tagName") == "INPUT" else el.locator("input").first


def _set_number(page: Any, label: str, value: float) -> None:
    set_number(page, label, value)  # a text field since issue 33 (the number box misread)


def _choose(page: Any, label: str, option: str) -> None:
    _input(page, label).click()
    page.get_by_role("option", name=option, exact=True).click()


def test_identify_short_run_in_the_browser(
    page: Any, dashboard: Dashboard, probe: ControllerClient, artifacts: Path
) -> None:
    page.wait_for_selector("text=E-STOP", timeout=20_000)
    tabs = page.get_by_role("tab", name="Identify")
    tabs.nth(0).click()
    tabs.nth(1).click()
    page.wait_for_selector(".dt-identify-note", timeout=10_000)
    assert "offline on the simulated rig" in page.locator(".dt-identify-note").inner_text()
    assert _input(page, "Run on").input_value() == "controller"
    _choose(page, "Signal", "multisine")
    _set_number(page, "f min (Hz)", 1.0)
    _set_number(page, "f max (Hz)", 8.0)
    _set_number(page, "Points per decade", 4)
    _set_number(page, "Positions", 1)
    page.wait_for_timeout(300)  # the values reach the server
    ident = dashboard.identify
    assert ident is not None
    s = ident.settings()
    v = s.values
    assert (s.where, v["signal"], v["f_min_hz"], v["f_max_hz"], v["positions"]) == (
        "controller", "multisine", 1.0, 8.0, 1)
    before = probe.get_config()
    page.get_by_role("button", name="Start identification").click()
    page.wait_for_selector("text=Start the identification?", timeout=10_000)  # the rig moves
    asked = page.locator(".dt-confirm").last.inner_text()
    assert "The rig moves" in asked
    # The run as the progress text will name it (issue 33: the confirmation said the asked
    # 10 deg/s while the run moved at 3), and its planned duration.
    said = re.search(r"(multisine [0-9.]+-[0-9.]+ Hz, [0-9.]+ deg/s)", asked)
    assert said is not None and re.search(r"about \d+ s", asked), asked
    assert probe.get_config().version == before.version and ident.state != "running"
    page.get_by_role("button", name="Start identification").last.click()
    page.wait_for_selector(".dt-identify-status.dt-id-running", timeout=15_000)
    page.wait_for_function(
        "(t) => document.querySelector('.dt-identify-status').innerText.includes(t)",
        arg=said[1], timeout=120_000)  # the progress names the same band and amplitude
    # (after the move to the first position: 30 s ran out at load ~12 in a clean-clone run)
    page.wait_for_function(
        "() => /\\d+ %/.test(document.querySelector('.dt-identify-status').innerText)",
        timeout=10_000)  # progress from the controller's status
    assert "on the controller" in page.locator(".dt-identify-status").inner_text()
    page.screenshot(path=str(artifacts / "identify_1_running.png"))
    page.wait_for_selector(".dt-identify-status.dt-id-done", timeout=60_000)
    page.wait_for_selector(".dt-id-fit", timeout=15_000)
    page.wait_for_function(f"() => ({FINITE_JS})('pos 1 |G|') >= 4", timeout=10_000)
    page.wait_for_function(f"() => ({FINITE_JS})('fit Mn Pn') >= 50", timeout=10_000)
    page.screenshot(path=str(artifacts / "identify_2_done.png"))
    fit = page.locator(".dt-id-fit").inner_text()
    cut = page.locator(".dt-id-cutoff").inner_text()
    assert "Hz" in fit and "±" in fit
    assert "Q31" in cut and "Q20" in cut
    assert page.evaluate(f"() => ({FINITE_JS})('pos 1 coherence')") >= 4

    # Use as nominal: the candidate changes, the controller's config does not.
    page.get_by_role("button", name="Use as nominal model").click()
    page.wait_for_selector(".dt-id-used", timeout=15_000)
    t = only_panel(dashboard)  # this browser's candidate
    assert t.wait_idle(5.0)
    view = ident.view  # what the controller reported
    assert view is not None and view.nominal is not None
    assert t.candidate().nominal == view.nominal
    page.get_by_role("tab", name="Tune").click()
    page.wait_for_selector(".dt-verdict", timeout=15_000)
    page.wait_for_selector(".dt-nominal-fitted", timeout=15_000)
    page.screenshot(path=str(artifacts / "identify_3_used_as_nominal.png"))
    after = probe.get_config()
    assert after.version == before.version and after.config == before.config
