"""The browsers of one dashboard's viser server: who is at each (its user and role), the page and
candidate slot its page named, its own GUI, and what to tell it. Built with the server (the
dashboard's `__enter__`); the message gate and the page views ask it."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING
from urllib.parse import parse_qs, urlsplit

import viser

from server.escape import esc
from server.http_access import HttpAccess
from server.session import BrowserSessions, tell
from server.viser_adapter import connection_of, live_connections, resend_value

__all__ = ["VIEWPORT_PARAM", "VIEWPORT_PX", "Browsers"]

#: The websocket URL's parameter with the page's window width (web_assets/dashboard.js).
VIEWPORT_PARAM = "dt_vw"
#: The window widths taken from it (CSS px); another value is not believed.
VIEWPORT_PX = (320, 16384)

if TYPE_CHECKING:
    from websockets.asyncio.server import ServerConnection

log = logging.getLogger(__name__)


class Browsers:
    """The browsers connected to `server`, as the access gate (`access`: whose token opened
    each websocket, what its page named) and the sessions (`sessions`: who signed in) know
    them."""

    def __init__(self, server: viser.ViserServer, access: HttpAccess,
                 sessions: BrowserSessions) -> None:
        self._server = server
        self._access = access
        self._sessions = sessions

    def browser(self, client_id: int) -> viser.ClientHandle | None:
        """The browser of viser client id `client_id` (None: gone)."""
        return self._server.get_clients().get(client_id)

    def all(self) -> list[viser.ClientHandle]:
        """Every browser connected now."""
        return list(self._server.get_clients().values())

    def _connection_of(self, browser: viser.ClientHandle | None) -> ServerConnection | None:
        """viser's websocket connection of `browser` (None: none, or gone)."""
        return None if browser is None else connection_of(self._server, browser.client_id)

    def slot_of(self, browser: viser.ClientHandle | None) -> str:
        """The candidate slot the browser's page named ("": none: a page without the page
        script, or no browser)."""
        conn = self._connection_of(browser)
        return self._access.slot_of_connection(conn) if conn is not None else ""

    def page_of(self, browser: viser.ClientHandle | None) -> str:
        """The id the browser's page named ("": a page without the page script, or no
        browser)."""
        conn = self._connection_of(browser)
        return self._access.page_of_connection(conn) if conn is not None else ""

    def viewport_px_of(self, browser: viser.ClientHandle | None) -> int | None:
        """The width (CSS px) of the window the browser's page said it had when it connected
        (`?dt_vw=` in its websocket's URL, from the page script; None: not said, or not a
        width from VIEWPORT_PX)."""
        conn = self._connection_of(browser)
        request = None if conn is None else conn.request
        if request is None:
            return None
        values = parse_qs(urlsplit(request.path).query).get(VIEWPORT_PARAM, [])
        if len(values) != 1 or not values[0].isdigit():
            return None
        width = int(values[0])
        return width if VIEWPORT_PX[0] <= width <= VIEWPORT_PX[1] else None

    def connected_pages(self) -> set[str]:
        """The ids the pages behind the websockets open now named (viser's connection table:
        a page whose websocket is up before viser counts its browser is there too)."""
        return {self._access.page_of_connection(c)
                for c in live_connections(self._server).values()}

    def role_of(self, client_id: int) -> str | None:
        """The role of the user at browser `client_id` ("operator" with one identity: every
        browser may change the rig; None: not signed in)."""
        users = self._sessions.users
        if not users:
            return "operator"
        user = self._sessions.user_of(self.browser(client_id))
        return None if user is None else str(users[user].role)

    def name_of(self, client_id: int) -> str:
        return self._sessions.user_of(self.browser(client_id)) or ""

    def gui_of(self, client_id: int) -> viser.GuiApi | None:
        browser = self.browser(client_id)
        return None if browser is None else browser.gui

    def restore(self, client_id: int, handle: object) -> None:
        """Send `handle`'s value as the dashboard holds it to that browser again."""
        browser = self.browser(client_id)
        if browser is not None:
            resend_value(handle, browser)

    def tell(self, client_id: int, why: str) -> None:
        tell(self.browser(client_id), "Refused", why, "red")

    def sign_in(self, browser: viser.ClientHandle) -> None:
        """Note who is at a new browser (with several users: the user whose token opened its
        websocket) and say so in its page; a browser with no user may only watch."""
        users = self._sessions.users
        if not users:
            return
        conn = self._connection_of(browser)
        user = self._access.user_of_connection(conn) if conn is not None else None
        if user is None:
            log.error("browser %s: no user for its connection: it may only watch",
                      browser.client_id)
            return
        self._sessions.signed_in(browser.client_id, user)
        role = users[user].role
        note = " (watch and E-STOP only)" if role == "viewer" else ""
        browser.gui.add_html(
            f"<div class='dt-whoami' style='font-size:12px'>Signed in as "
            f"<b>{esc(user)}</b>, {esc(role)}{note}</div>")
