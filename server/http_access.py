"""Who may open the dashboard: a token in the URL (as Jupyter does), Origin and Host checks.

viser has no authentication and accepts any Origin: anyone who reaches the port could press any
control (a raw websocket client can press a hidden or disabled one). The dashboard therefore
checks every HTTP request and the websocket handshake before viser sees them:

- The printed URL carries `?token=<random>`; with several users (`HttpAccess.users`), each user has
  a token of their own and the dashboard knows which user is behind each websocket
  (`user_of_connection`). A request with the right token gets the page and
  a cookie (HttpOnly, SameSite=Strict) that the page's own requests and its websocket then
  carry; a request with neither gets 401 and a short page that says how to get in.
- The websocket handshake needs the cookie, an allowed Host (the configured host, localhost
  and 127.0.0.1 at the dashboard's port) and, when the client sends one (browsers always do),
  an Origin of that same host: a page on another site cannot drive the dashboard from the
  user's browser (cross-site websocket hijacking), and a raw client without the token cannot
  connect at all.

How: viser starts its server with `websockets.asyncio.server.serve(..., process_request=...)`;
`install` wraps that function once per process so that the `process_request` of a server
started while a `HttpAccess` is being installed runs its check first (`HttpAccess.serving`). The
comparison of tokens is constant-time.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gzip
import hmac
import http
import logging
import re
import secrets
import threading
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from server.assets import web_asset
from server.escape import esc

__all__ = ["COOKIE", "ESTOP_LINK_HTML", "ESTOP_PATH", "PAGE_SCRIPT_FILE", "VIEW_PATH", "HttpAccess",
           "Refused", "install", "page_script_html", "title_html"]

log = logging.getLogger(__name__)

COOKIE = "dobtune_token"
#: GET with the cookie (or token): e-stop, outside viser's websocket. The page's always-visible
#: E-STOP is a plain link to it (into a hidden frame): no script, no websocket needed.
ESTOP_PATH = "/__dobtune_estop"
#: GET with the cookie, from the page script: whether the page shows the live traces
#: (`?dt_page=<the page's id>&live=1`, `live=0`: another plots tab), so that their data goes
#: only to the pages that show them (`HttpAccess.on_view`). Answered 204, 400 naming a bad field.
VIEW_PATH = "/__dobtune_view"
#: Put into the page itself (outside viser's panels, which unmount what they collapse): fixed
#: to the window above everything, whatever is collapsed or scrolled; a link into a hidden
#: frame, so it needs neither script nor websocket.
ESTOP_LINK_HTML = (
    f"<a class='dt-estop-fixed' href='{ESTOP_PATH}' target='dt-estop-frame' title='E-STOP: "
    "speed command 0 and drive disabled' style='position:fixed;left:50%;bottom:18px;"
    "transform:translateX(-50%);z-index:2147483647;background:#d62728;color:#fff;"
    "font:bold 22px sans-serif;letter-spacing:1px;padding:14px 34px;border-radius:8px;"
    "border:3px solid #7f0000;box-shadow:0 2px 10px rgba(0,0,0,.35);text-decoration:none'>"
    "E-STOP</a><iframe name='dt-estop-frame' title='e-stop answer' style='display:none'>"
    "</iframe>"
)
#: The page's own script: a PNG button beside every chart's CSV button, and the selected tabs
#: kept in the URL's fragment (put into the page after `HttpAccess.page_extra`).
PAGE_SCRIPT_FILE = web_asset("dashboard.js")
_lock = threading.Lock()
#: One server start at a time: the gate a starting server takes is the one being installed.
_starting = threading.Lock()
_pending: list[HttpAccess] = []
_installed = False

_DENIED_PAGE = (
    "<!doctype html><meta charset=utf-8><title>dobtune: token required</title>"
    "<p style='font:16px sans-serif;margin:2em'>This dashboard needs its access token: open "
    "the URL the dashboard printed when it started (it ends in <code>?token=...</code>).</p>"
)


def title_html(rig_name: str) -> str:
    """A script element naming the browser tab after the rig: "dobtune - <rig>"."""
    import json

    title = json.dumps(f"dobtune - {rig_name}").replace("<", "\\u003c")
    return f"<script>document.title = {title};</script>"


def page_script_html(path: Path = PAGE_SCRIPT_FILE) -> str:
    """`path` as an inline script element; "" (logged) when it cannot be read: the page then
    works without PNG export and without the view in its URL."""
    try:
        source = path.read_text(encoding="utf-8")
    except OSError as exc:
        log.warning("page script %s unreadable (%s): no PNG export, the URL keeps no view",
                    path, exc)
        return ""
    if "</script" in source.lower():
        raise ValueError(f"page script: {path} contains '</script' (it would end the element)")
    return f"<script>{source}</script>"


class Refused(RuntimeError):
    """An action the dashboard refuses for the browser that asked (the message says why)."""


@dataclass
class HttpAccess:
    """The access check of one dashboard."""

    host: str
    token: str = field(default_factory=lambda: secrets.token_urlsafe(24))
    port: int = 0
    refused: int = 0
    """Requests refused so far (HTTP and websocket)."""
    users: dict[str, str] = field(default_factory=dict)
    """With several users: user name -> that user's token (``token`` is then not accepted)."""
    _by_connection: weakref.WeakKeyDictionary[Any, str] = field(
        default_factory=weakref.WeakKeyDictionary, repr=False)
    _slot_by_connection: weakref.WeakKeyDictionary[Any, str] = field(
        default_factory=weakref.WeakKeyDictionary, repr=False)
    _page_by_connection: weakref.WeakKeyDictionary[Any, str] = field(
        default_factory=weakref.WeakKeyDictionary, repr=False)
    page_extra: str = ""
    """HTML put at the end of the page's body (the index page only)."""
    page_script: str = field(default_factory=page_script_html, repr=False)
    """A script element put after `page_extra` (by default web_assets/dashboard.js)."""
    on_estop: Callable[[str], str] | None = None
    """Called with the user for a request to ESTOP_PATH (on the server's event loop: it must
    not block); returns the text to answer."""

    on_view: Callable[[str, bool], None] | None = None
    """Called with a page's id and whether it shows the live traces, for a request to
    VIEW_PATH (on the server's event loop: it must not block)."""

    def token_of(self, user: str = "") -> str:
        return self.users[user] if self.users else self.token

    def user_of_connection(self, connection: Any) -> str | None:
        """The user whose token opened this websocket ("" with a single token), None if
        the connection did not pass this check."""
        return self._by_connection.get(connection)

    def slot_of_connection(self, connection: Any) -> str:
        """The candidate slot the page behind this websocket named ("": none; see
        `slot_of_path`)."""
        return self._slot_by_connection.get(connection, "")

    def page_of_connection(self, connection: Any) -> str:
        """The id of the page behind this websocket (`?dt_page=...`, one per page load; "":
        none, a page without the page script)."""
        return self._page_by_connection.get(connection, "")

    def allowed_hosts(self) -> set[str]:
        hosts = {self.host, "localhost", "127.0.0.1"}
        return {f"{h}:{self.port}" for h in hosts} | ({*hosts} if self.port == 80 else set())

    def _user_by(self, value: str | None) -> str | None:
        """Whose token `value` is (constant-time against each), None: nobody's."""
        if value is None:
            return None
        if not self.users:
            return "" if hmac.compare_digest(value.encode(), self.token.encode()) else None
        found = None
        for user, token in self.users.items():
            if hmac.compare_digest(value.encode(), token.encode()):
                found = user
        return found

    def user_of(self, path: str, headers: Any) -> str | None:
        """The user a request speaks for: its URL token first, else its cookie."""
        query = parse_qs(urlsplit(path).query)
        by_query = self._user_by(query["token"][0] if query.get("token") else None)
        if by_query is not None:
            return by_query
        return self._user_by(_cookie(headers.get("Cookie", ""), COOKIE))

    def check(self, path: str, headers: Any) -> tuple[str, bool]:
        """("", set_cookie) when the request may go on, else why not."""
        query = parse_qs(urlsplit(path).query)
        by_query = self._user_by(query["token"][0] if query.get("token") else None) is not None
        by_cookie = self._user_by(_cookie(headers.get("Cookie", ""), COOKIE)) is not None
        if urlsplit(path).path in (ESTOP_PATH, VIEW_PATH):  # actions: a websocket's Host check
            host = headers.get("Host", "")
            if self.port and host not in self.allowed_hosts():
                return f"host {host!r} is not this dashboard", False
            if not (by_cookie or by_query):
                return "no valid token", False
            return "", False
        if headers.get("Upgrade", "").lower() == "websocket":
            host = headers.get("Host", "")
            if self.port and host not in self.allowed_hosts():
                return f"host {host!r} is not this dashboard", False
            origin = headers.get("Origin")
            if origin is not None and urlsplit(origin).netloc != host:
                return f"origin {origin!r} is not this dashboard ({host})", False
            if not (by_cookie or by_query):
                return "no valid token", False
            return "", False
        if not (by_cookie or by_query):
            return "no valid token", False
        return "", by_query

    def wrap(self, process_request: Callable[..., Any] | None) -> Callable[..., Any]:
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        def gated(connection: Any, request: Any) -> Any:
            why, set_cookie = self.check(request.path, request.headers)
            if why:
                self.refused += 1
                status = http.HTTPStatus.FORBIDDEN if "Upgrade" in request.headers else (
                    http.HTTPStatus.UNAUTHORIZED)
                body = _DENIED_PAGE.encode()
                return Response(status.value, status.phrase, Headers(**{
                    "Content-Type": "text/html; charset=utf-8",
                    "Content-Length": str(len(body)),
                }), body)
            user = self.user_of(request.path, request.headers)
            assert user is not None  # check() passed
            if urlsplit(request.path).path == ESTOP_PATH and self.on_estop is not None:
                text = self.on_estop(user)
                body = (f"<!doctype html><meta charset=utf-8><title>E-STOP</title>"
                        f"<p>{esc(text)}</p>").encode()
                return Response(200, "OK", Headers(**{
                    "Content-Type": "text/html; charset=utf-8",
                    "Content-Length": str(len(body)), "Cache-Control": "no-store",
                }), body)
            if urlsplit(request.path).path == VIEW_PATH:
                return self._view(request.path)
            if "Upgrade" in request.headers:
                self._by_connection[connection] = user
                slot = slot_of_path(request.path)
                if slot:
                    self._slot_by_connection[connection] = slot
                page = _id_param(request.path, PAGE_PARAM)
                if page:
                    self._page_by_connection[connection] = page
            response = process_request(connection, request) if process_request else None
            extra = self.page_extra + self.page_script
            if extra and response is not None and urlsplit(request.path).path in (
                    "/", "/index.html"):
                response = _with_extra(response, extra)
            if set_cookie and response is not None:
                response.headers["Set-Cookie"] = (
                    f"{COOKIE}={self.token_of(user)}; HttpOnly; SameSite=Strict; Path=/"
                )
            return response

        return gated

    def _view(self, path: str) -> Any:
        """A page's report of what it shows (VIEW_PATH): 204, or 400 naming the bad field."""
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        page = _id_param(path, PAGE_PARAM)
        live = parse_qs(urlsplit(path).query).get("live", [])
        bad = (PAGE_PARAM if not page else
               "live" if live not in (["0"], ["1"]) else "")
        if bad:
            body = f"{bad}: missing or not valid".encode()
            return Response(400, "Bad Request", Headers(**{
                "Content-Type": "text/plain; charset=utf-8", "Content-Length": str(len(body)),
            }), body)
        if self.on_view is not None:
            self.on_view(page, live == ["1"])
        return Response(204, "No Content", Headers(**{"Cache-Control": "no-store"}), b"")

    @contextlib.contextmanager
    def serving(self) -> Iterator[None]:
        """Servers started (by viser) inside this block are checked by this one."""
        install()
        with _starting:
            with _lock:
                _pending.append(self)
            try:
                yield
            finally:
                with _lock, contextlib.suppress(ValueError):
                    _pending.remove(self)


