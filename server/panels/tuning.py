"""Tuning panel: the candidate's controls, verdict, Apply/Revert, and the Bode and preview charts.

The computation is `server.engine.TuningEngine`; this module only builds viser widgets and
shows what the engine returns. Every control change wakes one worker thread that evaluates
only the newest candidate (latest wins), so GUI callbacks stay short; the slower preview and
the recommended cut-off run in a second, debounced worker.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import PositionSpread
from server import charts
from server.candidate_apply import CandidateApply
from server.candidate_store import KeptCandidate
from server.engine import (
    CUTOFF_MAX_HZ,
    CUTOFF_MIN_HZ,
    Evaluation,
    PreviewComparison,
    PreviewResult,
    TuningEngine,
    candidate_from_values,
)
from server.escape import esc
from server.panels.bode import MARGIN_LABELS as _MARGIN_LABELS
from server.panels.bode import BodeTab
from server.panels.bode import fmt_value as _fmt
from server.panels.widgets import (
    ACCEPT,
    CAUTION,
    NEUTRAL,
    REJECT,
    box,
    confirm,
    set_html,
)
from server.panels.widgets import reason_list as _reason_list
from server.suggest import (
    SUGGEST_CHART,
    SuggestSettings,
    suggest,
    suggest_data,
    suggest_html,
    suggested_config,
)
from server.viser_adapter import set_slider_marks
from server.workers import LatestWins

__all__ = ["StepState", "TuningPanel", "cutoff_marks", "format_gate_html", "kept_problem"]

log = logging.getLogger(__name__)

# -- presentation (pure) ------------------------------------------------------------------------

def format_gate_html(ev: Evaluation | None, error: str | None = None) -> str:
    """Margins and verdict as a small HTML block; a red box when the gate would reject."""
    if error is not None:
        return box("dt-verdict dt-reject", REJECT, f"<b>Invalid candidate</b><br>{esc(error)}",
                   font_px=None)
    assert ev is not None
    g = ev.verdict
    rows = "".join(
        f"<tr><td>{label}</td><td style='text-align:right'>"
        f"{_fmt(getattr(g.margins, key), d)} {unit}</td></tr>"
        for key, label, unit, d in _MARGIN_LABELS
    )
    table = f"<table style='width:100%;font-size:12px'>{rows}</table>"
    judged = (f"<div class='dt-knowledge' style='font-size:11px;color:#555'>judged on "
              f"{esc(g.knowledge)}</div>" if g.knowledge else "")
    if g.verdict == "accept":
        return box("dt-verdict dt-accept", ACCEPT, f"<b>Verdict: accept</b>{table}{judged}",
                   font_px=None)
    reasons = _reason_list(g.reasons, "dt-reason")
    if g.verdict == "caution":
        return box("dt-verdict dt-caution", CAUTION,
                   f"<b>Verdict: CAUTION</b> (applies only after you confirm){table}{reasons}"
                   f"{judged}", font_px=None)
    return box("dt-verdict dt-reject", REJECT,
               f"<b>Verdict: REJECT</b> (cannot be sent){table}{reasons}{judged}", font_px=None)


_BASE_MARKS: tuple[tuple[float, str], ...] = ((-1.0, "0.1 Hz"), (0.0, "1 Hz"), (1.0, "10 Hz"))
_LOG_LO, _LOG_HI = math.log10(CUTOFF_MIN_HZ), math.log10(CUTOFF_MAX_HZ)


#: The closest a decade mark may sit to 'max' (decades): nearer, their labels overlapped (1.34 Hz
#: next to "1 Hz": 0.13 decade, ~10 px apart on the sidebar's slider), and the decade goes.
_MARK_GAP_DEC = 0.45


def cutoff_marks(rec_hz: float | None) -> tuple[tuple[float, str], ...]:
    """The cut-off slider's marks: decades, and 'max' at the gate's recommendation (a decade
    too close to it left out, so that no two labels overlap)."""
    if rec_hz is not None and CUTOFF_MIN_HZ < rec_hz < CUTOFF_MAX_HZ:
        at = round(math.log10(rec_hz), 3)
        decades = tuple(m for m in _BASE_MARKS if abs(m[0] - at) >= _MARK_GAP_DEC)
        return tuple(sorted((*decades, (at, "max"))))
    return _BASE_MARKS


def diff_html(cand: LoopConfig, active: LoopConfig, version: int | None) -> str:
    """The fields the candidate changes against the active configuration (always shown)."""
    against = f"active v{version}" if version is not None else "the active configuration"
    return config_diff_html(active, cand, against, "Candidate")


def config_diff_html(old: LoopConfig, new: LoopConfig, old_label: str, new_label: str,
                     cls: str = "dt-diff") -> str:
    """The fields in which `new` differs from `old`, one per line (old &rarr; new)."""
    from controller.core.config import config_to_builtins

    a, c = config_to_builtins(old), config_to_builtins(new)
    rows = [f"<li>{esc(k)}: {esc(str(a.get(k)))} &rarr; <b>{esc(str(c[k]))}</b></li>"
            for k in c if c[k] != a.get(k)]
    if not rows:
        return (f"<div class='{cls}' style='font-size:12px;color:#555'>{esc(new_label)}: same "
                f"as {esc(old_label)}.</div>")
    return (f"<div class='{cls}' style='font-size:12px'>{esc(new_label)} vs {esc(old_label)}:"
            f"<ul style='margin:2px 0 0 16px;padding:0'>{''.join(rows)}</ul></div>")


def _fmt_hz_value(hz: float) -> str:
    """A cut-off as the Hz field shows it (up to 6 significant digits, no trailing zeros)."""
    return f"{hz:.6g}"


def _cutoff_log(hz: float) -> float:
    """The log slider's position of a cut-off in Hz (clamped to the slider)."""
    return _clamp(math.log10(max(hz, CUTOFF_MIN_HZ)), _LOG_LO, _LOG_HI)


