"""A candidate's analysis: every change wakes one worker that evaluates only the newest
candidate (latest wins: the verdict, the charts, the difference from the active configuration,
the cut-off line); a second, debounced worker runs the preview and the recommended cut-off.
Apply is on only when the verdict shown is the present candidate's."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Protocol, TypeVar

import viser

from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory
from server import charts, viser_adapter
from server.engine import Evaluation, PreviewResult, TuningEngine
from server.gui import set_scales
from server.panels.apply_box import ApplyBox
from server.panels.bode import BodeTab
from server.panels.controls import CandidateControls
from server.panels.tuning_html import computing_html, diff_html, format_gate_html, preview_html
from server.panels.widgets import set_html
from server.workers import LatestWins

__all__ = ["AnalysedCandidate", "CandidateAnalysis"]

log = logging.getLogger(__name__)
_T = TypeVar("_T")


class AnalysedCandidate(Protocol):
    """What the analysis needs of its candidate panel."""

    engine: TuningEngine
    active: LoopConfig
    active_version: int | None
    trajectory: Trajectory
    controls: CandidateControls
    bode: BodeTab | None
    box: ApplyBox

    @property
    def stale(self) -> bool: ...

    @property
    def stale_by_reset(self) -> bool: ...

    def candidate(self) -> LoopConfig: ...

    def cutoff_line_html(self, cutoff_hz: float, rec: float | None, known: bool = True,
                         error: str = "", invalid: bool = False) -> str: ...


class CandidateAnalysis:
    """The verdict box, the difference line and the workers of one candidate panel."""

    computing: viser.GuiHtmlHandle
    verdict: viser.GuiHtmlHandle
    diff_text: viser.GuiHtmlHandle

    def __init__(self, panel: AnalysedCandidate) -> None:
        self.panel = panel
        self._gen_lock = threading.Lock()
        self._submitted_gen = self._done_gen = 0
        self._invalid = self._same_as_active = False
        self._verdict_color = "gray"
        self.built = False
        self.last_update_s = 0.0
        self.last_evaluation: Evaluation | None = None
        self.last_preview: PreviewResult | None = None
        self.update_count = 0
        self._worker = LatestWins(self._update, name="tuning-update")
        self._preview_worker = LatestWins(
            self._preview, name="tuning-preview", debounce_s=0.08
        )

    def build_verdict(self, gui: viser.GuiApi) -> None:
        self.computing = gui.add_html(computing_html(True))
        self.verdict = gui.add_html('<div class="dt-verdict">evaluating...</div>')

    def build_diff(self, gui: viser.GuiApi) -> None:
        self.diff_text = gui.add_html('<div class="dt-diff"></div>')
        self.built = True

    def start(self) -> None:
        self._worker.start()
        self._preview_worker.start()

    def stop(self) -> None:
        self._worker.stop()
        self._preview_worker.stop()

    def request(self) -> None:
        """The candidate may have changed: evaluate it (the newest only), Apply off meanwhile."""
        with self._gen_lock:
            self._submitted_gen += 1
            gen = self._submitted_gen
        if self.built:
            set_html(self.computing, computing_html(True))
            self.refresh_apply()
        self._worker.submit(gen)

    @property
    def computing_verdict(self) -> bool:
        """A change is not evaluated yet: the verdict shown is of an earlier candidate."""
        with self._gen_lock:
            return self._done_gen < self._submitted_gen

    def apply_blocked(self) -> str:
        """Why Apply is disabled ("" : it is enabled): only a current (evaluated), valid,
        non-stale candidate that differs from the active configuration may be sent."""
        p = self.panel
        return ("computing the verdict" if self.computing_verdict
                else "invalid candidate" if self._invalid
                else "made against a version the controller has since reset (Revert first)"
                if p.stale_by_reset
                else "based on an older version (Revert first)" if p.stale
                else "the candidate is the active configuration: nothing to send"
                if self._same_as_active else "")

    def refresh_apply(self) -> None:
        self.panel.box.refresh(self.apply_blocked(), self._verdict_color)

    def _evaluated(self, gen: int, invalid: bool) -> None:
        """`_update` for submission `gen` is done (`invalid`: the controls give no config)."""
        with self._gen_lock:
            self._done_gen = max(self._done_gen, gen)
            current = self._done_gen >= self._submitted_gen
        self._invalid = invalid
        if current:
            set_html(self.computing, computing_html(False))
        self.refresh_apply()

    def wait_idle(self, timeout_s: float = 5.0) -> bool:
        return self._worker.wait_idle(timeout_s)

    def wait_preview_idle(self, timeout_s: float = 10.0) -> bool:
        return self._worker.wait_idle(timeout_s) and self._preview_worker.wait_idle(timeout_s)

    # -- the workers -------------------------------------------------------------------------

    def page_closed(self) -> bool:
        """The browser of this panel left: viser removed the panel's elements (the verdict's
        among them) at the disconnect, and refuses to show anything in them."""
        return self.built and viser_adapter.removed(self.verdict)

    def _update(self, gen: int) -> None:
        self._unless_closed(self._evaluate, gen, "verdict")

    def _preview(self, item: tuple[LoopConfig, LoopConfig, Trajectory]) -> None:
        self._unless_closed(self._run_preview, item, "preview")

    def _unless_closed(self, work: Callable[[_T], None], arg: _T, what: str) -> None:
        """`work(arg)` (the verdict's `_evaluate`, the preview's `_run_preview`); a page closed
        meanwhile ends it quietly (`viser_adapter.unless_closed`)."""
        if not viser_adapter.unless_closed(self.page_closed, work, arg):
            log.debug("%s not shown: its page was closed", what)

    def _evaluate(self, gen: int) -> None:
        p, engine = self.panel, self.panel.engine
        t0 = time.perf_counter()
        try:
            cand = p.candidate()
        except ConfigError as exc:
            set_html(self.verdict, format_gate_html(None, str(exc)))
            set_html(p.controls.cutoff_text, p.cutoff_line_html(
                p.controls.cutoff_hz, None, True, error=p.controls.cutoff_error,
                invalid=True))
            set_html(self.diff_text, "<div class='dt-diff'></div>")
            if p.bode is not None:
                p.bode.show_invalid()
            self._verdict_color = "red"
            self._same_as_active = False
            self._evaluated(gen, invalid=True)
            return
        active = p.active
        cmp = engine.compare(cand, active)
        ev = cmp.candidate
        # The verdict first: the page shows it before it works through the charts' data.
        set_html(self.verdict, format_gate_html(ev))
        if p.bode is not None:
            p.bode.show(cmp)
        set_html(self.diff_text, diff_html(cand, active, p.active_version))
        known, rec = engine.cached_recommendation(cand)
        set_html(p.controls.cutoff_text, p.cutoff_line_html(cand.q_cutoff_hz, rec, known))
        if known:
            p.controls.update_marks(rec)
        self._verdict_color = {"accept": "green", "caution": "orange"}.get(
            ev.verdict.verdict, "red")
        self._same_as_active = cand == active
        self.last_evaluation = ev
        self.last_update_s = time.perf_counter() - t0
        self.update_count += 1
        self._evaluated(gen, invalid=False)
        self._preview_worker.submit((cand, active, p.trajectory))

    def _cutoff_line_now(self) -> None:
        """The cut-off line of the candidate the controls hold now, if its recommendation is
        known. A recommendation computed for the candidate a preview was asked for may arrive
        after the user typed another value (whose verdict drew its line, "computing..."): the
        line is drawn for the current candidate, never for the one that asked (the chromium
        156 runs left "0.500 Hz" under a typed 0.9 for good)."""
        p, engine = self.panel, self.panel.engine
        try:
            cur = p.candidate()
        except ConfigError:
            return  # the verdict shows the rejected field and its line
        known, rec = engine.cached_recommendation(cur)
        if known:
            set_html(p.controls.cutoff_text, p.cutoff_line_html(cur.q_cutoff_hz, rec, True))
            p.controls.update_marks(rec)

    def _run_preview(self, item: tuple[LoopConfig, LoopConfig, Trajectory]) -> None:
        p, engine = self.panel, self.panel.engine
        cand, active, traj = item
        known, _ = engine.cached_recommendation(cand)
        if not known:
            engine.recommended_max_cutoff_hz(cand)  # computed here, off the verdict's path
            self._cutoff_line_now()
        preview = engine.compare_preview(cand, active, traj)
        if p.bode is not None:
            p.bode.steps_chart.data = engine.steps_data(cand, active)
            scales, t_end, early_peak = charts.settled_scales(
                charts.PREVIEW_CHART, preview.chart_data, charts.PREVIEW_SETTLE_FRAC)
            if scales != p.bode.preview_chart.scales:
                set_scales(p.bode.preview_chart, scales)
            p.bode.preview_chart.data = preview.chart_data
            note = ("" if math.isnan(early_peak) else
                    f"<div class='dt-preview-startup' style='font-size:12px;color:#555'>The "
                    f"chart's scale is that of the settled run: the start-up before "
                    f"{t_end:.1f} s (up to {early_peak:.3g} deg) runs off it.</div>")
            set_html(p.bode.preview_text, preview_html(traj, preview) + note)
        self.last_preview = preview.candidate
