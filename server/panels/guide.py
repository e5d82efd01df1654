"""The guided tuning path on the Tune tab: measure -> fit -> tune the whole loop -> suggest ->
check -> apply -> watch.

Each step shows where it stands (not started / running with its progress / done / failed with
the reason) and what it produced. The path only orchestrates and shows: its buttons press the
existing pieces (the Identify panel's Start and "Use as nominal model", the candidate's Suggest
and Apply, with every check those do), and its states are read from them:

1. measure: the identification (on the controller, the rig moves; or offline on the simulated
   rig: the Identify tab's "Run on"): positions and frequency points measured, coherence;
2. fit: the fitted Mn Pn (natural frequency, damping, residual) and whether it is in this
   browser's candidate;
3. tune the whole loop: the speed PI, position PI, feedforward and Q designed together on the
   rig's twin for the chosen objective (`server.panels.tune_step`; operators only), put into
   the candidate, never applied;
4. suggest: the search for the Q type and cut-off on the rig's twin (its result is put into
   the candidate, never applied);
5. check: the gate's verdict on the candidate as it is now (computing while it is stale);
6. apply: the controller's answer (the applied version, or why not);
7. watch: after an accepted apply, one trajectory period (10 s when it has none, at most 30 s)
   of the live tracking error under the new version against the same length before it, and
   whether the watchdog rolled it back.

One per browser (its candidate is its own); the states are refreshed a few times a second by
one thread per path, which only assigns changed HTML.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import viser

from controller import protocol as proto
from controller.client import ControllerClient
from controller.core.errors import ConfigError
from server import viser_adapter
from server.escape import esc
from server.gui import Browser
from server.panels.identify import ABORTED, DONE, FAILED, RUNNING, IdentifyPanel
from server.panels.tune_step import TuneStep
from server.panels.tuning import StepState, TuningPanel
from server.panels.widgets import set_html
from server.session import tell
from server.workers import Periodic

__all__ = ["GUIDE_STEPS", "GuidePanel", "Watch", "guide_html"]

#: (key, title) of the steps, in order.
GUIDE_STEPS = (("measure", "Measure"), ("fit", "Fit"), ("tune", "Tune the whole loop"),
               ("suggest", "Suggest"), ("check", "Check"), ("apply", "Apply"),
               ("watch", "Watch"))
WATCH_DEFAULT_S = 10.0
WATCH_MAX_S = 30.0

_STATE_STYLE = {  # state -> (label, colour)
    "todo": ("not started", "#777"),
    "running": ("running", "#1f77b4"),
    "done": ("done", "#2e7d32"),
    "failed": ("failed", "#d62728"),
}


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x * x))) if len(x) else math.nan


@dataclass
class Watch:
    """What the loop did after one accepted apply (pure: fed statuses and ring windows)."""

    version: int
    length_s: float
    rollbacks_before: int
    before_rms_deg: float = math.nan
    after_rms_deg: float = math.nan
    after_s: float = 0.0
    rolled_back_to: int | None = None
    rollback_reason: str = ""

    def see(self, st: proto.Status | None, t_s: np.ndarray, error_deg: np.ndarray,
            versions: np.ndarray) -> None:
        """Update from the latest status and the samples of the last `2 * length_s`."""
        if st is not None and self.rolled_back_to is None and st.rollbacks > self.rollbacks_before \
                and st.config_version > self.version:
            self.rolled_back_to = st.config_version
            self.rollback_reason = st.watchdog or "the watchdog rolled the configuration back"
        if not len(t_s):
            return
        mine = versions == self.version
        if mine.any():
            t_first = float(t_s[mine][0])
            before = (versions < self.version) & (t_s >= t_first - self.length_s)
            if before.any() and math.isnan(self.before_rms_deg):
                self.before_rms_deg = _rms(error_deg[before])
            if self.rolled_back_to is None or math.isnan(self.after_rms_deg):
                self.after_rms_deg = _rms(error_deg[mine])
                self.after_s = float(t_s[mine][-1]) - t_first

    @property
    def finished(self) -> bool:
        return self.rolled_back_to is not None or self.after_s >= self.length_s

    def step(self) -> StepState:
        nums = (f"error RMS before {_deg(self.before_rms_deg)}, after {_deg(self.after_rms_deg)}"
                f" ({_change(self.before_rms_deg, self.after_rms_deg)})")
        if self.rolled_back_to is not None:
            return StepState("failed", None,
                              f"ROLLED BACK to v{self.rolled_back_to}: {self.rollback_reason}; "
                              f"{nums} over {self.after_s:.1f} s of v{self.version}")
        if self.finished:
            return StepState("done", 1.0, f"v{self.version} over {self.after_s:.1f} s: {nums};"
                             " no rollback")
        return StepState("running", min(self.after_s / self.length_s, 1.0),
                         f"v{self.version}: {self.after_s:.1f} of {self.length_s:.0f} s; "
                         f"{nums} so far")


def _deg(v: float) -> str:
    return "n/a" if math.isnan(v) else f"{v:.4f} deg"


def _change(before: float, after: float) -> str:
    if math.isnan(before) or math.isnan(after) or before <= 0:
        return "change n/a"
    return f"{after / before - 1.0:+.0%}"


def guide_html(steps: list[tuple[str, str, StepState]]) -> str:
    """The steps as an ordered list, each with its state (and progress) and what it gave."""
    rows = []
    for key, title, s in steps:
        label, color = _STATE_STYLE.get(s.state, (s.state, "#777"))
        if s.state == "running" and s.progress is not None:
            label += f" {100 * s.progress:.0f} %"
        rows.append(
            f"<li class='dt-step dt-step-{key} dt-step-{s.state}' style='margin:2px 0'>"
            f"<b>{esc(title)}</b> <span class='dt-step-state' style='color:{color};"
            f"font-weight:600'>[{esc(label)}]</span> "
            f"<span class='dt-step-text'>{esc(s.text)}</span></li>")
    return ("<div class='dt-guide' style='font-size:12px'><ol style='margin:0 0 0 18px;"
            f"padding:0'>{''.join(rows)}</ol></div>")


class GuidePanel:
    """The guided path of one browser (built into the current GUI container)."""

    def __init__(self, gui: viser.GuiApi, tuning: TuningPanel, identify: IdentifyPanel | None,
                 client: ControllerClient, period_s: float = 0.25,
                 authorize: Callable[[Browser, str], object] | None = None,
                 may_change: bool = True) -> None:
        """`authorize(browser, action)`: raises `Refused` (told to that browser) unless its
        user may change the rig (None: anyone may); `may_change`: this page's user may (False:
        the operators' controls, the whole-loop tune's, are built disabled)."""
        self.gui = gui
        self.tuning = tuning
        self.identify = identify
        self.client = client
        self.watch: Watch | None = None
        self._watched_at = 0.0
        self._updater = Periodic(lambda _k: self.refresh(), period_s, name="guide")
        self.steps: list[tuple[str, str, StepState]] = []
        self.tune = TuneStep(tuning, authorize, may_change)

    def build(self) -> None:
        gui = self.gui
        self.folder = gui.add_folder("Guided tuning", expand_by_default=True)
        with self.folder:
            # (Built before the candidate's controls: the states come with the first refresh.)
            self.html = gui.add_html(guide_html(
                [(k, title, StepState("todo")) for k, title in GUIDE_STEPS]))
            self.buttons = gui.add_button_group(
                "Step", ("Measure", "Use fit", "Suggest", "Apply"),
                hint="Measure: the Identify tab's run (its settings; on the controller the rig "
                "moves, asked first). Use fit: the fitted model into your candidate. Suggest: "
                "the Q search into your candidate. Apply: your candidate through the gate (as "
                "the Apply button). Tune the whole loop: its own button below")
            self.buttons.on_click(self._on_click)
            self.tune.build(gui)

    def start(self) -> None:
        self.tune.start()
        self._updater.start()

    def stop(self) -> None:
        self._updater.stop()
        self.tune.stop()

    # -- the buttons: the existing pieces' own actions ---------------------------------------------

    def _on_click(self, event: viser.GuiEvent[viser.GuiButtonGroupHandle]) -> None:
        what, browser = event.target.value, event.client
        if what == "Measure" and self.identify is not None:
            self.identify.ask_start(browser)
        elif what == "Use fit" and self.identify is not None:
            self.identify.use_as_nominal(browser)
        elif what == "Suggest":
            self.tuning.suggest.request()
        elif what == "Apply":
            why = self.tuning.apply_blocked()
            if why:
                self._tell(browser, f"Apply is off: {why}.")
            else:
                self.tuning.apply(browser)
        self.refresh()

    @staticmethod
    def _tell(browser: viser.ClientHandle | None, text: str) -> None:
        tell(browser, "Guided tuning", text, "orange")

    # -- the states -----------------------------------------------------------------------------

    def refresh(self) -> None:
        steps = self._steps()
        self.steps = steps
        if hasattr(self, "html"):
            # a page closed meanwhile ends it quietly, as the verdict and the preview
            viser_adapter.unless_closed(lambda: viser_adapter.removed(self.html), set_html,
                                        self.html, guide_html(steps))

    def step(self, key: str) -> StepState:
        """One step's state as last shown."""
        return next(s for k, _t, s in self.steps if k == key)

    def _steps(self) -> list[tuple[str, str, StepState]]:
        by = {"measure": self._measure(), "fit": self._fit(), "tune": self.tune.state,
              "suggest": self._suggest(),
              "check": self._check(), "apply": self._apply(), "watch": self._watch()}
        return [(k, title, by[k]) for k, title in GUIDE_STEPS]

    def _measure(self) -> StepState:
        idp = self.identify
        if idp is None:
            return StepState("todo", None, "no identification in this dashboard")
        where = idp.where_note
        if idp.state == RUNNING:
            return StepState("running", idp.progress, f"{idp.text} ({where})")
        view = idp.view
        if idp.state in (ABORTED, FAILED):
            return StepState("failed", None, f"{idp.text} ({where})")
        if idp.state != DONE or view is None:
            return StepState("todo", None, "press Measure: the Identify tab's settings and "
                             "\"Run on\" (controller: the rig moves; or the simulated rig)")
        curves = [c for c in view.curves if c is not None]
        points = sum(len(c.freq_hz) for c in curves)
        coh = np.concatenate([c.coherence for c in curves]) if curves else np.zeros(0)
        coh = coh[np.isfinite(coh)]
        band = (f", {min(float(c.freq_hz[0]) for c in curves):.3g}-"
                f"{max(float(c.freq_hz[-1]) for c in curves):.3g} Hz" if curves else "")
        coh_txt = (f"; coherence min {coh.min():.2f}, median {np.median(coh):.2f}"
                   if len(coh) else "")
        return StepState("done", 1.0, f"{len(curves)} position(s), {points} FRD points{band}"
                         f"{coh_txt} ({where})")

    def _fit(self) -> StepState:
        idp = self.identify
        view = idp.view if idp is not None else None
        if idp is None or view is None or idp.state != DONE:
            return StepState("todo", None, "after Measure")
        f = view.fit
        if f is None or view.nominal is None:
            return StepState("failed", None, "no usable fit of Mn Pn from this measurement")
        used = getattr(self.tuning, "nominal_override", None) == view.nominal
        return StepState(
            "done", 1.0,
            f"Mn Pn = 1/({f.a2:.3g} s^2 + {f.a1:.3g} s + 1): f_n {f.natural_freq_hz:.3f} Hz, "
            f"zeta {f.zeta:.3f}, residual {f.residual_rms_db:.2f} dB / "
            f"{f.residual_rms_deg:.1f} deg; "
            + ("in your candidate" if used else "not in your candidate: press Use fit"))

    def _suggest(self) -> StepState:
        s = self.tuning.suggest.state
        if s.state == "todo":
            return StepState("todo", None, "press Suggest: the best Q type and cut-off on the "
                             "simulated rig, put into your candidate (never applied)")
        if s.state == "done" and self.tuning.suggest.last is not None:
            r = self.tuning.suggest.last
            best = r.best
            what = (f"suggested {best.q_type.upper()} at {best.q_cutoff_hz:.3g} Hz"
                    if r.dob_helps and best is not None else "suggested: DOB off")
            return StepState("done", 1.0, f"{what} ({s.text})")
        return s

    def _check(self) -> StepState:
        t = self.tuning
        if t.computing_verdict:
            return StepState("running", None, "computing the verdict of the present candidate")
        try:
            t.candidate()
        except ConfigError as exc:  # what the controls give is not a configuration
            return StepState("failed", None, f"invalid candidate: {exc}")
        ev = t.last_evaluation
        if ev is None:
            return StepState("todo", None, "waiting for the first verdict")
        g = ev.verdict
        m = g.margins
        nums = f"{m.gain_margins_text()}, PM {m.phase_margin_deg:.1f} deg"
        c = ev.config
        cand = (f"{c.q_type.upper()} {c.q_cutoff_hz:.3g} Hz" if c.dob_on else "DOB off")
        if g.verdict == "reject":
            return StepState("failed", None, f"{cand}: REJECT: {'; '.join(g.reasons[:1])}")
        extra = f": {'; '.join(g.reasons[:1])}" if g.verdict == "caution" else ""
        same = " (the active configuration)" if "active configuration" in t.apply_blocked() \
            else ""
        return StepState("done", 1.0, f"{cand}{same}: {g.verdict}, {nums}{extra}")

    def _apply(self) -> StepState:
        """The last Apply's outcome while the candidate is the one it sent; after a change of
        the candidate, whether Apply is on (no outcome left standing for another candidate)."""
        t = self.tuning
        s = t.apply_state
        try:
            cand = t.candidate()
        except ConfigError:
            cand = None
        if s.state != "todo" and cand is not None and cand == t.sent:
            return s
        why = t.apply_blocked()
        return StepState("todo", None, f"Apply is off: {why}" if why else
                         "ready: Apply sends your candidate through the gate")

    def _watch(self) -> StepState:
        a = self.tuning.apply_state
        if a.state != "done" or a.version is None:
            return StepState("todo", None, "after an accepted Apply: the tracking error before "
                             "and after, and whether the watchdog rolls it back")
        st = self.client.status
        if self.watch is None or self._watched_at != a.at_s:
            period = st.trajectory.period_s if st is not None else None
            length = min(period or WATCH_DEFAULT_S, WATCH_MAX_S)
            self.watch = Watch(a.version, length, st.rollbacks if st is not None else 0)
            self._watched_at = a.at_s
        w = self.watch
        if not w.finished:
            cols, versions = self.client.ring.window(2.0 * w.length_s + 1.0)
            w.see(st, cols["t_s"], cols["error_deg"], versions)
        return w.step()

