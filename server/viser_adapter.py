"""Every reach into viser's and websockets' private parts, in one place (issue 32 item 2).

viser's public API does not offer what the dashboard needs for these; each function below says
which private part it uses and why, and tests/test_viser_adapter.py checks each assumption on
the installed versions (a release that renames or reshapes one fails a test there, not a
user). The tested versions are pinned in pyproject.toml; README.md says how to move to a new
one (run tests/test_viser_adapter.py first).

The access gate (server/http_access.py): viser 1.1 has no public hook for HTTP requests or the
websocket handshake (`ViserServer(host, port, label, verbose)`; it builds its server with
`websockets.asyncio.server.serve(..., process_request=...)` inside its own thread). The check
is therefore installed by wrapping that library function (`gated_serve`); because a wrapper can
be bypassed by a future viser that starts its server another way, the dashboard then proves,
on loopback, that the gate answers in front of every route before it serves anyone
(`server.http_access.prove_gate`), and refuses to start if not.

Incoming messages (server/message_gate.py): viser copies any attribute a client names in a
`GuiUpdateMessage` onto the control's server-side state and has no public hook before its
handlers; `filter_incoming` puts a judge in front of its dispatch (`_handle_incoming_message`
of the server and of each client connection).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from typing import Any

__all__ = ["IncomingJudge", "connection_of", "control_uuid", "disable_share_url", "drop_upload",
           "filter_incoming", "gated_serve", "input_handle", "live_connections",
           "messages", "resend_value", "send_prop_to", "set_slider_marks", "set_width_in"]

#: judge(client_id, message, report) -> whether viser may handle the message; `report`: the
#: call that should count, log and tell (the server-level dispatch; the per-client dispatch of
#: the same message judges it again quietly).
IncomingJudge = Callable[[int, Any, bool], bool]

_serve_lock = threading.Lock()
#: One server start at a time: the wrapper a starting server takes is the one being installed.
_starting = threading.Lock()
_pending: list[Callable[[Callable[..., Any] | None], Callable[..., Any]]] = []
_installed = False


def _install_serve_wrapper() -> None:
    """Wrap `websockets.asyncio.server.serve` once per process (private use of a public
    function: viser calls it by module attribute, `websockets.asyncio.server.serve(...)`, so
    the replacement is what it calls). A server started while a `gated_serve` block runs gets
    that block's wrapper around its `process_request`; any other server is left alone."""
    global _installed
    with _serve_lock:
        if _installed:
            return
        import websockets.asyncio.server as ws_server

        original = ws_server.serve

        def serve(*args: Any, **kwargs: Any) -> Any:
            with _serve_lock:
                wrap = _pending[-1] if _pending else None
            if wrap is not None:
                kwargs["process_request"] = wrap(kwargs.get("process_request"))
            return original(*args, **kwargs)

        ws_server.serve = serve  # type: ignore[misc,assignment]
        _installed = True


@contextlib.contextmanager
def gated_serve(wrap: Callable[[Callable[..., Any] | None], Callable[..., Any]]) -> Iterator[None]:
    """Servers that viser starts inside this block run `wrap(their process_request)` for every
    HTTP request and websocket handshake."""
    _install_serve_wrapper()
    with _starting:
        with _serve_lock:
            _pending.append(wrap)
        try:
            yield
        finally:
            with _serve_lock, contextlib.suppress(ValueError):
                _pending.remove(wrap)


def live_connections(server: Any) -> dict[int, Any]:
    """viser's websocket connections by client id (a copy): `ViserServer._websock_server.
    _live_connections` (the connection object is the one the gate saw in `process_request`;
    viser exposes client handles, not their connections)."""
    return dict(server._websock_server._live_connections)


def connection_of(server: Any, client_id: int) -> Any:
    """The websocket connection of client `client_id` (None: none, or gone)."""
    return server._websock_server._live_connections.get(client_id)


def disable_share_url(server: Any) -> None:
    """Never open a public share tunnel: `ViserServer.request_share_url` replaced on this
    server (viser has no option to turn the tunnel off)."""
    server.request_share_url = lambda *a, **k: None


