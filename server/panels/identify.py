"""The Identify panel: measure the frequency response, fit Mn Pn, recommend the Q cut-off.

Two places to run, chosen on the panel (and always named in the status line):

* **on the controller** (default when connected): the IdentifyStart command carries the spec,
  the controller runs the excitation inside its loop; a worker thread polls the
  ``dobtune/<rig>/identify`` queryable (IdentifyStatus: progress, then the results) and Abort
  sends IdentifyAbort (the controller holds the position and keeps the partial data). While
  the run goes on, the status carries the frequencies finished so far with their per-point
  standard deviation: the curves build up on the charts, with their band, as they arrive.
* **offline on the simulated rig**, in a worker thread of the dashboard
  (`controller.ident.identify.run_identification` against a `SimRig`).

Offline, it runs as one `run_identification` per measurement position on one simulated rig (the load
moves on from where the previous position left it), so each position's response is drawn as
soon as it is measured; the positions are then fitted together (fit, Delta, agreement, the
gate's recommended cut-offs). An optional pace ("x real time") slows the simulation down so a
run can be watched and aborted. Abort stops the simulation at the next tick; the positions
measured so far stay on the charts, marked incomplete (the interrupted position is dropped).

"Use as nominal model" never talks to the controller: it puts the fitted nominal (and the
measured responses, as the gate's plant knowledge) into the tuning candidate, which is then
evaluated like any other change and sent only by the Tune tab's Apply.

GUI callbacks only read widgets, check the state under a lock and start/signal the worker;
viser's ``disabled`` flags are cosmetic, every button re-checks the state here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from controller import protocol as proto
from controller.client import ControllerClient, ControllerUnavailable
from controller.core.config import LoopConfig, NominalModel
from controller.core.errors import ConfigError
from controller.gate.analysis import MeasuredResponse
from controller.ident.identify import (
    IdentifyAborted,
    IdentifyResult,
    IdentifySpec,
    PositionRecord,
    RigLike,
    run_identification,
)
from server import charts
from server.panels.tuning import TuningPanel

__all__ = [
    "ABORTED",
    "DONE",
    "FAILED",
    "IDLE",
    "RUNNING",
    "FitView",
    "IdentifyPanel",
    "IdentifySettings",
    "IdentifyView",
    "NominalTuningPanel",
    "UserAbort",
    "curve_of",
    "format_result_html",
    "view_from_result",
    "view_from_status",
]

IDLE, RUNNING, DONE, ABORTED, FAILED = "idle", "running", "done", "aborted", "failed"

OFFLINE_NOTE = "offline on the simulated rig"
WHERE_CONTROLLER, WHERE_OFFLINE = "controller", "offline simulation"


class UserAbort(Exception):
    """Raised inside the simulation when the user presses Abort."""


# -- the tuning candidate's nominal -------------------------------------------------------------


class NominalTuningPanel(TuningPanel):
    """The tuning panel with a nominal-model slot in the candidate.

    ``nominal_override`` (set by "Use as nominal model") replaces the active configuration's
    nominal in the candidate; the gate evaluates it and Apply sends it like any other change.
    Revert clears it.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.nominal_override: NominalModel | None = None

    def candidate(self) -> LoopConfig:
        cand = super().candidate()
        if self.nominal_override is not None:
            cand = cand.with_(nominal=self.nominal_override)
        return cand

    def set_nominal(self, nominal: NominalModel | None) -> None:
        """Use `nominal` in the candidate (None: the active one) and re-evaluate; no apply."""
        self.nominal_override = nominal
        self.request_update()

    def revert(self) -> None:
        self.nominal_override = None
        super().revert()

    def _cutoff_html(self, cutoff_hz: float, rec: float | None, known: bool = True) -> str:
        html = super()._cutoff_html(cutoff_hz, rec, known)
        n = self.nominal_override
        if n is None:
            return html
        a2, a1, _ = n.pn_den
        return html + (
            "<div class='dt-nominal-fitted' style='font-size:12px;color:#1f77b4'>Candidate "
            f"nominal: <b>fitted by Identify</b> (Pn den {a2:.3g} s&sup2; + {a1:.3g} s + 1); "
            "Revert drops it.</div>"
        )


