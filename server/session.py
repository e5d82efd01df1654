"""Who is at each browser, and the controller client that acts for them (the per-browser
session: user and lease; the candidate is in `server.dashboard.candidates`).

Without authentication, or with `--auth` and one `--user`, every browser acts as the
dashboard's one identity (the streams' client). With several users, each browser came through
its user's token: a viewer's changes are refused here (told to that browser only; a raw
websocket client can press any control, so the check is on the server, per client), and an
operator's changes go through a Zenoh session logged in as that operator, so the controller's
access control, lease and audit see the real user, never the dashboard.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Literal, NoReturn, TypeVar

import viser

from controller.auth import User
from controller.client import ClientOptions, ControllerClient
from server.http_access import Refused
from server.options import DashboardOptions
from server.workers import Requests, run_logged

__all__ = ["LEASE_S", "BrowserSessions", "leased"]

log = logging.getLogger(__name__)

#: How long a lease the dashboard takes for its user's changes (renewed on the next change).
LEASE_S = 300.0
R = TypeVar("R")


def leased(client: ControllerClient, act: Callable[[], R]) -> R:
    """`act()`, under `client`'s user's operator lease when the controller authenticates:
    taken when that client holds none (the controller refuses it if someone else holds it:
    the reply says so), renewed once if the controller says the lease lapsed."""
    if not client.opts.user:
        return act()
    if not client.lease_token:
        client.lease("acquire", LEASE_S)
    reply = act()
    if getattr(reply, "field", "") == "lease":
        got = client.lease("renew" if client.lease_token else "acquire", LEASE_S)
        if not got.ok:
            got = client.lease("acquire", LEASE_S)
        if got.ok:
            reply = act()
    return reply


class BrowserSessions:
    """The users behind the browsers and their acting clients (opened once per user)."""

    def __init__(self, opts: DashboardOptions, users: dict[str, User], client: ControllerClient,
                 requests: Requests) -> None:
        """`users`: `dashboard_users(opts)` ({}: one identity); `client`: the streams' client
        (acts for every browser with one identity); `requests`: where logins run."""
        self.opts = opts
        self.users = users
        self.client = client
        self._requests = requests
        self._browser_users: dict[int, str] = {}
        self._acting: dict[str, ControllerClient] = {}
        self._lock = threading.Lock()
        self.refusals = 0
        """Actions refused here (a viewer's change, an unknown browser)."""

    def close(self) -> None:
        with self._lock:
            acting, self._acting = list(self._acting.values()), {}
        for c in acting:
            c.__exit__(None, None, None)

    # -- who is where ----------------------------------------------------------------------------

    def signed_in(self, browser_id: int, user: str) -> None:
        """`user` is at browser `browser_id`; an operator's session is opened ahead of need."""
        self._browser_users[browser_id] = user
        if self.users[user].role == "operator":
            self._requests.submit(self.open_acting, user)

    def left(self, browser_id: int) -> None:
        self._browser_users.pop(browser_id, None)

    def user_of(self, browser: viser.ClientHandle | None) -> str | None:
        """The user behind a browser (viser client handle); "" with one identity; None:
        unknown (with several users, a browser must have come through its user's token)."""
        if not self.users:
            return ""
        return self._browser_users.get(getattr(browser, "client_id", -1))

    def signed_in_user(self, browser: viser.ClientHandle | None, action: str) -> str:
        """The user behind `browser`; `Refused` (told to it) if it is not signed in."""
        user = self.user_of(browser)
        if user is None:
            self.refuse(browser, f"{action}: this browser is not signed in")
        return user

    # -- who may act -----------------------------------------------------------------------------

    def client_for(self, browser: viser.ClientHandle | None, action: str) -> ControllerClient:
        """The controller client that does `action` for this browser; `Refused` here (a
        viewer's change, an unknown browser), with the reason shown to that browser too."""
        if not self.users:
            return self.client
        user = self.signed_in_user(browser, action)
        if action == "e-stop":
            return self.estop_client(user)
        self.check_may_change(browser, action)
        with self._lock:
            c = self._acting.get(user)
        return c if c is not None else self.open_acting(user)

    def act(self, browser: viser.ClientHandle | None, action: str,
            do: Callable[[ControllerClient], R]) -> R:
        """`do(client)` for `browser`, through its acting client, under its lease; raises
        `Refused` (told to that browser), `ControllerUnavailable`, `ProtocolError`."""
        c = self.client_for(browser, action)
        return leased(c, lambda: do(c))

    def check_may_change(self, browser: viser.ClientHandle | None, action: str) -> None:
        """`Refused` (told to that browser alone) unless the user at `browser` may change the
        rig: an operator, or anyone without users (one identity for every browser)."""
        if not self.users:
            return
        user = self.signed_in_user(browser, action)
        if self.users[user].role != "operator":
            self.refuse(browser, f"{action}: {user} is a viewer: viewers watch and may E-STOP, "
                        f"not change the rig")

    def estop_client(self, user: str) -> ControllerClient:
        """`user`'s own session when it is open; else, never waiting for a login, the
        streams' session (every role may e-stop)."""
        if not self.users:
            return self.client
        with self._lock:
            c = self._acting.get(user)
        if c is None:
            self._requests.submit(self.open_acting, user)
            return self.client
        return c

    def open_acting(self, user: str) -> ControllerClient:
        """`user`'s own controller session (logged in as them), opened once."""
        with self._lock:
            c = self._acting.get(user)
            if c is None:
                o = self.opts
                c = ControllerClient(ClientOptions(
                    connect=tuple(o.connect), rig_name=o.rig_name,
                    query_timeout_s=o.query_timeout_s, client_name=f"{o.client_name}:{user}",
                    auth=o.auth, user=user, subscribe=False))
                c.__enter__()
                self._acting[user] = c
        return c

    def refuse(self, browser: viser.ClientHandle | None, why: str) -> NoReturn:
        """Count, log and tell `browser` (alone) why; raises `Refused`."""
        self.refusals += 1
        log.warning("refused in the dashboard: %s", why)
        tell(browser, "Refused", why, "red")
        raise Refused(why)


#: The colours a notification is told in (viser's names).
NoticeColor = Literal["red", "orange", "blue"]


def tell(browser: viser.ClientHandle | None, title: str, body: str, color: NoticeColor) -> None:
    """A notification in the browser that asked (nothing without one)."""
    if browser is not None:
        run_logged(lambda: browser.add_notification(title, body, color=color,
                                                    auto_close_seconds=8.0),
                   what="telling a browser")
