"""Who may open the dashboard: a token in the URL (as Jupyter does), bound to its origin.

viser has no authentication and accepts any Origin: anyone who reaches the port could press any
control (a raw websocket client can press a hidden or disabled one). The dashboard therefore
checks every HTTP request and the websocket handshake before viser sees them (`HttpAccess.wrap`,
put in front of viser's server by `server.viser_adapter.gated_serve`):

- The printed URL carries `?token=<random>`; with several users (`HttpAccess.users`), each user
  has a token of their own and the dashboard knows which user is behind each websocket
  (`user_of_connection`). Every request must carry the token itself, in its URL: the page
  (`/?token=...`), its websocket (the page script adds `token` to viser's websocket URL) and
  the page's own requests (the E-STOP link, written into the page with the token of the
  user who opened it, and the view reports).
- No cookie. Browsers do not bind cookies to a port: a cookie of 127.0.0.1:8080 is sent to
  every other port of 127.0.0.1, so any local web server (a developer's, a notebook's) would
  receive the bearer secret and could use it from a raw client (measured: a page of another
  port received the operator's cookie and a plain `<img>` there fired the E-STOP link). The
  token lives only where other origins cannot read it: the page's URL and the page itself
  (the same-origin policy does bind those to the port), with `Referrer-Policy: no-referrer`
  so that it does not leave in a Referer. A cookie an older version set is deleted.
- Origin binding on every request: the Host must be this dashboard (the configured host,
  localhost or 127.0.0.1 at its port: DNS rebinding); an Origin, when sent (browsers send it
  on the websocket handshake and on scripted requests), must be this dashboard's; a
  `Sec-Fetch-Site` (every current browser sends it) must be `same-origin` on the websocket
  and the dashboard's own routes: a page of another port (`same-site`) or another site
  (`cross-site`) fires nothing even if it learnt a token, and an `<img>` or link there to the
  E-STOP is refused. The page itself may be opened from anywhere (a terminal, the Fleet tab's
  link to another rig's view on another port): its URL's token is the proof, and no other
  origin may frame it (`frame-ancestors 'self'`).
- A request refused gets 401 (403 for a websocket) and a short page that says how to get in.
- Fail closed: until `prove` has shown, by requests without the token on loopback, that this
  check answers in front of every route (the page, the websocket, each of the dashboard's own
  routes), even a request with the token gets 503; `prove` raises `GateOpen` if not.

The comparison of tokens is constant-time.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import gzip
import hmac
import http
import http.client
import logging
import re
import secrets
import weakref
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import parse_qs, quote, urlsplit

from server import viser_adapter
from server.assets import web_asset
from server.escape import esc

if TYPE_CHECKING:
    from websockets.asyncio.server import ServerConnection
    from websockets.http11 import Request, Response

    from server.viser_adapter import ProcessRequest

__all__ = ["ESTOP_PATH", "LEGACY_COOKIE", "PAGE_SCRIPT_FILE", "VIEW_PATH", "GateOpen",
           "HttpAccess", "Refused", "estop_link_html", "page_script_html", "title_html"]

log = logging.getLogger(__name__)

#: The cookie older versions kept the token in (sent to every port of the host: deleted).
LEGACY_COOKIE = "dobtune_token"
#: GET with the token, from this dashboard's page: e-stop, outside viser's websocket. The
#: page's always-visible E-STOP is a plain link to it (into a hidden frame): no script, no
#: websocket needed.
ESTOP_PATH = "/__dobtune_estop"
#: GET with the token, from the page script: whether the page shows the live traces
#: (`?dt_page=<the page's id>&live=1`, `live=0`: another plots tab), so that their data goes
#: only to the pages that show them (`HttpAccess.on_view`). Answered 204, 400 naming a bad field.
VIEW_PATH = "/__dobtune_view"
#: The page's own script: a PNG button beside every chart's CSV button, and the selected tabs
#: kept in the URL's fragment (put into the page after `HttpAccess.page_extra`).
PAGE_SCRIPT_FILE = web_asset("dashboard.js")


class _ViewReportAnswered(logging.Filter):
    """Drops websockets' "connection rejected (204 No Content)": the answer to a view report
    (only it is answered 204 here); every real refusal (401, 403, 400, 503) stays logged."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.getMessage() != "connection rejected (204 No Content)"