#: The query parameter of the websocket's URL that names the page's candidate slot.
SLOT_PARAM = "dt_slot"
_SLOT_RE = re.compile(r"[A-Za-z0-9_-]{8,64}")


def slot_of_path(path: str) -> str:
    """The candidate slot a websocket request names (`?dt_slot=...`; "" : none, or not a
    slot). The page script (web_assets/dashboard.js) makes one per browser tab, kept in the
    tab's sessionStorage, so a reload of the tab finds its candidate again (the candidate is
    then checked like any other: it names only where to look)."""
    return _id_param(path, SLOT_PARAM)


#: The query parameter that names the page (one id per page load, web_assets/dashboard.js):
#: in its websocket's URL and its VIEW_PATH reports.
PAGE_PARAM = "dt_page"


def _id_param(path: str, name: str) -> str:
    """The id the query parameter `name` of `path` holds ("": none, or not an id)."""
    values = parse_qs(urlsplit(path).query).get(name, [])
    return values[0] if values and _SLOT_RE.fullmatch(values[0]) else ""


def _with_extra(response: Any, extra: str) -> Any:
    """`response` (an HTML page, maybe gzipped) with `extra` before its closing body tag."""
    if response.status_code != 200 or not response.headers.get(
            "Content-Type", "").startswith("text/html"):
        return response
    zipped = response.headers.get("Content-Encoding") == "gzip"
    page = gzip.decompress(response.body) if zipped else bytes(response.body)
    end = page.rfind(b"</body>")
    page = page[:end] + extra.encode() + page[end:] if end >= 0 else page + extra.encode()
    body = gzip.compress(page) if zipped else page
    del response.headers["Content-Length"]  # a multi-dict: assigning would add a second one
    response.headers["Content-Length"] = str(len(body))
    return dataclasses.replace(response, body=body)


def _cookie(header: str, name: str) -> str | None:
    for part in header.split(";"):
        k, eq, v = part.strip().partition("=")
        if eq and k == name:
            return v
    return None


def install() -> None:
    """Wrap `websockets.asyncio.server.serve` once: a server started while an HttpAccess is pending
    gets its check in front of its `process_request`."""
    global _installed
    with _lock:
        if _installed:
            return
        import websockets.asyncio.server as ws_server

        original = ws_server.serve

        def serve(*args: Any, **kwargs: Any) -> Any:
            with _lock:
                gate = _pending[-1] if _pending else None
            if gate is not None:
                kwargs["process_request"] = gate.wrap(kwargs.get("process_request"))
            return original(*args, **kwargs)

        ws_server.serve = serve  # type: ignore[misc,assignment]
        _installed = True