def _preview_html(traj: Trajectory, p: PreviewComparison) -> str:
    """The preview's numbers: the candidate, the same gains with the DOB off (the DOB's value
    and its price: the command noise above 20 Hz), the active configuration."""
    pc, pa, pn = p.candidate, p.active, p.no_dob

    def run(label: str, r: PreviewResult, cls: str) -> str:
        return (f"<li class='{cls}'>{label}: peak <b>{r.peak_error_deg:.4f}</b> deg, RMSE "
                f"<b>{r.rmse_deg:.4f}</b> deg, command noise &gt;20 Hz "
                f"{r.command_noise_deg_s:.3g} deg/s</li>")

    c = pc.config
    dob = f"DOB {c.q_type.upper()} at {c.q_cutoff_hz:.3g} Hz" if c.dob_on else "DOB off"
    rows = [run(f"candidate ({dob})", pc, "dt-preview-cand")]
    if pn is not None:
        rows.append(run("candidate, DOB off", pn, "dt-preview-nodob"))
    rows.append(run("active", pa, "dt-preview-active"))
    verdict = ""
    if pn is not None and c.dob_on:
        better = pc.rmse_deg < pn.rmse_deg
        verdict = (f"<div class='dt-preview-verdict'>DOB {'beats' if better else 'does not beat'}"
                   f" DOB off here: RMSE {pc.rmse_deg / pn.rmse_deg - 1.0:+.1%}, peak "
                   f"{pc.peak_error_deg / pn.peak_error_deg - 1.0:+.1%}, command noise "
                   f"x{pc.command_noise_deg_s / max(pn.command_noise_deg_s, 1e-12):.2g}</div>")
    return (
        "<div class='dt-preview' style='font-size:13px'>"
        f"<b>Preview</b> ({esc(traj.kind)}, {pc.t_s[-1] + pc.t_s[1]:.1f} s simulated, "
        f"disturbances: {esc(pc.disturbances)}) "
        f"<span style='color:#888'>({pc.elapsed_s * 1e3:.0f} ms)</span>"
        f"<ul style='margin:2px 0 0 16px;padding:0'>{''.join(rows)}</ul>{verdict}</div>"
    )


def _divergence_html(sp: PositionSpread | None) -> str:
    """Where the measured responses part (the recommendation keeps Q below it)."""
    if sp is None:
        return ""
    n = len(sp.names)
    if sp.divergence_hz is None:
        return f" &middot; the {n} measured responses agree within 1 dB on their band"
    return (f" &middot; the {n} measured responses diverge above "
            f"<b>{sp.divergence_hz:.2f} Hz</b>")


@dataclass(frozen=True)
class StepState:
    """Where one step of the work stands (the guided path shows it: server/panels/guide.py)."""

    state: str  # "todo" | "running" | "done" | "failed"
    progress: float | None = None
    """0..1 while running (None: unknown)."""
    text: str = ""
    version: int | None = None
    """Apply: the active version the controller answered with."""
    at_s: float = 0.0
    """Apply: when it was accepted (time.monotonic())."""


# -- the GUI panel ------------------------------------------------------------------------------

_Q_LABELS = {"Q31 (3rd order, rel. deg 2)": "q31", "Q20 (2nd order)": "q20"}


@dataclass(frozen=True)
class _Gain:
    """A linear slider for one LoopConfig gain."""

    attr: str  # the panel attribute holding the handle
    field: str  # the LoopConfig field
    label: str
    lo: float
    hi: float
    step: float
    hint: str | None = None

    def position(self, cfg: LoopConfig) -> float:
        return _clamp(float(getattr(cfg, self.field)), self.lo, self.hi)


