"""Tuning panel: the candidate's controls, verdict, Apply/Revert, and the Bode and preview charts.

The computation is `server.engine.TuningEngine`; this module only builds viser widgets and
shows what the engine returns. Every control change wakes one worker thread that evaluates
only the newest candidate (latest wins), so GUI callbacks stay short; the slower preview and
the recommended cut-off run in a second, debounced worker.

The parts: the controls (`server.panels.controls`: one callback each), the Apply box and the
controller's replies (`server.panels.apply_box`), the page's HTML
(`server.panels.tuning_html`), Suggest (`server.panels.suggest_step`); the candidate's state
and its analysis here.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

import viser

from controller.core.config import LoopConfig, NominalModel
from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory
from server.candidate_apply import CandidateApply
from server.candidate_store import KeptCandidate
from server.engine import Evaluation, TuningEngine, candidate_from_values
from server.escape import esc
from server.panels.apply_box import ApplyBox, StepState
from server.panels.bode import BodeTab
from server.panels.candidate_analysis import CandidateAnalysis
from server.panels.controls import CandidateControls, cutoff_marks, kept_problem
from server.panels.suggest_step import SuggestStep
from server.panels.tuning_html import (
    active_html,
    config_diff_html,
    cutoff_html,
    format_gate_html,
    kept_problem_html,
    stale_html,
)
from server.panels.widgets import NEUTRAL, REJECT, box, confirm, set_html
from server.panels.widgets import reason_list as _reason_list

__all__ = ["StepState", "TuningPanel", "config_diff_html", "cutoff_marks", "format_gate_html",
           "kept_problem"]

log = logging.getLogger(__name__)


class TuningPanel:
    """One candidate: controls, verdict, Apply/Revert (built into the current GUI container)
    and the Bode and preview charts (built separately with `build_charts`, e.g. in another
    panel). The dashboard gives each browser a panel of its own (its `gui` is that browser's
    `client.gui`): the candidate is per browser; the active configuration is shared.

    The candidate is built on `base`, the configuration its controls were last loaded from
    (the active one at a revert, or a version from the history), and carries `base_version`,
    the active version it was made against: Apply sends it as `expect_version`, so the
    controller refuses it if someone else applied in between, and the panel says so before.
    """

    def __init__(self, gui: viser.GuiApi, engine: TuningEngine, applier: CandidateApply,
                 initial: LoopConfig | None = None,
                 on_change: Callable[[TuningPanel], None] | None = None) -> None:
        """`applier` sends a candidate (with `base_version` as the expected version) and
        shows the reply here; `on_change(panel)` (GUI thread, short): the candidate may have
        changed (called once the panel is started)."""
        self.gui = gui
        self.engine = engine
        self.applier = applier
        self.active: LoopConfig = initial or LoopConfig()
        self.active_version: int | None = None
        self.base: LoopConfig = self.active
        self.base_version: int | None = None
        """The active version this candidate was made against (None: not known yet)."""
        self.trajectory = Trajectory()
        self._controls_lock = threading.RLock()
        """Held while a control's change is read and judged, while the controls are set as a
        whole (`load`, `restore`) and while `set_active` decides whether the first known
        version loads them."""
        self.controls = CandidateControls(gui, self._controls_lock, self.request_update)
        self.box = ApplyBox()
        self.suggest = SuggestStep(self)
        self.analysis = CandidateAnalysis(self)
        self._on_change = on_change
        self._started = False
        self.bode: BodeTab | None = None
        self._charts: dict[str, Any] = {}
        self._restored = False
        self._restored_against: LoopConfig | None = None
        """Restored (`restore`) and not loaded or re-based since: the controller's
        configuration at `base_version` when the candidate was kept (None: not known)."""
        self.sent: LoopConfig | None = None
        """The candidate of the last Apply pressed (`apply_state` is about it)."""

    # -- building --------------------------------------------------------------------------

    def build_controls(self) -> None:
        gui = self.gui
        self.controls.build(self.active, self.cutoff_line_html(self.active.q_cutoff_hz, None))
        for name, handle in self.controls.handles().items():
            setattr(self, name, handle)  # (t.cv_kp, t.cutoff_log, ...: scripts and tests)
        self.cutoff_text = self.controls.cutoff_text
        self.analysis.build_verdict(gui)
        self.computing, self.verdict = self.analysis.computing, self.analysis.verdict
        self.stale_text = gui.add_html('<div class="dt-stale"></div>')
        self.kept_problem = gui.add_html(kept_problem_html(""))
        self.analysis.build_diff(gui)
        self.diff_text = self.analysis.diff_text
        self.box.build_button(gui)
        self.apply_button, self.apply_why = self.box.button, self.box.why
        self.revert_button = gui.add_button("Revert to active", color="gray")
        self.suggest.build_controls(gui)
        self.suggest_button, self.suggest_text = self.suggest.button, self.suggest.text
        self.box.build_result(gui)
        self.apply_result = self.box.result
        self.active_text = gui.add_html(active_html(self.active, self.active_version))
        self.apply_button.on_click(lambda e: self.apply(e.client))
        self.revert_button.on_click(lambda _e: self.revert())

    def build_charts(self) -> None:
        """The Bode tab's sub-tabs and charts (`server.panels.bode`)."""
        view = BodeTab(self.gui, self.engine.freq_hz)
        view.build()
        self.bode = view
        self._charts = view.charts
        self.suggest.chart = view.suggest_chart
        self.suggest.note = view.suggest_note

    def start(self) -> None:
        self._started = True
        self.analysis.start()
        self.suggest.start()
        self.request_update()

    def stop(self) -> None:
        self.analysis.stop()
        self.suggest.stop()

    # -- the candidate -----------------------------------------------------------------------

    @property
    def cutoff_hz(self) -> float:
        """The candidate's cut-off (`CandidateControls.cutoff_hz`)."""
        return self.controls.cutoff_hz

    @property
    def apply_state(self) -> StepState:
        """Where this panel's last Apply stands (`ApplyBox.state`)."""
        return self.box.state

    def candidate(self) -> LoopConfig:
        """The candidate from the controls on top of `base` (the fields without a control come
        from there); raises ConfigError."""
        return candidate_from_values(self.base, self.controls.values())

    def nominal(self) -> NominalModel | None:
        """The candidate's own nominal model, when it has one apart from `base`'s."""
        return None

    @property
    def stale(self) -> bool:
        """Made against an older active version than the controller's present one; or,
        restored (`restore`), against a version the controller now runs as another
        configuration than when the candidate was kept (or one not known then: its state was
        reset since, e.g. the demo's, or a restart with --config)."""
        if self.base_version is None or self.active_version is None:
            return False
        if self.base_version != self.active_version:
            return True
        return self._restored and self._restored_against != self.active

    @property
    def stale_by_reset(self) -> bool:
        """Stale, though made against the present version number (see `stale`): the
        controller would accept its Apply, so the dashboard refuses it."""
        return self.stale and self.base_version == self.active_version

    def _show_stale(self) -> None:
        set_html(self.stale_text, stale_html(self.stale, self.stale_by_reset, self.base_version,
                                             self.active_version))

    def kept(self) -> KeptCandidate:
        """The candidate as its controls show it, with what it was made against (kept for a
        reload: server/candidate_store.py)."""
        against = (self._restored_against if self._restored else self.active
                   if self.base_version is not None and self.base_version == self.active_version
                   else None)
        return KeptCandidate(self.base, self.base_version, self.controls.kept(), self.nominal(),
                             against)

    def restore(self, k: KeptCandidate) -> None:
        """The controls as `k` kept them, made against `k.base_version` (stale, as before the
        reload, if the active version has moved on since)."""
        with self._controls_lock:
            self.base, self.base_version = k.base, k.base_version
            self._restored, self._restored_against = True, k.against
            self.restore_nominal(k.nominal)
            self.controls.restore(k.controls)
            self._show_stale()
            self.apply_result.content = box(
                "dt-apply dt-apply-restored", NEUTRAL,
                "Your candidate from before the reload (or the dashboard's restart)"
                + (f" (made against v{k.base_version})." if k.base_version is not None else "."))
            self.request_update()

    def restore_nominal(self, nominal: NominalModel | None) -> None:
        """A kept candidate's own nominal model (this panel keeps none)."""

    # -- the verdict -------------------------------------------------------------------------

    def request_update(self) -> None:
        """The candidate may have changed: kept (`on_change`), judged again, and Suggest's
        text no longer says the candidate has its setting once it has not."""
        if self._on_change is not None and self._started and self.analysis.built:
            self._on_change(self)
        self.suggest.candidate_changed()
        self.analysis.request()

    # (what scripts and tests read of the analysis: `CandidateAnalysis`)

    @property
    def last_evaluation(self) -> Evaluation | None:
        return self.analysis.last_evaluation

    @property
    def update_count(self) -> int:
        return self.analysis.update_count

    @property
    def computing_verdict(self) -> bool:
        return self.analysis.computing_verdict

    def apply_blocked(self) -> str:
        return self.analysis.apply_blocked()

    def wait_idle(self, timeout_s: float = 5.0) -> bool:
        return self.analysis.wait_idle(timeout_s)

    def wait_preview_idle(self, timeout_s: float = 10.0) -> bool:
        return self.analysis.wait_preview_idle(timeout_s)

    # -- the active configuration ------------------------------------------------------------

    def set_active(self, cfg: LoopConfig, version: int | None) -> None:
        """The controller's active configuration changed (any browser or client may have
        applied it). The candidate stays as it is (based on its version: the panel says so);
        the first one known loads the controls."""
        with self._controls_lock:
            if cfg == self.active and version == self.active_version:
                return
            self.active = cfg
            self.active_version = version
            self.active_text.content = active_html(cfg, version)
            self.box.superseded(version)
            if self.base_version is None and version is not None:
                self.load(cfg, version)
            else:
                self._show_stale()
                self.request_update()

    def rebase(self, cfg: LoopConfig, version: int) -> None:
        """This panel's own candidate became the active `version`: the candidate is now based
        on it (the controls keep what they show)."""
        self.base, self.base_version = cfg, version
        self._restored = False
        self._show_stale()
        self.request_update()

    def set_trajectory(self, traj: Trajectory) -> None:
        if traj != self.trajectory:
            self.trajectory = traj
            self.request_update()

    # -- Apply, Revert -----------------------------------------------------------------------

    def apply(self, browser: viser.ClientHandle | None = None) -> None:
        """Send the candidate unless the gate rejects it; a caution asks `browser` (the viser
        client that pressed Apply; None: this process) to confirm first."""
        self.sent = None
        try:
            cand = self.candidate()
        except ConfigError as exc:
            log.info("candidate not sent: %s", exc)
            self.box.not_sent("dt-apply", REJECT, f"Not sent: {esc(str(exc))}",
                              f"not sent: {exc}")
            return
        self.sent = cand
        verdict = self.box.checked(cand, self.active, self.stale, self.stale_by_reset,
                                   self.base_version, lambda c: self.engine.evaluate(c).verdict)
        if verdict is None:
            return
        if verdict.verdict == "caution":
            self._confirm_caution(cand, verdict.reasons, browser)
            return
        self.box.sending(confirmed=False)
        self.applier.submit(self, cand, False, browser)

    def _confirm_caution(self, cand: LoopConfig, reasons: tuple[str, ...],
                         browser: viser.ClientHandle | None) -> None:
        """A dialog (in the browser that asked) listing the reasons; only "Apply anyway"
        sends (with confirm)."""

        def go(who: viser.ClientHandle | None) -> None:
            self.box.sending(confirmed=True)
            self.applier.submit(self, cand, True, who)

        confirm(self.gui, browser, "Apply with caution?",
                "The gate's verdict is <b>caution</b>:"
                f"{_reason_list(reasons, 'dt-caution-reason')}", "Apply anyway", go)

    def show_reply(self, accepted: bool, version: int, reasons: list[str], note: str = "") -> None:
        self.box.show_reply(accepted, version, reasons, note)

    def note_refused(self, why: str) -> None:
        self.box.note_refused(why)

    def show_error(self, text: str) -> None:
        self.box.show_error(text)

    def revert(self, say: bool = True) -> None:
        """Set every control to the active configuration (no re-evaluation per control)."""
        self.load(self.active, self.active_version,
                  say_text="Reverted to the active configuration." if say else "")

    def load(self, a: LoopConfig, version: int | None, say_text: str = "") -> None:
        """Set every control to `a` (a revert, or an older version from the history: it goes
        through the gate like any candidate when applied), made against the active
        `version`."""
        with self._controls_lock:
            self.base, self.base_version = a, version
            self._restored = False
            self._show_stale()
            self.controls.show(a)
            if say_text:
                self.box.say(say_text)
            self.request_update()

    # -- text --------------------------------------------------------------------------------

    def cutoff_line_html(self, cutoff_hz: float, rec: float | None, known: bool = True,
                         error: str = "", invalid: bool = False) -> str:
        """The cut-off line under the slider (`tuning_html.cutoff_html`)."""
        return cutoff_html(cutoff_hz, rec, known, error, self.engine.position_spread(),
                           invalid)

    def show_kept_problem(self, text: str) -> None:
        """What the user should know about their candidates on disk ("" : nothing)."""
        set_html(self.kept_problem, kept_problem_html(text))
