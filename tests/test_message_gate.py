"""Every message a browser sends is judged before viser handles it (server/message_gate.py): the
attacks of issue 31 item 5 from a raw websocket client against a real dashboard (no controller
needed; one identity: every browser may change the rig, so what is refused here is refused for
everyone). The viewer's attacks, with real users: tests/integration/test_dashboard_messages.py.

Each attack is followed by a harmless message whose effect is awaited: viser judges and
handles one connection's messages in order, so when it shows, the attack was judged before."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from typing import Any

import pytest
from helpers import free_port, wait_for
from viser_raw import RawViser, connected

from server.dashboard.app import Dashboard, DashboardOptions
from server.message_gate import LOG_EVERY_S
from server.viser_adapter import control_uuid


@pytest.fixture(scope="module")
def dash() -> Iterator[Dashboard]:
    opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{free_port()}",), rig_name="msgs",
                            port=free_port(), verbose=False, query_timeout_s=0.5)
    with Dashboard(opts) as d:
        yield d


@pytest.fixture
def raw(dash: Dashboard) -> Iterator[RawViser]:
    with connected(dash) as c:
        yield c


def _window(dash: Dashboard) -> Any:
    assert dash.live is not None
    return dash.live.window_s


def _then_window(dash: Dashboard, c: RawViser, value: float) -> None:
    """A valid change of the shared Window slider, awaited: what was sent before it has been
    judged."""
    c.update(control_uuid(_window(dash)), {"value": value})
    wait_for(lambda: _window(dash).value == value, 20.0, f"Window never became {value}")


def test_only_a_value_may_change_not_a_controls_state(dash: Dashboard, raw: RawViser) -> None:
    """One message removed the E-STOP's callback for every browser (`update_cb`), another
    marked Reset fault removed (`removed: true`): refused, the controls keep working."""
    assert dash.live is not None and dash.messages is not None
    estop, run = dash.live.estop_button, dash.live.run_buttons
    refused = dash.messages.refused
    attacks = [(estop, {"removed": True}), (estop, {"update_cb": []}),
               (run, {"removed": True}), (run, {"disabled": True, "value": "Start"}),
               (estop, {"value": True, "visible": False}), (run, {"options": ["x"]})]
    for handle, updates in attacks:
        raw.update(control_uuid(handle), updates)
    _then_window(dash, raw, 11.0)
    assert dash.messages.refused == refused + len(attacks)
    assert not estop._impl.removed and not run._impl.removed  # viser's own state
    assert estop._impl.update_cb and run._impl.update_cb
    assert estop.visible and not run.disabled and tuple(run.options) == (
        "Start", "Stop", "Reset fault")
    pressed: list[int] = []
    estop.on_click(lambda e: pressed.append(e.client_id))
    raw.update(control_uuid(estop), {"value": True})
    wait_for(lambda: pressed, 20.0, "the E-STOP's press reached no callback")


@pytest.mark.parametrize("value", [1e9, -1.0, 1.5, math.nan, math.inf, "10", True, None, [10]])
def test_a_number_outside_its_range_or_not_a_number_is_refused(
    dash: Dashboard, raw: RawViser, value: Any
) -> None:
    assert dash.messages is not None
    refused = dash.messages.refused
    _then_window(dash, raw, 12.0)
    raw.update(control_uuid(_window(dash)), {"value": value})
    _then_window(dash, raw, 13.0)
    assert dash.messages.refused == refused + 1


@pytest.mark.parametrize("value", ["bogus", "", 3, None, "sine "])
def test_a_choice_outside_its_options_is_refused(dash: Dashboard, raw: RawViser,
                                                 value: Any) -> None:
    assert dash.live is not None and dash.messages is not None
    refused = dash.messages.refused
    before = dash.live.trajectory.value
    raw.update(control_uuid(dash.live.trajectory), {"value": value})
    raw.update(control_uuid(dash.live.run_buttons), {"value": value})
    _then_window(dash, raw, 14.0 + len(str(value)))
    assert dash.messages.refused == refused + 2
    assert dash.live.trajectory.value == before


def test_a_refused_value_is_sent_back_to_that_page(dash: Dashboard, raw: RawViser) -> None:
    """The page shows what it sent until told otherwise: a refused value is answered with the
    value the dashboard keeps."""
    assert dash.live is not None
    trajectory = dash.live.trajectory
    kept, uuid = trajectory.value, control_uuid(trajectory)
    raw.update(uuid, {"value": "bogus"})
    raw.pump_until(lambda: any(m["type"] == "GuiUpdateMessage" and m["uuid"] == uuid
                               and m["updates"] == {"value": kept} for m in raw.messages),
                   20.0, "the kept value was not sent back")
    assert trajectory.value == kept


def test_a_disabled_or_unknown_control_and_other_messages_are_refused(
    dash: Dashboard, raw: RawViser
) -> None:
    assert dash.identify is not None and dash.messages is not None
    abort = dash.identify.abort_button
    assert abort.disabled  # no identification runs
    pressed: list[int] = []
    abort.on_click(lambda e: pressed.append(e.client_id))
    refused = dash.messages.refused
    raw.update(control_uuid(abort), {"value": True})
    raw.update("no-such-control", {"value": True})
    raw.send({"type": "GuiButtonHoldMessage", "uuid": control_uuid(abort), "frequency": 10.0})
    raw.send({"type": "ShareUrlRequest"})
    raw.send({"type": "FileTransferPart", "source_component_uuid": None,
              "transfer_uuid": "t", "part_index": 0, "content": b"x" * 1000})
    raw.send({**_camera_with(math.nan)})
    _then_window(dash, raw, 30.0)
    assert dash.messages.refused == refused + 6
    assert pressed == []


def _camera_with(x: float) -> dict[str, Any]:
    from viser_raw import CAMERA

    return {**CAMERA, "position": (x, 1.0, 1.0)}


def test_refusals_are_logged_at_a_bounded_rate(dash: Dashboard, raw: RawViser,
                                               caplog: pytest.LogCaptureFixture) -> None:
    assert dash.live is not None and dash.messages is not None
    refused = dash.messages.refused
    with caplog.at_level(logging.WARNING, logger="server.message_gate"):
        for _ in range(200):
            raw.update(control_uuid(dash.live.estop_button), {"removed": True})
        _then_window(dash, raw, 31.0)
    assert dash.messages.refused == refused + 200
    lines = [r.getMessage() for r in caplog.records if "removed" in r.getMessage()]
    # 200 refusals within LOG_EVERY_S: one line (two if the window turned meanwhile).
    assert 1 <= len(lines) <= 2, lines
    assert "E-STOP" in lines[0] and "only a value may change" in lines[0]
    assert LOG_EVERY_S >= 1.0


def test_an_upload_goes_only_to_an_upload_button_and_its_parts_only_after_it_started(
    dash: Dashboard, raw: RawViser
) -> None:
    """An operator's upload (one identity: every browser's) passes: viser acknowledges its
    part; a start on a control that is not an upload button, and parts of a transfer never
    started, are refused."""
    assert dash.messages is not None and dash.live is not None
    raw.pump_until(lambda: any(m["type"] == "GuiUploadButtonMessage" for m in raw.messages),
                   30.0, "no upload button was sent")
    button = next(m["uuid"] for m in raw.messages if m["type"] == "GuiUploadButtonMessage")
    refused = dash.messages.refused

    def start(uuid: str, transfer: str) -> None:
        raw.send({"type": "FileTransferStartUpload", "source_component_uuid": uuid,
                  "transfer_uuid": transfer, "filename": "m.csv", "mime_type": "text/csv",
                  "part_count": 1, "size_bytes": 3})

    def part(uuid: str, transfer: str) -> None:
        raw.send({"type": "FileTransferPart", "source_component_uuid": uuid,
                  "transfer_uuid": transfer, "part_index": 0, "content": b"a,b"})

    start(control_uuid(dash.live.estop_button), "not-a-button")
    part(control_uuid(dash.live.estop_button), "not-a-button")
    part(button, "never-started")
    start(button, "good")
    part(button, "good")
    raw.pump_until(lambda: any(m["type"] == "FileTransferPartAck"
                               and m["transfer_uuid"] == "good" for m in raw.messages),
                   30.0, "the upload's part was not acknowledged")
    assert dash.messages.refused == refused + 3
    assert not any(m["type"] == "FileTransferPartAck" and m["transfer_uuid"] != "good"
                   for m in raw.messages)
