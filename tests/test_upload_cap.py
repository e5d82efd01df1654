"""Uploads capped while they arrive (issue 31 item 6: "an upload that never completes grows the
dashboard by 300 MB in 5 s, kept after disconnect; the 5 MB cap applies only once the upload is
complete"): the attacks from a raw websocket client (tests/viser_raw.py) against a real
dashboard (one identity: every browser may upload, so what is refused here is refused for
everyone), each followed by a check of what viser buffers. Memory under the attack:
tests/bench/bench_upload_memory.py. A viewer's page without the button, and a viewer's upload
refused: tests/integration/test_panel_roles.py."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from helpers import free_port, wait_for
from viser_raw import RawViser

from server.app import Dashboard, DashboardOptions
from server.message_gate import MAX_TRANSFERS, MAX_UPLOAD_BYTES, MAX_UPLOAD_PARTS
from server.viser_adapter import control_uuid

PART = 512 * 1024  # as viser's page sends them


@pytest.fixture(scope="module")
def dash(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Dashboard]:
    base = tmp_path_factory.mktemp("upload")
    opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{free_port()}",), rig_name="upload",
                            port=free_port(), verbose=False, query_timeout_s=0.5,
                            recordings_dir=base / "rec")
    with Dashboard(opts) as d:
        yield d


@pytest.fixture
def raw(dash: Dashboard) -> Iterator[RawViser]:
    assert dash.server is not None
    before = set(dash.server.get_clients())
    with RawViser(dash.url.replace("http://", "ws://"), origin=dash.url.split("/?")[0]) as c:
        wait_for(lambda: set(dash.server.get_clients()) - before, 20.0, "never connected")
        yield c


def _buffered(dash: Dashboard) -> dict[str, Any]:
    """viser's uploads in progress (their parts so far), by transfer."""
    assert dash.server is not None
    return dash.server.gui._current_file_upload_states  # type: ignore[no-any-return]


def _start(raw: RawViser, dash: Dashboard, transfer: str, size: int, parts: int) -> None:
    assert dash.knowledge is not None
    raw.send({"type": "FileTransferStartUpload",
              "source_component_uuid": control_uuid(dash.knowledge.upload),
              "transfer_uuid": transfer, "filename": "x.csv", "mime_type": "text/csv",
              "part_count": parts, "size_bytes": size})


def _part(raw: RawViser, dash: Dashboard, transfer: str, index: int, content: bytes) -> None:
    assert dash.knowledge is not None
    raw.send({"type": "FileTransferPart",
              "source_component_uuid": control_uuid(dash.knowledge.upload),
              "transfer_uuid": transfer, "part_index": index, "content": content})


def _refused_then(dash: Dashboard, before: int, n: int) -> None:
    wait_for(lambda: dash.messages is not None and dash.messages.refused >= before + n, 20.0,
             f"{n} refusals expected")


@pytest.mark.parametrize("size, parts", [
    (300_000_000, 573),  # the attack: 300 MB announced
    (MAX_UPLOAD_BYTES + 1, 10),
    (1_000_000, MAX_UPLOAD_PARTS + 1),  # many small parts
    (-1, 1), (1000, 0), (0, 3),
])
def test_an_upload_announced_over_the_cap_is_refused_at_its_start(
        dash: Dashboard, raw: RawViser, size: int, parts: int) -> None:
    assert dash.messages is not None
    refused = dash.messages.refused
    _start(raw, dash, f"big-{size}-{parts}", size, parts)
    _part(raw, dash, f"big-{size}-{parts}", 0, b"x" * 1000)  # refused: never started
    _refused_then(dash, refused, 2)
    assert f"big-{size}-{parts}" not in _buffered(dash)


def test_parts_beyond_what_was_announced_drop_the_upload(dash: Dashboard, raw: RawViser) -> None:
    """A small file announced, then parts that bring more: dropped at the part that goes over,
    with what viser buffered of it; its later parts are refused."""
    assert dash.messages is not None
    refused = dash.messages.refused
    _start(raw, dash, "liar", 2 * PART, 4)
    _part(raw, dash, "liar", 0, b"a" * PART)
    wait_for(lambda: "liar" in _buffered(dash) and _buffered(dash)["liar"]["parts"], 20.0,
             "the first part was not buffered")
    _part(raw, dash, "liar", 1, b"b" * PART)
    _part(raw, dash, "liar", 2, b"c" * PART)  # over the 2 parts' worth announced
    _refused_then(dash, refused, 1)
    assert "liar" not in _buffered(dash)
    for i in range(3, 40):
        _part(raw, dash, "liar", i, b"d" * PART)
    _refused_then(dash, refused, 38)
    assert "liar" not in _buffered(dash)


def test_a_browser_keeps_at_most_max_transfers_buffered(dash: Dashboard, raw: RawViser) -> None:
    """Transfers started and never finished, one after another: the oldest are dropped (viser
    kept each one's parts until the browser left)."""
    for k in range(3 * MAX_TRANSFERS):
        _start(raw, dash, f"many-{k}", 2 * PART, 2)
        _part(raw, dash, f"many-{k}", 0, b"m" * PART)
    last = f"many-{3 * MAX_TRANSFERS - 1}"
    wait_for(lambda: last in _buffered(dash) and _buffered(dash)[last]["parts"], 20.0,
             "the last transfer's part was not buffered")
    mine = [t for t in _buffered(dash) if t.startswith("many-")]
    assert len(mine) == MAX_TRANSFERS, mine
    assert last in mine and "many-0" not in mine


def test_an_upload_left_unfinished_is_dropped_when_its_browser_leaves(dash: Dashboard) -> None:
    assert dash.server is not None
    before = set(dash.server.get_clients())
    with RawViser(dash.url.replace("http://", "ws://"), origin=dash.url.split("/?")[0]) as c:
        wait_for(lambda: set(dash.server.get_clients()) - before, 20.0, "never connected")
        _start(c, dash, "left", 4 * PART, 4)
        _part(c, dash, "left", 0, b"l" * PART)
        wait_for(lambda: "left" in _buffered(dash), 20.0, "the part was not buffered")
    wait_for(lambda: "left" not in _buffered(dash), 20.0, "the left upload stayed buffered")


def test_a_file_within_the_cap_still_arrives(dash: Dashboard, raw: RawViser) -> None:
    """The cap takes nothing from a real upload: one under the limit, in two parts, reaches
    the knowledge panel (which reads it: this one is not a measured response, and says so)."""
    assert dash.knowledge is not None
    content = b"not,a\nmeasured,response\n" * 1000
    half = len(content) // 2
    _start(raw, dash, "good", len(content), 2)
    _part(raw, dash, "good", 0, content[:half])
    _part(raw, dash, "good", 1, content[half:])
    wait_for(lambda: "x.csv" in dash.knowledge.text.content, 30.0,
             "the upload did not reach the knowledge panel")
    assert "good" not in _buffered(dash)
