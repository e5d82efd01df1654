"""Each private part of viser or websockets that server/viser_adapter.py reaches, checked on the
installed versions: a release that renames or reshapes one fails here, not in a user's browser.
Run this file first when moving to a new viser (README.md). A real viser server on loopback and
a raw websocket client (tests/viser_raw.py)."""

from __future__ import annotations

import contextlib
import io
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from helpers import free_port, wait_for
from viser_raw import RawViser

from server import viser_adapter


class _Seen:
    """A wrapper for viser's process_request that notes what it saw."""

    def __init__(self) -> None:
        self.inner: list[Any] = []
        self.paths: list[str] = []
        self.connections: list[Any] = []

    def wrap(self, process_request: Any) -> Any:
        self.inner.append(process_request)

        def seen(connection: Any, request: Any) -> Any:
            self.paths.append(request.path)
            if "Upgrade" in request.headers:
                self.connections.append(connection)
            return process_request(connection, request) if process_request else None

        return seen


@pytest.fixture(scope="module")
def served() -> Iterator[tuple[Any, _Seen]]:
    import viser

    seen = _Seen()
    with viser_adapter.gated_serve(seen.wrap), contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        yield server, seen
    finally:
        server.stop()


@pytest.fixture
def raw(served: tuple[Any, _Seen]) -> Iterator[tuple[RawViser, Any]]:
    """A connected raw client and its viser client handle."""
    server, _ = served
    before = set(server.get_clients())
    with RawViser(f"ws://127.0.0.1:{server.get_port()}/") as c:
        wait_for(lambda: set(server.get_clients()) - before, 20.0, "the client never connected")
        (client_id,) = set(server.get_clients()) - before
        yield c, server.get_clients()[client_id]


def test_viser_starts_its_server_through_websockets_serve_with_a_process_request(
    served: tuple[Any, _Seen]
) -> None:
    """The gate's way in: viser calls `websockets.asyncio.server.serve(...,
    process_request=...)` while it starts, and every HTTP request goes through it."""
    import urllib.request

    server, seen = served
    assert len(seen.inner) == 1 and callable(seen.inner[0])
    with urllib.request.urlopen(f"http://127.0.0.1:{server.get_port()}/?x=1", timeout=5) as r:
        assert r.status == 200
    assert "/?x=1" in seen.paths


def test_a_server_started_outside_the_block_is_left_alone() -> None:
    import viser

    seen = _Seen()
    with viser_adapter.gated_serve(seen.wrap):
        pass
    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    server.stop()
    assert seen.inner == []


def test_the_connection_table_holds_the_connection_the_gate_saw(
    served: tuple[Any, _Seen], raw: tuple[RawViser, Any]
) -> None:
    server, seen = served
    _, browser = raw
    conn = viser_adapter.connection_of(server, browser.client_id)
    assert conn is not None and conn is seen.connections[-1]
    assert viser_adapter.live_connections(server)[browser.client_id] is conn
    assert viser_adapter.connection_of(server, 10_000) is None


def test_the_share_url_is_a_method_that_can_be_disabled(served: tuple[Any, _Seen]) -> None:
    import viser

    server, _ = served
    assert callable(getattr(viser.ViserServer, "request_share_url", None))
    viser_adapter.disable_share_url(server)
    assert server.request_share_url() is None


def test_controls_are_found_by_the_uuid_their_messages_carry(
    served: tuple[Any, _Seen], raw: tuple[RawViser, Any]
) -> None:
    server, _ = served
    c, browser = raw
    shared = server.gui.add_button("adapter shared")
    own = browser.gui.add_slider("adapter own", min=0.0, max=1.0, step=0.1, initial_value=0.5)
    uuid = viser_adapter.control_uuid(shared)
    c.pump_until(lambda: any(m.get("uuid") == uuid for m in c.messages), 20.0,
                 "the button's creation message never came")
    assert viser_adapter.input_handle(server.gui, uuid) is shared
    assert viser_adapter.input_handle(browser.gui, viser_adapter.control_uuid(own)) is own
    assert viser_adapter.input_handle(server.gui, viser_adapter.control_uuid(own)) is None
    shared.remove()
    own.remove()


