"""The dashboard's credentials are bound to its origin (issue 31 item 4), in a real browser.

The attack as measured: the operator has the dashboard open; a page served by another local web
server, on another port of 127.0.0.1, is opened in the same browser. Browsers do not bind
cookies to a port, so that server received the operator's token in a cookie, and a plain
`<img>` there fired the E-STOP link. Here the other server records every request it gets, and
its page tries the E-STOP link (as an image, a frame and a scripted request), the view report
and the websocket. Nothing may carry the token to it, and the dashboard must fire nothing;
the dashboard's own E-STOP link still works."""

from __future__ import annotations

import http.server
import threading
from collections.abc import Iterator
from typing import Any, ClassVar

import pytest
from conftest import FIRST_LOAD_S, VIEWPORT
from helpers import free_port, wait_for

from server.dashboard.app import Dashboard, DashboardOptions
from server.http_access import ESTOP_PATH, VIEW_PATH

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def dash() -> Iterator[Dashboard]:
    opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{free_port()}",), rig_name="origin",
                            port=free_port(), verbose=False, query_timeout_s=0.5)
    with Dashboard(opts) as d:
        yield d


def _evil_page(dash_port: int) -> bytes:
    base = f"http://127.0.0.1:{dash_port}"
    return f"""<!doctype html><meta charset=utf-8><title>another local app</title>
<img id=a src="{base}{ESTOP_PATH}">
<iframe id=f src="{base}{ESTOP_PATH}"></iframe>
<script>
const done = [];
const note = (what) => () => {{ done.push(what); document.title = "done " + done.length; }};
document.getElementById("a").onerror = note("img");
document.getElementById("a").onload = note("img");
document.getElementById("f").onload = note("frame");
fetch("{base}{ESTOP_PATH}", {{credentials: "include", mode: "no-cors"}})
  .then(note("fetch"), note("fetch"));
fetch("{base}{VIEW_PATH}?dt_page={'0' * 24}&live=0", {{credentials: "include", mode: "no-cors"}})
  .then(note("view"), note("view"));
const ws = new WebSocket("ws://127.0.0.1:{dash_port}/", ["viser-v1"]);
ws.onerror = note("ws");
</script>""".encode()


class _Recorder(http.server.BaseHTTPRequestHandler):
    seen: ClassVar[list[dict[str, str]]] = []
    page = b""

    def do_GET(self) -> None:
        type(self).seen.append({"path": self.path, **{k: v for k, v in self.headers.items()}})
        self.send_response(200)
        self.send_header("Content-Type", "text/html; charset=utf-8")
        self.send_header("Content-Length", str(len(self.page)))
        self.end_headers()
        self.wfile.write(self.page)

    def log_message(self, *args: Any) -> None:
        pass


@pytest.fixture
def evil(dash: Dashboard) -> Iterator[tuple[str, type[_Recorder]]]:
    class Handler(_Recorder):
        seen: ClassVar[list[dict[str, str]]] = []
        page = _evil_page(dash.access.port)

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/", Handler
    finally:
        server.shutdown()
        server.server_close()


def test_another_local_port_gets_no_token_and_fires_nothing(
    dash: Dashboard, evil: tuple[str, type[_Recorder]], chromium_browser: Any
) -> None:
    evil_url, recorder = evil
    fired: list[str] = []
    real = dash.access.on_estop
    dash.access.on_estop = lambda user: fired.append(user) or "E-STOP sent"
    context = chromium_browser.new_context(viewport=VIEWPORT)
    try:
        page = context.new_page()
        page.goto(dash.url, wait_until="domcontentloaded", timeout=FIRST_LOAD_S * 1000)
        page.wait_for_selector(".dt-estop-fixed", timeout=FIRST_LOAD_S * 1000)
        wait_for(lambda: dash.server is not None and dash.server.get_clients(), FIRST_LOAD_S,
                 "the dashboard's page never connected")
        refused = dash.access.refused

        other = context.new_page()
        other.goto(evil_url, wait_until="load")
        other.wait_for_function("document.title === 'done 5'", timeout=30_000)
        # Four requests and the websocket reached the dashboard and were refused.
        wait_for(lambda: dash.access.refused >= refused + 5, 10.0,
                 "the other page's requests were not refused by the dashboard")
        assert fired == []
        # The other server got no token: in no cookie, no header, no URL.
        assert recorder.seen, "the other server got no request"
        for request in recorder.seen:
            assert dash.access.token not in str(request), request

        # The dashboard's own E-STOP link (same origin, the token in the page) still fires.
        page.bring_to_front()
        page.locator(".dt-estop-fixed").click()
        wait_for(lambda: fired == [""], 20.0, "the page's own E-STOP link did not fire")
    finally:
        context.close()
        dash.access.on_estop = real
