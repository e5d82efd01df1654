"""The dashboard's door: a token in the URL, bound to the dashboard's origin (Host, Origin,
Sec-Fetch-Site; no cookie), no share tunnel, and a gate that proves itself before serving. A real
dashboard (no controller needed) and raw HTTP / websocket clients, as an attacker would use."""

from __future__ import annotations

import contextlib
import socket
import urllib.error
import urllib.request
from collections.abc import Iterator

import pytest
from helpers import free_port, wait_for
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from server import viser_adapter
from server.dashboard.app import Dashboard, DashboardOptions
from server.http_access import (
    ESTOP_PATH,
    LEGACY_COOKIE,
    PROOF_ROUTES,
    VIEW_PATH,
    GateOpen,
    HttpAccess,
)


@pytest.fixture(scope="module")
def dash() -> Iterator[Dashboard]:
    opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{free_port()}",), rig_name="gate",
                            port=free_port(), verbose=False, query_timeout_s=0.5)
    with Dashboard(opts) as d:
        yield d


def _base(d: Dashboard) -> str:
    return f"127.0.0.1:{d.access.port}"


def _viser_protocol() -> list[str]:
    import viser

    return [f"viser-v{viser.__version__}"]


def test_the_page_needs_the_token_and_sets_no_cookie(dash: Dashboard) -> None:
    for url in (f"http://{_base(dash)}/", f"http://{_base(dash)}/?token=wrong"):
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(url, timeout=5)
        assert err.value.code == 401 and b"token" in err.value.read()
    # The token in a cookie (as older versions kept it) opens nothing: every port of the
    # host gets a cookie of 127.0.0.1.
    cookie = {"Cookie": f"{LEGACY_COOKIE}={dash.access.token}"}
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(urllib.request.Request(f"http://{_base(dash)}/", headers=cookie),
                               timeout=5)
    assert err.value.code == 401
    with urllib.request.urlopen(dash.url, timeout=5) as r:
        assert r.status == 200
        set_cookie = r.headers.get_all("Set-Cookie") or []
        page = r.read()
        assert r.headers["Referrer-Policy"] == "no-referrer"  # the URL's token stays here
        assert "frame-ancestors 'self'" in r.headers["Content-Security-Policy"]
    assert b"dt-estop-fixed" in page and ESTOP_PATH.encode() in page  # the E-STOP is in it
    assert f"{ESTOP_PATH}?token={dash.access.token}".encode() in page
    # The only cookie: the deletion of an older version's.
    assert set_cookie == [f"{LEGACY_COOKIE}=; Max-Age=0; HttpOnly; SameSite=Strict; Path=/"]


@pytest.mark.parametrize("query, headers, why", [
    ("", {}, "no token"),
    ("?token=wrong", {}, "a wrong token"),
    ("", {"Cookie": "COOKIE"}, "the token in a cookie, as any local port receives it"),
    ("?token=TOKEN", {"Origin": "http://evil.example"}, "another site"),
    ("?token=TOKEN", {"Origin": "http://127.0.0.1:1"}, "another port of this host"),
    ("?token=TOKEN", {"Sec-Fetch-Site": "same-site"}, "a page of another port"),
    ("?token=TOKEN", {"Sec-Fetch-Site": "cross-site"}, "a page of another site"),
])
def test_a_websocket_without_the_token_or_from_another_origin_is_refused(
    dash: Dashboard, query: str, headers: dict[str, str], why: str
) -> None:
    query = query.replace("TOKEN", dash.access.token)
    if headers.get("Cookie") == "COOKIE":
        headers = {**headers, "Cookie": f"{LEGACY_COOKIE}={dash.access.token}"}
    before = dash.access.refused
    with pytest.raises(InvalidStatus) as err:
        connect(f"ws://{_base(dash)}/{query}", additional_headers=headers, open_timeout=5,
                subprotocols=_viser_protocol())  # type: ignore[arg-type]
    assert err.value.response.status_code == 403, why
    assert dash.access.refused == before + 1
    assert not dash.server.get_clients()  # viser never saw it


def test_the_page_origin_with_the_token_connects(dash: Dashboard) -> None:
    headers = {"Origin": f"http://{_base(dash)}", "Sec-Fetch-Site": "same-origin"}
    with connect(f"ws://{_base(dash)}/?token={dash.access.token}", additional_headers=headers,
                 open_timeout=5) as ws:
        assert ws.response is not None and ws.response.status_code == 101  # handshake passed


