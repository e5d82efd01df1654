"""The guided path's "Tune the whole loop" step (issue 35 item 3): the speed PI, the position
PI, the feedforward and the Q type and cut-off designed together for the controller's
trajectory (`controller.tune.whole_loop.tune_whole_loop`, the procedure `dobtune tune` runs),
on the plant the previews run on (the rig's twin; the built-in model when nothing was
measured, and the text says which), robust over the knowledge's measured positions and bound,
accepted by the gate. The result is put into this browser's candidate, never applied; the
engineer's explanation (where each loop crosses over, what limits it, what the DOB adds and
costs) is shown with it. In its own worker thread.

The objective is chosen beside the button: the tracking RMSE or the peak |error| on the
controller's trajectory, with a command-noise budget (0: twice the designed loop's without the
DOB, the procedure's default). Operators only: a viewer's controls are disabled (so the message
gate refuses a viewer's press before viser handles it) and a press on a viewer's behalf is
refused here too (`authorize`), told to that browser."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import viser

from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory
from controller.tune.whole_loop import Objective, WholeLoopResult, tune_whole_loop
from server.escape import esc
from server.gui import Browser, on_press
from server.http_access import Refused
from server.panels.apply_box import StepState
from server.panels.suggest_step import SuggestTarget
from server.panels.widgets import REJECT, box, set_html
from server.workers import LatestWins

__all__ = ["METRICS", "TuneStep", "TuneTarget", "objective_of", "tune_html"]

log = logging.getLogger(__name__)

#: The shortest run the tune ranks on (s; its objective needs more than 2.5 s).
MIN_RUN_S = 8.0
#: The objective's choices as the dropdown shows them -> `Objective.metric`.
METRICS = {"tracking RMSE": "rmse", "peak |error|": "peak"}
#: The largest command-noise budget the field takes (deg/s).
MAX_BUDGET_DEG_S = 1000.0
#: The procedure's own default budget (twice the designed loop's without the DOB).
AUTO = "twice the designed loop's without the DOB"


#: What the tune needs of its candidate panel: what Suggest needs (the same panel).
TuneTarget = SuggestTarget


def objective_text(o: Objective) -> str:
    """What the tune aimed at, in words."""
    label = next(k for k, v in METRICS.items() if v == o.metric)
    budget = (f"{o.noise_budget_deg_s:.3g} deg/s" if o.noise_budget_deg_s is not None
              else AUTO)
    return (f"tuned for the {label} on the {o.trajectory.kind} trajectory ({o.duration_s:.3g} s),"
            f" command-noise budget {budget}")


def figures(res: WholeLoopResult) -> str:
    """The result's RMSE, peak and command noise against the loop it started from."""
    b, s = res.best, res.start
    if b is None:
        return ""
    return (f"RMSE {b.rmse_deg:.4g} deg (start {s.rmse_deg:.4g}), peak {b.peak_error_deg:.4g} "
            f"deg (start {s.peak_error_deg:.4g}), command noise {b.command_noise_deg_s:.3g} "
            f"deg/s (start {s.command_noise_deg_s:.3g})")


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
                + (f"speed-command filter: {esc(c.command_filter.describe())}; "
                   if c.command_filter.kind != "off" else "")
                + (f"DOB {c.q_type.upper()} at {c.q_cutoff_hz:.3g} Hz" if c.dob_on else "DOB off")
                + f" &mdash; {esc(figures(res))} ({best.verdict}).")
    lines = "".join(f"<li>{esc(line)}</li>" for line in res.explanation)
    return (f"<div class='dt-tune' style='font-size:12px'>{head}<ul style='margin:2px 0 0 "
            f"16px;padding:0'>{lines}</ul><div style='color:#666'>on the "
            f"{esc(res.plant_source)}; {esc(objective_text(res.objective))}; {res.runs} runs in "
            f"{elapsed_s:.1f} s</div></div>")