#: One filter, added once per logger (`Filterer.addFilter` skips one already there).
_VIEW_REPORT_ANSWERED = _ViewReportAnswered()


#: The strip at the bottom of the window that holds the E-STOP: viser's app ends above it (the
#: E-STOP floated over the plots and covered the bottom chart's axis and title).
ESTOP_STRIP_PX = 52


def estop_link_html(token: str) -> str:
    """The page's E-STOP (put into the page itself, outside viser's panels, which unmount what
    they collapse): fixed to the window above everything, whatever is collapsed or scrolled, in
    a strip of its own under viser's app (`ESTOP_STRIP_PX`: it covers nothing); a link with the
    token of the page's user into a hidden frame, so it needs neither script nor websocket."""
    return (
        f"<style>#root{{height:calc(100% - {ESTOP_STRIP_PX}px) !important}}</style>"
        f"<a class='dt-estop-fixed' href='{ESTOP_PATH}?token={esc(quote(token))}' "
        "target='dt-estop-frame' title='E-STOP: "
        "speed command 0 and drive disabled' style='position:fixed;left:50%;bottom:4px;"
        "transform:translateX(-50%);z-index:2147483647;background:#d62728;color:#fff;"
        "font:bold 20px sans-serif;letter-spacing:1px;padding:8px 34px;border-radius:8px;"
        "border:3px solid #7f0000;box-shadow:0 1px 4px rgba(0,0,0,.35);text-decoration:none;"
        "line-height:22px'>"
        "E-STOP</a><iframe name='dt-estop-frame' title='e-stop answer' style='display:none'>"
        "</iframe>"
    )


