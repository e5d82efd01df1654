"""Command routing: a browser's commands (E-STOP included) to the controller, through that
browser's acting client (`server.session`), in a worker; the reply shown in the Live tab's
command line. (A candidate's Apply: `server.candidate_apply`.)"""

from __future__ import annotations

import logging
from collections.abc import Callable

import viser

from controller import protocol as proto
from controller.client import ControllerClient, ControllerUnavailable
from server.escape import esc
from server.http_access import Refused
from server.session import BrowserSessions
from server.workers import Requests

__all__ = ["CommandRouter", "command_html"]

log = logging.getLogger(__name__)


def command_html(text: str, ok: bool) -> str:
    color = "#2e7d32" if ok else "#d62728"
    return f"<div class='dt-cmd' style='color:{color};font-size:12px'>{text}</div>"


class CommandRouter:
    """Sends what browsers ask for; GUI callbacks call the `*_async` methods and return."""

    def __init__(self, sessions: BrowserSessions, requests: Requests,
                 show_command: Callable[[str], None]) -> None:
        """`show_command(html)`: the outcome of a command, for every browser (Live tab)."""
        self.sessions = sessions
        self._requests = requests
        self._show_command = show_command

    # -- commands ------------------------------------------------------------------------------

    def command_async(self, body: proto.CommandBody,
                      browser: viser.ClientHandle | None = None) -> None:
        if isinstance(body, proto.EStop):
            # The put goes out at once from the callback; the reply is shown when it comes.
            try:
                self.sessions.client_for(browser, "e-stop").put_estop()
            except Exception:
                log.exception("e-stop put failed; the EStop command follows")
        self._requests.submit(self.command, body, browser)

    def estop_from_link(self, user: str) -> str:
        """The always-visible E-STOP link (on viser's event loop: the put at once, the
        command for a reply in a worker)."""
        c = self.sessions.estop_client(user)
        try:
            c.put_estop()
        except Exception as exc:  # told to the page and logged; the command still follows
            log.exception("e-stop put from the E-STOP link failed")
            self._requests.submit(self.command, proto.EStop(), None, c)
            return f"E-STOP put failed ({exc}); the EStop command follows"
        self._requests.submit(self.command, proto.EStop(), None, c)
        log.warning("E-STOP from the page's E-STOP link (%s)", user or "dashboard")
        return "E-STOP sent"

    def command(self, body: proto.CommandBody, browser: viser.ClientHandle | None = None,
                via: ControllerClient | None = None) -> None:
        """Send `body` for `browser` (or through `via`) and show the reply."""
        name = type(body).__name__
        try:
            if via is not None:
                reply = via.command(body)
            elif isinstance(body, proto.EStop):
                reply = self.sessions.client_for(browser, "e-stop").command(body)
            else:
                reply = self.sessions.act(browser, name, lambda c: c.command(body))
        except Refused:
            return  # logged, and told to the browser that asked (only)
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("command %s failed: %s", name, exc)
            self._show_command(command_html(f"{name}: {esc(str(exc))}", False))
            return
        if not reply.ok:
            log.warning("command %s refused: %s", name, reply.message)
        self._show_command(command_html(
            f"{name}: {'ok' if reply.ok else 'refused'} {esc(reply.message)} "
            f"(mode {reply.mode})", reply.ok))

