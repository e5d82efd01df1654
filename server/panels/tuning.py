"""Tuning: a candidate configuration -> Bode curves, margins, verdict, time-domain preview.

`TuningEngine` is pure computation (no viser): it evaluates a candidate with the shared
stability check (`controller.gate.analysis`) and runs the offline experiment for the preview.
`TuningPanel` wires viser controls to it: every control change wakes one worker thread that
evaluates only the newest candidate (latest wins), so GUI callbacks stay short.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory
from controller.gate.analysis import (
    Analysis,
    MeasuredResponse,
    PlantKnowledge,
    analyse,
    default_grid,
    recommended_max_cutoff_hz,
)
from server import charts
from server.charts import BodeCurves, FloatArray

__all__ = ["Evaluation", "GateView", "PreviewResult", "TuningEngine", "format_gate_html"]

#: Log-slider range of the Q cut-off, Hz.
CUTOFF_MIN_HZ = 0.05
CUTOFF_MAX_HZ = 50.0


@dataclass(frozen=True)
class GateView:
    """What the stability check says about one configuration, ready to display."""

    verdict: str  # "accept" | "reject"
    reasons: tuple[str, ...]
    margins: dict[str, float]
    recommended_max_cutoff_hz: float | None = None

    @property
    def accepted(self) -> bool:
        return self.verdict == "accept"


@dataclass(frozen=True)
class Evaluation:
    config: LoopConfig
    curves: BodeCurves
    gate: GateView
    elapsed_s: float


@dataclass(frozen=True)
class PreviewResult:
    config: LoopConfig
    trajectory: Trajectory
    t_s: FloatArray
    error_deg: FloatArray
    peak_error_deg: float
    rmse_deg: float
    elapsed_s: float


def freq_grid_hz(rate_hz: float = 1000.0, n: int = 240) -> FloatArray:
    """Log grid of the Bode plots: 0.01 Hz to just under Nyquist (the gate's own grid)."""
    return np.asarray(default_grid(rate_hz, n), dtype=np.float64)


# -- the analysis adapter -------------------------------------------------------------------------


def curves_from_analysis(a: Analysis) -> tuple[BodeCurves, GateView]:
    """Adapter: the gate's Analysis -> what the charts draw and the verdict box shows."""
    bound = [src.inv_delta_db for src in a.sources if src.kind == "bound"]
    measured = [src.inv_delta_db for src in a.sources if src.kind == "measured"]
    curves = BodeCurves(
        freq_hz=a.freq_hz,
        open_loop_db=a.open_loop_mag_db,
        open_loop_phase_deg=_wrap_start(a.open_loop_phase_deg),
        closed_dob_db=charts.db(a.closed_loop_dob),
        closed_nodob_db=charts.db(a.closed_loop_no_dob),
        dist_dob_db=charts.db(a.disturbance_dob),
        dist_nodob_db=charts.db(a.disturbance_no_dob),
        noise_dob_db=charts.db(a.noise_dob),
        noise_nodob_db=charts.db(a.noise_no_dob),
        q_db=a.q_mag_db,
        rejection_db=a.rejection_db,
        inv_delta_db=bound[0] if bound else None,
        # The worst measured response at each frequency (smallest 1/|Delta|).
        inv_delta_measured_db=np.min(np.stack(measured), axis=0) if measured else None,
    )
    margins = {
        "gain_margin_db": a.gain_margin_db,
        "phase_margin_deg": a.phase_margin_deg,
        "peak_sensitivity_db": a.peak_sensitivity_db,
        "small_gain_peak": a.small_gain_peak,
        "max_pole_radius": a.max_pole_radius,
        "noise_to_command_peak_db": a.noise_to_command_peak_db,
    }
    return curves, GateView(a.verdict, tuple(a.reasons), margins)


def _wrap_start(phase_deg: FloatArray) -> FloatArray:
    """Shift an unwrapped phase by whole turns so that it starts in (-270, 90] deg."""
    if len(phase_deg) == 0:
        return phase_deg
    turns = math.floor((phase_deg[0] + 270.0) / 360.0)
    return np.asarray(phase_deg - 360.0 * turns, dtype=np.float64)


def measured_from_csv(name: str, data: Any) -> MeasuredResponse:
    """A CSV response (FrdData) as the gate's plant knowledge: a continuous response u -> w."""
    return MeasuredResponse(name=name, freq_hz=data.freq_hz, response=data.response)


class TuningEngine:
    """Evaluates candidates; caches the evaluation of configurations seen before."""

    def __init__(self, n_freq: int = 240, preview_duration_s: float = 12.6):
        self.n_freq = n_freq
        self.freq_hz = freq_grid_hz(1000.0, n_freq)
        self.preview_duration_s = preview_duration_s
        self.plant = PlantKnowledge()
        self._cache: dict[LoopConfig, Evaluation] = {}
        self._rec_cache: dict[LoopConfig, float | None] = {}
        self._preview_cache: dict[tuple[LoopConfig, Trajectory], PreviewResult] = {}
        self._lock = threading.Lock()

    @property
    def measured(self) -> tuple[MeasuredResponse, ...]:
        return self.plant.measured

    def add_measured(self, m: MeasuredResponse) -> None:
        """A measured response (CSV upload; same name replaces); invalidates cached verdicts."""
        with self._lock:
            kept = tuple(x for x in self.plant.measured if x.name != m.name)
            self.plant = PlantKnowledge(measured=(*kept, m), bound=self.plant.bound)
            self._cache.clear()
            self._rec_cache.clear()

    def cached_recommendation(self, cfg: LoopConfig) -> tuple[bool, float | None]:
        """(known, value) without computing."""
        key = cfg.with_(q_cutoff_hz=1.0, dob_on=True)
        with self._lock:
            if key in self._rec_cache:
                return True, self._rec_cache[key]
        return False, None

    def recommended_max_cutoff_hz(self, cfg: LoopConfig) -> float | None:
        """The gate's largest accepted Q cut-off for this candidate's other settings (cached;
        ~0.1 s, so call it off the slider path)."""
        key = cfg.with_(q_cutoff_hz=1.0, dob_on=True)
        with self._lock:
            if key in self._rec_cache:
                return self._rec_cache[key]
            plant = self.plant
        rec = recommended_max_cutoff_hz(key, plant, highest_hz=CUTOFF_MAX_HZ)
        with self._lock:
            self._rec_cache[key] = rec
        return rec

    def evaluate(self, cfg: LoopConfig) -> Evaluation:
        with self._lock:
            hit = self._cache.get(cfg)
        if hit is not None:
            return hit
        t0 = time.perf_counter()
        with self._lock:
            plant = self.plant
        grid = freq_grid_hz(cfg.rate_hz, self.n_freq)
        curves, gate = curves_from_analysis(analyse(cfg, plant, freq_hz=grid))
        ev = Evaluation(cfg, curves, gate, time.perf_counter() - t0)
        with self._lock:
            if len(self._cache) > 64:
                self._cache.clear()
            self._cache[cfg] = ev
        return ev

    def preview(self, cfg: LoopConfig, trajectory: Trajectory) -> PreviewResult:
        """The offline experiment over one sine period (12.6 s) or `preview_duration_s`."""
        key = (cfg, trajectory)
        with self._lock:
            hit = self._preview_cache.get(key)
        if hit is not None:
            return hit
        from controller.sim.experiment import run_experiment

        t0 = time.perf_counter()
        duration = trajectory.period_s or self.preview_duration_s
        res = run_experiment(cfg, trajectory, min(duration, 30.0), seed=0)
        out = PreviewResult(
            config=cfg,
            trajectory=trajectory,
            t_s=np.asarray(res.t_s, dtype=np.float64),
            error_deg=np.asarray(res.error_deg, dtype=np.float64),
            peak_error_deg=float(res.peak_error_deg),
            rmse_deg=float(res.rmse_deg),
            elapsed_s=time.perf_counter() - t0,
        )
        with self._lock:
            if len(self._preview_cache) > 16:
                self._preview_cache.clear()
            self._preview_cache[key] = out
        return out


# -- presentation (pure) ------------------------------------------------------------------------

_MARGIN_LABELS = (
    ("gain_margin_db", "gain margin", "dB", 1),
    ("phase_margin_deg", "phase margin", "deg", 1),
    ("peak_sensitivity_db", "peak |S|", "dB", 2),
    ("small_gain_peak", "small-gain peak", "", 3),
    ("max_pole_radius", "max |pole|", "", 5),
    ("noise_to_command_peak_db", "noise -> command", "dB", 1),
)


def _fmt(v: float, digits: int) -> str:
    if math.isinf(v):
        return "inf"
    if math.isnan(v):
        return "n/a"
    return f"{v:.{digits}f}"


def format_gate_html(ev: Evaluation | None, error: str | None = None) -> str:
    """Margins and verdict as a small HTML block; a red box when the gate would reject."""
    if error is not None:
        return (
            '<div class="dt-verdict dt-reject" style="border:2px solid #d62728;'
            'background:#fdecea;padding:6px;border-radius:4px">'
            f"<b>Invalid candidate</b><br>{_esc(error)}</div>"
        )
    assert ev is not None
    g = ev.gate
    rows = "".join(
        f"<tr><td>{label}</td><td style='text-align:right'>{_fmt(g.margins[key], d)} {unit}"
        "</td></tr>"
        for key, label, unit, d in _MARGIN_LABELS
        if key in g.margins
    )
    if g.accepted:
        head = (
            '<div class="dt-verdict dt-accept" style="border:2px solid #2ca02c;'
            'background:#eaf7ea;padding:6px;border-radius:4px"><b>Verdict: accept</b>'
        )
        reasons = ""
    else:
        head = (
            '<div class="dt-verdict dt-reject" style="border:2px solid #d62728;'
            'background:#fdecea;padding:6px;border-radius:4px"><b>Verdict: REJECT</b>'
        )
        reasons = "<ul style='margin:4px 0 0 16px;padding:0'>" + "".join(
            f"<li class='dt-reason'>{_esc(r)}</li>" for r in g.reasons
        ) + "</ul>"
    return f"{head}<table style='width:100%;font-size:12px'>{rows}</table>{reasons}</div>"


def _esc(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


@dataclass
class LatestWins:
    """A worker thread that runs `fn(item)` for the newest submitted item only."""

    fn: Callable[[Any], None]
    name: str = "latest-wins"
    #: Wait this long for a newer item before running (keeps slow work off a moving slider).
    debounce_s: float = 0.0
    _item: Any = None
    _has: bool = False
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _stop: bool = False
    _busy: bool = False
    _thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def submit(self, item: Any) -> None:
        with self._cond:
            self._item = item
            self._has = True
            self._cond.notify()

    def idle(self) -> bool:
        with self._cond:
            return not self._has and not self._busy

    def wait_idle(self, timeout_s: float = 5.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.idle():
                return True
            time.sleep(0.002)
        return False

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._has and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                self._busy = True
                if self.debounce_s > 0.0:
                    while self._has and not self._stop:
                        self._has = False
                        self._cond.wait(self.debounce_s)
                    if self._stop:
                        return
                item = self._item
                self._has = False
                self._item = None
            try:
                self.fn(item)
            except Exception as exc:  # a failing update must not kill the worker
                import traceback

                traceback.print_exception(exc)
            finally:
                with self._cond:
                    self._busy = False


def candidate_from_values(base: LoopConfig, values: dict[str, Any]) -> LoopConfig:
    """A validated candidate: `base` with the control values; raises ConfigError."""
    return base.with_(**values)


__all__ += ["CUTOFF_MAX_HZ", "CUTOFF_MIN_HZ", "ConfigError", "LatestWins", "candidate_from_values"]


# -- the GUI panel ------------------------------------------------------------------------------

_Q_LABELS = {"Q31 (3rd order, rel. deg 2)": "q31", "Q20 (2nd order)": "q20"}


class TuningPanel:
    """Controls, verdict, Apply/Revert (built into the current GUI container) and the Bode and
    preview charts (built separately with `build_charts`, e.g. in another panel)."""

    def __init__(
        self,
        gui: Any,
        engine: TuningEngine,
        apply_fn: Callable[[LoopConfig], None],
        initial: LoopConfig | None = None,
    ) -> None:
        self.gui = gui
        self.engine = engine
        self._apply_fn = apply_fn
        self.active: LoopConfig = initial or LoopConfig()
        self.active_version: int | None = None
        self.trajectory = Trajectory()
        self._suppress = False
        self.last_update_s = 0.0
        self.last_evaluation: Evaluation | None = None
        self.last_preview: PreviewResult | None = None
        self.update_count = 0
        self._charts: dict[str, Any] = {}
        self._marks: tuple[tuple[float, str], ...] = ()
        self._preview_chart: Any = None
        self._preview_text: Any = None
        self._worker = LatestWins(self._update, name="tuning-update")
        self._preview_worker = LatestWins(
            self._run_preview, name="tuning-preview", debounce_s=0.08
        )

    # -- building --------------------------------------------------------------------------

    def build_controls(self) -> None:
        gui = self.gui
        a = self.active
        self.q_type = gui.add_dropdown(
            "Q type", tuple(_Q_LABELS), initial_value=_label_of(a.q_type),
            hint="Q31: 3rd-order Q-filter (3 tau s + 1)/(tau s + 1)^3; Q20: 1/(tau s + 1)^2",
        )
        lo, hi = math.log10(CUTOFF_MIN_HZ), math.log10(CUTOFF_MAX_HZ)
        self.cutoff_log = gui.add_slider(
            "Q cut-off (log10 Hz)", min=round(lo, 3), max=round(hi, 3), step=0.005,
            initial_value=_clamp(math.log10(a.q_cutoff_hz), lo, hi),
            marks=((-1.0, "0.1 Hz"), (0.0, "1 Hz"), (1.0, "10 Hz")),
            hint="-3 dB cut-off of Q, log scale. The mark 'max' is the gate's recommendation.",
        )
        self.cutoff_hz_input = gui.add_number(
            "Q cut-off (Hz)", initial_value=round(a.q_cutoff_hz, 4), min=CUTOFF_MIN_HZ,
            max=CUTOFF_MAX_HZ, step=0.001, hint="type the -3 dB cut-off in Hz; the slider follows",
        )
        self.cutoff_hz_input.on_update(self._on_cutoff_hz_typed)
        self.cutoff_log.on_update(self._on_cutoff_slider)
        self.cutoff_text = gui.add_html(self._cutoff_html(a.q_cutoff_hz, None))
        self.dob_on = gui.add_checkbox("DOB on", a.dob_on)
        self.ff_on = gui.add_checkbox("Velocity feedforward", a.ff_on)
        self.cv_kp = gui.add_slider("Cv Kp", 0.05, 3.0, 0.01, _clamp(a.cv_kp, 0.05, 3.0),
                                    hint="speed loop Cv = Kp (1 + Ki/s)")
        self.cv_ki = gui.add_slider("Cv Ki (1/s)", 0.0, 200.0, 1.0,
                                    _clamp(a.cv_ki_per_s, 0.0, 200.0))
        self.pos_kp = gui.add_slider("Pos Kp (1/s)", 0.5, 40.0, 0.1,
                                     _clamp(a.pos_kp_per_s, 0.5, 40.0),
                                     hint="position loop Cp = Kp (1 + Ki/s)")
        self.pos_ki = gui.add_slider("Pos Ki (1/s)", 0.0, 20.0, 0.1,
                                     _clamp(a.pos_ki_per_s, 0.0, 20.0))
        self.verdict = gui.add_html('<div class="dt-verdict">evaluating...</div>')
        self.apply_button = gui.add_button("Apply candidate", color="green",
                                           hint="send to the controller; its gate decides")
        self.revert_button = gui.add_button("Revert to active", color="gray")
        self.apply_result = gui.add_html('<div class="dt-apply">No change sent yet.</div>')
        self.active_text = gui.add_html(self._active_html())
        for h in (self.q_type, self.cutoff_log, self.dob_on, self.ff_on, self.cv_kp, self.cv_ki,
                  self.pos_kp, self.pos_ki):
            h.on_update(self._on_control)
        self.apply_button.on_click(lambda _e: self.apply())
        self.revert_button.on_click(lambda _e: self.revert())

    def build_charts(self) -> None:
        gui = self.gui
        self.preview_text = gui.add_html('<div class="dt-preview">preview: running...</div>')
        spec = charts.PREVIEW_CHART
        self._preview_chart = gui.add_uplot(
            data=(np.array([0.0, 1.0]), np.zeros(2), np.zeros(2)),
            series=spec.series, scales=spec.scales, axes=spec.axes, title=spec.title,
            height=spec.height, aspect=2.0,
        )
        for spec in charts.BODE_CHARTS:
            n = len(spec.series)
            self._charts[spec.key] = gui.add_uplot(
                data=(self.engine.freq_hz, *([np.ones_like(self.engine.freq_hz)] * (n - 1))),
                series=spec.series, scales=spec.scales, axes=spec.axes, title=spec.title,
                height=spec.height, aspect=2.0,
            )

    def start(self) -> None:
        self._worker.start()
        self._preview_worker.start()
        self.request_update()

    def stop(self) -> None:
        self._worker.stop()
        self._preview_worker.stop()

    # -- reading the controls ----------------------------------------------------------------

    @property
    def cutoff_hz(self) -> float:
        return float(10.0 ** float(self.cutoff_log.value))

    def control_values(self) -> dict[str, Any]:
        return {
            "q_type": _Q_LABELS.get(self.q_type.value, "q31"),
            "q_cutoff_hz": round(self.cutoff_hz, 4),
            "dob_on": bool(self.dob_on.value),
            "ff_on": bool(self.ff_on.value),
            "cv_kp": float(self.cv_kp.value),
            "cv_ki_per_s": float(self.cv_ki.value),
            "pos_kp_per_s": float(self.pos_kp.value),
            "pos_ki_per_s": float(self.pos_ki.value),
        }

    def candidate(self) -> LoopConfig:
        """The candidate from the controls on top of the active config; raises ConfigError."""
        return candidate_from_values(self.active, self.control_values())

    # -- events (GUI thread pool: short) -----------------------------------------------------

    def _on_cutoff_hz_typed(self, _event: Any) -> None:
        """The Hz box drives the log slider (the slider's own callback then re-evaluates)."""
        if self._suppress:
            return
        hz = float(self.cutoff_hz_input.value)
        lo, hi = math.log10(CUTOFF_MIN_HZ), math.log10(CUTOFF_MAX_HZ)
        target = _clamp(math.log10(max(hz, CUTOFF_MIN_HZ)), lo, hi)
        if abs(float(self.cutoff_log.value) - target) > 1e-9:
            self.cutoff_log.value = target  # its callback re-evaluates the candidate

    def _on_cutoff_slider(self, _event: Any) -> None:
        hz = round(self.cutoff_hz, 4)
        if abs(float(self.cutoff_hz_input.value) - hz) > 1e-9:
            prev, self._suppress = self._suppress, True
            try:
                self.cutoff_hz_input.value = hz
            finally:
                self._suppress = prev

    def _on_control(self, _event: Any) -> None:
        if not self._suppress:
            self.request_update()

    def request_update(self) -> None:
        self._worker.submit(time.perf_counter())

    def wait_idle(self, timeout_s: float = 5.0) -> bool:
        return self._worker.wait_idle(timeout_s)

    def wait_preview_idle(self, timeout_s: float = 10.0) -> bool:
        return self._worker.wait_idle(timeout_s) and self._preview_worker.wait_idle(timeout_s)

    def set_active(self, cfg: LoopConfig, version: int | None) -> None:
        """The controller's active configuration changed (any dashboard may have applied it)."""
        if cfg == self.active and version == self.active_version:
            return
        self.active = cfg
        self.active_version = version
        self.active_text.content = self._active_html()
        self.request_update()

    def set_trajectory(self, traj: Trajectory) -> None:
        if traj != self.trajectory:
            self.trajectory = traj
            self.request_update()

    def apply(self) -> None:
        try:
            cand = self.candidate()
        except ConfigError as exc:
            self.apply_result.content = _box("#d62728", "#fdecea", f"Not sent: {_esc(str(exc))}")
            return
        self.apply_result.content = _box("#888", "#f4f4f4", "Sending the candidate...")
        self._apply_fn(cand)

    def show_reply(self, accepted: bool, version: int, reasons: list[str], note: str = "") -> None:
        if accepted:
            self.apply_result.content = _box(
                "#2ca02c", "#eaf7ea", f"<b>Accepted</b>: active config is now version {version}."
            )
        else:
            items = "".join(f"<li class='dt-reject-reason'>{_esc(r)}</li>" for r in reasons)
            self.apply_result.content = _box(
                "#d62728", "#fdecea",
                f"<b>Rejected by the controller</b> (active stays version {version}):"
                f"<ul style='margin:4px 0 0 16px;padding:0'>{items}</ul>{_esc(note)}",
                cls="dt-apply dt-apply-rejected",
            )

    def show_error(self, text: str) -> None:
        self.apply_result.content = _box("#d62728", "#fdecea", f"<b>Error</b>: {_esc(text)}")

    def revert(self) -> None:
        a = self.active
        self._suppress = True
        try:
            self.q_type.value = _label_of(a.q_type)
            lo, hi = math.log10(CUTOFF_MIN_HZ), math.log10(CUTOFF_MAX_HZ)
            self.cutoff_log.value = _clamp(math.log10(a.q_cutoff_hz), lo, hi)
            self.cutoff_hz_input.value = round(a.q_cutoff_hz, 4)
            self.dob_on.value = a.dob_on
            self.ff_on.value = a.ff_on
            self.cv_kp.value = _clamp(a.cv_kp, 0.05, 3.0)
            self.cv_ki.value = _clamp(a.cv_ki_per_s, 0.0, 200.0)
            self.pos_kp.value = _clamp(a.pos_kp_per_s, 0.5, 40.0)
            self.pos_ki.value = _clamp(a.pos_ki_per_s, 0.0, 20.0)
        finally:
            self._suppress = False
        self.request_update()

    # -- the workers -------------------------------------------------------------------------

    def _update(self, _submitted: Any) -> None:
        t0 = time.perf_counter()
        try:
            cand = self.candidate()
        except ConfigError as exc:
            self.verdict.content = format_gate_html(None, str(exc))
            self.cutoff_text.content = self._cutoff_html(self.cutoff_hz, None, True)
            return
        ev = self.engine.evaluate(cand)
        act = self.engine.evaluate(self.active)
        for key, handle in self._charts.items():
            handle.data = charts.bode_data(key, ev.curves, act.curves)
        self.verdict.content = format_gate_html(ev)
        known, rec = self.engine.cached_recommendation(cand)
        self.cutoff_text.content = self._cutoff_html(cand.q_cutoff_hz, rec, known)
        if known:
            self._update_marks(rec)
        self.apply_button.color = "green" if ev.gate.accepted else "orange"
        self.last_evaluation = ev
        self.last_update_s = time.perf_counter() - t0
        self.update_count += 1
        self._preview_worker.submit((cand, self.active, self.trajectory))

    def _update_marks(self, rec: float | None) -> None:
        marks: tuple[tuple[float, str], ...] = ((-1.0, "0.1 Hz"), (0.0, "1 Hz"), (1.0, "10 Hz"))
        if rec is not None and CUTOFF_MIN_HZ < rec < CUTOFF_MAX_HZ:
            marks = (*marks, (round(math.log10(rec), 3), "max"))
        if marks != self._marks:
            from viser._messages import GuiSliderMark  # viser exposes marks only at creation

            self._marks = marks
            self.cutoff_log._marks = tuple(GuiSliderMark(value=v, label=t) for v, t in marks)

    def _run_preview(self, item: tuple[LoopConfig, LoopConfig, Trajectory]) -> None:
        cand, active, traj = item
        known, _ = self.engine.cached_recommendation(cand)
        if not known:
            rec = self.engine.recommended_max_cutoff_hz(cand)
            self.cutoff_text.content = self._cutoff_html(cand.q_cutoff_hz, rec, True)
            self._update_marks(rec)
        pc = self.engine.preview(cand, traj)
        pa = self.engine.preview(active, traj)
        if self._preview_chart is not None:
            self._preview_chart.data = charts.preview_data(pc.t_s, pc.error_deg, pa.error_deg)
            self.preview_text.content = (
                "<div class='dt-preview' style='font-size:13px'>"
                f"<b>Preview</b> ({traj.kind}, {pc.t_s[-1] + pc.t_s[1]:.1f} s simulated): "
                f"candidate peak {pc.peak_error_deg:.4f} deg, RMSE {pc.rmse_deg:.4f} deg; "
                f"active peak {pa.peak_error_deg:.4f} deg, RMSE {pa.rmse_deg:.4f} deg"
                f" <span style='color:#888'>({pc.elapsed_s * 1e3:.0f} ms)</span></div>"
            )
        self.last_preview = pc

    # -- text --------------------------------------------------------------------------------

    def _cutoff_html(self, cutoff_hz: float, rec: float | None, known: bool = True) -> str:
        if not known:
            rec_txt = " &middot; recommended max: computing..."
        elif rec is None:
            rec_txt = " &middot; <span style='color:#d62728'>the gate accepts no cut-off with " \
                "these gains</span>"
        else:
            rec_txt = f" &middot; gate's recommended max <b>{rec:.2f} Hz</b>"
        warn = ""
        if rec is not None and cutoff_hz > rec:
            warn = " <span style='color:#d62728'>(above the recommendation)</span>"
        return (f"<div class='dt-cutoff' style='font-size:13px'>Q cut-off "
                f"<b>{cutoff_hz:.3f} Hz</b>{rec_txt}{warn}</div>")

    def _active_html(self) -> str:
        a = self.active
        v = "?" if self.active_version is None else str(self.active_version)
        return (
            f"<div class='dt-active' style='font-size:12px;color:#555'>Active (v{v}): "
            f"{a.q_type.upper()} {a.q_cutoff_hz:.3g} Hz, DOB {'on' if a.dob_on else 'off'}, "
            f"FF {'on' if a.ff_on else 'off'}, Cv {a.cv_kp:g}(1+{a.cv_ki_per_s:g}/s), "
            f"Cp {a.pos_kp_per_s:g}(1+{a.pos_ki_per_s:g}/s)</div>"
        )


def _box(border: str, bg: str, html: str, cls: str = "dt-apply") -> str:
    return (f"<div class='{cls}' style='border:2px solid {border};background:{bg};"
            f"padding:6px;border-radius:4px;font-size:13px'>{html}</div>")


def _label_of(q_type: str) -> str:
    for label, q in _Q_LABELS.items():
        if q == q_type:
            return label
    return next(iter(_Q_LABELS))


def _clamp(v: float, lo: float, hi: float) -> float:
    return min(max(v, lo), hi)
