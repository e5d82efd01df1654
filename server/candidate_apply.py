"""A candidate's Apply, from the panel that pressed it to the controller: in a worker, through
the browser's acting client (`server.session`), the reply back to that panel and the new active
configuration to every candidate.

The path a reader follows: the Apply button's callback -> `TuningPanel.apply` (the checks the
dashboard makes first) -> `CandidateApply.submit` -> worker -> `CandidateApply.send` ->
`BrowserSessions.act` (the user's client, the lease) -> `ControllerClient.apply`."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Protocol

import viser

from controller import protocol as proto
from controller.client import ControllerUnavailable
from controller.core.config import LoopConfig
from server.http_access import Refused
from server.session import BrowserSessions
from server.workers import Requests

__all__ = ["ApplyTarget", "CandidateApply"]

log = logging.getLogger(__name__)


class ApplyTarget(Protocol):
    """What an Apply needs of the panel that sent it: the version its candidate was made
    against, and where the outcome is shown."""

    @property
    def base_version(self) -> int | None: ...

    def note_refused(self, why: str) -> None: ...

    def show_error(self, text: str) -> None: ...

    def show_reply(self, accepted: bool, version: int, reasons: list[str]) -> None: ...

    def rebase(self, cfg: LoopConfig, version: int) -> None: ...


class CandidateApply:
    """Sends candidates to the controller (one per dashboard; every candidate panel is given
    it when it is built)."""

    def __init__(self, sessions: BrowserSessions, requests: Requests,
                 on_active: Callable[[LoopConfig, int], None]) -> None:
        """`on_active(config, version)`: the controller's active configuration after a reply
        (every browser's candidate follows it)."""
        self.sessions = sessions
        self._requests = requests
        self._on_active = on_active

    def submit(self, panel: ApplyTarget, cand: LoopConfig, confirm: bool = False,
               browser: viser.ClientHandle | None = None) -> None:
        """Send `cand` in a worker (GUI callbacks return at once)."""
        self._requests.submit(self.send, panel, cand, confirm, browser)

    def send(self, panel: ApplyTarget, cand: LoopConfig, confirm: bool = False,
             browser: viser.ClientHandle | None = None) -> None:
        """Send `panel`'s candidate, made against `panel.base_version` (the controller refuses
        it if the active version has moved on), and show the reply on `panel`."""
        expect = panel.base_version
        try:
            reply = self.sessions.act(browser, "apply", lambda c: c.apply(
                cand, confirm=confirm, expect_version=expect))
        except Refused as exc:
            panel.note_refused(str(exc))
            return  # logged, and told to the browser that asked (only)
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("apply failed: %s", exc)
            panel.show_error(str(exc))
            return
        log.info("apply: %s, version %d", "accepted" if reply.accepted else "rejected",
                 reply.version)
        panel.show_reply(reply.accepted, reply.version, list(reply.reasons))
        self._on_active(reply.config, reply.version)
        if reply.accepted:
            panel.rebase(reply.config, reply.version)
