"""The recordings comparison opens only the files the list shows, and shows what one browser
compares to that browser only (issue 31 item 6: it opened `../` and absolute paths, showed them
to every browser, and its error told whether a file existed).

A real dashboard (one identity) with two recordings in its directory and one outside it, two
raw websocket clients (tests/viser_raw.py), each with its own comparison in the Compare runs
tab (server/panels/recordings.py `CompareView`)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import free_port, wait_for
from sine_recordings import write_sine_recording
from viser_raw import RawViser

from controller.core.config import LoopConfig
from server.dashboard.app import Dashboard, DashboardOptions
from server.panels.recordings import NOT_LISTED, CompareView
from server.viser_adapter import control_uuid

A_NAME, B_NAME = "1-before.mcap", "2-after.mcap"


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    base = tmp_path_factory.mktemp("recaccess")
    rec = base / "rec"
    rec.mkdir()
    cfg = LoopConfig()
    write_sine_recording(rec / A_NAME, cfg, 0.0, 1.0, seconds=8.0)
    write_sine_recording(rec / B_NAME, cfg.with_(q_cutoff_hz=0.8), 1.0, 0.5, seconds=8.0)
    outside = write_sine_recording(base / "secret.mcap", cfg, 0.0, 2.0, seconds=8.0)
    opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{free_port()}",), rig_name="recaccess",
                            port=free_port(), verbose=False, query_timeout_s=0.5,
                            recordings_dir=rec)
    with Dashboard(opts) as d:
        assert d.recordings is not None
        wait_for(lambda: len(d.recordings.rows) == 2, 60.0, "the list was never read")
        yield {"dash": d, "rec": rec, "outside": outside}


def _browser(dash: Dashboard) -> tuple[RawViser, Any]:
    assert dash.server is not None
    before = set(dash.server.get_clients())
    raw = RawViser(dash.url.replace("http://", "ws://"), origin=dash.url.split("/?")[0])
    found: list[Any] = []

    def built() -> bool:
        assert dash.recordings is not None
        for cid, b in dash.server.get_clients().items():
            if cid not in before and dash.recordings.view_of(b) is not None:
                found.append(b)
                return True
        return False

    wait_for(built, 30.0, "no comparison built for the new browser")
    return raw, found[0]


@pytest.fixture(scope="module")
def two(env: dict[str, Any]) -> Iterator[list[tuple[RawViser, Any]]]:
    out = [_browser(env["dash"]), _browser(env["dash"])]
    yield out
    for raw, _b in out:
        raw.ws.close()


def _view(dash: Dashboard, browser: Any) -> CompareView:
    assert dash.recordings is not None
    view = dash.recordings.view_of(browser)
    assert view is not None
    return view


def test_only_listed_recordings_are_opened(env: dict[str, Any],
                                           two: list[tuple[RawViser, Any]]) -> None:
    dash: Dashboard = env["dash"]
    rec: Path = env["rec"]
    outside: Path = env["outside"]
    view = _view(dash, two[0][1])
    names = [f"../{outside.name}", str(outside), str(rec / A_NAME), "/etc/passwd",
             "../nothing-here.mcap", "/no/such/file.mcap", f"./{A_NAME}", f"x/../{A_NAME}",
             "not-listed.mcap", ""]
    answers = {view.compare(A_NAME, name) for name in names}
    answers |= {view.compare(name, B_NAME) for name in names}
    # One answer for all of them: whether such a file exists is not told.
    assert len(answers) == 1 and NOT_LISTED in answers.pop()
    assert view.chart is not None and view.replay(1.0) is None  # nothing was compared
    assert str(outside) not in view.compare_box.content


def test_a_file_not_in_the_list_is_not_opened_until_listed(
        env: dict[str, Any], two: list[tuple[RawViser, Any]]) -> None:
    """A recording written after the list was read is compared once the list shows it; a
    listed file replaced by garbage is said to be unreadable (it is listed: no secret)."""
    dash: Dashboard = env["dash"]
    rec: Path = env["rec"]
    assert dash.recordings is not None
    view = _view(dash, two[0][1])
    late = rec / "3-late.mcap"
    write_sine_recording(late, LoopConfig(), 0.0, 0.7, seconds=8.0)
    try:
        assert NOT_LISTED in view.compare(A_NAME, late.name)
        dash.recordings.refresh()
        assert "3-late.mcap" in view.compare(A_NAME, late.name)
        late.write_bytes(b"not an mcap file")
        assert "Cannot compare" in view.compare(A_NAME, late.name)
    finally:
        late.unlink()
        dash.recordings.refresh()


def test_what_one_browser_compares_is_shown_to_it_only(
        env: dict[str, Any], two: list[tuple[RawViser, Any]]) -> None:
    dash: Dashboard = env["dash"]
    assert dash.live is not None
    (raw1, b1), (raw2, b2) = two
    v1, v2 = _view(dash, b1), _view(dash, b2)
    assert v1 is not v2
    before2 = v2.compare_box.content
    # The first browser presses its own Compare (A and B picked: the list's first and last).
    assert v1.pick_a is not None and v1.pick_b is not None
    raw1.update(control_uuid(v1.pick_a), {"value": A_NAME})
    raw1.update(control_uuid(v1.pick_b), {"value": B_NAME})
    wait_for(lambda: v1.pick_b.value == B_NAME and v1.pick_a.value == A_NAME, 20.0,
             "the picks did not arrive")
    raw1.update(control_uuid(v1.compare_button), {"value": True})
    wait_for(lambda: B_NAME in v1.compare_box.content and "dt-compare-run" in
             v1.compare_box.content, 60.0, "the first browser's comparison never showed")
    raw1.pump_until(lambda: _shows(raw1, "dt-compare-run"), 20.0,
                    "the first page was not sent its comparison")
    # The second browser's comparison is as it was, and its page is sent nothing of it: a
    # shared change made after the comparison reaches it, the comparison does not.
    assert v2.compare_box.content == before2 and v2.replay(1.0) is None
    dash.live.window_s.value = 17.0
    raw2.pump_until(lambda: any(m.get("updates") == {"value": 17.0} for m in raw2.messages),
                    20.0, "the second page never got the shared change")
    assert not _shows(raw2, "dt-compare-run")


def _shows(raw: RawViser, text: str) -> bool:
    return any(text in str(m) for m in raw.messages)