def test_a_panel_width_goes_to_one_browser(served: tuple[Any, _Seen],
                                           raw: tuple[RawViser, Any]) -> None:
    server, _ = served
    c, browser = raw
    panel = server.gui.add_panel()
    viser_adapter.set_width_in(browser, panel, 1234.0)
    c.pump_until(lambda: any(m["type"] == "GuiSetPanelWidthMessage" and m.get("width") == 1234.0
                             for m in c.messages), 20.0, "the width never came")
    (sent,) = [m for m in c.messages if m["type"] == "GuiSetPanelWidthMessage"
               and m.get("width") == 1234.0]
    assert panel._placement_uuid in sent.values()


def test_a_property_goes_to_the_browsers_named_and_is_kept_here(
    served: tuple[Any, _Seen], raw: tuple[RawViser, Any]
) -> None:
    import viser.uplot

    server, _ = served
    c, browser = raw
    chart = server.gui.add_uplot(data=(np.arange(3.0), np.zeros(3)),
                                 series=(viser.uplot.Series(label="x"),
                                         viser.uplot.Series(label="y")))
    uuid = viser_adapter.control_uuid(chart)
    viser_adapter.send_prop_to(chart, "data", (np.arange(4.0), np.ones(4)), [browser])
    c.pump_until(lambda: any(m["type"] == "GuiUpdateMessage" and m["uuid"] == uuid
                             and "data" in m["updates"] for m in c.messages),
                 20.0, "the chart's data never came")
    assert np.array_equal(np.asarray(chart.data[1]), np.ones(4))
    chart.remove()


def test_a_property_may_go_as_another_value_than_is_kept_here(
    served: tuple[Any, _Seen], raw: tuple[RawViser, Any]
) -> None:
    """`wire`: the message carries float32 arrays (their dtype named, as the page decodes
    them: viser's BinaryMessageDecode makes a Float32Array of "<f4"), the value kept here is
    viser's float64 cast."""
    import viser.uplot

    server, _ = served
    c, browser = raw
    chart = server.gui.add_uplot(data=(np.arange(3.0), np.zeros(3)),
                                 series=(viser.uplot.Series(label="x"),
                                         viser.uplot.Series(label="y")))
    uuid = viser_adapter.control_uuid(chart)
    viser_adapter.send_prop_to(chart, "data", (np.arange(4.0), np.full(4, 0.1)), [browser],
                               wire=lambda v: tuple(np.asarray(a, np.float32) for a in v))
    got: list[Any] = []

    def came() -> bool:
        got[:] = [m for m in c.messages if m["type"] == "GuiUpdateMessage"
                  and m["uuid"] == uuid and "data" in m["updates"]]
        return bool(got)

    c.pump_until(came, 20.0, "the chart's data never came")
    assert [a["dtype"] for a in got[0]["updates"]["data"]] == ["<f4", "<f4"]
    kept = chart.data
    assert all(np.asarray(a).dtype == np.float64 for a in kept)
    assert np.asarray(kept[1])[0] == 0.1  # not rounded to float32 (0.100000001...)
    chart.remove()


def test_slider_marks_change_after_creation(served: tuple[Any, _Seen],
                                            raw: tuple[RawViser, Any]) -> None:
    server, _ = served
    c, _ = raw
    slider = server.gui.add_slider("marks", min=0.0, max=1.0, step=0.1, initial_value=0.5)
    uuid = viser_adapter.control_uuid(slider)
    viser_adapter.set_slider_marks(slider, ((0.2, "low"), (0.8, "high")))

    def marks_sent() -> bool:
        return any(m["type"] == "GuiUpdateMessage" and m["uuid"] == uuid
                   and "_marks" in m["updates"] for m in c.messages)

    c.pump_until(marks_sent, 20.0, "the marks never came")
    (sent,) = [m["updates"]["_marks"] for m in c.messages if m["type"] == "GuiUpdateMessage"
               and m["uuid"] == uuid and "_marks" in m["updates"]]
    assert [(m["value"], m["label"]) for m in sent] == [(0.2, "low"), (0.8, "high")]
    slider.remove()


