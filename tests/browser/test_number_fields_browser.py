"""Every number a user types is read as typed or refused by name (issue 33): the gains' and the
Identify panel's fields behave as the Q cut-off's does. Typed into the page as a user does: a
value out of range, a word, an empty field are refused with a message naming the field and its
range (the box keeps what was typed, the candidate is invalid and Apply is off, nothing falls
back to an old value or a clamped one); exponent notation is read ("1e1" is 10, not 11). The
labels name their fields (get_by_label finds the Q cut-off's and the gains' text fields).
"""

from __future__ import annotations

from typing import Any

import pytest
from conftest import field_box, only_panel, set_number, wait_shown_text
from helpers import wait_for

from controller.core.errors import ConfigError
from server.dashboard.app import Dashboard

pytestmark = pytest.mark.browser

SLOW_S = 60.0

#: JS: the Apply button is disabled.
APPLY_OFF_JS = """() => [...document.querySelectorAll('button')].find(
  b => b.textContent.trim() === 'Apply candidate')?.disabled === true"""


def _refused(dashboard: Dashboard, field: str) -> bool:
    try:
        only_panel(dashboard).candidate()
    except ConfigError as exc:
        return exc.field == field
    return False


@pytest.mark.parametrize("typed", ["-1", "5", "abc", ""])
def test_a_gain_out_of_range_or_not_a_number_is_refused_by_name(
        page: Any, dashboard: Dashboard, typed: str) -> None:
    """Cv Kp "-1" (was clamped to 0.05), "5" (clamped to 3), "abc" and "" (the box went blank
    and the candidate kept its old gain): each refused, naming Cv Kp and its range; the box
    shows what was typed; the verdict says the candidate is invalid; Apply is off. A valid
    value then clears it."""
    page.wait_for_selector(".dt-verdict", timeout=SLOW_S * 1000)
    set_number(page, "Cv Kp", typed)
    want = f"Cv Kp: {typed!r} is not a number from 0.05 to 3"
    wait_shown_text(page, ".dt-gain-invalid", want, SLOW_S * 1000)
    assert field_box(page, "Cv Kp").input_value() == typed  # not clamped, not blanked
    wait_shown_text(page, ".dt-verdict.dt-reject", "Invalid candidate", SLOW_S * 1000)
    assert "cv_kp" in page.locator(".dt-verdict").first.inner_text()
    page.wait_for_function(APPLY_OFF_JS, timeout=SLOW_S * 1000)
    assert _refused(dashboard, "cv_kp")
    set_number(page, "Cv Kp", "1.2")
    wait_for(lambda: not _refused(dashboard, "cv_kp")
             and only_panel(dashboard).candidate().cv_kp == 1.2, SLOW_S,
             "Cv Kp 1.2 was not taken")
    page.wait_for_function("() => !document.querySelector('.dt-gain-invalid')",
                           timeout=SLOW_S * 1000)


def test_exponent_notation_is_read_and_the_slider_follows(
        page: Any, dashboard: Dashboard) -> None:
    """Cv Ki "1e1" is 10 (the number box dropped the "e": 11); "2.5e-1" for Pos Ki is 0.25;
    each slider follows its field; the labels name their fields (get_by_label)."""
    page.wait_for_selector(".dt-verdict", timeout=SLOW_S * 1000)
    set_number(page, "Cv Ki (1/s)", "1e1")
    set_number(page, "Pos Ki (1/s)", "2.5e-1")
    t = only_panel(dashboard)
    wait_for(lambda: (t.candidate().cv_ki_per_s, t.candidate().pos_ki_per_s) == (10.0, 0.25),
             SLOW_S, "the exponents were not read")
    assert (t.cv_ki.value, t.pos_ki.value) == (10.0, 0.25)  # the sliders follow
    assert page.get_by_label("Cv Ki (1/s)", exact=True).input_value() == "1e1"
    cutoff = page.get_by_label("Q cut-off (Hz)", exact=True)
    assert float(cutoff.input_value()) == pytest.approx(t.candidate().q_cutoff_hz, rel=1e-5)
    t.revert()
    assert t.wait_idle(SLOW_S)


def test_an_identify_field_is_read_as_typed_or_refused_by_name(
        page: Any, dashboard: Dashboard) -> None:
    """Identify's Amplitude "1e9" (became 19, and the confirmation offered 19.0 deg/s) is
    refused naming the field and its range, and Start starts nothing; "2e1" is 20 (the
    confirmation says "20 deg/s asked"); Positions "2.5" is no whole number."""
    page.wait_for_selector("text=E-STOP", timeout=SLOW_S * 1000)
    tabs = page.get_by_role("tab", name="Identify")
    tabs.nth(0).click(timeout=SLOW_S * 1000)
    tabs.nth(1).click(timeout=SLOW_S * 1000)
    ident = dashboard.identify
    assert ident is not None
    set_number(page, "Amplitude (deg/s)", "1e9")
    wait_shown_text(page, ".dt-identify-field-invalid",
                    "Amplitude (deg/s): '1e9' is not a number from 0.1 to 100", SLOW_S * 1000)
    assert field_box(page, "Amplitude (deg/s)").input_value() == "1e9"
    with pytest.raises(ConfigError, match="Amplitude"):
        ident.settings()
    page.get_by_role("button", name="Start identification").click(timeout=SLOW_S * 1000)
    page.wait_for_selector("text=/not started: .*Amplitude/", timeout=SLOW_S * 1000)
    assert page.locator(".dt-confirm").count() == 0 and ident.state != "running"
    set_number(page, "Positions", "2.5")
    wait_shown_text(page, ".dt-identify-field-invalid",
                    "Positions: '2.5' is not a whole number from 1 to 36", SLOW_S * 1000)
    set_number(page, "Positions", "1")
    set_number(page, "Amplitude (deg/s)", "2e1")
    page.wait_for_function("() => !document.querySelector('.dt-identify-field-invalid')",
                           timeout=SLOW_S * 1000)
    wait_for(lambda: ident.settings().values["amplitude_deg_s"] == 20.0, SLOW_S,
             "Amplitude 2e1 was not read as 20")
    page.get_by_role("button", name="Start identification").click(timeout=SLOW_S * 1000)
    wait_shown_text(page, ".dt-confirm", "20 deg/s asked", SLOW_S * 1000)
    page.get_by_role("button", name="Cancel").click(timeout=SLOW_S * 1000)
    assert ident.state != "running"
    page.get_by_role("tab", name="Tune").click(timeout=SLOW_S * 1000)


def test_reloads_do_not_pile_up_the_page_id_in_the_address_bar(
        page: Any, dashboard: Dashboard) -> None:
    """viser writes the websocket's URL into the address bar unescaped; each reload added one
    more dt_page (and token) to it. After two reloads: one dt_page, one dt_slot. (Last: the
    reload gives the page a new candidate panel.)"""
    for _ in range(2):
        before = set(dashboard.server.get_clients())
        page.reload(wait_until="domcontentloaded", timeout=SLOW_S * 2000)
        wait_for(lambda b=before: set(dashboard.server.get_clients()) - b, SLOW_S * 2,
                 "the reloaded page never connected")
        page.wait_for_function("() => location.search.includes('dt_page=')",
                               timeout=SLOW_S * 1000)
    url = page.url
    assert url.count("dt_page=") == 1 and url.count("dt_slot=") == 1, url