_GAINS = (
    _Gain("cv_kp", "cv_kp", "Cv Kp", 0.05, 3.0, 0.01, "speed loop Cv = Kp (1 + Ki/s)"),
    _Gain("cv_ki", "cv_ki_per_s", "Cv Ki (1/s)", 0.0, 200.0, 1.0),
    _Gain("pos_kp", "pos_kp_per_s", "Pos Kp (1/s)", 0.5, 40.0, 0.1,
          "position loop Cp = Kp (1 + Ki/s)"),
    _Gain("pos_ki", "pos_ki_per_s", "Pos Ki (1/s)", 0.0, 20.0, 0.1),
)
#: (panel attribute = LoopConfig field, label) of the switches.
_SWITCHES = (("dob_on", "DOB on"), ("ff_on", "Velocity feedforward"))


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

    # The control handles (build_controls): the switches and gains are made from the tables.
    dob_on: Any
    ff_on: Any
    cv_kp: Any
    cv_ki: Any
    pos_kp: Any
    pos_ki: Any

    def __init__(
        self,
        gui: Any,
        engine: TuningEngine,
        applier: CandidateApply,
        initial: LoopConfig | None = None,
        on_change: Callable[[TuningPanel], None] | None = None,
    ) -> None:
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
        self._writing = threading.local()
        """`on` while this thread sets controls itself: the callbacks viser then runs at once
        in this thread are its own echoes, not a user's change (a flag of this thread only:
        another thread's user event is never taken for one)."""
        self._reply_version: int | None = None
        self._gen_lock = threading.Lock()
        self._controls_lock = threading.RLock()
        """Held while the controls are set as a whole (`load`, `restore`) and while
        `set_active` decides whether the first known version loads them: a status thread's
        first load must not interleave with a browser's load of another version."""
        self._submitted_gen = 0
        self._done_gen = 0
        self._on_change = on_change
        self._started = False
        self._invalid = False
        self._same_as_active = False
        self._verdict_color = "gray"
        self.verdict: Any = None
        """The active version the apply box last announced (None: it announces none)."""
        self.last_update_s = 0.0
        self.last_evaluation: Evaluation | None = None
        self.last_preview: PreviewResult | None = None
        self.update_count = 0
        self._charts: dict[str, Any] = {}
        self._marks: tuple[tuple[float, str], ...] = ()
        self._preview_chart: Any = None
        self._steps_chart: Any = None
        self.nyquist: Any = None
        self.bode: BodeTab | None = None
        self._worker = LatestWins(self._update, name="tuning-update")
        self._preview_worker = LatestWins(
            self._run_preview, name="tuning-preview", debounce_s=0.08
        )
        self._suggest_worker = LatestWins(self._run_suggest, name="tuning-suggest")
        self._suggest_chart: Any = None
        self.last_suggestion: Any = None
        """The last Suggest's `TuneResult` (None: not run)."""
        self.suggest_state = StepState("todo")
        self.apply_state = StepState("todo")
        self._restored = False
        self._restored_against: LoopConfig | None = None
        """Restored (`restore`) and not loaded or re-based since: the controller's
        configuration at `base_version` when the candidate was kept (None: not known)."""
        self.sent: LoopConfig | None = None
        """The candidate of the last Apply pressed (`apply_state` is about it)."""
        """The last Apply of this panel: sending (running), accepted (done, `version`), not
        sent or refused (failed, with the reason)."""

    # -- building --------------------------------------------------------------------------

    def build_controls(self) -> None:
        gui = self.gui
        a = self.active
        self.q_type = gui.add_dropdown(
            "Q type", tuple(_Q_LABELS), initial_value=_label_of(a.q_type),
            hint="Q31: 3rd-order Q-filter (3 tau s + 1)/(tau s + 1)^3; Q20: 1/(tau s + 1)^2",
        )
        self.cutoff_log = gui.add_slider(
            "Q cut-off, log scale", min=round(_LOG_LO, 3), max=round(_LOG_HI, 3), step=0.005,
            initial_value=_cutoff_log(a.q_cutoff_hz), marks=_BASE_MARKS,
            hint="-3 dB cut-off of Q: drag on a log scale (the Hz field below is the value). "
            "The mark 'max' is the gate's recommendation.",
        )
        # A text field, not a number field: the server never writes into it while the user
        # types (a number field's limits made the server clamp the first typed "0" and send
        # it back), and "1e-1" or "2.5" parse as typed.
        self.cutoff_hz_input = gui.add_text(
            "Q cut-off (Hz)", initial_value=_fmt_hz_value(a.q_cutoff_hz),
            hint=f"type the -3 dB cut-off in Hz ({CUTOFF_MIN_HZ:g} to {CUTOFF_MAX_HZ:g}); "
            "the slider follows",
        )
        self._cutoff_hz = float(a.q_cutoff_hz)
        self._cutoff_error = ""
        self.cutoff_hz_input.on_update(self._on_cutoff_hz_typed)
        self.cutoff_log.on_update(self._on_cutoff_slider)
        self.cutoff_text = gui.add_html(self._cutoff_html(a.q_cutoff_hz, None))
        controls = [self.q_type]  # (one callback each; the cut-off's two have their own)
        for attr, label in _SWITCHES:
            setattr(self, attr, gui.add_checkbox(label, bool(getattr(a, attr))))
            controls.append(getattr(self, attr))
        for g in _GAINS:
            setattr(self, g.attr, gui.add_slider(g.label, g.lo, g.hi, g.step, g.position(a),
                                                 hint=g.hint))
            controls.append(getattr(self, g.attr))
        self.computing = gui.add_html(_computing_html(True))
        self.verdict = gui.add_html('<div class="dt-verdict">evaluating...</div>')
        self.stale_text = gui.add_html('<div class="dt-stale"></div>')
        self.kept_problem = gui.add_html(_kept_problem_html(""))
        self.diff_text = gui.add_html('<div class="dt-diff"></div>')
        self.apply_button = gui.add_button("Apply candidate", color="gray", disabled=True,
                                           hint="send to the controller; its gate decides")
        self.apply_why = gui.add_html(_apply_why_html("computing the verdict"))
        self.revert_button = gui.add_button("Revert to active", color="gray")
        self.suggest_button = gui.add_button(
            "Suggest Q cut-off", color="gray",
            hint="search Q type and cut-off for the controller's trajectory on the simulated "
            "rig (only what the gate accepts counts) and put the best into this candidate; "
            "never applied")
        self.suggest_text = gui.add_html("<div class='dt-suggest'></div>")
        self.apply_result = gui.add_html('<div class="dt-apply">No change sent yet.</div>')
        self.active_text = gui.add_html(self._active_html())
        for h in controls:
            h.on_update(self._on_control)
        self.apply_button.on_click(lambda e: self.apply(e.client))
        self.revert_button.on_click(lambda _e: self.revert())
        self.suggest_button.on_click(lambda _e: self.request_suggest())

    def build_charts(self) -> None:
        """The Bode tab's sub-tabs and charts (`server.panels.bode`)."""
        view = BodeTab(self.gui, self.engine.freq_hz)
        view.build()
        self.bode = view
        self._charts = view.charts
        self.nyquist = view.nyquist
        self.preview_text = view.preview_text
        self._preview_chart = view.preview_chart
        self._steps_chart = view.steps_chart
        self._suggest_chart = view.suggest_chart

    def start(self) -> None:
        self._started = True
        self._worker.start()
        self._preview_worker.start()
        self._suggest_worker.start()
        self.request_update()

    def stop(self) -> None:
        self._worker.stop()
        self._preview_worker.stop()
        self._suggest_worker.stop()

    def request_suggest(self) -> None:
        """Run Suggest on the present candidate (in its own worker thread)."""
        self.suggest_state = StepState("running", 0.0, "starting")
        set_html(self.suggest_text,
                 "<div class='dt-suggest dt-suggest-running'>Suggest: starting...</div>")
        self._suggest_worker.submit(time.perf_counter())

    def wait_suggest_idle(self, timeout_s: float = 60.0) -> bool:
        return self._suggest_worker.wait_idle(timeout_s)

    # -- reading the controls ----------------------------------------------------------------

    @property
    def cutoff_hz(self) -> float:
        """The candidate's cut-off: as typed in the Hz field, or where the slider was dragged
        (rounded to 3 significant digits)."""
        return self._cutoff_hz

    def control_values(self) -> dict[str, Any]:
        if self._cutoff_error:
            raise ConfigError("q_cutoff_hz", self._cutoff_error)
        values: dict[str, Any] = {
            "q_type": _Q_LABELS.get(self.q_type.value, "q31"),
            "q_cutoff_hz": self._cutoff_hz,
        }
        for attr, _label in _SWITCHES:
            values[attr] = bool(getattr(self, attr).value)
        for g in _GAINS:
            values[g.field] = float(getattr(self, g.attr).value)
        return values

    def candidate(self) -> LoopConfig:
        """The candidate from the controls on top of `base` (the fields without a control come
        from there); raises ConfigError."""
        return candidate_from_values(self.base, self.control_values())

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

    # -- events (GUI thread pool: short) -----------------------------------------------------

    @contextmanager
    def _setting_controls(self) -> Iterator[None]:
        """This thread sets controls: their callbacks (run at once, in this thread) are
        echoes."""
        prev = getattr(self._writing, "on", False)
        self._writing.on = True
        try:
            yield
        finally:
            self._writing.on = prev

    def _echo(self) -> bool:
        """The present callback is the echo of this thread's own setting of a control."""
        return bool(getattr(self._writing, "on", False))

    def _on_cutoff_hz_typed(self, _event: Any) -> None:
        """The Hz field is the value (never written back while typed); the slider follows."""
        if self._echo():
            return
        with self._controls_lock:
            self._read_cutoff_text()
            self.request_update()

    def _read_cutoff_text(self) -> None:
        text = str(self.cutoff_hz_input.value).strip()
        try:
            hz = float(text)
        except ValueError:
            hz = math.nan
        if not (math.isfinite(hz) and CUTOFF_MIN_HZ <= hz <= CUTOFF_MAX_HZ):
            self._cutoff_error = (
                f"{text!r} is not a cut-off in Hz between {CUTOFF_MIN_HZ:g} and {CUTOFF_MAX_HZ:g}"
            )
        else:
            self._cutoff_error = ""
            self._cutoff_hz = hz
            with self._setting_controls():
                self.cutoff_log.value = _cutoff_log(hz)

    # -- kept for a reload (server/candidate_store.py) -------------------------------------------

    def kept(self) -> KeptCandidate:
        """The candidate as its controls show it, with what it was made against."""
        against = (self._restored_against if self._restored else self.active
                   if self.base_version is not None and self.base_version == self.active_version
                   else None)
        return KeptCandidate(self.base, self.base_version,
                             tuple((n, getattr(self, n).value) for n in _KEPT_CONTROLS),
                             getattr(self, "nominal_override", None), against)

    def restore(self, k: KeptCandidate) -> None:
        """The controls as `k` kept them, made against `k.base_version` (stale, as before the
        reload, if the active version has moved on since)."""
        with self._controls_lock:
            self.base, self.base_version = k.base, k.base_version
            self._restored, self._restored_against = True, k.against
            if hasattr(self, "nominal_override"):
                self.nominal_override = k.nominal
            with self._setting_controls():
                for name, value in k.controls:
                    getattr(self, name).value = value
                self._read_cutoff_text()
            set_html(self.stale_text, self._stale_html())
            self.apply_result.content = box(
                "dt-apply dt-apply-restored", NEUTRAL,
                "Your candidate from before the reload (or the dashboard's restart)"
                + (f" (made against v{k.base_version})." if k.base_version is not None else "."))
            self.request_update()

    def _on_cutoff_slider(self, _event: Any) -> None:
        """A drag of the slider (its one callback): the cut-off (3 significant digits) and the
        Hz field follow, then the verdict is asked for, in that order and under the controls'
        lock (viser runs a control's callbacks on its thread pool in any order: with the
        update in a callback of its own, a drag could be judged before its cut-off was read)."""
        if self._echo():
            return
        with self._controls_lock:
            self._cutoff_hz = float(f"{10.0 ** float(self.cutoff_log.value):.3g}")
            self._cutoff_error = ""
            with self._setting_controls():
                self.cutoff_hz_input.value = _fmt_hz_value(self._cutoff_hz)
            self.request_update()

    def _on_control(self, _event: Any) -> None:
        if not self._echo():
            self.request_update()

    def request_update(self) -> None:
        if self._on_change is not None and self._started and self.verdict is not None:
            self._on_change(self)
        with self._gen_lock:
            self._submitted_gen += 1
            gen = self._submitted_gen
        if self.verdict is not None:
            set_html(self.computing, _computing_html(True))
            self._refresh_apply()
        self._worker.submit(gen)

    @property
    def computing_verdict(self) -> bool:
        """A change is not evaluated yet: the verdict shown is of an earlier candidate."""
        with self._gen_lock:
            return self._done_gen < self._submitted_gen

    def apply_blocked(self) -> str:
        """Why Apply is disabled ("" : it is enabled): only a current (evaluated), valid,
        non-stale candidate that differs from the active configuration may be sent."""
        return ("computing the verdict" if self.computing_verdict
                else "invalid candidate" if self._invalid
                else "made against a version the controller has since reset (Revert first)"
                if self.stale_by_reset
                else "based on an older version (Revert first)" if self.stale
                else "the candidate is the active configuration: nothing to send"
                if self._same_as_active else "")

    def _refresh_apply(self) -> None:
        why = self.apply_blocked()
        disabled = bool(why)
        if self.apply_button.disabled != disabled:
            self.apply_button.disabled = disabled
        color = "gray" if disabled else self._verdict_color
        if self.apply_button.color != color:
            self.apply_button.color = color
        set_html(self.apply_why, _apply_why_html(why))

    def _evaluated(self, gen: int, invalid: bool) -> None:
        """`_update` for submission `gen` is done (`invalid`: the controls give no config)."""
        with self._gen_lock:
            self._done_gen = max(self._done_gen, gen)
            current = self._done_gen >= self._submitted_gen
        self._invalid = invalid
        if current:
            set_html(self.computing, _computing_html(False))
        self._refresh_apply()

    def wait_idle(self, timeout_s: float = 5.0) -> bool:
        return self._worker.wait_idle(timeout_s)

    def wait_preview_idle(self, timeout_s: float = 10.0) -> bool:
        return self._worker.wait_idle(timeout_s) and self._preview_worker.wait_idle(timeout_s)

    def set_active(self, cfg: LoopConfig, version: int | None) -> None:
        """The controller's active configuration changed (any browser or client may have
        applied it). The candidate stays as it is (based on its version: the panel says so);
        the first one known loads the controls."""
        with self._controls_lock:
            if cfg == self.active and version == self.active_version:
                return
            self.active = cfg
            self.active_version = version
            self.active_text.content = self._active_html()
            shown = self._reply_version
            if shown is not None and version is not None and version > shown:
                # The apply box spoke of v{shown}; the controller has moved on (a rollback, or
                # another browser): no success text stands for a state that is gone.
                self._reply_version = None
                self.apply_result.content = box(
                    "dt-apply dt-apply-superseded", CAUTION,
                    f"<b>Active config is now v{version}</b>, no longer v{shown} of your last "
                    "apply: changed since (a watchdog rollback or another client; see the alarms "
                    "and History).")
            if self.base_version is None and version is not None:
                self.load(cfg, version)
            else:
                set_html(self.stale_text, self._stale_html())
                self.request_update()

    def rebase(self, cfg: LoopConfig, version: int) -> None:
        """This panel's own candidate became the active `version`: the candidate is now based
        on it (the controls keep what they show)."""
        self.base, self.base_version = cfg, version
        self._restored = False
        set_html(self.stale_text, self._stale_html())
        self.request_update()

    def set_trajectory(self, traj: Trajectory) -> None:
        if traj != self.trajectory:
            self.trajectory = traj
            self.request_update()

    def apply(self, browser: Any = None) -> None:
        """Send the candidate unless the gate rejects it; a caution asks `browser` (the viser
        client that pressed Apply; None: this process) to confirm first."""
        self.sent = None
        try:
            cand = self.candidate()
        except ConfigError as exc:
            log.info("candidate not sent: %s", exc)
            self.apply_state = StepState("failed", None, f"not sent: {exc}")
            self.apply_result.content = box("dt-apply", REJECT, f"Not sent: {esc(str(exc))}")
            return
        self.sent = cand
        if self.stale_by_reset:
            # The controller would take it (its version number matches): refused here.
            self.apply_result.content = box(
                "dt-apply dt-apply-rejected", REJECT,
                f"<b>Not sent</b>: made against v{self.base_version} as it was before the "
                "controller's state was reset; Revert first.")
            self.apply_state = StepState("failed", None,
                                         "not sent: made against a version since reset")
            return
        if cand == self.active and not self.stale:
            # Checked here too, whatever the browser's button showed: a new version of the
            # same configuration changes nothing on the rig.
            self.apply_result.content = box(
                "dt-apply dt-apply-same", NEUTRAL,
                "<b>Not sent</b>: the candidate is the active configuration.")
            self.apply_state = StepState("failed", None,
                                         "not sent: the candidate is the active configuration")
            return
        ev = self.engine.evaluate(cand)
        if ev.verdict.verdict == "reject":
            # Checked here, on the server, whatever the browser's button showed.
            self.apply_result.content = box(
                "dt-apply dt-apply-rejected", REJECT,
                "<b>Not sent</b>: the gate rejects this candidate"
                f"{_reason_list(ev.verdict.reasons, 'dt-reject-reason')}")
            self.apply_state = StepState("failed", None, "not sent: the gate rejects it: "
                                         + "; ".join(ev.verdict.reasons[:1]))
            return
        if ev.verdict.verdict == "caution":
            self._confirm_caution(cand, ev.verdict.reasons, browser)
            return
        self._reply_version = None
        self.apply_state = StepState("running", None, "sending to the controller")
        self.apply_result.content = box("dt-apply", NEUTRAL, "Sending the candidate...")
        self.applier.submit(self, cand, False, browser)

    def _confirm_caution(self, cand: LoopConfig, reasons: tuple[str, ...], browser: Any) -> None:
        """A dialog (in the browser that asked) listing the reasons; only "Apply anyway"
        sends (with confirm)."""

        def go(who: Any) -> None:
            self._reply_version = None
            self.apply_state = StepState("running", None,
                                         "sending to the controller (caution confirmed)")
            self.apply_result.content = box("dt-apply", NEUTRAL,
                                            "Sending the candidate (confirmed)...")
            self.applier.submit(self, cand, True, who)

        confirm(self.gui, browser, "Apply with caution?",
                "The gate's verdict is <b>caution</b>:"
                f"{_reason_list(reasons, 'dt-caution-reason')}", "Apply anyway", go)

    def show_reply(self, accepted: bool, version: int, reasons: list[str], note: str = "") -> None:
        self._reply_version = version
        self.apply_state = (
            StepState("done", None, f"accepted: the active configuration is v{version}",
                      version, time.monotonic()) if accepted else
            StepState("failed", None, "rejected by the controller: "
                      + "; ".join(reasons[:1] or ["no reason given"]), version))
        if accepted:
            self.apply_result.content = box(
                "dt-apply", ACCEPT, f"<b>Accepted</b>: active config is now version {version}."
            )
        else:
            self.apply_result.content = box(
                "dt-apply dt-apply-rejected", REJECT,
                f"<b>Rejected by the controller</b> (active stays version {version}):"
                f"{_reason_list(reasons, 'dt-reject-reason')}{esc(note)}",
            )

    def note_refused(self, why: str) -> None:
        """The dashboard refused to send (the browser was told): nothing is under way."""
        self.apply_state = StepState("failed", None, f"refused in the dashboard: {why}")

    def show_error(self, text: str) -> None:
        self.apply_state = StepState("failed", None, f"error: {text}")
        self.apply_result.content = box("dt-apply", REJECT, f"<b>Error</b>: {esc(text)}")

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
            set_html(self.stale_text, self._stale_html())
            with self._setting_controls():
                self.q_type.value = _label_of(a.q_type)
                self.cutoff_log.value = _cutoff_log(a.q_cutoff_hz)
                self.cutoff_hz_input.value = _fmt_hz_value(a.q_cutoff_hz)
                self._cutoff_hz = float(a.q_cutoff_hz)
                self._cutoff_error = ""
                if say_text:  # (a reply box from an earlier candidate no longer applies)
                    self._reply_version = None
                    self.apply_result.content = box("dt-apply", NEUTRAL, esc(say_text))
                for attr, _label in _SWITCHES:
                    getattr(self, attr).value = bool(getattr(a, attr))
                for g in _GAINS:
                    getattr(self, g.attr).value = g.position(a)
            self.request_update()

    # -- the workers -------------------------------------------------------------------------

    def _update(self, gen: int) -> None:
        t0 = time.perf_counter()
        try:
            cand = self.candidate()
        except ConfigError as exc:
            set_html(self.verdict, format_gate_html(None, str(exc)))
            set_html(self.cutoff_text, self._cutoff_html(self.cutoff_hz, None, True,
                                                         error=self._cutoff_error))
            set_html(self.diff_text, "<div class='dt-diff'></div>")
            self._verdict_color = "red"
            self._same_as_active = False
            self._evaluated(gen, invalid=True)
            return
        cmp = self.engine.compare(cand, self.active)
        if self.bode is not None:
            self.bode.show(cmp)
        ev = cmp.candidate
        set_html(self.verdict, format_gate_html(ev))
        set_html(self.diff_text, diff_html(cand, self.active, self.active_version))
        known, rec = self.engine.cached_recommendation(cand)
        set_html(self.cutoff_text, self._cutoff_html(cand.q_cutoff_hz, rec, known))
        if known:
            self._update_marks(rec)
        self._verdict_color = {"accept": "green", "caution": "orange"}.get(
            ev.verdict.verdict, "red")
        self._same_as_active = cand == self.active
        self.last_evaluation = ev
        self.last_update_s = time.perf_counter() - t0
        self.update_count += 1
        self._evaluated(gen, invalid=False)
        self._preview_worker.submit((cand, self.active, self.trajectory))

    def _update_marks(self, rec: float | None) -> None:
        marks = cutoff_marks(rec)
        if marks != self._marks:
            self._marks = marks
            set_slider_marks(self.cutoff_log, marks)  # viser takes marks only at creation

    def _run_preview(self, item: tuple[LoopConfig, LoopConfig, Trajectory]) -> None:
        cand, active, traj = item
        known, _ = self.engine.cached_recommendation(cand)
        if not known:
            rec = self.engine.recommended_max_cutoff_hz(cand)
            set_html(self.cutoff_text, self._cutoff_html(cand.q_cutoff_hz, rec, True))
            self._update_marks(rec)
        p = self.engine.compare_preview(cand, active, traj)
        if self._steps_chart is not None:
            self._steps_chart.data = self.engine.steps_data(cand, active)
        if self._preview_chart is not None:
            self._preview_chart.data = p.chart_data
            set_html(self.preview_text, _preview_html(traj, p))
        self.last_preview = p.candidate

    def _run_suggest(self, _submitted: Any) -> None:
        try:
            base = self.candidate()
        except ConfigError as exc:
            self.suggest_state = StepState("failed", None, f"needs a valid candidate: {exc}")
            set_html(self.suggest_text, box("dt-suggest", REJECT,
                                            f"Suggest needs a valid candidate: {esc(str(exc))}"))
            return
        t0 = time.perf_counter()
        traj = self.trajectory
        shown = [t0]

        def progress(frac: float) -> None:
            now = time.perf_counter()
            self.suggest_state = StepState("running", frac, "searching on the simulated rig")
            if now - shown[0] >= 0.25:
                shown[0] = now
                set_html(self.suggest_text, "<div class='dt-suggest dt-suggest-running'>"
                         f"Suggest: searching on the simulated rig... {100 * frac:.0f} %</div>")

        settings = SuggestSettings(duration_s=self.engine.preview_run_s(traj))
        try:
            result = suggest(base, self.engine.plant, traj, settings, progress=progress,
                             setup=self.engine.sim_setup)
        except Exception as exc:  # shown and logged: the worker goes on
            log.exception("Suggest failed")
            self.suggest_state = StepState("failed", None, f"{type(exc).__name__}: {exc}")
            set_html(self.suggest_text, box("dt-suggest dt-suggest-failed", REJECT,
                                            f"Suggest failed: {esc(str(exc))}"))
            return
        self.last_suggestion = result
        self.suggest_state = StepState("done", 1.0, result.summary())
        if self._suggest_chart is not None:
            data = suggest_data(result)
            self._suggest_chart.scales = charts.ranged_scales(SUGGEST_CHART, data)
            self._suggest_chart.data = data
        self.load(suggested_config(base, result), self.base_version)
        set_html(self.suggest_text, suggest_html(result, traj, time.perf_counter() - t0))

    # -- text --------------------------------------------------------------------------------

    def _cutoff_html(self, cutoff_hz: float, rec: float | None, known: bool = True,
                     error: str = "") -> str:
        if error:
            return ("<div class='dt-cutoff dt-cutoff-invalid' style='font-size:13px;"
                    "color:#d62728'><b>Q cut-off (Hz) rejected</b>: "
                    f"{esc(error)}. Apply is disabled until it is a number in range.</div>")
        if not known:
            rec_txt = " &middot; recommended max: computing..."
        elif rec is None:
            rec_txt = " &middot; <span style='color:#d62728'>the gate accepts no cut-off with " \
                "these gains</span>"
        else:
            rec_txt = f" &middot; gate's recommended max <b>{rec:.2f} Hz</b>"
        rec_txt += _divergence_html(self.engine.position_spread())
        warn = ""
        if rec is not None and cutoff_hz > rec:
            warn = " <span style='color:#d62728'>(above the recommendation)</span>"
        return (f"<div class='dt-cutoff' style='font-size:13px'>Q cut-off "
                f"<b>{cutoff_hz:.3f} Hz</b>{rec_txt}{warn}</div>")

    def show_kept_problem(self, text: str) -> None:
        """What the user should know about their candidates on disk ("" : nothing)."""
        set_html(self.kept_problem, _kept_problem_html(text))

    def _stale_html(self) -> str:
        if not self.stale:
            return "<div class='dt-stale'></div>"
        if self.stale_by_reset:
            return box(
                "dt-stale", CAUTION,
                f"<b>Based on v{self.base_version} as it was</b>: the controller's "
                f"v{self.active_version} is another configuration now (its state was reset "
                "since this candidate was made). Apply is off; <b>Revert</b> loads "
                f"v{self.active_version}.")
        return box(
            "dt-stale", CAUTION,
            f"<b>Based on v{self.base_version}</b>: the active configuration is now "
            f"v{self.active_version} (changed since: another client, or a watchdog rollback). "
            f"Apply would be refused (it carries "
            f"v{self.base_version}); <b>Revert</b> loads v{self.active_version}.")

    def _active_html(self) -> str:
        a = self.active
        v = "?" if self.active_version is None else str(self.active_version)
        return (
            f"<div class='dt-active' style='font-size:12px;color:#555'>Active (v{v}): "
            f"{a.q_type.upper()} {a.q_cutoff_hz:.3g} Hz, DOB {'on' if a.dob_on else 'off'}, "
            f"FF {'on' if a.ff_on else 'off'}, Cv {a.cv_kp:g}(1+{a.cv_ki_per_s:g}/s), "
            f"Cp {a.pos_kp_per_s:g}(1+{a.pos_ki_per_s:g}/s)</div>"
        )