_DENIED_PAGE = (
    "<!doctype html><meta charset=utf-8><title>dobtune: token required</title>"
    "<p style='font:16px sans-serif;margin:2em'>This dashboard needs its access token: open "
    "the URL the dashboard printed when it started (it ends in <code>?token=...</code>), in "
    "a tab of its own: other sites and other local ports cannot use it.</p>"
)
_STARTING_PAGE = (
    "<!doctype html><meta charset=utf-8><title>dobtune: starting</title>"
    "<p style='font:16px sans-serif;margin:2em'>The dashboard is starting: reload in a moment."
    "</p>"
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
    _by_connection: weakref.WeakKeyDictionary[ServerConnection, str] = field(
        default_factory=weakref.WeakKeyDictionary, repr=False)
    _slot_by_connection: weakref.WeakKeyDictionary[ServerConnection, str] = field(
        default_factory=weakref.WeakKeyDictionary, repr=False)
    _page_by_connection: weakref.WeakKeyDictionary[ServerConnection, str] = field(
        default_factory=weakref.WeakKeyDictionary, repr=False)
    page_extra: str = ""
    """HTML put at the end of the page's body (the index page only), after the E-STOP link."""
    page_script: str = field(default_factory=page_script_html, repr=False)
    """A script element put after `page_extra` (by default web_assets/dashboard.js)."""
    on_estop: Callable[[str], str] | None = None
    """Called with the user for a request to ESTOP_PATH (on the server's event loop: it must
    not block); returns the text to answer."""

    _proofs_refused: set[str] = field(default_factory=set, repr=False)
    proven: bool = False
    """Whether `prove` has shown the check in front of every route (until then nothing is
    served: 503)."""
    on_view: Callable[[str, bool], None] | None = None
    """Called with a page's id and whether it shows the live traces, for a request to
    VIEW_PATH (on the server's event loop: it must not block)."""

    def token_of(self, user: str = "") -> str:
        return self.users[user] if self.users else self.token

    def user_of_connection(self, connection: ServerConnection) -> str | None:
        """The user whose token opened this websocket ("" with a single token), None if
        the connection did not pass this check."""
        return self._by_connection.get(connection)

    def slot_of_connection(self, connection: ServerConnection) -> str:
        """The candidate slot the page behind this websocket named ("": none; see
        `slot_of_path`)."""
        return self._slot_by_connection.get(connection, "")

    def page_of_connection(self, connection: ServerConnection) -> str:
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

    def user_of(self, path: str) -> str | None:
        """The user a request speaks for: the token in its URL (None: nobody's)."""
        query = parse_qs(urlsplit(path).query)
        return self._user_by(query["token"][0] if query.get("token") else None)

    def check(self, path: str, headers: Mapping[str, str]) -> str:
        """"" when the request may go on, else why not (see the module's description)."""
        host = headers.get("Host", "")
        if self.port and host not in self.allowed_hosts():
            return f"host {host!r} is not this dashboard"
        origin = headers.get("Origin")
        if origin is not None and urlsplit(origin).netloc != host:
            return f"origin {origin!r} is not this dashboard ({host})"
        page = urlsplit(path).path in PAGE_PATHS and "Upgrade" not in headers
        site = headers.get("Sec-Fetch-Site")
        if not page and site is not None and site != "same-origin":
            return f"a request from another site or port (Sec-Fetch-Site: {site})"
        if self.user_of(path) is None:
            return "no valid token"
        return ""

    def wrap(self, process_request: ProcessRequest | None) -> ProcessRequest:
        """viser's `process_request` with this check in front of it."""
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        def answer(status: http.HTTPStatus, body: bytes) -> Response:
            return Response(status.value, status.phrase, Headers(**{
                "Content-Type": "text/html; charset=utf-8", "Content-Length": str(len(body)),
                "Cache-Control": "no-store", "Referrer-Policy": "no-referrer",
            }), body)

        def gated(connection: ServerConnection, request: Request) -> Response | None:
            why = self.check(request.path, request.headers)
            upgrade = "Upgrade" in request.headers
            if why:
                self.refused += 1
                proof = request.headers.get(PROOF_HEADER)
                if proof:
                    self._proofs_refused.add(proof)
                log.debug("refused %s: %s", urlsplit(request.path).path, why)
                return answer(http.HTTPStatus.FORBIDDEN if upgrade else
                              http.HTTPStatus.UNAUTHORIZED, _DENIED_PAGE.encode())
            if not self.proven:
                return answer(http.HTTPStatus.SERVICE_UNAVAILABLE, _STARTING_PAGE.encode())
            user = self.user_of(request.path)
            assert user is not None  # check() passed
            route = urlsplit(request.path).path
            if route == ESTOP_PATH and self.on_estop is not None:
                text = self.on_estop(user)
                return answer(http.HTTPStatus.OK, (
                    f"<!doctype html><meta charset=utf-8><title>E-STOP</title>"
                    f"<p>{esc(text)}</p>").encode())
            if route == VIEW_PATH:
                # websockets logs every answer but a websocket's as "connection rejected":
                # the page's report, answered 204 every 10 s per tab, is no rejection.
                adapter = connection.logger
                (adapter.logger if isinstance(adapter, logging.LoggerAdapter)
                 else adapter).addFilter(_VIEW_REPORT_ANSWERED)
                return self._view(request.path)
            if upgrade:
                self._by_connection[connection] = user
                slot = slot_of_path(request.path)
                if slot:
                    self._slot_by_connection[connection] = slot
                page = _id_param(request.path, PAGE_PARAM)
                if page:
                    self._page_by_connection[connection] = page
            response = process_request(connection, request) if process_request else None
            if response is not None and route in PAGE_PATHS:
                extra = estop_link_html(self.token_of(user)) + self.page_extra + self.page_script
                response = _with_extra(response, extra)
                response.headers["Referrer-Policy"] = "no-referrer"
                response.headers["Content-Security-Policy"] = "frame-ancestors 'self'"
                response.headers["Cache-Control"] = "no-store"
                response.headers["Set-Cookie"] = (  # a token an older version left in a cookie
                    f"{LEGACY_COOKIE}=; Max-Age=0; HttpOnly; SameSite=Strict; Path=/")
            return response

        return gated

    def prove(self, host: str, timeout_s: float = 5.0) -> None:
        """Show that this check answers in front of every route of the server it was put in
        front of: a request without the token, on loopback, to the page, the websocket and
        each of the dashboard's own routes, must be refused by this check (each request
        carries a nonce the check notes when it refuses it: a browser refused meanwhile
        proves nothing and spoils nothing). Then requests with the token are served; else
        `GateOpen`, naming the routes that were not refused."""
        loopback = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
        open_routes = []
        for route, upgrade in PROOF_ROUTES:
            nonce = secrets.token_hex(8)
            status: int | str
            try:
                status = _request_status(loopback, self.port, route, upgrade, nonce, timeout_s)
            except (OSError, http.client.HTTPException) as exc:
                status = f"no answer ({exc})"
            refused_here = nonce in self._proofs_refused and status in (401, 403)
            if not refused_here:
                what = "websocket" if upgrade else route.split("?")[0]
                open_routes.append(f"{what} (answered {status} without the token)")
        if open_routes:
            raise GateOpen(
                "the access gate is not in front of every route: " + "; ".join(open_routes) +
                ". Refusing to serve: anyone who reaches the port could use the dashboard. "
                "viser or websockets may start the server in a way server/viser_adapter.py "
                "does not know (run tests/test_viser_adapter.py)")
        self.proven = True

    def _view(self, path: str) -> Response:
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
        with viser_adapter.gated_serve(self.wrap):
            yield


class GateOpen(RuntimeError):
    """The access gate is not in front of every route: the dashboard must not serve."""


#: The header that marks `HttpAccess.prove`'s own requests (a nonce each).
PROOF_HEADER = "X-Dobtune-Gate-Proof"
#: The page's paths (viser serves its page at both).
PAGE_PATHS = ("/", "/index.html")
#: What `HttpAccess.prove` asks without the token: (path, as a websocket handshake).
PROOF_ROUTES: tuple[tuple[str, bool], ...] = (
    ("/", False), ("/index.html", False), ("/", True), (ESTOP_PATH, False),
    (f"{VIEW_PATH}?dt_page={'0' * 24}&live=1", False),
)


def _request_status(host: str, port: int, path: str, upgrade: bool, nonce: str,
                    timeout_s: float) -> int:
    """The status of one GET (a websocket handshake if `upgrade`) without any token."""
    conn = http.client.HTTPConnection(host, port, timeout=timeout_s)
    try:
        headers = {"Host": f"{'localhost' if ':' in host else host}:{port}", PROOF_HEADER: nonce}
        if upgrade:
            headers.update({"Upgrade": "websocket", "Connection": "Upgrade",
                            "Sec-WebSocket-Version": "13",
                            "Sec-WebSocket-Key": "ZG9idHVuZS1wcm9vZi0xNg=="})
        conn.request("GET", path, headers=headers)
        return conn.getresponse().status
    finally:
        conn.close()


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


def _with_extra(response: Response, extra: str) -> Response:
    """`response` (an HTML page, maybe gzipped) with `extra` before its closing body tag."""
    if response.status_code != 200 or not response.headers.get(
            "Content-Type", "").startswith("text/html"):
        return response
    body = _page_with_extra(bytes(response.body),
                            response.headers.get("Content-Encoding") == "gzip", extra)
    del response.headers["Content-Length"]  # a multi-dict: assigning would add a second one
    response.headers["Content-Length"] = str(len(body))
    return dataclasses.replace(response, body=body)


@functools.lru_cache(maxsize=8)
def _page_with_extra(body: bytes, zipped: bool, extra: str) -> bytes:
    """`body` (gzipped if `zipped`) with `extra` before its closing body tag. Cached: viser
    serves the same page's bytes (its own gzip cache) every time, and recompressing its ~0.8 MB
    took ~0.5 s of the dashboard's CPU per page load at load 15-20 (py-spy), before the page's
    first byte."""
    page = gzip.decompress(body) if zipped else body
    end = page.rfind(b"</body>")
    page = page[:end] + extra.encode() + page[end:] if end >= 0 else page + extra.encode()
    return gzip.compress(page, mtime=0) if zipped else page
