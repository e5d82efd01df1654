"""Every message a browser sends, judged by its sender's role before viser handles it.

viser copies any attribute a client names in a GUI update onto the control's server-side state
(one message from a viewer removed the E-STOP button's callback for every browser; `removed:
true` did the same to Reset fault), takes values outside a dropdown's options or a slider's
range, and `disabled` only greys the control in the page. What passes here:

- a GUI value update (`updates == {"value": v}`, nothing else) on a control that exists, is
  neither disabled nor hidden, and that the sender's role may change, with a value the control
  could have shown: a dropdown's or button group's option, a number inside its range (finite),
  a checkbox's bool, a text of at most `MAX_TEXT` characters;
- who may change what: a control of the browser's own GUI (its candidate) is the browser's;
  a shared control (the server's GUI) only an operator's (or anybody's with one identity),
  but for the ones marked `open_to_all` (the E-STOP, each browser's own view: export, the 3-D
  view's toggle), which any signed-in browser may press;
- the browser's own camera (finite numbers), and an operator's file uploads to an upload
  button (`FileTransferStartUpload` on one, then that transfer's parts), capped while they
  arrive: a file announced over `MAX_UPLOAD_BYTES` or in more than `MAX_UPLOAD_PARTS` parts is
  refused at its start, and a transfer whose parts bring more bytes than it announced is
  dropped at that part (viser's buffer of it too). Before, viser buffered whatever parts came
  until the last one, and the 5 MB limit was checked on the assembled file: an upload that
  never completed grew the dashboard by 300 MB in 5 s (tests/bench/bench_upload_memory.py).

Everything else is refused: counted, logged (at most one line per browser and reason per
`LOG_EVERY_S`, with the number held back), a role refusal told to that browser, and a refused
value sent back as the dashboard holds it (the page would otherwise show the value it sent).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from server import viser_adapter

if TYPE_CHECKING:
    import viser
    from viser._messages import FileTransferPart, FileTransferStartUpload, GuiUpdateMessage

    from server.viser_adapter import InputHandle
from server.measured import MAX_BYTES

__all__ = ["LOG_EVERY_S", "MAX_TEXT", "MAX_UPLOAD_BYTES", "MAX_UPLOAD_PARTS", "MessageGate"]

log = logging.getLogger(__name__)

#: At most one log line per browser and kind of refusal in this many seconds.
LOG_EVERY_S = 10.0
#: The longest text a text field takes (characters).
MAX_TEXT = 4096
#: Upload transfers remembered per browser (a browser that starts more loses the oldest, and
#: viser's buffer of it).
MAX_TRANSFERS = 8
#: The largest file a page may upload (bytes): the measured responses' CSV limit.
MAX_UPLOAD_BYTES = MAX_BYTES
#: Most parts an upload may come in (viser's page sends 512 KiB parts: 10 for 5 MB).
MAX_UPLOAD_PARTS = 64


def _is_button(handle: object) -> bool:
    """A button's value is a press, not a state to show again."""
    import viser

    return isinstance(handle, (viser.GuiButtonHandle, viser.GuiButtonGroupHandle))


def _number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


