"""The dashboard's door: a token in the URL, Origin and Host checks, no share tunnel. A real
dashboard (no controller needed) and raw HTTP / websocket clients, as an attacker would use."""

from __future__ import annotations

import socket
import urllib.error
import urllib.request
from collections.abc import Iterator

import pytest
from helpers import free_port, wait_for
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from server.app import Dashboard, DashboardOptions
from server.http_access import COOKIE, ESTOP_PATH, VIEW_PATH, HttpAccess


@pytest.fixture(scope="module")
def dash() -> Iterator[Dashboard]:
    opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{free_port()}",), rig_name="gate",
                            port=free_port(), verbose=False, query_timeout_s=0.5)
    with Dashboard(opts) as d:
        yield d


def _base(d: Dashboard) -> str:
    return f"127.0.0.1:{d.access.port}"


def test_the_page_needs_the_token_and_sets_a_cookie(dash: Dashboard) -> None:
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(f"http://{_base(dash)}/", timeout=5)
    assert err.value.code == 401 and b"token" in err.value.read()
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(f"http://{_base(dash)}/?token=wrong", timeout=5)
    assert err.value.code == 401
    with urllib.request.urlopen(dash.url, timeout=5) as r:
        assert r.status == 200
        cookie = r.headers["Set-Cookie"]
        page = r.read()
    assert b"dt-estop-fixed" in page and ESTOP_PATH.encode() in page  # the E-STOP is in it
    assert cookie.startswith(f"{COOKIE}={dash.access.token};") and "HttpOnly" in cookie
    assert "SameSite=Strict" in cookie


@pytest.mark.parametrize("headers, why", [
    ({}, "no cookie, no token"),
    ({"Cookie": f"{COOKIE}=wrong"}, "a wrong token"),
    ({"Cookie": "COOKIE", "Origin": "http://evil.example"}, "another site"),
])
def test_a_websocket_without_the_token_or_from_another_site_is_refused(
    dash: Dashboard, headers: dict[str, str], why: str
) -> None:
    if headers.get("Cookie") == "COOKIE":
        headers = {**headers, "Cookie": f"{COOKIE}={dash.access.token}"}
    before = dash.access.refused
    with pytest.raises(InvalidStatus) as err:
        connect(f"ws://{_base(dash)}/", additional_headers=headers, open_timeout=5,
                subprotocols=["viser-v1"])  # type: ignore[list-item]
    assert err.value.response.status_code == 403, why
    assert dash.access.refused == before + 1
    assert not dash.server.get_clients()  # viser never saw it


def test_the_page_origin_with_the_cookie_connects(dash: Dashboard) -> None:
    headers = {"Cookie": f"{COOKIE}={dash.access.token}", "Origin": f"http://{_base(dash)}"}
    with connect(f"ws://{_base(dash)}/", additional_headers=headers, open_timeout=5) as ws:
        assert ws.response is not None and ws.response.status_code == 101  # handshake passed


def test_gate_checks_host_and_origin() -> None:
    g = HttpAccess("127.0.0.1", token="t" * 32, port=8080)
    ok = {"Upgrade": "websocket", "Host": "127.0.0.1:8080", "Cookie": f"{COOKIE}={'t' * 32}",
          "Origin": "http://127.0.0.1:8080"}
    assert g.check("/", ok) == ("", False)
    assert g.check("/", {**ok, "Host": "evil:8080"})[0].startswith("host")
    assert g.check("/", {**ok, "Origin": "http://localhost:8080"})[0].startswith("origin")
    assert g.check("/?token=" + "t" * 32, {}) == ("", True)
    assert g.check("/?token=" + "t" * 31 + "u", {})[0] == "no valid token"


def test_the_share_tunnel_is_never_opened(dash: Dashboard) -> None:
    assert dash.server.request_share_url() is None


def test_a_busy_http_port_is_an_error_not_another_port(capsys: pytest.CaptureFixture) -> None:
    from server.app import PortBusy, run_dashboard

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
    from server.app import PortBusy, check_port_free

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


def test_the_estop_link_needs_the_token_and_this_host(dash: Dashboard) -> None:
    """The always-visible E-STOP is a plain GET: anyone with the page (any role) may press it,
    nobody without the token, and no other host name (DNS rebinding)."""
    calls: list[str] = []
    real = dash.access.on_estop
    dash.access.on_estop = lambda user: calls.append(user) or "E-STOP sent"
    try:
        url = f"http://{_base(dash)}{ESTOP_PATH}"
        for bad in ({}, {"Cookie": f"{COOKIE}=wrong"}):
            with pytest.raises(urllib.error.HTTPError) as err:
                urllib.request.urlopen(urllib.request.Request(url, headers=bad), timeout=5)
            assert err.value.code == 401
        rebound = {"Cookie": f"{COOKIE}={dash.access.token}", "Host": f"evil:{dash.access.port}"}
        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(urllib.request.Request(url, headers=rebound), timeout=5)
        assert calls == []
        ok = {"Cookie": f"{COOKIE}={dash.access.token}"}
        with urllib.request.urlopen(urllib.request.Request(url, headers=ok), timeout=5) as r:
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
    ok = {"Cookie": f"{COOKIE}={dash.access.token}"}
    with connect(f"ws://{_base(dash)}/?dt_page={page}", additional_headers=ok, open_timeout=5,
                 subprotocols=[f"viser-v{viser.__version__}"]):  # type: ignore[list-item]
        assert dash.server is not None
        conns = dash.server._websock_server._live_connections
        wait_for(lambda: any(dash.access.page_of_connection(c) == page
                             for c in list(conns.values())), 10.0,
                 "the websocket's page id is not known")
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(f"{url}?dt_page={page}&live=0", timeout=5)
        assert err.value.code == 401 and page not in dash._live_hidden
        rebound = {**ok, "Host": f"evil:{dash.access.port}"}
        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(urllib.request.Request(
                f"{url}?dt_page={page}&live=0", headers=rebound), timeout=5)
        assert page not in dash._live_hidden
        for query, field in (("dt_page=x&live=0", "dt_page"), (f"dt_page={page}&live=2", "live"),
                             (f"dt_page={page}", "live")):
            with pytest.raises(urllib.error.HTTPError) as err:
                urllib.request.urlopen(urllib.request.Request(f"{url}?{query}", headers=ok),
                                       timeout=5)
            assert err.value.code == 400 and err.value.read().decode().startswith(field)
        assert page not in dash._live_hidden
        for live, hidden in (("0", True), ("1", False), ("0", True)):
            with urllib.request.urlopen(
                    urllib.request.Request(f"{url}?dt_page={page}&live={live}", headers=ok),
                    timeout=5) as r:
                assert r.status == 204 and r.headers["Cache-Control"] == "no-store"
            assert (page in dash._live_hidden) is hidden, f"live={live}"
        # A hostile client's made-up ids (no page of theirs is connected) are not kept.
        for k in range(200):
            with urllib.request.urlopen(urllib.request.Request(
                    f"{url}?dt_page={k:024d}&live=0", headers=ok), timeout=5) as r:
                assert r.status == 204
        made_up = {f"{k:024d}" for k in range(200)}
        assert page in dash._live_hidden and not made_up & dash._live_hidden