def test_gate_checks_host_origin_and_fetch_site() -> None:
    t = "t" * 32
    g = HttpAccess("127.0.0.1", token=t, port=8080)
    ok = {"Upgrade": "websocket", "Host": "127.0.0.1:8080", "Origin": "http://127.0.0.1:8080",
          "Sec-Fetch-Site": "same-origin"}
    assert g.check(f"/?token={t}", ok) == ""
    assert g.check("/", ok) == "no valid token"
    assert g.check(f"/?token={t}", {**ok, "Host": "evil:8080"}).startswith("host")
    assert g.check(f"/?token={t}", {**ok, "Origin": "http://localhost:8080"}).startswith("origin")
    assert g.check(f"/?token={t}", {**ok, "Sec-Fetch-Site": "same-site"}).startswith("a request")
    host = {"Host": "127.0.0.1:8080"}
    assert g.check(f"/?token={t[:-1]}u", host) == "no valid token"
    for route in (ESTOP_PATH, VIEW_PATH):
        assert g.check(f"{route}?token={t}", {**host, "Sec-Fetch-Site": "same-origin"}) == ""
        for site in ("same-site", "cross-site", "none"):
            assert g.check(f"{route}?token={t}", {**host, "Sec-Fetch-Site": site}).startswith(
                "a request"), (route, site)
    # The page itself may be opened from anywhere with its token (a terminal, the Fleet
    # tab's link to another rig's view on another port).
    for site in ("none", "same-site", "cross-site"):
        assert g.check(f"/?token={t}", {**host, "Sec-Fetch-Site": site}) == ""


def test_nothing_is_served_until_the_gate_is_proven() -> None:
    """Fail closed: between the server's start and the proof, even the token gets 503."""
    from websockets.datastructures import Headers
    from websockets.http11 import Request

    g = HttpAccess("127.0.0.1", token="t" * 32, port=8080)
    served: list[str] = []
    gated = g.wrap(lambda _c, r: served.append(r.path))
    request = Request(f"/?token={'t' * 32}", Headers(Host="127.0.0.1:8080"))
    assert gated(object(), request).status_code == 503 and served == []
    g.proven = True
    assert gated(object(), request) is None and served == [request.path]


def test_the_share_tunnel_is_never_opened(dash: Dashboard) -> None:
    assert dash.server.request_share_url() is None


def test_a_busy_http_port_is_an_error_not_another_port(capsys: pytest.CaptureFixture) -> None:
    from server.dashboard.app import PortBusy, run_dashboard

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        opts = DashboardOptions(connect=("tcp/127.0.0.1:1",), rig_name="busy", port=port,
                                verbose=False)
        assert run_dashboard(opts) == 2
        assert f"--port {port}" in capsys.readouterr().out
        with pytest.raises(PortBusy, match="in use"):
            Dashboard(opts).__enter__()


def test_a_port_whose_last_dashboard_just_stopped_is_free() -> None:
    """A dashboard stopped while browsers were connected leaves its side of their connections
    in TIME_WAIT for a minute: a restart on the same port must not count it as busy (found by
    tests/browser/test_restart_browser.py); a listener still does."""
    from server.dashboard.app import PortBusy, check_port_free

    with socket.socket() as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        with pytest.raises(PortBusy, match="in use"):
            check_port_free("127.0.0.1", port)
        browser = socket.create_connection(("127.0.0.1", port))
        served, _ = listener.accept()
        served.close()  # the server closes first: its side waits in TIME_WAIT
        browser.recv(1)
        browser.close()
    check_port_free("127.0.0.1", port)


def test_the_estop_link_needs_the_token_this_host_and_this_origin(dash: Dashboard) -> None:
    """The always-visible E-STOP is a plain GET: anyone with the page (any role) may press it,
    nobody without the token (a cookie is not the token), no other host name (DNS
    rebinding), no page of another port or site."""
    calls: list[str] = []
    real = dash.access.on_estop
    dash.access.on_estop = lambda user: calls.append(user) or "E-STOP sent"
    try:
        url = f"http://{_base(dash)}{ESTOP_PATH}"
        token = f"?token={dash.access.token}"
        for bad_url, bad in (
                (url, {}),
                (url, {"Cookie": f"{LEGACY_COOKIE}={dash.access.token}"}),
                (url + "?token=wrong", {}),
                (url + token, {"Host": f"evil:{dash.access.port}"}),
                (url + token, {"Sec-Fetch-Site": "same-site"}),
                (url + token, {"Origin": "http://127.0.0.1:1"})):
            with pytest.raises(urllib.error.HTTPError) as err:
                urllib.request.urlopen(urllib.request.Request(bad_url, headers=bad), timeout=5)
            assert err.value.code == 401, bad
        assert calls == []
        ok = {"Sec-Fetch-Site": "same-origin"}
        with urllib.request.urlopen(urllib.request.Request(url + token, headers=ok),
                                    timeout=5) as r:
            assert r.status == 200 and b"E-STOP sent" in r.read()
            assert r.headers["Cache-Control"] == "no-store"
        assert calls == [""]
    finally:
        dash.access.on_estop = real