def test_the_judge_sees_every_message_before_viser_handles_it(
    served: tuple[Any, _Seen]
) -> None:
    """viser dispatches an incoming message through the server's and the connection's
    `_handle_incoming_message`: the judge is asked at both (reporting once), and a message
    it refuses reaches no callback."""
    server, _ = served
    judged: list[tuple[str, bool]] = []
    allow = {"ok": True}

    def judge(_client: int, message: Any, report: bool) -> bool:
        judged.append((type(message).__name__, report))
        return allow["ok"]

    viser_adapter.filter_incoming(server, judge)
    before = set(server.get_clients())
    pressed: list[str] = []
    shared = server.gui.add_button("judged shared")
    shared.on_click(lambda _e: pressed.append("shared"))
    with RawViser(f"ws://127.0.0.1:{server.get_port()}/") as c:
        wait_for(lambda: set(server.get_clients()) - before, 20.0, "never connected")
        (client_id,) = set(server.get_clients()) - before
        own = server.get_clients()[client_id].gui.add_button("judged own")
        own.on_click(lambda _e: pressed.append("own"))
        assert ("ViewerCameraMessage", True) in judged and ("ViewerCameraMessage", False) in judged
        allow["ok"] = False
        for b in (shared, own):
            c.update(viser_adapter.control_uuid(b), {"value": True})
        wait_for(lambda: judged.count(("GuiUpdateMessage", False)) >= 2, 20.0,
                 "the refused presses were not judged")
        allow["ok"] = True
        for b in (shared, own):
            c.update(viser_adapter.control_uuid(b), {"value": True})
        wait_for(lambda: sorted(pressed) == ["own", "shared"], 20.0,
                 "the allowed presses did not reach their callbacks")
    assert judged.count(("GuiUpdateMessage", True)) == 4  # reported once per message
    assert sorted(pressed) == ["own", "shared"]  # the refused two reached nothing
    shared.remove()


def test_a_value_is_sent_again_to_one_browser(served: tuple[Any, _Seen],
                                              raw: tuple[RawViser, Any]) -> None:
    server, _ = served
    c, browser = raw
    dropdown = server.gui.add_dropdown("resend", ("a", "b"), initial_value="b")
    uuid = viser_adapter.control_uuid(dropdown)
    viser_adapter.resend_value(dropdown, browser)
    c.pump_until(lambda: any(m["type"] == "GuiUpdateMessage" and m["uuid"] == uuid
                             and m["updates"] == {"value": "b"} for m in c.messages),
                 20.0, "the value never came")
    dropdown.remove()


def test_the_incoming_messages_have_the_fields_the_message_gate_reads() -> None:
    import dataclasses

    m = viser_adapter.messages()

    def fields(cls: Any) -> set[str]:
        return {f.name for f in dataclasses.fields(cls)}

    assert {"uuid", "updates"} <= fields(m.GuiUpdateMessage)
    assert {"wxyz", "position", "fov", "near", "far", "look_at", "up_direction"} <= fields(
        m.ViewerCameraMessage)
    assert {"source_component_uuid", "transfer_uuid"} <= fields(m.FileTransferStartUpload)
    assert {"transfer_uuid"} <= fields(m.FileTransferPart)


def test_a_browsers_own_element_is_removed_when_it_leaves(served: tuple[Any, _Seen]) -> None:
    """A browser's own elements in a shared tab (as each browser's candidate panel is built)
    are marked removed when that browser leaves, and viser then refuses assignments to them:
    `removed` reads that mark (what a worker of a closed page checks)."""
    server, _ = served
    before = set(server.get_clients())
    tabs = server.gui.add_tab_group()
    tab = tabs.add_tab("shared tab")
    with RawViser(f"ws://127.0.0.1:{server.get_port()}/"):
        wait_for(lambda: set(server.get_clients()) - before, 20.0, "the client never connected")
        (client_id,) = set(server.get_clients()) - before
        browser = server.get_clients()[client_id]
        with tab:
            own = browser.gui.add_html("<p>own</p>")
        assert not viser_adapter.removed(own)
        own.content = "<p>still here</p>"  # no error while the browser is there
    wait_for(lambda: viser_adapter.removed(own), 20.0, "the element was never marked removed")
    with pytest.raises(RuntimeError, match="removed"):
        own.content = "<p>after</p>"
    shared = server.gui.add_html("<p>shared</p>")
    assert not viser_adapter.removed(shared)
    shared.remove()
    assert viser_adapter.removed(shared)
    with pytest.raises(TypeError):
        viser_adapter.removed(object())
    tabs.remove()