# -- pure helpers -------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class IdentifySettings:
    """What the panel's controls ask for."""

    mode: str = "open"
    signal: str = "sine"
    f_min_hz: float = 0.1
    f_max_hz: float = 20.0
    points_per_decade: int = 10
    positions: int = 3
    amplitude_deg_s: float = 10.0
    pace: float = 0.0
    """Simulated seconds per wall second (0: as fast as possible); offline only."""
    where: str = WHERE_OFFLINE
    """WHERE_CONTROLLER or WHERE_OFFLINE."""

    def spec(self) -> IdentifySpec:
        """The validated spec; raises ConfigError naming the field."""
        return IdentifySpec(
            mode=self.mode,
            signal=self.signal,
            f_min_hz=float(self.f_min_hz),
            f_max_hz=float(self.f_max_hz),
            points_per_decade=int(self.points_per_decade),
            positions=int(self.positions),
            amplitude_deg_s=float(self.amplitude_deg_s),
        )


def curve_of(p: PositionRecord) -> charts.MeasuredCurve | None:
    """A position's measured response for the charts (None if nothing was measured)."""
    e = p.estimate
    if e is None or e.freq_hz.size == 0:
        return None
    return charts.MeasuredCurve(
        label=f"pos {p.index + 1} ({p.center_deg:g} deg)",
        freq_hz=np.asarray(e.freq_hz, dtype=np.float64),
        mag_db=np.asarray(e.mag_db, dtype=np.float64),
        phase_deg=np.asarray(e.phase_deg, dtype=np.float64),
        mag_std_db=np.asarray(e.mag_std_db, dtype=np.float64),
        coherence=np.asarray(e.coherence, dtype=np.float64),
        complete=p.complete,
    )