def test_a_page_says_whether_it_shows_the_live_traces(dash: Dashboard) -> None:
    """The page script reports whether its page shows the live traces (VIEW_PATH, as the E-STOP:
    the token and this host); the page is known by the id its websocket named. A bad report is
    refused naming its field. (That the data then goes to the other pages only: the browser
    test test_ui_browser.py, with real pages.)"""
    import viser

    page = "p" * 24
    url = f"http://{_base(dash)}{VIEW_PATH}"
    tk = f"&token={dash.access.token}"
    ok = {"Sec-Fetch-Site": "same-origin"}
    with connect(f"ws://{_base(dash)}/?dt_page={page}{tk}", open_timeout=5,
                 subprotocols=[f"viser-v{viser.__version__}"]):  # type: ignore[list-item]
        assert dash.server is not None
        wait_for(lambda: any(dash.access.page_of_connection(c) == page
                             for c in viser_adapter.live_connections(dash.server).values()),
                 10.0,
                 "the websocket's page id is not known")
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(f"{url}?dt_page={page}&live=0", timeout=5)
        assert err.value.code == 401 and page not in dash.pages.live_hidden()
        for bad in ({**ok, "Host": f"evil:{dash.access.port}"}, {"Sec-Fetch-Site": "same-site"},
                    {"Cookie": f"{LEGACY_COOKIE}={dash.access.token}"}):
            with pytest.raises(urllib.error.HTTPError):
                urllib.request.urlopen(urllib.request.Request(
                    f"{url}?dt_page={page}&live=0" + ("" if "Cookie" in bad else tk),
                    headers=bad), timeout=5)
        assert page not in dash.pages.live_hidden()
        for query, field in (("dt_page=x&live=0", "dt_page"), (f"dt_page={page}&live=2", "live"),
                             (f"dt_page={page}", "live")):
            with pytest.raises(urllib.error.HTTPError) as err:
                urllib.request.urlopen(urllib.request.Request(f"{url}?{query}{tk}", headers=ok),
                                       timeout=5)
            assert err.value.code == 400 and err.value.read().decode().startswith(field)
        assert page not in dash.pages.live_hidden()
        for live, hidden in (("0", True), ("1", False), ("0", True)):
            with urllib.request.urlopen(
                    urllib.request.Request(f"{url}?dt_page={page}&live={live}{tk}", headers=ok),
                    timeout=5) as r:
                assert r.status == 204 and r.headers["Cache-Control"] == "no-store"
            assert (page in dash.pages.live_hidden()) is hidden, f"live={live}"
        # A hostile client's made-up ids (no page of theirs is connected) are not kept.
        for k in range(200):
            with urllib.request.urlopen(urllib.request.Request(
                    f"{url}?dt_page={k:024d}&live=0{tk}", headers=ok), timeout=5) as r:
                assert r.status == 204
        made_up = {f"{k:024d}" for k in range(200)}
        assert page in dash.pages.live_hidden() and not made_up & dash.pages.live_hidden()


# -- fail closed: the gate proves itself before anything is served ---------------------------


def test_the_dashboard_proved_its_gate_on_every_route(dash: Dashboard) -> None:
    assert dash.access.proven
    routes = {r for r, _ in PROOF_ROUTES}
    assert {"/", "/index.html", ESTOP_PATH} <= routes and any(u for _, u in PROOF_ROUTES)
    assert any(r.startswith(VIEW_PATH) for r in routes)


@contextlib.contextmanager
def _no_gate(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """viser's server started without the check in front of it (as a viser that starts its
    server another way than `websockets.asyncio.server.serve` would)."""
    monkeypatch.setattr(viser_adapter, "gated_serve", lambda _wrap: contextlib.nullcontext())
    yield


def test_a_dashboard_whose_gate_is_not_in_front_refuses_to_start(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    from server.dashboard.app import run_dashboard

    port = free_port()
    opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{free_port()}",), rig_name="open",
                            port=port, verbose=False, query_timeout_s=0.5)
    with _no_gate(monkeypatch):
        with pytest.raises(GateOpen) as err:
            Dashboard(opts).__enter__()
        why = str(err.value)
        assert "not in front of every route" in why and "Refusing to serve" in why
        for route in ("/ (answered 200", "/index.html (answered 200", "websocket",
                      ESTOP_PATH, VIEW_PATH):
            assert route in why, route
        # Nothing listens any more: the server was stopped.
        with socket.socket() as s:
            assert s.connect_ex(("127.0.0.1", port)) != 0
        assert run_dashboard(opts) == 2
    out = capsys.readouterr().out
    assert "dobtune dashboard: the access gate is not in front of every route" in out
    assert "token=" not in out  # no URL was printed


def test_the_proof_holds_while_other_browsers_are_refused(dash: Dashboard) -> None:
    """A browser tab left open from an earlier run reconnects with its old token, refused
    over and over, as the dashboard proves its gate: the proof knows its own requests (a
    nonce each) and is neither spoiled nor helped by them."""
    import threading

    stop = threading.Event()
    sent = [0]

    def old_tab() -> None:
        while not stop.is_set():
            with contextlib.suppress(urllib.error.HTTPError, OSError):
                urllib.request.urlopen(f"http://{_base(dash)}/?token=old", timeout=5)
            sent[0] += 1

    before = dash.access.refused
    thread = threading.Thread(target=old_tab)
    thread.start()
    try:
        wait_for(lambda: sent[0] >= 3, 10.0, "the old tab sent nothing")
        for _ in range(3):
            dash.access.prove("127.0.0.1")
    finally:
        stop.set()
        thread.join()
    assert dash.access.refused - before == sent[0] + 3 * len(PROOF_ROUTES)
