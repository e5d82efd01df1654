"""A candidate's Suggest: the Q type and cut-off searched on the simulated rig for the
controller's trajectory (only what the gate accepts counts), the best put into the candidate,
never applied; in its own worker thread."""

from __future__ import annotations

import logging
import time
from typing import Protocol

import viser

from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory
from controller.tune.autotune import TuneResult
from server import charts
from server.engine import TuningEngine
from server.escape import esc
from server.gui import set_scales
from server.panels.apply_box import StepState
from server.panels.widgets import REJECT, box, set_html
from server.suggest import (
    SUGGEST_CHART,
    SuggestSettings,
    suggest,
    suggest_data,
    suggest_html,
    suggested_config,
)
from server.workers import LatestWins

__all__ = ["SuggestStep", "SuggestTarget"]

log = logging.getLogger(__name__)


class SuggestTarget(Protocol):
    """What Suggest needs of its candidate panel."""

    engine: TuningEngine
    trajectory: Trajectory
    base_version: int | None

    def candidate(self) -> LoopConfig: ...

    def load(self, a: LoopConfig, version: int | None, say_text: str = "") -> None: ...


class SuggestStep:
    """The Suggest button, its progress and result text, its chart (given by the Bode tab) and
    its worker, for one candidate panel."""

    button: viser.GuiButtonHandle
    text: viser.GuiHtmlHandle

    def __init__(self, panel: SuggestTarget) -> None:
        """`panel`: the candidate searched from and loaded with the result."""
        self.panel = panel
        self.chart: viser.GuiUplotHandle | None = None
        """The Bode tab's Suggest chart (None: no charts built)."""
        self.note: viser.GuiHtmlHandle | None = None
        """The note the Bode tab shows in its place until Suggest has run."""
        self.state = StepState("todo")
        self.last: TuneResult | None = None
        """The last Suggest's result (None: not run)."""
        self._put: LoopConfig | None = None
        """What the last Suggest put into the candidate, while the candidate still is it."""
        self._worker = LatestWins(self._run, name="tuning-suggest")

    def build_controls(self, gui: viser.GuiApi) -> None:
        self.button = gui.add_button(
            "Suggest Q cut-off", color="gray",
            hint="search Q type and cut-off for the controller's trajectory on the simulated "
            "rig (only what the gate accepts counts) and put the best into this candidate; "
            "never applied")
        self.text = gui.add_html("<div class='dt-suggest'></div>")
        self.button.on_click(lambda _e: self.request())

    def start(self) -> None:
        self._worker.start()

    def stop(self) -> None:
        self._worker.stop()

    def candidate_changed(self) -> None:
        """The candidate may have changed: once it is no longer what Suggest put into it, the
        text stops saying that it is (the result stays, said as Suggest's)."""
        put, result = self._put, self.last
        if put is None or result is None:
            return
        try:
            same = self.panel.candidate() == put
        except ConfigError:
            same = False
        if not same:
            self._put = None
            set_html(self.text, suggest_html(result, self.panel.trajectory, None))

    def request(self) -> None:
        """Run Suggest on the present candidate (in its own worker thread)."""
        self.state = StepState("running", 0.0, "starting")
        set_html(self.text, "<div class='dt-suggest dt-suggest-running'>Suggest: starting...</div>")
        self._worker.submit(time.perf_counter())

    def wait_idle(self, timeout_s: float = 60.0) -> bool:
        return self._worker.wait_idle(timeout_s)

    def _run(self, _submitted: float) -> None:
        panel, engine = self.panel, self.panel.engine
        try:
            base = panel.candidate()
        except ConfigError as exc:
            self.state = StepState("failed", None, f"needs a valid candidate: {exc}")
            set_html(self.text, box("dt-suggest", REJECT,
                                    f"Suggest needs a valid candidate: {esc(str(exc))}"))
            return
        t0 = time.perf_counter()
        traj = panel.trajectory
        shown = [t0]

        def progress(frac: float) -> None:
            now = time.perf_counter()
            self.state = StepState("running", frac, "searching on the simulated rig")
            if now - shown[0] >= 0.25:
                shown[0] = now
                set_html(self.text, "<div class='dt-suggest dt-suggest-running'>"
                         f"Suggest: searching on the simulated rig... {100 * frac:.0f} %</div>")

        settings = SuggestSettings(duration_s=engine.preview_run_s(traj))
        try:
            result = suggest(base, engine.plant, traj, settings, progress=progress,
                             setup=engine.sim_setup)
        except Exception as exc:  # shown and logged: the worker goes on
            log.exception("Suggest failed")
            self.state = StepState("failed", None, f"{type(exc).__name__}: {exc}")
            set_html(self.text, box("dt-suggest dt-suggest-failed", REJECT,
                                    f"Suggest failed: {esc(str(exc))}"))
            return
        self.last = result
        self.state = StepState("done", 1.0, result.summary())
        if self.chart is not None:
            data = suggest_data(result)
            set_scales(self.chart, charts.ranged_scales(SUGGEST_CHART, data))
            self.chart.data = data
            self.chart.visible = True
            if self.note is not None:
                set_html(self.note, "<div class='dt-suggest-note'></div>")
        put = suggested_config(base, result)
        self._put = put  # (before the load, which asks `candidate_changed`)
        panel.load(put, panel.base_version)
        set_html(self.text, suggest_html(result, traj, time.perf_counter() - t0))
