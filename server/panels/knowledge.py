"""The plant knowledge the verdicts use (shared by every browser): the controller's record,
fetched whenever its version changes, and measured responses sent to the controller for
adoption (a CSV uploaded in the Tune tab, or Identify's "Use as nominal model")."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence

import viser

from controller import protocol as proto
from controller.client import ControllerClient, ControllerUnavailable
from controller.gate.frd import measured_from_frd
from controller.gate.knowledge import MeasuredResponse
from server.engine import TuningEngine
from server.escape import esc
from server.gui import Browser
from server.http_access import Refused
from server.measured import MAX_BYTES, read_measured
from server.session import BrowserSessions
from server.workers import Refetch, Requests

__all__ = ["ORDER_LAST", "KnowledgePanel"]

log = logging.getLogger(__name__)

#: viser's order of the shared elements that follow each browser's own ones in a tab.
ORDER_LAST = 1e9


def _measured_html(text: str, error: bool = False) -> str:
    style = "color:#d62728" if error else "font-size:12px"
    return f"<div class='dt-measured' style='{style}'>{text}</div>"


class KnowledgePanel:
    """The knowledge line and the operators' upload buttons at the foot of the Tune tab."""

    def __init__(self, gui: viser.GuiApi, client: ControllerClient, engine: TuningEngine,
                 sessions: BrowserSessions, requests: Requests,
                 on_changed: Callable[[], None]) -> None:
        """`on_changed()`: the knowledge the engine judges on changed (re-evaluate)."""
        self.gui = gui
        self.client = client
        self.engine = engine
        self.sessions = sessions
        self._requests = requests
        self._on_changed = on_changed
        self._lock = threading.Lock()
        self._build_lock = threading.Lock()
        self._uploads: dict[int, viser.GuiUploadButtonHandle] = {}
        """Each operator's upload button by browser (viser client id)."""
        self.follow = Refetch(requests, self.fetch)
        """`follow.note(version)`: the controller's knowledge version (from a status);
        fetched again when it moves."""

    def build(self) -> None:
        """The Plant knowledge box below each browser's own candidate controls (built when it
        connects): the knowledge line (every browser's) and, in an operator's page only, its
        own upload button (`offer_to`)."""
        self.box = self.gui.add_folder("Plant knowledge", order=ORDER_LAST,
                                       expand_by_default=True)
        with self.box:
            self.text = self.gui.add_html(
                "<div class='dt-measured' style='font-size:12px;color:#555'>No measured "
                "responses: 1/|Delta| is the stated bound.</div>", order=1.0)

    def offer_to(self, browser: Browser, may_upload: bool) -> None:
        """The upload button, built in `browser`'s own GUI, only when its user may use it
        (operators, or anyone with one identity): a viewer's page has none (and the message
        gate refuses an upload to another page's or a shared button). Built in the browser's
        GUI, not hidden there: a shared button hidden per page came back when viser's shared
        messages reached the page after the page's own."""
        if not may_upload or browser is None:
            return
        with self._build_lock, self.box:  # a container takes one `with` at a time
            upload = browser.gui.add_upload_button(
                "Upload measured responses (CSV)", mime_type="text/csv,.csv", color="gray",
                order=0.0, hint="the controller adopts them into its plant knowledge (at "
                f"most {MAX_BYTES // 1_000_000} MB)")
        upload.on_upload(self._on_upload)
        with self._lock:
            self._uploads[browser.client_id] = upload

    def upload_of(self, browser: Browser,
                  ) -> viser.GuiUploadButtonHandle | None:
        """`browser`'s upload button (None: it has none)."""
        with self._lock:
            return self._uploads.get(getattr(browser, "client_id", -1))

    def drop(self, browser_id: int) -> None:
        """The browser left (its GUI went with it)."""
        with self._lock:
            self._uploads.pop(browser_id, None)

    def fetch(self) -> None:
        """The controller's plant knowledge: the dashboard judges on nothing else."""
        try:
            reply = self.client.knowledge()
            self.engine.set_knowledge(reply.record)
        except (ControllerUnavailable, proto.ProtocolError, ValueError) as exc:
            log.warning("plant knowledge not fetched: %s", exc)
            self.follow.forget()  # try again with the next status
            return
        log.info("plant knowledge v%d fetched (%s)", reply.record.version, reply.record.source)
        self._on_changed()

    def _on_upload(self, event: viser.GuiEvent[viser.GuiUploadButtonHandle]) -> None:
        f = event.target.value
        self._requests.submit(self.load_csv, f.name, f.content, event.client)

    def load_csv(self, name: str, content: bytes, browser: Browser = None) -> None:
        try:
            measured = measured_from_frd(read_measured(name, content), name)
        except ValueError as exc:
            log.warning("measured response %s not used: %s", name, exc)
            self.text.content = _measured_html(f"{esc(name)}: {esc(str(exc))}", error=True)
            return
        self.adopt((measured,), "CSV", browser)
        self._on_changed()

    def add_identified(self, ms: Sequence[MeasuredResponse], browser: Browser = None) -> None:
        """An identification's responses (one per position), adopted together: one new
        plant knowledge, judged once (one by one made a version, a verdict and a twin each)."""
        self.adopt(tuple(ms), "Identify", browser)

    def adopt(self, ms: tuple[MeasuredResponse, ...], source: str,
              browser: Browser = None) -> None:
        """Send the response(s) to the controller for adoption into its plant knowledge: the
        verdicts (the controller's and this dashboard's) use them once the controller has
        them."""
        what = ", ".join(x.name for x in ms)
        try:
            req = proto.KnowledgeRequest(record=self.engine.with_measured(*ms))
            reply = self.sessions.act(browser, "plant knowledge", lambda c: c.knowledge(req))
        except Refused:
            return  # logged, and told to the browser that asked (only)
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("measured response(s) %s not adopted: %s", what, exc)
            self.text.content = _measured_html(
                f"{esc(what)}: not adopted by the controller: {esc(str(exc))}", error=True)
            return
        if not reply.ok:
            self.text.content = _measured_html(
                f"{esc(what)}: refused by the controller: {esc(reply.message)}", error=True)
            return
        self.engine.set_knowledge(reply.record)
        self.follow.version = reply.record.version
        n = len(reply.record.measured)
        log.info("measured response(s) %s adopted (%s); plant knowledge v%d has %d", what,
                 source, reply.record.version, n)
        self.text.content = _measured_html(
            f"plant knowledge v{reply.record.version}: {n} measured response(s); last: "
            f"{esc(what)} ({esc(source)}). The verdicts (here and in the controller) use "
            "them.")
