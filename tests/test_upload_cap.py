"""Uploads capped while they arrive (issue 31 item 6: "an upload that never completes grows the
dashboard by 300 MB in 5 s, kept after disconnect; the 5 MB cap applies only once the upload is
complete"): the attacks from a raw websocket client (tests/viser_raw.py) on its own upload
button against a real dashboard (one identity: every browser is offered one), each followed by
a check of what viser buffers. Memory under the attack:
tests/bench/bench_upload_memory.py. A viewer's page without the button, and a viewer's upload
refused: tests/integration/test_panel_roles.py."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from helpers import free_port, wait_for
from viser_raw import RawViser

from server.dashboard.app import Dashboard, DashboardOptions
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


class Page:
    """A raw client and viser's handle of its browser (whose own upload button it uses)."""

    def __init__(self, dash: Dashboard) -> None:
        assert dash.server is not None and dash.knowledge is not None
        before = set(dash.server.get_clients())
        self.raw = RawViser(dash.url.replace("http://", "ws://"), origin=dash.url.split("/?")[0])
        found: list[Any] = []

        def built() -> bool:
            assert dash.knowledge is not None
            found.extend(b for cid, b in dash.server.get_clients().items()
                         if cid not in before and dash.knowledge.upload_of(b) is not None)
            return bool(found)

        wait_for(built, 20.0, "no upload button built for the new browser")
        self.browser = found[0]
        self.uuid = control_uuid(dash.knowledge.upload_of(self.browser))

    def buffered(self) -> dict[str, Any]:
        """viser's uploads in progress in this browser's GUI (their parts so far)."""
        return self.browser.gui._current_file_upload_states  # type: ignore[no-any-return]

    def start(self, transfer: str, size: int, parts: int) -> None:
        self.raw.send({"type": "FileTransferStartUpload", "source_component_uuid": self.uuid,
                       "transfer_uuid": transfer, "filename": "x.csv",
                       "mime_type": "text/csv", "part_count": parts, "size_bytes": size})

    def part(self, transfer: str, index: int, content: bytes) -> None:
        self.raw.send({"type": "FileTransferPart", "source_component_uuid": self.uuid,
                       "transfer_uuid": transfer, "part_index": index, "content": content})


@pytest.fixture
def page(dash: Dashboard) -> Iterator[Page]:
    p = Page(dash)
    with p.raw:
        yield p


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
        dash: Dashboard, page: Page, size: int, parts: int) -> None:
    assert dash.messages is not None
    refused = dash.messages.refused
    page.start(f"big-{size}-{parts}", size, parts)
    page.part(f"big-{size}-{parts}", 0, b"x" * 1000)  # refused: never started
    _refused_then(dash, refused, 2)
    assert f"big-{size}-{parts}" not in page.buffered()


def test_parts_beyond_what_was_announced_drop_the_upload(dash: Dashboard, page: Page) -> None:
    """A small file announced, then parts that bring more: dropped at the part that goes over,
    with what viser buffered of it; its later parts are refused."""
    assert dash.messages is not None
    refused = dash.messages.refused
    page.start("liar", 2 * PART, 4)
    page.part("liar", 0, b"a" * PART)
    wait_for(lambda: "liar" in page.buffered() and page.buffered()["liar"]["parts"], 20.0,
             "the first part was not buffered")
    page.part("liar", 1, b"b" * PART)
    page.part("liar", 2, b"c" * PART)  # over the 2 parts' worth announced
    _refused_then(dash, refused, 1)
    assert "liar" not in page.buffered()
    for i in range(3, 40):
        page.part("liar", i, b"d" * PART)
    _refused_then(dash, refused, 38)
    assert "liar" not in page.buffered()


def test_a_browser_keeps_at_most_max_transfers_buffered(page: Page) -> None:
    """Transfers started and never finished, one after another: the oldest are dropped (viser
    kept each one's parts until the browser left)."""
    for k in range(3 * MAX_TRANSFERS):
        page.start(f"many-{k}", 2 * PART, 2)
        page.part(f"many-{k}", 0, b"m" * PART)
    last = f"many-{3 * MAX_TRANSFERS - 1}"
    wait_for(lambda: last in page.buffered() and page.buffered()[last]["parts"], 20.0,
             "the last transfer's part was not buffered")
    mine = [t for t in page.buffered() if t.startswith("many-")]
    assert len(mine) == MAX_TRANSFERS, mine
    assert last in mine and "many-0" not in mine


def test_an_upload_left_unfinished_is_dropped_when_its_browser_leaves(dash: Dashboard) -> None:
    p = Page(dash)
    with p.raw:
        p.start("left", 4 * PART, 4)
        p.part("left", 0, b"l" * PART)
        wait_for(lambda: "left" in p.buffered(), 20.0, "the part was not buffered")
    wait_for(lambda: "left" not in p.buffered(), 20.0, "the left upload stayed buffered")
    assert dash.knowledge is not None
    wait_for(lambda: dash.knowledge is not None and dash.knowledge.upload_of(p.browser) is None,
             20.0, "the left browser's upload button was kept")


def test_a_file_within_the_cap_still_arrives(dash: Dashboard, page: Page) -> None:
    """The cap takes nothing from a real upload: one under the limit, in two parts, reaches
    the knowledge panel (which reads it: this one is not a measured response, and says so)."""
    assert dash.knowledge is not None
    content = b"not,a\nmeasured,response\n" * 1000
    half = len(content) // 2
    page.start("good", len(content), 2)
    page.part("good", 0, content[:half])
    page.part("good", 1, content[half:])
    wait_for(lambda: "x.csv" in dash.knowledge.text.content, 30.0,
             "the upload did not reach the knowledge panel")
    assert "good" not in page.buffered()
