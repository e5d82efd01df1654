"""One dashboard, several users, each in their own browser (issue 12: per-browser roles).

A controller with `--auth` (operator op1, viewer view) and a dashboard given the auth directory
without `--user`: each user has a URL of their own. Two headless Chromium pages, one per user,
press the same shared controls; what each may do is decided per browser on the server (and
again by the controller, which sees the real user behind each change):

- the viewer's Apply and Start are refused (told in the viewer's page), nothing changes;
- the operator's Apply changes the controller's configuration, recorded as op1;
- the viewer's E-STOP stops the rig;
- a token that is not one of the users' opens nothing.
"""

from __future__ import annotations

import contextlib
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import (
    CONTROLLER_START_S,
    FIRST_LOAD_S,
    VIEWPORT,
    cutoff_box,
    free_port,
    set_number,
    wait_shown_text,
)
from helpers import answers, spawn, wait_for

from controller.auth import init_auth_dir, new_users
from controller.client import ClientOptions, ControllerClient
from server.dashboard.app import Dashboard, DashboardOptions
from server.dashboard.demo import controller_command, stop_process

pytestmark = pytest.mark.browser
RIG = "usertest"




@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    base = tmp_path_factory.mktemp("users")
    auth = base / "auth"
    init_auth_dir(auth, new_users([("op1", "operator"), ("view", "viewer")]))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = spawn(controller_command(endpoint, RIG, base / "state",
                                    extra=("--auth", str(auth))))
    try:
        opts = ClientOptions(connect=(endpoint,), rig_name=RIG, auth=auth, user="view",
                             client_name="probe", connect_timeout_s=CONTROLLER_START_S)
        with ControllerClient(opts) as probe:
            wait_for(lambda: answers(probe), CONTROLLER_START_S, "the controller did not answer")
            dopts = DashboardOptions(connect=(endpoint,), rig_name=RIG, port=free_port(),
                                     verbose=False, auth=auth, recordings_dir=base / "rec")
            with Dashboard(dopts) as dash:
                yield {"auth": auth, "endpoint": endpoint, "probe": probe, "dash": dash,
                       "recordings": base / "rec"}
    finally:
        stop_process(proc)


@pytest.fixture(scope="module")
def pages(env: dict[str, Any], chromium_browser: Any) -> Iterator[dict[str, Any]]:
    dash: Dashboard = env["dash"]
    with contextlib.ExitStack() as contexts:
        out = {}
        for user in ("op1", "view"):
            # Separate contexts: separate cookie jars, as two people's browsers.
            context = chromium_browser.new_context(viewport=VIEWPORT)
            contexts.callback(context.close)
            page = context.new_page()
            page.goto(dash.url_for(user), wait_until="domcontentloaded",
                      timeout=FIRST_LOAD_S * 1000)
            page.wait_for_selector(".dt-whoami", timeout=FIRST_LOAD_S * 1000)
            page.wait_for_selector(".dt-verdict", timeout=FIRST_LOAD_S * 1000)
            out[user] = page
        yield out


def test_each_browser_is_signed_in_as_its_user(pages: dict[str, Any]) -> None:
    assert "Signed in as op1, operator" in pages["op1"].locator(".dt-whoami").inner_text()
    viewer = pages["view"].locator(".dt-whoami").inner_text()
    assert "Signed in as view, viewer" in viewer and "E-STOP only" in viewer


def test_a_token_of_nobody_opens_nothing(env: dict[str, Any]) -> None:
    dash: Dashboard = env["dash"]
    url = dash.url_for("op1").rsplit("=", 1)[0] + "=" + "x" * 32
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(url, timeout=5)
    assert err.value.code == 401
    assert dash.access.token_of("op1") != dash.access.token_of("view")