@dataclass
class MessageGate:
    """The judge of one dashboard's incoming messages (`viser_adapter.filter_incoming`)."""

    role_of: Callable[[int], str | None]
    """The role of the browser (viser client id): "operator", "viewer"; None: not signed in."""
    shared_gui: viser.GuiApi
    """The server's GUI (the shared controls)."""
    gui_of: Callable[[int], viser.GuiApi | None]
    """The browser's own GUI (None: gone)."""
    name_of: Callable[[int], str] = lambda _c: ""
    """The name of the user at the browser (for a refusal's text)."""
    tell: Callable[[int, str], None] = lambda _c, _t: None
    """Tells the browser why (a role refusal)."""
    restore: Callable[[int, object], None] = lambda _c, _h: None
    """Sends the control's value as kept here to the browser whose change was refused."""
    open_if: Callable[[object], bool] = lambda _h: False
    """Whether a shared control is open to every role by what it is (a chart's Export row)."""
    refused: int = 0
    """Messages refused so far."""
    _open: set[str] = field(default_factory=set)
    _uploads: dict[int, dict[str, list[int]]] = field(default_factory=dict)
    """Per browser, its transfers (oldest first): [bytes announced, bytes received]."""
    _last_log: dict[tuple[int, str], tuple[float, int]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def open_to_all(self, handle: object) -> None:
        """Any signed-in browser may press this shared control (the E-STOP, a browser's own
        view)."""
        self._open.add(viser_adapter.control_uuid(handle))

    def __call__(self, client_id: int, message: object, report: bool) -> bool:
        why = self.why_refused(client_id, message, count=report)
        if why is None:
            return True
        if report:
            self._refuse(client_id, type(message).__name__, why)
            self._restore(client_id, message)
        return False

    def forget(self, client_id: int) -> None:
        with self._lock:
            self._uploads.pop(client_id, None)
            for key in [k for k in self._last_log if k[0] == client_id]:
                del self._last_log[key]

    # -- the rules ---------------------------------------------------------------------------

    def why_refused(self, client_id: int, message: object, count: bool = True) -> str | None:
        """None: viser may handle it; else why not. `count`: an upload's part counts against
        its transfer (each message is judged at both dispatches, counted once)."""
        m = viser_adapter.messages()
        role = self.role_of(client_id)
        if isinstance(message, m.GuiUpdateMessage):
            return self._update(client_id, role, message)
        if isinstance(message, m.ViewerCameraMessage):
            numbers = [*message.wxyz, *message.position, message.fov, message.near, message.far,
                       *message.look_at, *message.up_direction]
            return None if all(_number(v) for v in numbers) else "camera: a number not finite"
        if isinstance(message, m.FileTransferStartUpload):
            return self._upload_start(client_id, role, message, count)
        if isinstance(message, m.FileTransferPart):
            return self._upload_part(client_id, message, count)
        return "not a message a page sends"

    def _control(self, client_id: int, uuid: str) -> tuple[InputHandle | None, bool]:
        """(the control, whether it is shared), (None, False): none."""
        own_gui = self.gui_of(client_id)
        own = viser_adapter.input_handle(own_gui, uuid) if own_gui is not None else None
        if own is not None:
            return own, False
        shared = viser_adapter.input_handle(self.shared_gui, uuid)
        return shared, shared is not None

    def _update(self, client_id: int, role: str | None,
                message: GuiUpdateMessage) -> str | None:
        import viser

        handle, shared = self._control(client_id, message.uuid)
        if handle is None:
            return "no such control"
        label = getattr(handle, "label", "?")
        if set(message.updates) != {"value"}:
            return f"{label}: only a value may change, not {sorted(message.updates)}"
        if handle.disabled or not handle.visible:
            return f"{label}: the control is {'disabled' if handle.disabled else 'hidden'}"
        if (shared and role != "operator" and message.uuid not in self._open
                and not self.open_if(handle)):
            return f"ROLE{label}"
        v = message.updates["value"]
        if isinstance(handle, (viser.GuiButtonGroupHandle, viser.GuiDropdownHandle)):
            return None if isinstance(v, str) and v in handle.options else (
                f"{label}: {v!r} is not one of its options")
        if isinstance(handle, (viser.GuiSliderHandle, viser.GuiNumberHandle)):
            lo, hi = handle.min, handle.max
            inside = _number(v) and (lo is None or v >= lo) and (hi is None or v <= hi)
            return None if inside else f"{label}: {v!r} is outside [{lo}, {hi}] or not a number"
        if isinstance(handle, (viser.GuiButtonHandle, viser.GuiCheckboxHandle)):
            return None if isinstance(v, bool) else f"{label}: {v!r} is not true or false"
        if isinstance(handle, viser.GuiTextHandle):
            return None if isinstance(v, str) and len(v) <= MAX_TEXT else (
                f"{label}: not a text of at most {MAX_TEXT} characters")
        return f"{label}: a {type(handle).__name__} takes no value from a page"

    def _upload_start(self, client_id: int, role: str | None, message: FileTransferStartUpload,
                      count: bool) -> str | None:
        import viser

        handle, shared = self._control(client_id, message.source_component_uuid)
        if not isinstance(handle, viser.GuiUploadButtonHandle):
            return "upload to something that is not an upload button"
        if handle.disabled or not handle.visible:
            return f"{handle.label}: the control is disabled or hidden"
        if shared and role != "operator":
            return f"ROLE{handle.label}"
        size, parts = message.size_bytes, message.part_count
        if not 0 <= size <= MAX_UPLOAD_BYTES:
            return (f"{handle.label}: a file of {size} bytes: more than the {MAX_UPLOAD_BYTES} "
                    "an upload may have")
        if not 0 <= parts <= MAX_UPLOAD_PARTS or (parts == 0) != (size == 0):
            return f"{handle.label}: {parts} parts for {size} bytes"
        if not count:
            return None
        with self._lock:
            transfers = self._uploads.setdefault(client_id, {})
            transfers.pop(message.transfer_uuid, None)
            transfers[message.transfer_uuid] = [size, 0]
            dropped = list(transfers)[:-MAX_TRANSFERS]
            for uuid in dropped:
                del transfers[uuid]
        for uuid in dropped:
            self._drop_upload(client_id, uuid)
        return None

    def _upload_part(self, client_id: int, message: FileTransferPart,
                     count: bool) -> str | None:
        uuid = message.transfer_uuid
        with self._lock:
            transfer = self._uploads.get(client_id, {}).get(uuid)
            if transfer is None:
                return "upload part of a transfer not started here"
            if not count:  # counted at the server's dispatch, which judges it first
                return None
            announced, received = transfer[0], transfer[1] + len(message.content)
            if received <= announced:
                transfer[1] = received
                return None
            del self._uploads[client_id][uuid]
        self._drop_upload(client_id, uuid)
        return (f"upload: {received} bytes or more where {announced} were announced: the "
                "upload is dropped")

    def _drop_upload(self, client_id: int, transfer_uuid: str) -> None:
        """viser's buffer of a transfer dropped (the shared GUI's and the browser's own)."""
        viser_adapter.drop_upload(self.shared_gui, transfer_uuid)
        own_gui = self.gui_of(client_id)
        if own_gui is not None:
            viser_adapter.drop_upload(own_gui, transfer_uuid)

    # -- refusing ----------------------------------------------------------------------------

    def _restore(self, client_id: int, message: object) -> None:
        """A refused value change: the page is sent the value kept here (it shows the value
        it sent until told otherwise)."""
        m = viser_adapter.messages()
        if not isinstance(message, m.GuiUpdateMessage) or "value" not in message.updates:
            return
        handle, _ = self._control(client_id, message.uuid)
        if handle is not None and not _is_button(handle):
            self.restore(client_id, handle)

    def _refuse(self, client_id: int, kind: str, why: str) -> None:
        role_refusal = why.startswith("ROLE")
        if role_refusal:
            role = self.role_of(client_id)
            who = ("this browser is not signed in" if role is None else
                   f"{self.name_of(client_id) or 'this browser'} is a {role}")
            why = f"{why[4:]}: {who}: viewers watch and may E-STOP, not change the rig"
        now = time.monotonic()
        key = (client_id, kind + (why if role_refusal else why.split(":")[0]))
        with self._lock:
            self.refused += 1
            last, held = self._last_log.get(key, (-math.inf, 0))
            if now - last < LOG_EVERY_S:
                self._last_log[key] = (last, held + 1)
                return
            self._last_log[key] = (now, 0)
        more = f" ({held} more like it held back)" if held else ""
        log.warning("browser %s: %s refused: %s%s", client_id, kind, why, more)
        if role_refusal:
            self.tell(client_id, why)
