"""The Bode tab of one candidate: what a cut-off decision needs on one screen, the rest a
click away.

Sub-tabs: **Decide** (the verdict with its reasons and margins, the loop's classic Bode:
magnitude over phase on one frequency axis with the margins marked and a cursor read-out,
sensitivity and the DOB's rejection), **Responses** (closed loop, disturbance, noise, small
gain, the plant), **Time** (the simulated preview and the linear step responses), **Nyquist**
and **Suggest**. The charts' y scales are fixed from their data (`charts.ranged_scales`,
rounded out to whole steps), so NaN draws nothing and no column needs a stand-in value.
"""

from __future__ import annotations

import math

import viser

from controller.core.arrays import FloatArray
from controller.core.verdict import VerdictMargins
from server import charts
from server.engine import Comparison, Evaluation
from server.escape import esc
from server.gui import set_scales
from server.panels.widgets import ACCEPT, CAUTION, REJECT, add_chart, box, reason_list, set_html
from server.suggest import SUGGEST_CHART, suggest_data

__all__ = ["BODE_TABS", "DECIDE", "MARGIN_LABELS", "BodeTab", "decide_html", "fmt_value",
           "gain_margin_items", "margin_items"]

#: The sub-tab with what one cut-off decision needs.
DECIDE = "Decide"
#: The frequency-response charts of each sub-tab (chart keys of `charts.BODE_CHARTS`).
BODE_TABS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (DECIDE, ("loop_mag", "loop_phase", "sensitivity", "rejection")),
    ("Responses", ("closed_loop", "disturbance", "noise", "small_gain", "plant")),
)

#: (Verdict.margins field, label, unit, digits) of the margins the verdict shows after the
#: gain margins (`gain_margin_items`).
MARGIN_LABELS = (
    ("phase_margin_deg", "phase margin", "deg", 1),
    ("peak_sensitivity_db", "peak |S|", "dB", 2),
    ("small_gain_peak", "small-gain peak", "", 3),
    ("max_pole_radius", "max |pole|", "", 5),
    ("noise_to_command_peak_db", "noise -> command", "dB", 1),
)

#: Filled in by web_assets/dashboard.js while the cursor is over the loop's Bode charts.
READOUT_HTML = ("<div class='dt-loop-readout' style='font-size:13px;font-family:monospace;"
                "min-height:1.4em;color:#333'>cursor: hover the Bode charts for f, |L| and "
                "phase</div>")


def fmt_value(v: float, digits: int) -> str:
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if math.isnan(v):
        return "n/a"
    return f"{v:.{digits}f}"


def gain_margin_items(m: VerdictMargins) -> list[tuple[str, str, str]]:
    """(label, value, unit) of the gain margins as an engineer reads them, both positive and
    named: the gain margin up and, in a conditionally stable loop, the gain-reduction margin
    down (`VerdictMargins.gain_margins_text`). A verdict recorded before both were kept
    shows python-control's pick, a negative one as the gain-reduction margin it is."""
    up, down = m.gain_margin_up_db, m.gain_reduction_margin_db
    if math.isnan(up) and math.isnan(down):
        g = m.gain_margin_db
        if g < 0:
            return [("gain-reduction margin", fmt_value(-g, 1), "dB down")]
        return [("gain margin", fmt_value(g, 1), "dB")]
    if not math.isfinite(down):
        return [("gain margin", "none" if up == math.inf else fmt_value(up, 1),
                 "" if up == math.inf else "dB")]
    return [("gain margin", "unlimited" if up == math.inf else fmt_value(up, 1),
             "up" if up == math.inf else "dB up"),
            ("gain-reduction margin", fmt_value(down, 1), "dB down")]


def margin_items(m: VerdictMargins) -> list[tuple[str, str, str]]:
    """(label, value, unit) of every margin the verdict shows, the gain margins first."""
    return gain_margin_items(m) + [
        (label, fmt_value(getattr(m, key), d), unit) for key, label, unit, d in MARGIN_LABELS]


