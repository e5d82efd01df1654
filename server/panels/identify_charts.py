"""The Identify panel's charts: a note on the run, then the measured responses (magnitude,
phase, coherence; one series per position, with its band) and the fit, redrawn whole on each
change (a uPlot's series count is fixed: the charts are made again for another number of
positions)."""

from __future__ import annotations

import contextlib

import numpy as np
import viser

from server import charts
from server.escape import esc
from server.identify_view import FitView
from server.panels.widgets import add_chart

__all__ = ["IdentifyCharts"]


class IdentifyCharts:
    """The charts in `gui` (built by `build`, in the plots panel's Identify tab)."""

    def __init__(self, gui: viser.GuiApi) -> None:
        self._gui = gui
        self.charts: dict[str, viser.GuiUplotHandle] = {}
        self.curves: list[charts.MeasuredCurve | None] = []
        """The responses drawn, one per position (None: not measured)."""
        self.updates = 0
        """How many times the charts were redrawn."""
        self.n = 0
        """The positions the charts have series for."""
        self._box: viser.GuiFolderHandle | None = None
        self.note: viser.GuiHtmlHandle | None = None

    def build(self, n: int) -> None:
        self.note = self._gui.add_html(
            "<div class='dt-identify-charts' style='font-size:12px;color:#555'>Identification: "
            "the measured responses appear here.</div>")
        self._box = self._gui.add_folder("Measured response", expand_by_default=True)
        self.make(n)

    def make(self, n: int) -> None:
        """(Re)create the charts for `n` positions (nothing before `build`)."""
        if self._box is None:
            return
        for h in self.charts.values():
            with contextlib.suppress(Exception):
                h.remove()
        self.charts = {}
        data = charts.identify_data(n, [])
        with self._box:
            for spec in charts.identify_chart_specs(n):
                self.charts[spec.key] = add_chart(self._gui, spec, data[spec.key])
        self.n = n

    def start(self, n: int) -> None:
        """A run of `n` positions starts: empty charts with that many series."""
        if self.n != n:
            self.make(n)
        self.publish(None)

    def publish(self, fit: FitView | None) -> None:
        """Draw `curves` (and the fit, over their band of frequencies)."""
        fit_f = fit_g = None
        have = [c for c in self.curves if c is not None]
        if fit is not None and have:
            lo = min(float(c.freq_hz[0]) for c in have)
            hi = max(float(c.freq_hz[-1]) for c in have)
            fit_f = np.geomspace(lo, hi, 80)
            fit_g = fit.response(fit_f)
        data = charts.identify_data(self.n, self.curves, fit_f, fit_g)
        for key, h in self.charts.items():
            h.data = data[key]
        self.updates += 1

    def show_end(self, state: str, text: str, where_note: str) -> None:
        """The note says how the run ended (`state`: "done", else why it is incomplete)."""
        if self.note is None:
            return
        done = state == "done"
        self.note.content = (
            f"<div class='dt-identify-charts dt-id-{state}' style='font-size:12px;"
            f"color:{'#555' if done else '#d62728'}'>"
            + ("Identification complete" if done else f"<b>INCOMPLETE</b> ({esc(text)})")
            + f" &middot; {esc(where_note)}</div>")
