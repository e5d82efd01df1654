"""A viewer's hands off the shared panels (issue 31 item 6): acknowledging the alarms (they
vanished for every browser) and starting or aborting an identification (a viewer's offline run
blocked the operator's, and a viewer could abort a run) are an operator's, checked in the
panels themselves and told to the viewer's browser.

A real controller with `--auth` (operator op1, viewer view), a real dashboard for both users,
two raw websocket clients, one per user's URL (tests/viser_raw.py). A viewer's press of a shared
control is refused before viser handles it (server/message_gate.py); the panels check again
when their callback runs for the viewer's browser, as viser runs it (the callback's event
carries the browser), so a control the gate lets through by mistake changes nothing either.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import answers, free_port, wait_for
from procs import ControllerProcess, start_controller, wait_until
from statuses import status
from viser_raw import RawViser

from controller.auth import init_auth_dir, new_users
from controller.client import ClientOptions, ControllerClient, ControllerUnavailable
from server.dashboard.app import Dashboard, DashboardOptions
from server.panels.identify import IDLE, RUNNING, IdentifySettings
from server.viser_adapter import control_uuid

RIG = "roles"


@pytest.fixture(scope="module")
def dash(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Dashboard]:
    base = tmp_path_factory.mktemp("roles")
    auth = base / "auth"
    init_auth_dir(auth, new_users([("op1", "operator"), ("view", "viewer")]))
    proc = start_controller(base / "state", rig=RIG, extra_args=("--auth", str(auth)))
    try:
        assert wait_until(lambda: _ready(auth, proc), 180.0, poll_s=0.5), proc.log()
        opts = DashboardOptions(connect=(proc.endpoint,), rig_name=RIG, port=free_port(),
                                verbose=False, auth=auth, recordings_dir=base / "rec")
        with Dashboard(opts) as d:
            yield d
    finally:
        proc.stop()


def _ready(auth: Path, proc: ControllerProcess) -> bool:
    assert proc.proc.poll() is None, proc.log()
    opts = ClientOptions(connect=(proc.endpoint,), rig_name=RIG, auth=auth, user="view",
                         client_name="probe", query_timeout_s=2.0, connect_timeout_s=10.0)
    try:
        with ControllerClient(opts) as c:
            return answers(c)
    except ControllerUnavailable:
        return False


def _connect(dash: Dashboard, user: str) -> tuple[RawViser, Any]:
    """A raw client on `user`'s URL and viser's handle of its browser."""
    assert dash.server is not None
    before = set(dash.server.get_clients())
    url = dash.url_for(user)
    raw = RawViser(url.replace("http://", "ws://"), origin=url.split("/?")[0])
    found: list[Any] = []

    def signed_in() -> bool:
        for cid, browser in dash.server.get_clients().items():
            if cid not in before and dash.sessions.user_of(browser) == user:
                found.append(browser)
                return True
        return False

    wait_for(signed_in, 20.0, f"{user}'s browser never signed in")
    return raw, found[0]


@pytest.fixture(scope="module")
def browsers(dash: Dashboard) -> Iterator[dict[str, tuple[RawViser, Any]]]:
    out = {user: _connect(dash, user) for user in ("op1", "view")}
    yield out
    for raw, _browser in out.values():
        raw.ws.close()


def test_a_viewer_does_not_acknowledge_the_alarms(
        dash: Dashboard, browsers: dict[str, tuple[RawViser, Any]]) -> None:
    live = dash.live
    assert live is not None and dash.messages is not None
    live.observe_alarms(status(mode="estop", estop_seq=7))
    assert [a.kind for a in live.alarm_board.alarms] == ["estop"] and live.ack_button.visible
    view_raw, viewer = browsers["view"]
    gate_refused, panel_refused = dash.messages.refused, dash.sessions.refusals
    # The attack: the viewer presses Acknowledge alarms (refused by the message gate)...
    view_raw.update(control_uuid(live.ack_button), {"value": True})
    wait_for(lambda: dash.messages is not None and dash.messages.refused > gate_refused, 20.0,
             "the viewer's press was not refused")
    # ... and its callback, as viser would run it for the viewer's browser, refuses too.
    assert live.acknowledge_alarms(viewer) is False
    assert dash.sessions.refusals == panel_refused + 1
    assert [a.kind for a in live.alarm_board.alarms] == ["estop"]  # still there for everyone
    assert live.ack_button.visible
    # The operator's press clears them.
    op_raw, _operator = browsers["op1"]
    op_raw.update(control_uuid(live.ack_button), {"value": True})
    wait_for(lambda: not live.alarm_board.alarms, 20.0, "the operator's press cleared nothing")
    wait_for(lambda: not live.ack_button.visible, 20.0, "the button stayed")


def test_a_viewer_neither_starts_nor_aborts_an_identification(
        dash: Dashboard, browsers: dict[str, tuple[RawViser, Any]]) -> None:
    panel = dash.identify
    assert panel is not None
    offline = IdentifySettings(pace=1.0)  # offline, paced at real time: it runs until aborted
    _view_raw, viewer = browsers["view"]
    _op_raw, operator = browsers["op1"]
    refusals = dash.sessions.refusals
    # A viewer's offline run would hold the one run slot: refused.
    assert panel.start(offline, viewer) is False
    assert panel.state == IDLE and dash.sessions.refusals == refusals + 1
    assert panel.start(offline, operator) is True
    try:
        assert panel.state == RUNNING
        assert panel.abort(viewer) is False  # the operator's run goes on
        assert panel.state == RUNNING and dash.sessions.refusals == refusals + 2
        assert panel.start(dataclasses.replace(offline), viewer) is False
    finally:
        assert panel.abort(operator) is True
    assert panel.wait_done(60.0), "the aborted run did not end"
    assert panel.state != RUNNING


def test_without_users_any_browser_may(tmp_path: Path) -> None:
    """One identity (no users): every browser may acknowledge, as before."""
    opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{free_port()}",), rig_name="anyone",
                            port=free_port(), verbose=False, query_timeout_s=0.5,
                            recordings_dir=tmp_path / "rec")
    with Dashboard(opts) as d:
        assert d.live is not None
        d.live.observe_alarms(status(mode="estop", estop_seq=3))
        assert d.live.acknowledge_alarms(None) is True and not d.live.alarm_board.alarms


def _upload_buttons(raw: RawViser) -> list[str]:
    return [m["uuid"] for m in raw.messages if m.get("type") == "GuiUploadButtonMessage"]


def test_the_upload_is_offered_to_operators_only(
        dash: Dashboard, browsers: dict[str, tuple[RawViser, Any]]) -> None:
    """The operator's page gets an Upload measured responses button of its own, the viewer's
    none; the viewer's upload, sent anyway to the operator's button, is refused at its start
    and nothing is buffered."""
    assert dash.knowledge is not None and dash.messages is not None
    view_raw, viewer = browsers["view"]
    op_raw, operator = browsers["op1"]
    mine = dash.knowledge.upload_of(operator)
    assert mine is not None and dash.knowledge.upload_of(viewer) is None
    uuid = control_uuid(mine)
    op_raw.pump_until(lambda: uuid in _upload_buttons(op_raw), 20.0,
                      "the operator's page got no upload button")
    refused = dash.messages.refused
    view_raw.send({"type": "FileTransferStartUpload", "source_component_uuid": uuid,
                   "transfer_uuid": "viewer-upload", "filename": "x.csv",
                   "mime_type": "text/csv", "part_count": 1, "size_bytes": 10})
    view_raw.send({"type": "FileTransferPart", "source_component_uuid": uuid,
                   "transfer_uuid": "viewer-upload", "part_index": 0, "content": b"0123456789"})
    wait_for(lambda: dash.messages is not None and dash.messages.refused >= refused + 2, 20.0,
             "the viewer's upload was not refused")
    assert "viewer-upload" not in operator.gui._current_file_upload_states
    assert "viewer-upload" not in viewer.gui._current_file_upload_states
    assert _upload_buttons(view_raw) == []  # (what it was sent by now)