def _esc(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def _hz(v: float | None) -> str:
    return "none accepted" if v is None else f"{v:.3g} Hz"


@dataclasses.dataclass(frozen=True)
class FitView:
    """The fitted Mn Pn = 1 / (a2 s^2 + a1 s + 1), as displayed."""

    a2: float
    a1: float
    natural_freq_hz: float
    natural_freq_std_hz: float
    zeta: float
    zeta_std: float
    residual_rms_db: float
    residual_rms_deg: float
    f_lo_hz: float
    f_hi_hz: float
    n_points: int

    def response(self, freq_hz: charts.FloatArray) -> Any:
        s = 2j * np.pi * np.asarray(freq_hz, dtype=np.float64)
        return 1.0 / (self.a2 * s * s + self.a1 * s + 1.0)


@dataclasses.dataclass(frozen=True)
class IdentifyView:
    """What the panel shows of one run, wherever it ran."""

    n_positions: int
    complete: bool
    abort_reason: str | None
    positions_done: int
    curves: tuple[charts.MeasuredCurve | None, ...]
    fit: FitView | None = None
    agreement_hz: float | None = None
    agreement_tol: tuple[float, float] = (1.0, 10.0)
    recommended_cutoff_hz: dict[str, float | None] = dataclasses.field(default_factory=dict)
    checks: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    simulated_s: float | None = None
    nominal: NominalModel | None = None
    measured: tuple[MeasuredResponse, ...] = ()


def view_from_result(result: IdentifyResult, n_positions: int) -> IdentifyView:
    """Adapter: an offline IdentifyResult -> what the panel shows."""
    f = result.fit
    fit = None if f is None else FitView(
        a2=f.params["a2"], a1=f.params["a1"], natural_freq_hz=f.natural_freq_hz,
        natural_freq_std_hz=f.natural_freq_std_hz, zeta=float(f.zeta),
        zeta_std=float(f.zeta_std), residual_rms_db=f.residual_rms_db,
        residual_rms_deg=f.residual_rms_deg, f_lo_hz=f.f_lo_hz, f_hi_hz=f.f_hi_hz,
        n_points=f.n_points,
    )
    checks = []
    for c in result.gate_checks:
        why = "" if c.accepted or not c.reasons else f": {c.reasons[0]}"
        checks.append(f"gate at {c.q_type.upper()} {c.cutoff_hz:.3g} Hz: "
                      f"{'accept' if c.accepted else 'reject'} (small-gain peak "
                      f"{c.small_gain_peak:.2f}){why}")
    a = result.agreement
    return IdentifyView(
        n_positions=n_positions,
        complete=result.complete,
        abort_reason=result.abort_reason,
        positions_done=sum(1 for p in result.positions if p.complete),
        curves=tuple(curve_of(p) for p in result.positions),
        fit=fit,
        agreement_hz=None if a is None else a.agree_below_hz,
        agreement_tol=(result.spec.agreement_tol_db, result.spec.agreement_tol_deg),
        recommended_cutoff_hz=dict(result.recommended_cutoff_hz) if result.complete else {},
        checks=tuple(checks),
        notes=tuple(result.notes),
        simulated_s=result.simulated_s,
        nominal=result.nominal if result.complete else None,
        measured=result.measured_responses(),
    )


def view_from_status(
    st: proto.IdentifyStatus, n_positions: int, base: NominalModel
) -> IdentifyView:
    """Adapter: the controller's IdentifyStatus (and its summary JSON) -> what the panel shows.

    Works for a running status too (the partial positions; nothing fitted). The band is the
    per-point magnitude std (NaN, so no band, from a controller that sends none). `base`
    supplies Mn when the summary carries no nominal (the article form: Pn = Mn_den / fit_den).
    """
    summary: dict[str, Any] = {}
    if st.summary_json:
        with contextlib.suppress(ValueError):
            summary = json.loads(st.summary_json)
    curves: list[charts.MeasuredCurve | None] = []
    measured: list[MeasuredResponse] = []
    for p in st.positions:
        if not p.freq_hz:
            curves.append(None)
            continue
        f = np.asarray(p.freq_hz, dtype=np.float64)
        mag = np.asarray(p.mag_db, dtype=np.float64)
        ph = np.degrees(np.unwrap(np.radians(np.asarray(p.phase_deg, dtype=np.float64))))
        std = (np.asarray(p.mag_std_db, dtype=np.float64) if len(p.mag_std_db) == f.size
               else np.full(f.size, np.nan))
        curves.append(charts.MeasuredCurve(
            label=f"pos {p.index + 1} ({p.center_deg:g} deg)", freq_hz=f, mag_db=mag,
            phase_deg=ph, mag_std_db=std,
            coherence=np.asarray(p.coherence, dtype=np.float64), complete=p.complete,
        ))
        if p.complete and f.size >= 2:
            resp = (10.0 ** (mag / 20.0) * np.exp(1j * np.radians(ph))).astype(np.complex128)
            measured.append(MeasuredResponse(
                name=f"pos{p.index}_{p.center_deg:g}deg", freq_hz=f, response=resp))
    complete = st.state == "done" and bool(st.positions) and all(
        p.complete for p in st.positions) and len(st.positions) == n_positions
    fit: FitView | None = None
    fo = summary.get("fit")
    if complete and isinstance(fo, dict):
        with contextlib.suppress(KeyError, TypeError, ValueError):
            band = fo.get("band_hz") or [float("nan"), float("nan")]
            fit = FitView(
                a2=float(fo["a2"]), a1=float(fo["a1"]),
                natural_freq_hz=float(fo["natural_freq_hz"]),
                natural_freq_std_hz=float(fo.get("natural_freq_std_hz") or float("nan")),
                zeta=float(fo["zeta"]), zeta_std=float(fo.get("zeta_std") or float("nan")),
                residual_rms_db=float(fo["residual_rms_db"]),
                residual_rms_deg=float(fo["residual_rms_deg"]),
                f_lo_hz=float(band[0]), f_hi_hz=float(band[1]), n_points=int(fo["n_points"]),
            )
    nominal: NominalModel | None = None
    if fit is not None:
        no = summary.get("nominal")
        with contextlib.suppress(ConfigError, KeyError, TypeError, ValueError):
            nominal = (
                NominalModel(mn_den=tuple(no["mn_den"]), pn_num=tuple(no["pn_num"]),
                             pn_den=tuple(no["pn_den"]))
                if isinstance(no, dict)
                else NominalModel(mn_den=base.mn_den, pn_num=base.mn_den,
                                  pn_den=(fit.a2, fit.a1, 1.0))
            )
    agree = summary.get("agreement") or {}
    checks = []
    for g in summary.get("gate_checks") or []:
        with contextlib.suppress(KeyError, TypeError, ValueError):
            why = "" if g["accepted"] or not g.get("reasons") else f": {g['reasons'][0]}"
            peak = g.get("small_gain_peak")
            checks.append(
                f"gate at {str(g['q_type']).upper()} {float(g['cutoff_hz']):.3g} Hz: "
                f"{'accept' if g['accepted'] else 'reject'}"
                + (f" (small-gain peak {float(peak):.2f})" if peak is not None else "") + why)
    sim_s = summary.get("simulated_s")
    return IdentifyView(
        n_positions=n_positions,
        complete=complete,
        abort_reason=st.abort_reason or None,
        positions_done=sum(1 for p in st.positions if p.complete),
        curves=tuple(curves),
        fit=fit,
        agreement_hz=st.agreement_freq_hz,
        agreement_tol=(float(agree.get("tol_db", 1.0)), float(agree.get("tol_deg", 10.0))),
        recommended_cutoff_hz=dict(st.recommended_cutoff_hz) if complete else {},
        checks=tuple(checks),
        notes=tuple(str(x) for x in summary.get("notes") or ()),
        simulated_s=float(sim_s) if isinstance(sim_s, (int, float)) else None,
        nominal=nominal,
        measured=tuple(measured),
    )


def _query_identify(client: ControllerClient) -> proto.IdentifyStatus:
    """The controller's latest identification (raises ControllerUnavailable/ProtocolError)."""
    data = client._query(proto.key_identify(client.opts.rig_name), b"")
    return proto.decode(data, proto.IdentifyStatus)


def format_result_html(view: IdentifyView | None) -> str:
    """Fit, agreement, recommended cut-offs and notes as a small HTML block."""
    if view is None:
        return "<div class='dt-identify-result' style='font-size:12px;color:#555'>No result yet."\
               "</div>"
    rows: list[str] = []
    if not view.complete:
        rows.append(
            "<div class='dt-id-incomplete' style='color:#d62728'><b>INCOMPLETE</b>: "
            f"{view.positions_done} of {view.n_positions} position(s) measured"
            + (f" ({_esc(view.abort_reason)})" if view.abort_reason else "")
            + "; nothing fitted.</div>"
        )
    fit = view.fit
    if fit is not None:
        wn, wn_std = 2 * np.pi * fit.natural_freq_hz, 2 * np.pi * fit.natural_freq_std_hz
        rows.append(
            "<div class='dt-id-fit'><b>Fit Mn Pn</b> = 1/(a2 s&sup2; + a1 s + 1): "
            f"f<sub>n</sub> = <b>{fit.natural_freq_hz:.3f} &plusmn; "
            f"{fit.natural_freq_std_hz:.3f} Hz</b> "
            f"(&omega;<sub>n</sub> {wn:.2f} &plusmn; {wn_std:.2f} rad/s), "
            f"&zeta; = <b>{fit.zeta:.3f} &plusmn; {fit.zeta_std:.3f}</b>; residual "
            f"{fit.residual_rms_db:.2f} dB / {fit.residual_rms_deg:.1f} deg rms over "
            f"{fit.f_lo_hz:.3g}-{fit.f_hi_hz:.3g} Hz ({fit.n_points} points)</div>"
        )
    if view.complete:
        if view.agreement_hz is not None:
            tol_db, tol_deg = view.agreement_tol
            rows.append(
                f"<div class='dt-id-agree'>Positions agree (within {tol_db:g} dB / "
                f"{tol_deg:g} deg) below <b>{view.agreement_hz:.3g} Hz</b></div>"
            )
        else:
            rows.append("<div class='dt-id-agree'>Agreement across positions: needs at least "
                        "two positions.</div>")
        rec = view.recommended_cutoff_hz
        if rec:
            rows.append(
                "<div class='dt-id-cutoff'>Gate's recommended max cut-off with the fitted "
                f"nominal: <b>Q31 {_hz(rec.get('q31'))}</b>, <b>Q20 {_hz(rec.get('q20'))}</b>"
                "</div>"
            )
        for c in view.checks:
            rows.append(
                f"<div class='dt-id-check' style='font-size:11px;color:#555'>{_esc(c)}</div>")
    for note in view.notes:
        rows.append(f"<div class='dt-id-note' style='color:#b36b00'>{_esc(note)}</div>")
    if view.simulated_s is not None:
        rows.append(
            f"<div style='font-size:11px;color:#888'>{view.simulated_s:.1f} s on the rig</div>"
        )
    return "<div class='dt-identify-result' style='font-size:12px'>" + "".join(rows) + "</div>"


def _status_html(state: str, text: str, where: str = OFFLINE_NOTE) -> str:
    color = {RUNNING: "#1f77b4", DONE: "#2e7d32", ABORTED: "#d62728", FAILED: "#d62728"}.get(
        state, "#555"
    )
    return (
        f"<div class='dt-identify-status dt-id-{state}' style='font-size:12px;color:{color}'>"
        f"<b>{state}</b> &middot; {_esc(text)} <span style='color:#888'>({_esc(where)})"
        "</span></div>"
    )


class _PacedRig:
    """A rig wrapper: raises UserAbort at the next tick after `abort` is set and, with
    ``pace > 0``, keeps simulated time at most `pace` x the wall time."""

    def __init__(self, rig: RigLike, rate_hz: float, abort: threading.Event, pace: float) -> None:
        self.rig = rig
        self.read = rig.read  # no extra call layer on the hot path
        self._step = rig.step
        self.abort = abort
        self.ts = 1.0 / rate_hz
        self.pace = pace
        self.ticks = 0
        self.t0 = time.monotonic()
        self.chunk = max(1, round(0.01 * rate_hz))  # abort within 10 simulated ms

    def step(self, command_deg_s: float) -> None:
        self._step(command_deg_s)
        self.ticks += 1
        if self.ticks % self.chunk == 0:
            if self.abort.is_set():
                raise UserAbort("aborted by the user")
            if self.pace > 0.0:
                ahead = self.ticks * self.ts / self.pace - (time.monotonic() - self.t0)
                if ahead > 0.0:
                    self.abort.wait(ahead)


def _combine(spec: IdentifySpec, cfg: LoopConfig, results: list[IdentifyResult],
             complete: bool, reason: str | None) -> IdentifyResult:
    """One result from the per-position runs (`results` not empty), fitted together when
    complete."""
    positions = tuple(
        dataclasses.replace(p, index=k) for k, r in enumerate(results) for p in r.positions[:1]
    )
    if complete and len(results) == 1:
        return dataclasses.replace(results[0], spec=spec, positions=positions)
    base = IdentifyResult(
        spec=spec,
        config=cfg,
        excitation=results[0].excitation,
        positions=positions,
        complete=complete,
        abort_reason=reason,
        simulated_s=sum(r.simulated_s for r in results),
    )
    if not complete:
        return base
    # The positions were measured in separate runs: fit them together as one run does.
    from controller.ident.identify import _analyse_result

    return _analyse_result(spec, cfg, base)


# -- the panel ----------------------------------------------------------------------------------


_MODES = ("open", "closed")
_SIGNALS = ("sine", "multisine")


class IdentifyPanel:
    """Settings, Start/Abort, progress and result (`build_controls`) and the response charts
    (`build_charts`); the run happens in one worker thread at a time."""

    def __init__(
        self,
        gui: Any,
        tuning: NominalTuningPanel | None,
        config_fn: Callable[[], LoopConfig] | None = None,
        rig_factory: Callable[[LoopConfig, int], RigLike] | None = None,
        add_measured: Callable[[MeasuredResponse], None] | None = None,
        client: ControllerClient | None = None,
    ) -> None:
        self.gui = gui
        self.tuning = tuning
        self._config_fn = config_fn or (
            (lambda: tuning.active) if tuning is not None else LoopConfig
        )
        self._rig_factory = rig_factory or _sim_rig
        self._add_measured = add_measured
        self.client = client
        self.where_note = OFFLINE_NOTE
        self._closing = threading.Event()
        self._lock = threading.Lock()
        self._abort = threading.Event()
        self._thread: threading.Thread | None = None
        self.state = IDLE
        self.text = "not started"
        self.progress = 0.0
        self.result: IdentifyResult | None = None
        """The offline run's full result."""
        self.view: IdentifyView | None = None
        self.n_positions = 3
        self.curves: list[charts.MeasuredCurve | None] = []
        self.charts: dict[str, Any] = {}
        self.chart_updates = 0
        self._chart_n = 0
        self._last_publish = 0.0
        self._chart_box: Any = None
        self.chart_note: Any = None

    # -- building --------------------------------------------------------------------------

    def build_controls(self) -> None:
        gui = self.gui
        d = IdentifySettings()
        if self.client is not None:
            self.where = gui.add_dropdown(
                "Run on", (WHERE_CONTROLLER, WHERE_OFFLINE), initial_value=WHERE_CONTROLLER,
                hint="controller: the excitation runs in its loop and the rig moves; offline "
                     "simulation: the built-in simulated rig in this dashboard")
        gui.add_html(
            "<div class='dt-identify-note' style='font-size:12px;color:#b36b00'>"
            + ("On the controller the <b>rig moves</b> (limits: amplitude, position window, "
               "duration; E-STOP aborts). " if self.client is not None else "")
            + f"Offline: <b>{OFFLINE_NOTE}</b>.</div>"
        )
        self.mode = gui.add_dropdown("Mode", _MODES, initial_value=d.mode,
                                     hint="open: u = offset + excitation; closed: speed loop "
                                          "active, excitation added to its command")
        self.signal = gui.add_dropdown("Signal", _SIGNALS, initial_value=d.signal,
                                       hint="stepped sine or periodic multisine")
        self.f_min = gui.add_number("f min (Hz)", d.f_min_hz, min=0.01, max=200.0, step=0.01)
        self.f_max = gui.add_number("f max (Hz)", d.f_max_hz, min=0.02, max=400.0, step=0.01)
        self.ppd = gui.add_number("Points per decade", d.points_per_decade, min=1, max=200,
                                  step=1)
        self.positions = gui.add_number("Positions", d.positions, min=1, max=36, step=1,
                                        hint="evenly spread over a turn")
        self.amplitude = gui.add_number("Amplitude (deg/s)", d.amplitude_deg_s, min=0.1,
                                        max=100.0, step=0.1,
                                        hint="largest excitation amplitude, load speed")
        self.pace = gui.add_number("Pace (x real time, 0 = fastest)", d.pace, min=0.0,
                                   max=1000.0, step=0.5, hint="offline only")
        self.start_button = gui.add_button("Start identification", color="green")
        self.abort_button = gui.add_button("Abort", color="red", disabled=True)
        self.progress_bar = gui.add_progress_bar(0.0)
        self.status = gui.add_html(_status_html(IDLE, self.text))
        self.result_html = gui.add_html(format_result_html(None))
        self.use_button = gui.add_button("Use as nominal model", color="blue", disabled=True,
                                         hint="put the fitted Mn Pn into the tuning candidate "
                                              "(checked by the gate; Apply sends it)")
        self.use_result = gui.add_html("<div class='dt-id-use' style='font-size:12px'></div>")
        self.start_button.on_click(lambda _e: self.start())
        self.abort_button.on_click(lambda _e: self.abort())
        self.use_button.on_click(lambda _e: self.use_as_nominal())

    def build_charts(self) -> None:
        self.chart_note = self.gui.add_html(
            "<div class='dt-identify-charts' style='font-size:12px;color:#555'>Identification: "
            "the measured responses appear here.</div>")
        self._chart_box = self.gui.add_folder("Measured response", expand_by_default=True)
        self._make_charts(self.n_positions)

    def _make_charts(self, n: int) -> None:
        """(Re)create the charts for `n` positions (the series count of a uPlot is fixed)."""
        if self._chart_box is None:
            return
        for h in self.charts.values():
            with contextlib.suppress(Exception):
                h.remove()
        self.charts = {}
        data = charts.identify_data(n, [])
        with self._chart_box:
            for spec in charts.identify_chart_specs(n):
                self.charts[spec.key] = self.gui.add_uplot(
                    data=data[spec.key], series=spec.series, scales=spec.scales,
                    axes=spec.axes, title=spec.title, height=spec.height, aspect=2.0,
                    bands=spec.extra.get("bands"),
                )
        self._chart_n = n

    def stop(self) -> None:
        """Dashboard shutdown: an offline run stops; a run on the controller goes on there."""
        self._closing.set()
        self._abort.set()
        t = self._thread
        if t is not None:
            t.join(timeout=5.0)

    # -- reading the controls ----------------------------------------------------------------

    def settings(self) -> IdentifySettings:
        return IdentifySettings(
            mode=str(self.mode.value),
            signal=str(self.signal.value),
            f_min_hz=float(self.f_min.value),
            f_max_hz=float(self.f_max.value),
            points_per_decade=round(float(self.ppd.value)),
            positions=round(float(self.positions.value)),
            amplitude_deg_s=float(self.amplitude.value),
            pace=max(0.0, float(self.pace.value)),
            where=str(self.where.value) if self.client is not None else WHERE_OFFLINE,
        )

    # -- events (short) ----------------------------------------------------------------------

    def start(self, settings: IdentifySettings | None = None) -> bool:
        """Start a run unless one is running; False (and a message) if not started."""
        s = settings or self.settings()
        try:
            spec = s.spec()
            cfg = self._config_fn()
            if spec.f_max_hz >= 0.5 * cfg.rate_hz:
                raise ConfigError("f_max_hz", f"must be below Nyquist {0.5 * cfg.rate_hz} Hz")
        except ConfigError as exc:
            self.status.content = _status_html(self.state, f"not started: {exc}")
            return False
        with self._lock:
            if self.state == RUNNING:
                self.status.content = _status_html(
                    RUNNING, "a run is already in progress", self.where_note)
                return False
            self.state = RUNNING
            self._abort.clear()
            self.result = None
            self.view = None
            self.curves = []
            self.progress = 0.0
            self.n_positions = spec.positions
            remote = s.where == WHERE_CONTROLLER and self.client is not None
            self.where_note = (
                f"on the controller, rig {self.client.opts.rig_name}"
                if remote and self.client is not None else OFFLINE_NOTE
            )
            self._thread = threading.Thread(
                target=self._run_remote if remote else self._run,
                args=(spec, cfg, s.pace), name="identify", daemon=True,
            )
        self.text = "starting"
        self.start_button.disabled = True
        self.abort_button.disabled = False
        self.use_button.disabled = True
        self.use_result.content = "<div class='dt-id-use' style='font-size:12px'></div>"
        self.result_html.content = format_result_html(None)
        self.progress_bar.value = 0.0
        self.progress_bar.animated = True
        self.status.content = _status_html(RUNNING, self.text, self.where_note)
        self._thread.start()
        return True

    def abort(self) -> bool:
        with self._lock:
            if self.state != RUNNING:
                self.status.content = _status_html(self.state, "nothing to abort")
                return False
            self._abort.set()
        self.status.content = _status_html(RUNNING, "aborting...", self.where_note)
        return True

    def use_as_nominal(self) -> bool:
        """Put the fitted nominal into the tuning candidate (never sent from here)."""
        with self._lock:
            view = self.view if self.state == DONE else None
        if view is None or view.nominal is None or not view.complete:
            self.use_result.content = (
                "<div class='dt-id-use' style='color:#d62728;font-size:12px'>No complete "
                "identification with a usable fit: nothing to use.</div>")
            return False
        if self.tuning is None:
            return False
        if self._add_measured is not None:
            for m in view.measured:
                self._add_measured(dataclasses.replace(m, name=f"identify {m.name}"))
        self.tuning.set_nominal(view.nominal)
        fit = view.fit
        wn = f" (f<sub>n</sub> {fit.natural_freq_hz:.3f} Hz, &zeta; {fit.zeta:.3f})" if fit else ""
        self.use_result.content = (
            "<div class='dt-id-use dt-id-used' style='font-size:12px;border:2px solid #1f77b4;"
            "padding:4px;border-radius:4px'>The tuning candidate now uses the fitted Mn Pn"
            f"{wn} and the measured responses. Check the verdict on the <b>Tune</b> tab; "
            "<b>Apply</b> there sends it (the controller's gate decides). Revert drops it."
            "</div>")
        return True

    # -- the worker ----------------------------------------------------------------------------

    def wait_done(self, timeout_s: float = 30.0) -> bool:
        t = self._thread
        if t is not None:
            t.join(timeout=timeout_s)
        return self.state != RUNNING

    def _run(self, spec: IdentifySpec, cfg: LoopConfig, pace: float) -> None:
        n = spec.positions
        if self._chart_n != n:
            self._make_charts(n)
        self._publish_charts(None)
        sim = self._rig_factory(cfg, spec.seed)
        rig = _PacedRig(sim, cfg.rate_hz, self._abort, pace)
        results: list[IdentifyResult] = []
        reason: str | None = None
        state = DONE
        final: IdentifyResult | None = None
        try:
            for k, c in enumerate(spec.centers_deg):
                one = spec.with_(positions=1, first_position_deg=c, span_deg=spec.span_deg / n)

                def progress(frac: float, text: str, k: int = k) -> None:
                    self._on_progress((k + min(frac, 0.99)) / n,
                                      text.replace("position 1/1", f"position {k + 1}/{n}"))

                try:
                    r = run_identification(one, cfg, lambda: rig, progress)
                except IdentifyAborted as exc:
                    # a limit: keep what was measured, the position is incomplete
                    results.append(exc.result)
                    reason, state = exc.reason, ABORTED
                    break
                results.append(r)
                self.curves.append(curve_of(r.positions[0]))
                self._publish_charts(None)
            if results:
                final = _combine(spec, cfg, results, state == DONE, reason)
        except UserAbort:
            reason, state = "aborted by the user", ABORTED
            if results:
                final = _combine(spec, cfg, results, False, reason)
        except Exception as exc:  # show it; the worker must not die silently
            reason, state = f"{type(exc).__name__}: {exc}", FAILED
        self._finish(state, final, reason, spec)

    def _run_remote(self, spec: IdentifySpec, cfg: LoopConfig, _pace: float) -> None:
        """Start the run on the controller, poll its status until it is over."""
        client = self.client
        assert client is not None
        n = spec.positions
        if self._chart_n != n:
            self._make_charts(n)
        self._publish_charts(None)
        try:
            prev = _query_identify(client).run_id
            body = proto.IdentifyStart(spec=proto.IdentifySpecMsg(
                mode=spec.mode, signal=spec.signal, f_min_hz=spec.f_min_hz,
                f_max_hz=spec.f_max_hz, points_per_decade=spec.points_per_decade,
                positions=spec.positions, amplitude_deg_s=spec.amplitude_deg_s,
            ))
            reply = client.command(body)
            if not reply.ok:
                self._show_end(FAILED, None, f"refused by the controller: {reply.message}", n)
                return
            sent_abort = False
            drawn: tuple[int, ...] = ()
            while True:
                if self._closing.is_set():
                    return  # the dashboard closes; the run goes on in the controller
                if self._abort.is_set() and not sent_abort:
                    r = client.command(proto.IdentifyAbort())
                    sent_abort = True
                    if not r.ok:
                        self.status.content = _status_html(
                            RUNNING, f"abort refused: {r.message}", self.where_note)
                st = _query_identify(client)
                if st.run_id > prev:
                    if st.state in ("done", "aborted"):
                        break
                    self._on_progress(st.progress, st.text or st.state)
                    drawn = self.show_partial(st, n, cfg.nominal, drawn)
                time.sleep(0.2)  # polling period of the status queryable
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            self._show_end(FAILED, None, f"controller: {exc}", n)
            return
        view = view_from_status(st, n, cfg.nominal)
        aborted = st.state == "aborted" or not view.complete
        reason = st.abort_reason or (st.text if aborted else None)
        self._show_end(ABORTED if aborted else DONE, view, reason, n)

    def show_partial(self, st: proto.IdentifyStatus, n: int, base: NominalModel,
                     drawn: tuple[int, ...] = ()) -> tuple[int, ...]:
        """Draw the partial responses of a running status (with their band) if they changed
        since `drawn` (points per position, as returned here the previous time)."""
        now = tuple(p.points_done for p in st.positions)
        if now == drawn or not st.positions:
            return drawn
        self.curves = list(view_from_status(st, n, base).curves)
        self._publish_charts(None)
        return now

    def _on_progress(self, fraction: float, text: str) -> None:
        now = time.monotonic()
        self.progress, self.text = fraction, text
        if now - self._last_publish < 0.1:
            return
        self._last_publish = now
        self.progress_bar.value = round(100.0 * min(max(fraction, 0.0), 1.0), 1)
        self.status.content = _status_html(
            RUNNING, f"{100 * fraction:.0f} % {text}", self.where_note)

    def _publish_charts(self, fit: FitView | None) -> None:
        fit_f = fit_g = None
        have = [c for c in self.curves if c is not None]
        if fit is not None and have:
            lo = min(float(c.freq_hz[0]) for c in have)
            hi = max(float(c.freq_hz[-1]) for c in have)
            fit_f = np.geomspace(lo, hi, 80)
            fit_g = fit.response(fit_f)
        data = charts.identify_data(self._chart_n, self.curves, fit_f, fit_g)
        for key, h in self.charts.items():
            h.data = data[key]
        self.chart_updates += 1

    def _finish(self, state: str, result: IdentifyResult | None, reason: str | None,
                spec: IdentifySpec) -> None:
        view = None if result is None else view_from_result(result, spec.positions)
        with self._lock:
            self.result = result
        self._show_end(state, view, reason, spec.positions)

    def _show_end(self, state: str, view: IdentifyView | None, reason: str | None,
                  n: int) -> None:
        if view is not None:
            # an aborted run may have partial positions that were never drawn
            self.curves = list(view.curves)
        self._publish_charts(None if view is None else view.fit)
        if state == DONE:
            text = "done"
            if view is not None and view.fit is not None:
                text += f": fit f_n {view.fit.natural_freq_hz:.3f} Hz"
        else:
            text = f"{reason or state}"
            if state == ABORTED:
                kept = 0 if view is None else view.positions_done
                text = f"INCOMPLETE, {text}: {kept} of {n} position(s) kept"
        self.result_html.content = format_result_html(view)
        if self.chart_note is not None:
            done = state == DONE
            self.chart_note.content = (
                f"<div class='dt-identify-charts dt-id-{state}' style='font-size:12px;"
                f"color:{'#555' if done else '#d62728'}'>"
                + ("Identification complete" if done else f"<b>INCOMPLETE</b> ({_esc(text)})")
                + f" &middot; {_esc(self.where_note)}</div>")
        self.progress_bar.animated = False
        if state == DONE:
            self.progress_bar.value = 100.0
        with self._lock:
            self.view = view
            self.state = state
            self.text = text
        self.status.content = _status_html(state, text, self.where_note)
        self.start_button.disabled = False
        self.abort_button.disabled = True
        self.use_button.disabled = not (
            state == DONE and view is not None and view.nominal is not None
        )


def _sim_rig(cfg: LoopConfig, seed: int) -> RigLike:
    from controller.sim.sim_rig import SimRig

    return SimRig(rate_hz=cfg.rate_hz, seed=seed)