def _kept_problem_html(text: str) -> str:
    if not text:
        return "<div class='dt-kept-problem'></div>"
    # A file's path is long and has no spaces: broken anywhere rather than cut off.
    return box("dt-kept-problem", REJECT,
               f"<span style='overflow-wrap:anywhere'>{esc(text)}</span>")


#: The controls a kept candidate holds (panel attributes; `kept`, `restore`).
_KEPT_CONTROLS = ("q_type", "cutoff_hz_input", *(a for a, _ in _SWITCHES),
                  *(g.attr for g in _GAINS))


def kept_problem(k: KeptCandidate) -> str:
    """Why `k` (read from a file) cannot be put back into the controls ("" : it can): its
    controls must be this panel's, each once, with a value of the control's kind."""
    names = [n for n, _ in k.controls]
    if sorted(names) != sorted(_KEPT_CONTROLS):
        return f"controls: expected {', '.join(_KEPT_CONTROLS)}, got {', '.join(names)}"
    for name, value in k.controls:
        if name == "q_type":
            ok = value in _Q_LABELS
        elif name == "cutoff_hz_input":
            ok = isinstance(value, str) and len(value) <= 64
        elif name in dict(_SWITCHES):
            ok = isinstance(value, bool)
        else:
            g = next(g for g in _GAINS if g.attr == name)
            ok = isinstance(value, float) and g.lo <= value <= g.hi
        if not ok:
            return f"controls.{name}: {value!r} is not a value of this control"
    return ""


def _apply_why_html(why: str) -> str:
    if not why:
        return "<div class='dt-apply-why'></div>"
    return ("<div class='dt-apply-why dt-apply-blocked' style='font-size:12px;color:#555'>"
            f"Apply is off: {esc(why)}.</div>")


def _computing_html(on: bool) -> str:
    if not on:
        return "<div class='dt-computing'></div>"
    return ("<div class='dt-computing dt-computing-on' style='font-size:12px;color:#555;"
            "font-style:italic'>computing the verdict...</div>")


def _label_of(q_type: str) -> str:
    for label, q in _Q_LABELS.items():
        if q == q_type:
            return label
    return next(iter(_Q_LABELS))


def _clamp(v: float, lo: float, hi: float) -> float:
    return min(max(v, lo), hi)
