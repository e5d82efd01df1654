"""The guided path's "Tune the whole loop" step (issue 35 item 3): the speed PI, the position
PI, the feedforward and the Q type and cut-off designed together for the controller's
trajectory (`controller.tune.whole_loop.tune_whole_loop`, the procedure `dobtune tune` runs),
on the plant the previews run on (the rig's twin; the built-in model when nothing was
measured, and the text says which), robust over the knowledge's measured positions and bound,
accepted by the gate. The result is put into this browser's candidate, never applied; the
engineer's explanation (where each loop crosses over, what limits it, what the DOB adds and
costs) is shown with it. In its own worker thread."""

from __future__ import annotations

import logging
import time
from typing import Protocol

import viser

from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory
from controller.tune.whole_loop import Objective, WholeLoopResult, tune_whole_loop
from server.engine import TuningEngine
from server.escape import esc
from server.panels.apply_box import StepState
from server.panels.widgets import REJECT, box, set_html
from server.workers import LatestWins

__all__ = ["TuneStep", "TuneTarget", "tune_html"]

log = logging.getLogger(__name__)

#: The shortest run the tune ranks on (s; its objective needs more than 2.5 s).
MIN_RUN_S = 8.0


class TuneTarget(Protocol):
    """What the tune needs of its candidate panel."""

    engine: TuningEngine
    trajectory: Trajectory
    base_version: int | None

    def candidate(self) -> LoopConfig: ...

    def load(self, a: LoopConfig, version: int | None, say_text: str = "") -> None: ...


def tune_html(res: WholeLoopResult, elapsed_s: float) -> str:
    """The result in an engineer's words (the procedure's own explanation lines)."""
    best = res.best
    if best is None:
        head = ("<b>Tune the whole loop</b>: nothing the gate accepts was found; the candidate "
                "is unchanged.")
    else:
        c = best.config
        ff = f"feedforward {c.ff_gain:.3g}" if c.ff_on else "no feedforward"
        head = (f"<b>Tune the whole loop</b>: put into your candidate (not applied): speed PI "
                f"Kp {c.cv_kp:.3g}, Ki {c.cv_ki_per_s:.3g}/s; position PI Kp "
                f"{c.pos_kp_per_s:.3g}/s, Ki {c.pos_ki_per_s:.3g}/s; {ff}; "
                + (f"DOB {c.q_type.upper()} at {c.q_cutoff_hz:.3g} Hz" if c.dob_on else "DOB off")
                + f" &mdash; RMSE {best.rmse_deg:.4g} deg against {res.start.rmse_deg:.4g} deg "
                f"for the loop it started from ({best.verdict}).")
    lines = "".join(f"<li>{esc(line)}</li>" for line in res.explanation)
    return (f"<div class='dt-tune' style='font-size:12px'>{head}<ul style='margin:2px 0 0 "
            f"16px;padding:0'>{lines}</ul><div style='color:#666'>on the "
            f"{esc(res.plant_source)}; {res.runs} runs in {elapsed_s:.1f} s</div></div>")


class TuneStep:
    """The step's worker and its text, for one candidate panel."""

    def __init__(self, panel: TuneTarget) -> None:
        self.panel = panel
        self.state = StepState("todo", None, "press Tune loop: the speed PI, position PI, "
                               "feedforward and Q designed together on the twin, put into "
                               "your candidate (never applied)")
        self.last: WholeLoopResult | None = None
        self.text: viser.GuiHtmlHandle | None = None
        self._worker = LatestWins(self._run, name="tune-whole-loop")

    def build(self, gui: viser.GuiApi) -> None:
        self.text = gui.add_html("<div class='dt-tune'></div>")

    def start(self) -> None:
        self._worker.start()

    def stop(self) -> None:
        self._worker.stop()

    def request(self) -> None:
        self.state = StepState("running", 0.0, "starting")
        self._worker.submit(time.perf_counter())

    def wait_idle(self, timeout_s: float = 120.0) -> bool:
        return self._worker.wait_idle(timeout_s)

    def _show(self, html: str) -> None:
        if self.text is not None:
            set_html(self.text, html)

    def _run(self, _submitted: float) -> None:
        panel, engine = self.panel, self.panel.engine
        try:
            base = panel.candidate()
        except ConfigError as exc:
            self.state = StepState("failed", None, f"needs a valid candidate: {exc}")
            self._show(box("dt-tune dt-tune-failed", REJECT,
                           f"Tune needs a valid candidate: {esc(str(exc))}"))
            return
        t0 = time.perf_counter()

        def progress(frac: float) -> None:
            self.state = StepState("running", frac, "designing and ranking on the twin")

        from controller.sim.nonlinear_check import findings

        traj = panel.trajectory
        try:
            objective = Objective(traj, "rmse", max(MIN_RUN_S, engine.preview_run_s(traj)))
            res = tune_whole_loop(base, engine.plant, engine.sim_plant(), objective,
                                  nonlinear=findings, progress=progress)
        except Exception as exc:  # shown and logged: the worker goes on
            log.exception("the whole-loop tune failed")
            self.state = StepState("failed", None, f"{type(exc).__name__}: {exc}")
            self._show(box("dt-tune dt-tune-failed", REJECT, f"Tune failed: {esc(str(exc))}"))
            return
        elapsed = time.perf_counter() - t0
        self.last = res
        best = res.best
        if best is None:
            self.state = StepState("failed", None, "nothing the gate accepts was found")
        else:
            panel.load(best.config, panel.base_version,
                       say_text="The whole-loop tune's result is your candidate (not applied).")
            self.state = StepState(
                "done", 1.0, f"RMSE {best.rmse_deg:.4g} deg against {res.start.rmse_deg:.4g} "
                f"(start), {best.verdict}; in your candidate ({elapsed:.1f} s)")
        self._show(tune_html(res, elapsed))
