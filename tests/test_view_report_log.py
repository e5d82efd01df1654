"""The server's log and the page's view report (issue 33 smaller item): a real dashboard (no
controller needed) and raw HTTP requests. websockets logs every answer but a websocket's as
"connection rejected (...)": the view report (every 10 s per tab) is no rejection and is not
logged; a real refusal still is."""

from __future__ import annotations

import logging
import urllib.error
import urllib.request
from collections.abc import Iterator

import pytest
from helpers import free_port

try:
    from server.dashboard.app import Dashboard, DashboardOptions
except ImportError:  # (the tree before server/app.py moved to server/dashboard/)
    from server.app import Dashboard, DashboardOptions  # type: ignore[no-redef]
from server.http_access import VIEW_PATH


@pytest.fixture(scope="module")
def dash() -> Iterator[Dashboard]:
    opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{free_port()}",), rig_name="quiet",
                            port=free_port(), verbose=False, query_timeout_s=0.5)
    with Dashboard(opts) as d:
        yield d


def test_view_reports_are_not_logged_as_rejections_but_refusals_are(
    dash: Dashboard, caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="websockets")
    base = f"http://127.0.0.1:{dash.access.port}"
    ok = {"Sec-Fetch-Site": "same-origin"}
    for live in (1, 0, 1):
        req = urllib.request.Request(
            f"{base}{VIEW_PATH}?dt_page={'p' * 24}&live={live}&token={dash.access.token}",
            headers=ok)
        with urllib.request.urlopen(req, timeout=5) as r:
            assert r.status == 204
    # A report without the token, and a bad one: refusals, logged as before.
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(f"{base}{VIEW_PATH}?dt_page={'p' * 24}&live=0", timeout=5)
    assert err.value.code == 401
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(urllib.request.Request(
            f"{base}{VIEW_PATH}?dt_page=x&live=0&token={dash.access.token}", headers=ok),
            timeout=5)
    assert err.value.code == 400
    said = [r.getMessage() for r in caplog.records if r.name.startswith("websockets")]
    assert "connection rejected (401 Unauthorized)" in said, said
    assert "connection rejected (400 Bad Request)" in said, said
    assert not [m for m in said if "204" in m], said