def test_the_viewer_cannot_apply_or_start(env: dict[str, Any], pages: dict[str, Any],
                                          artifacts: Path) -> None:
    dash: Dashboard = env["dash"]
    probe: ControllerClient = env["probe"]
    before = probe.get_config()
    refusals = dash.sessions.refusals
    page = pages["view"]
    # A candidate of the viewer's own that differs from the active one (Apply is off for the
    # active configuration itself): the dashboard refuses the viewer's press.
    set_number(page, "Q cut-off (Hz)", round(before.config.q_cutoff_hz * 0.8, 3))
    page.wait_for_function("""() => [...document.querySelectorAll('button')].find(
      b => b.textContent.trim() === 'Apply candidate')?.disabled === false""", timeout=60_000)
    page.get_by_role("button", name="Apply candidate").click()
    page.wait_for_selector("text=view is a viewer", timeout=10_000)
    page.screenshot(path=str(artifacts / "users_1_viewer_refused.png"))
    wait_for(lambda: dash.sessions.refusals >= refusals + 1, 10.0,
             "the viewer's Apply was not refused")
    # Start is a shared control: the viewer's press is refused before viser handles it
    # (server/message_gate.py), and told to the viewer.
    assert dash.messages is not None
    refused = dash.messages.refused
    page.get_by_role("tab", name="Live", exact=True).click()
    page.get_by_role("button", name="Start", exact=True).click()
    page.wait_for_selector("text=Run: view is a viewer", timeout=10_000)
    assert dash.messages.refused == refused + 1
    assert "view is a viewer" not in pages["op1"].content()  # told to the viewer only
    after = probe.get_config()
    assert after.version == before.version and after.config == before.config


def _browser_of(dash: Dashboard, user: str) -> Any:
    """The viser client (a browser's websocket) signed in as `user`."""
    assert dash.server is not None
    return next(c for c in dash.server.get_clients().values()
                if dash.sessions.user_of(c) == user)


def test_the_viewer_cannot_start_or_stop_a_recording(env: dict[str, Any],
                                                     pages: dict[str, Any]) -> None:
    """Refused before viser handles the press (a shared control: server/message_gate.py), told
    to the viewer alone; the panel refuses the same press made on the viewer's behalf too
    (issue 24 item 9)."""
    dash: Dashboard = env["dash"]
    rec = dash.recordings
    assert rec is not None
    refusals = dash.sessions.refusals
    page = pages["view"]
    page.get_by_role("tab", name="Recordings", exact=True).click()
    page.get_by_role("button", name="Record", exact=True).click()
    page.wait_for_selector("text=Record: view is a viewer", timeout=10_000)
    viewer = _browser_of(dash, "view")
    assert rec.press("Record", viewer) is None
    assert rec.press("Stop recording", viewer) is None
    assert dash.sessions.refusals == refusals + 2
    assert rec.recording_to is None
    assert not list(env["recordings"].glob("*.mcap*"))
    assert "view is a viewer" not in pages["op1"].content()  # told to the viewer only


def test_the_whole_loop_tune_is_for_operators_only(env: dict[str, Any],
                                                  pages: dict[str, Any]) -> None:
    """Issue 35 item 3: the guided path's "Tune the whole loop" and its objective are disabled
    in the viewer's page (the message gate refuses a press on a disabled control: see
    tests/test_message_gate.py), on in the operator's; a press made on the viewer's behalf is
    refused by the step itself, told to the viewer alone, and nothing runs."""
    dash: Dashboard = env["dash"]
    view, op = pages["view"], pages["op1"]
    for page in (view, op):
        page.get_by_role("tab", name="Tune", exact=True).click()
    name = "Tune the whole loop"
    view.get_by_role("button", name=name, exact=True).wait_for(timeout=30_000)
    assert view.get_by_role("button", name=name, exact=True).is_disabled()
    assert op.get_by_role("button", name=name, exact=True).is_enabled()
    viewer = _browser_of(dash, "view")
    guide = dash.candidates.guides[viewer.client_id]
    assert guide.tune.button is not None and guide.tune.button.disabled
    assert guide.tune.metric is not None and guide.tune.metric.disabled
    assert "operators only" in guide.tune.state.text
    refusals = dash.sessions.refusals
    assert guide.tune.request(viewer) is False
    view.wait_for_selector("text=tune the whole loop: view is a viewer", timeout=10_000)
    assert dash.sessions.refusals == refusals + 1
    assert guide.tune.state.state == "todo" and guide.tune.last is None
    assert "view is a viewer" not in op.content()  # told to the viewer only
    operator = dash.candidates.guides[_browser_of(dash, "op1").client_id]
    assert operator.tune.button is not None and not operator.tune.button.disabled


