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
import types
from collections.abc import Awaitable, Callable, Iterable, Iterator
from typing import TYPE_CHECKING, TypeAlias

if TYPE_CHECKING:
    import viser
    from viser._gui_handles import _GuiHandle, _GuiInputHandle
    from viser.infra._messages import Message
    from websockets.asyncio.server import ServerConnection
    from websockets.http11 import Request, Response

__all__ = ["IncomingJudge", "connection_of", "control_uuid", "disable_share_url", "drop_upload",
           "filter_incoming", "gated_serve", "input_handle", "live_connections",
           "messages", "removed", "resend_value", "send_prop_to", "set_slider_marks",
           "set_width_in"]

#: judge(client_id, message, report) -> whether viser may handle the message; `report`: the
#: call that should count, log and tell (the server-level dispatch; the per-client dispatch of
#: the same message judges it again quietly).
IncomingJudge: TypeAlias = "Callable[[int, Message, bool], bool]"
#: What websockets calls for each HTTP request and handshake before answering (the gate's
#: check; viser's own serves its static files, synchronously): a response refuses or answers,
#: None goes on to the websocket.
ProcessRequest: TypeAlias = "Callable[[ServerConnection, Request], Response | None]"
#: The gate's wrapper: viser's own `process_request` (None: none) in, the gated one out.
GateWrap: TypeAlias = "Callable[[ProcessRequest | None], ProcessRequest]"
#: Any of viser's GUI input controls (slider, number, dropdown, button, ...).
InputHandle: TypeAlias = "_GuiInputHandle[object]"


def _gui_handle(handle: object) -> _GuiHandle[object]:
    """`handle` as one of viser's GUI handles (inputs and outputs: html, uplot, ...); TypeError
    for anything else (viser's handle classes are generic in their value's type, so the
    functions below take any handle as `object` and narrow it here)."""
    from viser._gui_handles import _GuiHandle

    if not isinstance(handle, _GuiHandle):
        raise TypeError(f"{handle!r} is not a viser GUI handle")
    return handle

_serve_lock = threading.Lock()
#: One server start at a time: the wrapper a starting server takes is the one being installed.
_starting = threading.Lock()
_pending: list[GateWrap] = []
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

        def serve(*args: object, **kwargs: object) -> object:
            with _serve_lock:
                wrap = _pending[-1] if _pending else None
            if wrap is not None:
                theirs = kwargs.get("process_request")
                if theirs is not None and not callable(theirs):
                    raise TypeError(f"process_request: {theirs!r} is not callable")
                kwargs["process_request"] = wrap(theirs)  # type: ignore[arg-type]
            return original(*args, **kwargs)  # type: ignore[arg-type]

        ws_server.serve = serve  # type: ignore[misc,assignment]
        _installed = True


@contextlib.contextmanager
def gated_serve(wrap: GateWrap) -> Iterator[None]:
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


def live_connections(server: viser.ViserServer) -> dict[int, ServerConnection]:
    """viser's websocket connections by client id (a copy): `ViserServer._websock_server.
    _live_connections` (the connection object is the one the gate saw in `process_request`;
    viser exposes client handles, not their connections)."""
    return dict(server._websock_server._live_connections)  # type: ignore[attr-defined]


def connection_of(server: viser.ViserServer, client_id: int) -> ServerConnection | None:
    """The websocket connection of client `client_id` (None: none, or gone)."""
    conns: dict[int, ServerConnection] = server._websock_server._live_connections  # type: ignore[attr-defined]
    return conns.get(client_id)


def disable_share_url(server: viser.ViserServer) -> None:
    """Never open a public share tunnel: `ViserServer.request_share_url` replaced on this
    server (viser has no option to turn the tunnel off)."""
    server.request_share_url = lambda *a, **k: None  # type: ignore[method-assign]


def input_handle(gui: viser.GuiApi, uuid: str) -> InputHandle | None:
    """The input control `uuid` of a GUI (the server's or one client's), None: none there
    (`GuiApi._gui_input_handle_from_uuid`, viser's own lookup for incoming updates)."""
    return gui._gui_input_handle_from_uuid.get(uuid)


def control_uuid(handle: object) -> str:
    """The id viser's messages name a GUI control by (`_impl.uuid`: no public name)."""
    return str(_gui_handle(handle)._impl.uuid)


def messages() -> types.ModuleType:
    """viser's message classes (`viser._messages`: private; the message gate reads
    `GuiUpdateMessage.uuid/updates`, `ViewerCameraMessage`'s numbers,
    `FileTransferStartUpload.source_component_uuid/transfer_uuid`,
    `FileTransferPart.transfer_uuid`)."""
    from viser import _messages

    return _messages


def drop_upload(gui: viser.GuiApi, transfer_uuid: str) -> None:
    """Forget the parts of upload `transfer_uuid` buffered so far in a GUI (the server's or one
    client's): `GuiApi._current_file_upload_states`, where viser keeps an upload's parts until
    its last one arrives or its browser disconnects."""
    gui._current_file_upload_states.pop(transfer_uuid, None)