def decide_html(ev: Evaluation) -> str:
    """The verdict in the wide Decide view: the word, every margin side by side, every
    reason."""
    g = ev.verdict
    chips = "".join(
        f"<span style='white-space:nowrap;margin-right:14px'>{label} "
        f"<b>{value}</b> {unit}</span> "
        for label, value, unit in margin_items(g.margins))
    judged = (f" <span style='color:#555'>judged on {esc(g.knowledge)}</span>"
              if g.knowledge else "")
    word, colors = {"accept": ("accept", ACCEPT), "caution": ("CAUTION", CAUTION)}.get(
        g.verdict, ("REJECT", REJECT))
    reasons = reason_list(g.reasons, "dt-decide-reason") if g.reasons else ""
    return box(f"dt-decide dt-decide-{g.verdict}", colors,
               f"<b>Verdict: {word}</b>{judged}<div style='margin-top:2px'>{chips}</div>"
               f"{reasons}")


#: The Suggest sub-tab before Suggest has run.
SUGGEST_NOTE = ("<div class='dt-suggest-note' style='font-size:13px;color:#555;margin:8px 0'>"
                "Nothing suggested yet: press <b>Suggest</b> (Tune tab, Guided tuning) to chart "
                "the tracking error against the Q cut-off on the simulated rig here.</div>")


class BodeTab:
    """The charts of one candidate, built into the current GUI container (the plots panel's
    Bode tab); `show` draws a comparison."""

    def __init__(self, gui: viser.GuiApi, freq_hz: FloatArray) -> None:
        self.gui = gui
        self.freq_hz = freq_hz
        self.charts: dict[str, viser.GuiUplotHandle] = {}
        self._specs = {s.key: s for s in charts.BODE_CHARTS}

    def build(self) -> None:
        gui = self.gui
        tabs = gui.add_tab_group()
        for name, keys in BODE_TABS:
            with tabs.add_tab(name):
                if name == DECIDE:
                    self.verdict = gui.add_html("<div class='dt-decide'>evaluating...</div>")
                    self.margins = gui.add_html("<div class='dt-loop-margins'></div>")
                    self.readout = gui.add_html(READOUT_HTML)
                for key in keys:
                    spec = self._specs[key]
                    self.charts[key] = add_chart(gui, spec, spec.placeholder(self.freq_hz))
        with tabs.add_tab("Time"):
            self.preview_text = gui.add_html('<div class="dt-preview">preview: running...</div>')
            self.preview_chart = add_chart(gui, charts.PREVIEW_CHART,
                                           charts.PREVIEW_CHART.placeholder([0.0, 1.0]))
            self.steps_chart = add_chart(gui, charts.STEP_CHART,
                                         charts.STEP_CHART.placeholder([0.0, 1.0]))
        with tabs.add_tab("Nyquist"):
            self.nyquist = gui.add_html("<div class='dt-nyquist-box'></div>")
        with tabs.add_tab("Suggest"):
            # Until Suggest has run: a note, not an empty 0..1 chart.
            self.suggest_note = gui.add_html(SUGGEST_NOTE)
            empty = suggest_data(None)
            self.suggest_chart = add_chart(gui, SUGGEST_CHART, empty)
            set_scales(self.suggest_chart, charts.ranged_scales(SUGGEST_CHART, empty))
            self.suggest_chart.visible = False
        self.tabs = tabs

    def show_invalid(self) -> None:
        """The candidate is invalid (the Tune tab names the field): no verdict and no margins
        here, and the charts said to be the last valid candidate's (not this one's)."""
        set_html(self.verdict, box("dt-decide dt-decide-invalid", REJECT,
                                   "<b>No verdict: the candidate is invalid</b> (the Tune tab "
                                   "names the field). The charts below are the last valid "
                                   "candidate's."))
        set_html(self.margins, "<div class='dt-loop-margins'></div>")

    def show(self, cmp: Comparison) -> None:
        """A candidate against the active configuration: every chart's data (a y scale is
        assigned only when its rounded range changes: a new scale re-creates the chart), the
        margins, the verdict and the Nyquist view. The verdict and the margins go first: the
        page shows them before it works through the charts' data."""
        cand = cmp.candidate.curves
        set_html(self.verdict, decide_html(cmp.candidate))
        set_html(self.margins, charts.loop_margins_html(cand))
        for key, handle in self.charts.items():
            data = cmp.chart_data[key]
            scales = charts.ranged_scales(self._specs[key], data, charts.Y_STEPS)
            if scales != handle.scales:
                set_scales(handle, scales)
            handle.data = data
        set_html(self.nyquist, "<div class='dt-nyquist-box'>" + charts.nyquist_svg(
            cand, cmp.active.curves) + "</div>")
