"""Who gets the live charts' data (server/dashboard/page_views.py PageViews.live_audience):
the pages that said they show the Live traces tab, and pages without the page script; a page
that has not said yet gets none (issue 33: a loading page got 400-570 pushes, 6-9 MB, before
its controls were drawn)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from server.dashboard.page_views import PageViews


class _Browsers:
    """What PageViews reads of the dashboard's Browsers: the browsers, each one's page id
    ("" without the page script) and the pages connected."""

    def __init__(self, pages: dict[int, str]) -> None:
        self.pages = pages

    def all(self) -> list[Any]:
        return [SimpleNamespace(client_id=k) for k in self.pages]

    def page_of(self, browser: Any) -> str:
        return self.pages[browser.client_id]

    def connected_pages(self) -> set[str]:
        return set(self.pages.values())


def _audience(views: PageViews) -> list[int]:
    return sorted(b.client_id for b in views.live_audience())


def test_only_the_pages_that_said_they_show_the_live_traces_get_their_data() -> None:
    browsers = _Browsers({1: "a" * 24, 2: "b" * 24, 3: ""})
    views = PageViews(browsers)  # type: ignore[arg-type]
    assert _audience(views) == [3]  # nobody said anything: only the page without the script
    back = views.note_view("a" * 24, True)
    assert [b.client_id for b in back] == [1]  # it gets the present data at once
    assert _audience(views) == [1, 3]
    assert views.note_view("b" * 24, False) == []
    assert _audience(views) == [1, 3]
    assert views.note_view("a" * 24, True) == []  # said again: nothing new to send
    assert views.note_view("a" * 24, False) == [] and _audience(views) == [3]
    assert [b.client_id for b in views.note_view("a" * 24, True)] == [1]
    # A made-up id (no page of it connected) is not kept and gets nothing.
    assert views.note_view("z" * 24, True) == []
    assert _audience(views) == [1, 3]
    # A page that left is forgotten: back under the same id, it has to say again.
    del browsers.pages[1]
    views.forget(1)
    browsers.pages[4] = "a" * 24
    assert _audience(views) == [3]
