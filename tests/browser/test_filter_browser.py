"""The speed-command filter in the candidate's controls (issue 35 item 3): a user chooses a
notch, types its centre, and the gate's verdict changes (a notch at 12 Hz, near the speed
loop's 6.9 Hz crossover, costs phase there: caution on the simulated rig's knowledge); the
candidate diff names the filter; a centre at or above 0.45 x the loop rate or a word is
refused naming `command_filter.notch_hz` (the box keeps what was typed, Apply is off), never
clamped; a notch far above the crossover is accepted; off again is the active configuration."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from conftest import field_box, only_panel, set_number, wait_shown_text
from helpers import wait_for

from controller.core.errors import ConfigError
from controller.gate.verdict import judge
from server.dashboard.app import Dashboard

pytestmark = pytest.mark.browser

SLOW_S = 60.0
APPLY_OFF_JS = """() => [...document.querySelectorAll('button')].find(
  b => b.textContent.trim() === 'Apply candidate')?.disabled === true"""


def _pick(page: Any, label: str, name: str) -> None:
    """Choose `name` in the dropdown labelled `label`, as a user does: open it, click it."""
    page.get_by_label(label, exact=True).click()
    page.get_by_role("option", name=name, exact=True).click()


def _pointer_off_the_fields(page: Any) -> None:
    """The pointer onto the 3-D view: the last field typed in keeps its hover hint on screen
    otherwise, over the field above it (the Notch (Hz) box in the screenshots)."""
    page.mouse.move(470, 900)


def _refused(dashboard: Dashboard, field: str) -> str:
    """The refusal's text when the candidate is refused naming `field` ("" : it is not)."""
    try:
        only_panel(dashboard).candidate()
    except ConfigError as exc:
        return str(exc) if exc.field == field else ""
    return ""


def test_a_notch_changes_the_verdict_and_a_bad_centre_is_refused_by_name(
        page: Any, dashboard: Dashboard, artifacts: Path) -> None:
    t = only_panel(dashboard)
    page.wait_for_selector(".dt-verdict.dt-accept", timeout=SLOW_S * 1000)
    assert t.candidate().command_filter.kind == "off"
    assert not page.get_by_label("Notch (Hz)", exact=True).is_visible()
    _pick(page, "Speed-command filter", "notch")
    page.get_by_label("Notch (Hz)", exact=True).wait_for(state="visible",
                                                          timeout=SLOW_S * 1000)
    assert not page.get_by_label("Low-pass (Hz)", exact=True).is_visible()
    set_number(page, "Notch (Hz)", "12")
    wait_for(lambda: not _refused(dashboard, "command_filter.notch_hz")
             and t.candidate().command_filter.notch_hz == 12.0, SLOW_S,
             "the notch at 12 Hz was not taken")
    cand = t.candidate()
    assert cand.command_filter.kind == "notch"
    # the page's verdict is the gate's on the same knowledge: caution, the speed loop's
    # margins moved by the notch's phase lag
    want = judge(cand, dashboard.engine.plant).verdict
    assert want == "caution"
    wait_shown_text(page, ".dt-verdict.dt-caution", "Verdict", SLOW_S * 1000)
    wait_shown_text(page, ".dt-diff", "speed-command filter: off", SLOW_S * 1000)
    wait_shown_text(page, ".dt-diff", "notch at 12 Hz", SLOW_S * 1000)
    wait_shown_text(page, ".dt-decide.dt-decide-caution", "Verdict: CAUTION", SLOW_S * 1000)
    _pointer_off_the_fields(page)
    page.screenshot(path=str(artifacts / "filter_notch_12hz_caution.png"))
    # at or above 0.45 x the loop rate (450 Hz at 1 kHz): refused by name, not clamped
    set_number(page, "Notch (Hz)", "600")
    wait_shown_text(page, ".dt-verdict.dt-reject", "Invalid candidate", SLOW_S * 1000)
    wait_shown_text(page, ".dt-verdict", "command_filter.notch_hz", SLOW_S * 1000)
    assert "450" in _refused(dashboard, "command_filter.notch_hz")
    assert field_box(page, "Notch (Hz)").input_value() == "600"
    page.wait_for_function(APPLY_OFF_JS, timeout=SLOW_S * 1000)
    # The Decide view's verdict is not the previous candidate's (it stood there, CAUTION,
    # beside "Invalid candidate"): no verdict, said so.
    wait_shown_text(page, ".dt-decide.dt-decide-invalid", "No verdict: the candidate is invalid",
                    SLOW_S * 1000)
    assert page.locator(".dt-decide-caution").count() == 0
    _pointer_off_the_fields(page)
    page.screenshot(path=str(artifacts / "filter_notch_refused.png"))
    set_number(page, "Notch (Hz)", "abc")
    wait_for(lambda: "'abc' is not a number" in _refused(dashboard, "command_filter.notch_hz"),
             SLOW_S, "'abc' was not refused by name")
    wait_shown_text(page, ".dt-verdict", "command_filter.notch_hz: 'abc' is not a number",
                    SLOW_S * 1000)
    # far above the crossover: accepted
    set_number(page, "Notch (Hz)", "100")
    wait_shown_text(page, ".dt-verdict.dt-accept", "Verdict", SLOW_S * 1000)
    wait_shown_text(page, ".dt-decide.dt-decide-accept", "Verdict: accept", SLOW_S * 1000)
    assert t.candidate().command_filter.notch_hz == 100.0
    # off again: the active configuration
    _pick(page, "Speed-command filter", "off")
    wait_for(lambda: t.candidate() == t.active, SLOW_S, "off was not the active filter")
    wait_shown_text(page, ".dt-diff", "same as", SLOW_S * 1000)
    t.revert()
    assert t.wait_idle(SLOW_S)