def objective_of(trajectory: Trajectory, metric_label: str, budget_deg_s: float,
                 run_s: float) -> Objective:
    """The tune's objective from the step's controls (ValueError naming the field)."""
    metric = METRICS.get(metric_label)
    if metric is None:
        raise ValueError(f"objective: {metric_label!r} is not one of {', '.join(METRICS)}")
    if not (math.isfinite(budget_deg_s) and 0.0 <= budget_deg_s <= MAX_BUDGET_DEG_S):
        raise ValueError(f"noise_budget_deg_s: {budget_deg_s!r} must be in "
                         f"[0, {MAX_BUDGET_DEG_S:g}] deg/s (0: {AUTO})")
    return Objective(trajectory, metric, max(MIN_RUN_S, run_s),
                     noise_budget_deg_s=budget_deg_s or None)


class TuneStep:
    """The step's controls, worker and text, for one candidate panel. `authorize(browser,
    action)` raises `Refused` (told to that browser) unless its user may change the rig;
    `may_change`: this page's user may (False: the controls are built disabled)."""

    def __init__(self, panel: TuneTarget,
                 authorize: Callable[[Browser, str], object] | None = None,
                 may_change: bool = True) -> None:
        self.panel = panel
        self._authorize = authorize
        self.may_change = may_change
        self.state = StepState("todo", None, (
            "press Tune the whole loop: the speed PI, position PI, feedforward and Q designed "
            "together on the twin, put into your candidate (never applied)") if may_change
            else "operators only: a viewer watches")
        self.last: WholeLoopResult | None = None
        self.text: viser.GuiHtmlHandle | None = None
        self.metric: viser.GuiDropdownHandle[str] | None = None
        self.budget: viser.GuiNumberHandle[float] | None = None
        self.button: viser.GuiButtonHandle | None = None
        self._worker = LatestWins(self._run, name="tune-whole-loop")

    def build(self, gui: viser.GuiApi) -> None:
        off = not self.may_change
        self.metric = gui.add_dropdown(
            "Tune for", tuple(METRICS), initial_value=next(iter(METRICS)), disabled=off,
            hint="What the whole-loop tune minimises on the controller's trajectory")
        self.budget = gui.add_number(
            "Noise budget (deg/s)", 0.0, min=0.0, max=MAX_BUDGET_DEG_S, step=0.1, disabled=off,
            hint=f"The most command noise (RMS above 20 Hz) a result may have; 0: {AUTO}")
        self.button = gui.add_button(
            "Tune the whole loop", disabled=off,
            hint="Speed PI, position PI, feedforward and Q designed together on the twin of "
                 "the measured rig, put into your candidate (never applied: the gate and "
                 "Apply as any candidate)" + (" (operators only)" if off else ""))
        on_press(self.button, self.request)
        self.text = gui.add_html("<div class='dt-tune'></div>")

    def start(self) -> None:
        self._worker.start()

    def stop(self) -> None:
        self._worker.stop()

    def request(self, browser: Browser = None) -> bool:
        """The press (of `browser`): False when refused (told to that browser) or the
        objective's fields are not valid (said in the step)."""
        if self._authorize is not None:
            try:
                self._authorize(browser, "tune the whole loop")
            except Refused:
                return False  # told to that browser alone
        try:
            objective = objective_of(
                self.panel.trajectory,
                str(self.metric.value) if self.metric is not None else next(iter(METRICS)),
                float(self.budget.value) if self.budget is not None else 0.0,
                self.panel.engine.preview_run_s(self.panel.trajectory))
        except ValueError as exc:
            self.state = StepState("failed", None, f"not started: {exc}")
            self._show(box("dt-tune dt-tune-failed", REJECT, f"Not started: {esc(str(exc))}"))
            return False
        self.state = StepState("running", 0.0, "starting")
        self._worker.submit(objective)
        return True

    def wait_idle(self, timeout_s: float = 120.0) -> bool:
        return self._worker.wait_idle(timeout_s)

    def _show(self, html: str) -> None:
        if self.text is not None:
            set_html(self.text, html)

    def _run(self, objective: Objective) -> None:
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

        try:
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
                "done", 1.0, f"{figures(res)}, {best.verdict}; in your candidate "
                f"({elapsed:.1f} s)")
        self._show(tune_html(res, elapsed))