def set_width_in(browser: viser.ClientHandle, panel: viser.PanelHandle,
                 width_px: float) -> None:
    """The docked `panel` (a panel of the shared GUI) `width_px` wide in `browser` alone:
    viser's `set_width` goes to every browser; the same placement message sent through a
    `MainPanelHandle` on the browser's own GUI (private class; `_placement_uuid` names the
    panel) goes to it only."""
    from viser._gui_handles import MainPanelHandle

    handle = MainPanelHandle(browser.gui)
    handle._placement_uuid = panel._placement_uuid
    handle.set_width(width_px)


def send_prop_to(handle: object, prop: str, value: object,
                 browsers: Iterable[viser.ClientHandle],
                 wire: Callable[[object], object] | None = None) -> None:
    """A GUI handle's property `prop` set here (cast as viser casts it) and sent to `browsers`
    only, where an assignment goes to every browser (and stays in viser's buffer for later
    ones): `_cast_value_recursive`, `_prop_hints`, `_impl.props`, `_impl.uuid`,
    `viser._messages.GuiUpdateMessage` and each browser GUI's `_websock_interface`.
    `wire(value)`: what the message carries instead of the value kept here (e.g. float32
    copies of float64 arrays: viser's messages carry an array's dtype and its page makes a
    typed array of it)."""
    from viser._messages import GuiUpdateMessage

    handle = _gui_handle(handle)
    value = handle._cast_value_recursive(handle._prop_hints[prop], value, prop)
    setattr(handle._impl.props, prop, value)
    message = GuiUpdateMessage(handle._impl.uuid, {prop: value if wire is None else wire(value)})
    for browser in browsers:
        browser.gui._websock_interface.queue_message(message)


def removed(handle: object) -> bool:
    """Whether viser removed the GUI element (`_impl.removed`; viser has no public reader):
    removed by `remove()`, or a browser's own element (in a shared tab or folder) whose
    browser left: viser marks those removed at the disconnect, before the dashboard's
    disconnect callback runs, and then refuses every assignment to them with RuntimeError."""
    return bool(_gui_handle(handle)._impl.removed)


def unless_closed(closed: Callable[[], bool], work: Callable[..., object],
                  *args: object) -> bool:
    """`work(*args)`; False if it was cut short because its page closed meanwhile (viser's
    RuntimeError on an element it removed at the disconnect, before the dashboard's callback
    stops the page's panels: a closed page is normal). Any other failure, or one while
    `closed()` is false, is raised."""
    try:
        work(*args)
    except RuntimeError:
        if not closed():
            raise
        return False
    return True


def resend_value(handle: object, browser: viser.ClientHandle) -> None:
    """The control's value (as kept here) sent again to `browser` alone: its page shows what
    the dashboard holds after a change it refused (a `GuiUpdateMessage` on the browser GUI's
    `_websock_interface`, as `send_prop_to`)."""
    from viser._gui_handles import _GuiInputHandle
    from viser._messages import GuiUpdateMessage

    if not isinstance(handle, _GuiInputHandle):
        raise TypeError(f"{handle!r} is not a viser input control")
    browser.gui._websock_interface.queue_message(
        GuiUpdateMessage(handle._impl.uuid, {"value": handle.value}))


def set_slider_marks(slider: viser.GuiSliderHandle[float],
                     marks: tuple[tuple[float, str], ...]) -> None:
    """A slider's marks changed after creation (viser takes them only in `add_slider`): its
    `_marks` property set to `viser._messages.GuiSliderMark`s (every browser gets them)."""
    from viser._messages import GuiSliderMark

    slider._marks = tuple(GuiSliderMark(value=v, label=t) for v, t in marks)


def filter_incoming(server: viser.ViserServer, judge: IncomingJudge) -> None:
    """`judge` in front of viser's dispatch of every message a browser sends: viser's server
    (`WebsockServer`) and each client's connection (`WebsockClientConnection`) dispatch each
    message through their own `_handle_incoming_message` (the server's handlers: the shared
    GUI, the scene; the connection's: that client's GUI, its camera); both are replaced on the
    instance, the connection's as it connects (before viser reads from it)."""
    ws = server._websock_server  # type: ignore[attr-defined]
    Dispatch = Callable[[int, "Message"], Awaitable[None]]

    def wrapped(original: Dispatch, report: bool) -> Dispatch:
        async def handle(client_id: int, message: Message) -> None:
            if judge(client_id, message, report):
                await original(client_id, message)
        return handle

    # (replaced on the instance: setattr, the method being viser's)
    setattr(ws, "_handle_incoming_message",  # noqa: B010
            wrapped(getattr(ws, "_handle_incoming_message"), True))  # noqa: B009

    def on_connect(connection: viser.infra.WebsockClientConnection) -> None:
        setattr(connection, "_handle_incoming_message",  # noqa: B010
                wrapped(getattr(connection, "_handle_incoming_message"), False))  # noqa: B009

    ws.on_client_connect(on_connect)