def test_a_refused_identification_is_told_to_that_browser_alone(
    env: dict[str, Any], pages: dict[str, Any]
) -> None:
    """The Identify status box is every browser's (the run's state): the viewer's refusal goes
    to the viewer's page, not into the box the operator reads (issue 24 item 9; the press of
    this shared control is refused before viser handles it: server/message_gate.py)."""
    dash: Dashboard = env["dash"]
    assert dash.messages is not None
    refused = dash.messages.refused
    page = pages["view"]
    page.get_by_role("tab", name="Identify", exact=True).first.click()
    page.get_by_role("button", name="Start identification").click()
    page.wait_for_selector("text=Start identification: view is a viewer", timeout=10_000)
    assert dash.messages.refused == refused + 1
    assert "viewer" not in dash.identify.status.content
    op = pages["op1"]
    op.get_by_role("tab", name="Identify", exact=True).first.click()
    op.wait_for_selector(".dt-identify-status", timeout=10_000)
    assert "viewer" not in op.locator(".dt-identify-status").first.inner_text()
    assert "view is a viewer" not in op.content()


def test_the_operator_applies_as_itself(env: dict[str, Any], pages: dict[str, Any],
                                        artifacts: Path) -> None:
    probe: ControllerClient = env["probe"]
    before = probe.get_config()
    page = pages["op1"]
    page.get_by_role("tab", name="Tune", exact=True).click()
    field = cutoff_box(page)
    field.fill("1.0")
    field.press("Enter")
    page.wait_for_selector(".dt-cutoff >> text=1.000 Hz", timeout=15_000)
    page.wait_for_selector(".dt-verdict.dt-accept", timeout=15_000)
    page.get_by_role("button", name="Apply candidate").click()
    wait_shown_text(page, ".dt-apply", "Accepted", 60_000)
    page.screenshot(path=str(artifacts / "users_2_operator_applied.png"))
    after = probe.get_config()
    assert after.version == before.version + 1 and after.config.q_cutoff_hz == 1.0
    last = probe.history(1).entries[-1]
    assert last.version == after.version
    assert "op1" in last.client  # the controller's record names the real user


def test_the_viewer_can_estop(env: dict[str, Any], pages: dict[str, Any]) -> None:
    probe: ControllerClient = env["probe"]
    pages["view"].get_by_role("button", name="E-STOP").click()
    wait_for(lambda: probe.status is not None and probe.status.mode == "estop", 10.0,
          "the viewer's E-STOP did not stop the rig")


def test_the_upload_is_offered_to_the_operator_only(pages: dict[str, Any]) -> None:
    """Issue 31 item 6: the Tune tab's Upload measured responses button is in the operator's
    page, not in the viewer's (built in each operator's own GUI: server/panels/knowledge.py)."""
    for user, shown in (("op1", True), ("view", False)):
        page = pages[user]
        page.get_by_role("tab", name="Tune", exact=True).click()
        button = page.get_by_role("button", name="Upload measured responses (CSV)")
        if shown:
            button.wait_for(state="visible", timeout=30_000)
        else:
            # The Tune tab has drawn (the viewer's own candidate controls), the button not.
            page.get_by_role("button", name="Apply candidate").wait_for(state="visible",
                                                                        timeout=30_000)
            assert not button.is_visible(), "the viewer's page shows the upload button"