def input_handle(gui: Any, uuid: str) -> Any:
    """The input control `uuid` of a GUI (the server's or one client's), None: none there
    (`GuiApi._gui_input_handle_from_uuid`, viser's own lookup for incoming updates)."""
    return gui._gui_input_handle_from_uuid.get(uuid)


def control_uuid(handle: Any) -> str:
    """The id viser's messages name a GUI control by (`_impl.uuid`: no public name)."""
    return str(handle._impl.uuid)


def messages() -> Any:
    """viser's message classes (`viser._messages`: private; the message gate reads
    `GuiUpdateMessage.uuid/updates`, `ViewerCameraMessage`'s numbers,
    `FileTransferStartUpload.source_component_uuid/transfer_uuid`,
    `FileTransferPart.transfer_uuid`)."""
    from viser import _messages

    return _messages


def drop_upload(gui: Any, transfer_uuid: str) -> None:
    """Forget the parts of upload `transfer_uuid` buffered so far in a GUI (the server's or one
    client's): `GuiApi._current_file_upload_states`, where viser keeps an upload's parts until
    its last one arrives or its browser disconnects."""
    gui._current_file_upload_states.pop(transfer_uuid, None)


def set_width_in(browser: Any, panel: Any, width_px: float) -> None:
    """The docked `panel` (a panel of the shared GUI) `width_px` wide in `browser` alone:
    viser's `set_width` goes to every browser; the same placement message sent through a
    `MainPanelHandle` on the browser's own GUI (private class; `_placement_uuid` names the
    panel) goes to it only."""
    from viser._gui_handles import MainPanelHandle

    handle = MainPanelHandle(browser.gui)
    handle._placement_uuid = panel._placement_uuid
    handle.set_width(width_px)


def send_prop_to(handle: Any, prop: str, value: Any, browsers: Any) -> None:
    """A GUI handle's property `prop` set here (cast as viser casts it) and sent to `browsers`
    only, where an assignment goes to every browser (and stays in viser's buffer for later
    ones): `_cast_value_recursive`, `_prop_hints`, `_impl.props`, `_impl.uuid`,
    `viser._messages.GuiUpdateMessage` and each browser GUI's `_websock_interface`."""
    from viser._messages import GuiUpdateMessage

    value = handle._cast_value_recursive(handle._prop_hints[prop], value, prop)
    setattr(handle._impl.props, prop, value)
    message = GuiUpdateMessage(handle._impl.uuid, {prop: value})
    for browser in browsers:
        browser.gui._websock_interface.queue_message(message)


def resend_value(handle: Any, browser: Any) -> None:
    """The control's value (as kept here) sent again to `browser` alone: its page shows what
    the dashboard holds after a change it refused (a `GuiUpdateMessage` on the browser GUI's
    `_websock_interface`, as `send_prop_to`)."""
    from viser._messages import GuiUpdateMessage

    browser.gui._websock_interface.queue_message(
        GuiUpdateMessage(handle._impl.uuid, {"value": handle.value}))


def set_slider_marks(slider: Any, marks: tuple[tuple[float, str], ...]) -> None:
    """A slider's marks changed after creation (viser takes them only in `add_slider`): its
    `_marks` property set to `viser._messages.GuiSliderMark`s (every browser gets them)."""
    from viser._messages import GuiSliderMark

    slider._marks = tuple(GuiSliderMark(value=v, label=t) for v, t in marks)


def filter_incoming(server: Any, judge: IncomingJudge) -> None:
    """`judge` in front of viser's dispatch of every message a browser sends: viser's server
    (`WebsockServer`) and each client's connection (`WebsockClientConnection`) dispatch each
    message through their own `_handle_incoming_message` (the server's handlers: the shared
    GUI, the scene; the connection's: that client's GUI, its camera); both are replaced on the
    instance, the connection's as it connects (before viser reads from it)."""
    ws = server._websock_server

    def wrapped(original: Any, report: bool) -> Any:
        async def handle(client_id: int, message: Any) -> None:
            if judge(client_id, message, report):
                await original(client_id, message)
        return handle

    ws._handle_incoming_message = wrapped(ws._handle_incoming_message, True)

    def on_connect(connection: Any) -> None:
        connection._handle_incoming_message = wrapped(connection._handle_incoming_message, False)

    ws.on_client_connect(on_connect)
