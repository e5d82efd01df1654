"""The plant knowledge the verdicts use (shared by every browser): the controller's record,
fetched whenever its version changes, and measured responses sent to the controller for
adoption (a CSV uploaded in the Tune tab, or Identify's "Use as nominal model")."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from controller import protocol as proto
from controller.client import ControllerClient, ControllerUnavailable
from controller.gate.frd import measured_from_frd
from controller.gate.knowledge import MeasuredResponse
from server.engine import TuningEngine
from server.escape import esc
from server.http_access import Refused
from server.measured import MAX_BYTES, read_measured
from server.session import BrowserSessions
from server.viser_adapter import hide_in
from server.workers import Refetch, Requests

__all__ = ["ORDER_LAST", "KnowledgePanel"]

log = logging.getLogger(__name__)

#: viser's order of the shared elements that follow each browser's own ones in a tab.
ORDER_LAST = 1e9


def _measured_html(text: str, error: bool = False) -> str:
    style = "color:#d62728" if error else "font-size:12px"
    return f"<div class='dt-measured' style='{style}'>{text}</div>"


class KnowledgePanel:
    """The upload button and the knowledge line at the foot of the Tune tab."""

    def __init__(self, gui: Any, client: ControllerClient, engine: TuningEngine,
                 sessions: BrowserSessions, requests: Requests,
                 on_changed: Callable[[], None]) -> None:
        """`on_changed()`: the knowledge the engine judges on changed (re-evaluate)."""
        self.gui = gui
        self.client = client
        self.engine = engine
        self.sessions = sessions
        self._requests = requests
        self._on_changed = on_changed
        self.follow = Refetch(requests, self.fetch)
        """`follow.note(version)`: the controller's knowledge version (from a status);
        fetched again when it moves."""

    def build(self) -> None:
        """Below each browser's own candidate controls (built when it connects)."""
        self.upload = upload = self.gui.add_upload_button(
            "Upload measured responses (CSV)", mime_type="text/csv,.csv", color="gray",
            order=ORDER_LAST, hint="an operator's: the controller adopts them into its plant "
            f"knowledge (at most {MAX_BYTES // 1_000_000} MB)")
        self.text = self.gui.add_html(
            "<div class='dt-measured' style='font-size:12px;color:#555'>No measured "
            "responses: 1/|Delta| is the stated bound.</div>", order=ORDER_LAST + 1)
        upload.on_upload(self._on_upload)

    def offer_to(self, browser: Any, may_upload: bool) -> None:
        """The upload button in `browser`'s page only when its user may use it (operators):
        a viewer's page does not show it (and the message gate refuses a viewer's upload)."""
        if not may_upload:
            hide_in(self.upload, browser)

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

    def _on_upload(self, event: Any) -> None:
        f = event.target.value
        self._requests.submit(self.load_csv, f.name, f.content, event.client)

    def load_csv(self, name: str, content: bytes, browser: Any = None) -> None:
        try:
            measured = measured_from_frd(read_measured(name, content), name)
        except ValueError as exc:
            log.warning("measured response %s not used: %s", name, exc)
            self.text.content = _measured_html(f"{esc(name)}: {esc(str(exc))}", error=True)
            return
        self.adopt(measured, "CSV", browser)
        self._on_changed()

    def add_identified(self, m: MeasuredResponse, browser: Any = None) -> None:
        self.adopt(m, "Identify", browser)

    def adopt(self, m: MeasuredResponse, source: str, browser: Any = None) -> None:
        """Send the response to the controller for adoption into its plant knowledge: the
        verdicts (the controller's and this dashboard's) use it once the controller has it."""
        try:
            req = proto.KnowledgeRequest(record=self.engine.with_measured(m))
            reply = self.sessions.act(browser, "plant knowledge", lambda c: c.knowledge(req))
        except Refused:
            return  # logged, and told to the browser that asked (only)
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("measured response %s not adopted: %s", m.name, exc)
            self.text.content = _measured_html(
                f"{esc(m.name)}: not adopted by the controller: {esc(str(exc))}", error=True)
            return
        if not reply.ok:
            self.text.content = _measured_html(
                f"{esc(m.name)}: refused by the controller: {esc(reply.message)}", error=True)
            return
        self.engine.set_knowledge(reply.record)
        self.follow.version = reply.record.version
        n = len(reply.record.measured)
        log.info("measured response %s adopted (%s); plant knowledge v%d has %d", m.name,
                 source, reply.record.version, n)
        self.text.content = _measured_html(
            f"plant knowledge v{reply.record.version}: {n} measured response(s); last: "
            f"{esc(m.name)} ({esc(source)}). The verdicts (here and in the controller) use "
            "them.")
