"""What each page shows: whether its 3-D view is hidden (the plots panel widened over it), and
whether it shows the Live traces tab (the live charts' data goes only to the pages that say
they do: 25 pushes/s of ~60 kB, which a page that had nothing to draw them on still received
and decoded)."""

from __future__ import annotations

import threading

import viser

from server.dashboard.browsers import Browsers
from server.viser_adapter import set_width_in

__all__ = ["PLOTS_WIDE_PX", "PLOTS_WIDTH_PX", "PageViews", "wide_plots_px"]

#: The plots panel's width: the Bode tab's Decide view (the verdict, the loop's Bode,
#: sensitivity, rejection) fits 1920 x 1080 beside the controls; the 3-D view keeps the rest.
PLOTS_WIDTH_PX = 900
#: The plots panel's width with the 3-D view hidden when the page did not say its window's
#: width (a page without the page script). viser scales both docked panels down in proportion
#: when they leave less than its MIN_CANVAS_PX of scene: this squeezed the controls to ~110 px.
PLOTS_WIDE_PX = 4000
#: The controls' panel width: viser's `control_width="large"` (24 em of 16 px; app.py).
CONTROLS_PX = 384
#: The scene viser always keeps between the docked panels (its dock's MIN_CANVAS_PX), and a
#: few px for the panels' edges.
MIN_CANVAS_PX = 120
EDGE_PX = 4


def wide_plots_px(viewport_px: int | None) -> float:
    """The plots panel's width with the 3-D view hidden, in a window `viewport_px` wide: all
    of it but the controls at their width and viser's minimum scene (the controls keep their
    width); PLOTS_WIDE_PX when the width is not known."""
    if viewport_px is None:
        return PLOTS_WIDE_PX
    return max(PLOTS_WIDTH_PX, viewport_px - CONTROLS_PX - MIN_CANVAS_PX - EDGE_PX)


class PageViews:
    """Each page's view choices, over the browsers of one server (`browsers`)."""

    def __init__(self, browsers: Browsers) -> None:
        self._browsers = browsers
        self._hidden_3d: set[int] = set()
        """The browsers (client ids) whose 3-D view is hidden."""
        self._hidden_3d_lock = threading.Lock()
        self._live_hidden: set[str] = set()
        """The pages (their page script's id) whose Live traces tab is not shown."""
        self._reported: set[str] = set()
        """The pages connected now that said what they show (the others get no live data)."""
        self._live_hidden_lock = threading.Lock()

    def toggle_3d(self, browser: viser.ClientHandle | None, plots: viser.PanelHandle) -> None:
        """Hide or show the 3-D view in `browser` (the plots panel widens over it)."""
        if browser is None:
            return
        with self._hidden_3d_lock:
            hidden = browser.client_id not in self._hidden_3d
            (self._hidden_3d.add if hidden else self._hidden_3d.discard)(browser.client_id)
        wide = wide_plots_px(self._browsers.viewport_px_of(browser))
        set_width_in(browser, plots, wide if hidden else PLOTS_WIDTH_PX)

    def shows_3d(self) -> bool:
        """Whether any browser connected now shows the 3-D view (the scene moves for none
        while every one has it hidden: viser's page draws each move it gets)."""
        with self._hidden_3d_lock:
            hidden = set(self._hidden_3d)
        return any(b.client_id not in hidden for b in self._browsers.all())

    def live_hidden(self) -> frozenset[str]:
        """The pages that said their Live traces tab is not shown."""
        with self._live_hidden_lock:
            return frozenset(self._live_hidden)

    def note_view(self, page: str, live_shown: bool) -> list[viser.ClientHandle]:
        """A page says whether it shows the live traces (its page script, on each change and
        every few seconds); returns its browsers when it shows them again (they get the
        present data at once). Only the pages connected now are kept: ids made up by a client
        do not pile up (a page that reported before its websocket was up gets the data until
        its next report)."""
        connected = page in self._browsers.connected_pages()
        with self._live_hidden_lock:
            was_hidden = page in self._live_hidden or page not in self._reported
            if connected:
                self._reported.add(page)
            if live_shown:
                self._live_hidden.discard(page)
            elif connected:
                self._live_hidden.add(page)
        if not (live_shown and was_hidden):
            return []
        return [b for b in self._browsers.all() if self._browsers.page_of(b) == page]

    def live_audience(self) -> list[viser.ClientHandle]:
        """The browsers the live charts' data goes to: the pages that said they show their
        Live traces tab, and those without the page script. A page that has not said yet gets
        none: a new page got 400-570 pushes (6-9 MB) while it loaded, before its controls were
        drawn, most of its load (`bench_dashboard.py --page`)."""
        with self._live_hidden_lock:
            showing = self._reported - self._live_hidden
        out = []
        for b in self._browsers.all():
            page = self._browsers.page_of(b)
            if not page or page in showing:
                out.append(b)
        return out

    def forget(self, client_id: int) -> None:
        """A browser left: its 3-D choice, and the pages no longer connected (a page that
        reported before its websocket was up reports again within seconds)."""
        with self._hidden_3d_lock:
            self._hidden_3d.discard(client_id)
        pages = {self._browsers.page_of(b) for b in self._browsers.all()}
        with self._live_hidden_lock:
            self._live_hidden &= pages
            self._reported &= pages
