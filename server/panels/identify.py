"""The Identify panel: measure the frequency response, fit Mn Pn, recommend the Q cut-off.

Two places to run, chosen on the panel (and always named in the status line):

* **on the controller** (default when connected): the IdentifyStart command carries the spec,
  the controller runs the excitation inside its loop; a worker thread polls the
  ``dobtune/<rig>/identify`` queryable (IdentifyStatus: progress, then the results) and Abort
  sends IdentifyAbort (the controller holds the position and keeps the partial data). While
  the run goes on, the status carries the frequencies finished so far with their per-point
  standard deviation: the curves build up on the charts, with their band, as they arrive.
* **offline on the simulated rig**, in a worker thread of the dashboard
  (`controller.ident.offline.run_offline`: position by position on a `SimRig`, paced and
  stoppable).

The spec's fields on the panel (`DASHBOARD_FIELDS`) are generated from the metadata of
`controller.ident.spec.IdentifySpec` (label, unit, range, help); what the panel shows of a run
comes from `server.identify_view`.

Offline, each position's response is drawn as soon as it is measured; an optional pace ("x real
time") slows the simulation down so a run can be watched and aborted. Abort stops the simulation
within 10 simulated ms; the positions measured so far stay on the charts, marked incomplete (the
interrupted position is dropped).

"Use as nominal model" never talks to the controller: it puts the fitted nominal (and the
measured responses, as the gate's plant knowledge) into the tuning candidate, which is then
evaluated like any other change and sent only by the Tune tab's Apply.

GUI callbacks only read widgets, check the state under a lock and start/signal the worker;
viser's ``disabled`` flags are cosmetic, every button re-checks the state here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from controller import protocol as proto
from controller.client import ControllerClient, ControllerUnavailable
from controller.core.config import LoopConfig, NominalModel
from controller.core.errors import ConfigError
from controller.gate.knowledge import MeasuredResponse
from controller.ident.engine import RigLike
from controller.ident.offline import run_offline, sim_rig
from controller.ident.plan import check_rate
from controller.ident.result import IdentifyResult
from controller.ident.spec import IDENTIFY_FIELDS, IdentifySpec
from server import charts
from server.escape import esc
from server.http_access import Refused
from server.identify_view import (
    FitView,
    IdentifyView,
    curve_of,
    format_result_html,
    view_from_result,
    view_from_status,
)
from server.panels.nominal_tuning import NominalTuningPanel
from server.panels.widgets import add_chart, confirm, parse_number
from server.session import tell

__all__ = [
    "ABORTED",
    "DASHBOARD_FIELDS",
    "DONE",
    "FAILED",
    "IDLE",
    "RUNNING",
    "IdentifyPanel",
    "IdentifySettings",
]

IDLE, RUNNING, DONE, ABORTED, FAILED = "idle", "running", "done", "aborted", "failed"

OFFLINE_NOTE = "offline on the simulated rig"
WHERE_CONTROLLER, WHERE_OFFLINE = "controller", "offline simulation"


# -- pure helpers -------------------------------------------------------------------------------


#: The IdentifySpec fields on the panel (those with a `Param.label`), in order.
DASHBOARD_FIELDS = tuple(f for f in IDENTIFY_FIELDS if f.param.label)


@dataclasses.dataclass(frozen=True)
class IdentifySettings:
    """What the panel's controls ask for."""

    values: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    """IdentifySpec fields by name (`DASHBOARD_FIELDS`; a missing one takes its default)."""
    pace: float = 0.0
    """Simulated seconds per wall second (0: as fast as possible); offline only."""
    where: str = WHERE_OFFLINE
    """WHERE_CONTROLLER or WHERE_OFFLINE."""

    def spec(self) -> IdentifySpec:
        """The validated spec; raises ConfigError naming the field."""
        try:
            return IdentifySpec(**self.values)
        except TypeError as exc:  # not a spec field
            raise ConfigError("settings", str(exc)) from exc


PACE_LABEL = "Pace (x real time, 0 = fastest)"
PACE_MAX = 1000.0


def _field_errors_html(errors: list[str] | tuple[str, ...]) -> str:
    if not errors:
        return "<div class='dt-identify-field-error'></div>"
    lines = "".join(f"<div>{esc(e)}</div>" for e in errors)
    return ("<div class='dt-identify-field-error dt-identify-field-invalid' "
            f"style='font-size:12px;color:#d62728'><b>Not a value:</b>{lines}"
            "Start refuses until each is one.</div>")


def _query_identify(client: ControllerClient) -> proto.IdentifyStatus:
    """The controller's identification status (raises ControllerUnavailable, ProtocolError)."""
    return client.identify_status()


def _status_html(state: str, text: str, where: str = OFFLINE_NOTE) -> str:
    color = {RUNNING: "#1f77b4", DONE: "#2e7d32", ABORTED: "#d62728", FAILED: "#d62728"}.get(
        state, "#555"
    )
    return (
        f"<div class='dt-identify-status dt-id-{state}' style='font-size:12px;color:{color}'>"
        f"<b>{state}</b> &middot; {esc(text)} <span style='color:#888'>({esc(where)})"
        "</span></div>"
    )


# -- the panel ----------------------------------------------------------------------------------


class IdentifyPanel:
    """Settings, Start/Abort, progress and result (`build_controls`) and the response charts
    (`build_charts`); the run happens in one worker thread at a time."""

    def __init__(
        self,
        gui: Any,
        tuning_for: Callable[[Any], NominalTuningPanel | None] | None,
        config_fn: Callable[[], LoopConfig] | None = None,
        rig_factory: Callable[[LoopConfig, int], RigLike] | None = None,
        add_measured: Callable[[MeasuredResponse, Any], None] | None = None,
        client: ControllerClient | None = None,
        client_for: Callable[[Any, str], ControllerClient] | None = None,
        leased: Callable[[ControllerClient, Callable[[], Any]], Any] | None = None,
        authorize: Callable[[Any, str], object] | None = None,
    ) -> None:
        """`tuning_for(browser)`: the candidate panel of that browser ("Use as nominal model"
        puts the fit there); `config_fn()`: the active configuration (the offline run's loop).
        `client`: the controller (None: offline only); `client_for(browser, action)`: the
        client that acts for a browser (raises `Refused`); `leased(client, act)`: `act()`
        under that client's operator lease. Without them, `client` acts as it is.
        `authorize(browser, action)`: raises `Refused` (told to that browser) unless the user
        at `browser` may start or abort a run (operators: an offline run is one at a time,
        so a viewer's would block the operator's); None: anyone may (one identity)."""
        self._authorize = authorize
        self.gui = gui
        self._tuning_for = tuning_for
        self._config_fn = config_fn or LoopConfig
        self._rig_factory = rig_factory or sim_rig
        self._add_measured = add_measured
        self.client = client
        self._client_for = client_for or self._as_is
        self._leased = leased or (lambda _client, act: act())
        self._run_client: ControllerClient | None = None
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

    def _as_is(self, _browser: Any, _action: str) -> ControllerClient:
        assert self.client is not None
        return self.client

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
        # the spec's fields, generated from their metadata (label, unit, range, help)
        self.fields: dict[str, Any] = {}
        for f in DASHBOARD_FIELDS:
            if f.param.choices:
                self.fields[f.name] = gui.add_dropdown(
                    f.title, f.param.choices, initial_value=f.default, hint=f.param.help)
            else:
                # A text field read here (a number box clamped, and dropped the "e" of
                # "1e9": 19 deg/s was then offered); a wrong value is refused naming the field.
                self.fields[f.name] = gui.add_text(f.title, f"{f.default:g}", hint=f.param.help)
        self.pace = gui.add_text(PACE_LABEL, f"{d.pace:g}", hint="offline only")
        self.field_errors = gui.add_html(_field_errors_html(()))
        for h in (*self.fields.values(), self.pace):
            h.on_update(lambda _e: self._show_field_errors())
        self.start_button = gui.add_button("Start identification", color="green")
        self.abort_button = gui.add_button("Abort", color="red", disabled=True)
        self.progress_bar = gui.add_progress_bar(0.0)
        self.status = gui.add_html(_status_html(IDLE, self.text))
        self.result_html = gui.add_html(format_result_html(None))
        self.use_button = gui.add_button("Use as nominal model", color="blue", disabled=True,
                                         hint="put the fitted Mn Pn into the tuning candidate "
                                              "(checked by the gate; Apply sends it)")
        self.use_result = gui.add_html("<div class='dt-id-use' style='font-size:12px'></div>")
        self.start_button.on_click(lambda e: self.ask_start(e.client))
        self.abort_button.on_click(lambda e: self.abort(e.client))
        self.use_button.on_click(lambda e: self.use_as_nominal(e.client))

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
                self.charts[spec.key] = add_chart(self.gui, spec, data[spec.key])
        self._chart_n = n

    def stop(self) -> None:
        """Dashboard shutdown: an offline run stops; a run on the controller goes on there."""
        self._closing.set()
        self._abort.set()
        t = self._thread
        if t is not None:
            t.join(timeout=5.0)

    # -- reading the controls ----------------------------------------------------------------

    def _field_values(self) -> tuple[dict[str, Any], float, list[str]]:
        """The fields' values, the pace, and why a field's text is none of its values."""
        values: dict[str, Any] = {}
        errors: list[str] = []
        for f in DASHBOARD_FIELDS:
            v = self.fields[f.name].value
            if f.param.choices:
                values[f.name] = f.type(v)
                continue
            lo, hi, _step = f.limits
            num, why = parse_number(str(v), f.title, lo, hi, integer=f.type is int)
            if num is None:
                errors.append(why)
            else:
                values[f.name] = round(num) if f.type is int else num
        pace, why = parse_number(str(self.pace.value), PACE_LABEL, 0.0, PACE_MAX)
        if pace is None:
            errors.append(why)
        return values, pace or 0.0, errors

    def _show_field_errors(self) -> None:
        self.field_errors.content = _field_errors_html(self._field_values()[2])

    def settings(self) -> IdentifySettings:
        """What the controls ask for; raises ConfigError naming a field whose text is none of
        its values."""
        values, pace, errors = self._field_values()
        if errors:
            raise ConfigError("settings", "; ".join(errors))
        return IdentifySettings(
            values=values,
            pace=pace,
            where=str(self.where.value) if self.client is not None else WHERE_OFFLINE,
        )

    # -- events (short) ----------------------------------------------------------------------

    def ask_start(self, browser: Any) -> None:
        """On the controller the rig moves: asked first, in the browser that pressed Start."""
        try:
            s = self.settings()
        except ConfigError as exc:
            self._tell(browser, f"not started: {exc}")
            return
        if s.where != WHERE_CONTROLLER or self.client is None:
            self.start(s, browser)
            return
        v = s.values
        confirm(self.gui, browser, "Start the identification?",
                f"<b>The rig moves</b> (rig {esc(self.client.opts.rig_name)}): "
                f"{esc(str(v.get('signal', '')))} excitation of "
                f"{esc(str(v.get('amplitude_deg_s', '')))} deg/s at "
                f"{esc(str(v.get('positions', '')))} position(s), within the position window "
                "and the duration limit; E-STOP aborts.",
                "Start identification", lambda who: self.start(s, who), ok_color="green")

    def start(self, settings: IdentifySettings | None = None, browser: Any = None) -> bool:
        """Start a run unless one is running; False (and a message) if not started."""
        try:
            s = settings or self.settings()
            if self._authorize is not None:
                self._authorize(browser, "identification")
            spec = s.spec()
            cfg = self._config_fn()
            check_rate(spec, cfg.rate_hz)
            acting = (self._client_for(browser, "identification")
                      if s.where == WHERE_CONTROLLER and self.client is not None else None)
        except Refused:
            return False  # told to that browser alone (the dashboard's refusal notification)
        except (ConfigError, ControllerUnavailable) as exc:
            self._tell(browser, f"not started: {exc}")
            return False
        with self._lock:
            if self.state == RUNNING:
                self._tell(browser, "a run is already in progress")
                return False
            self.state = RUNNING
            self._abort.clear()
            self.result = None
            self.view = None
            self.curves = []
            self.progress = 0.0
            self.n_positions = spec.positions
            remote = acting is not None
            self._run_client = acting
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

    def _tell(self, browser: Any, text: str) -> None:
        """The outcome of one browser's press, to that browser only (the status box is every
        browser's: the run's state); without a browser (the API), in the status box."""
        if browser is None:
            self.status.content = _status_html(self.state, text, self.where_note)
            return
        tell(browser, "Identification", text, "orange")

    def abort(self, browser: Any = None) -> bool:
        if self._authorize is not None:
            try:
                self._authorize(browser, "abort the identification")
            except Refused:
                return False  # told to that browser alone
        if self._run_client is not None and self.state == RUNNING:
            try:
                self._client_for(browser, "abort")
            except Refused:
                return False  # told to that browser alone
            except ControllerUnavailable as exc:
                self._tell(browser, f"not aborted: {exc}")
                return False
        with self._lock:
            if self.state != RUNNING:
                self._tell(browser, "nothing to abort")
                return False
            self._abort.set()
        self.status.content = _status_html(RUNNING, "aborting...", self.where_note)
        return True

    def use_as_nominal(self, browser: Any = None) -> bool:
        """Put the fitted nominal into the tuning candidate (never sent from here)."""
        with self._lock:
            view = self.view if self.state == DONE else None
        if view is None or view.nominal is None or not view.complete:
            self.use_result.content = (
                "<div class='dt-id-use' style='color:#d62728;font-size:12px'>No complete "
                "identification with a usable fit: nothing to use.</div>")
            return False
        tuning = self._tuning_for(browser) if self._tuning_for is not None else None
        if tuning is None:
            self.use_result.content = (
                "<div class='dt-id-use' style='color:#d62728;font-size:12px'>This browser has "
                "no tuning candidate to put the fit into.</div>")
            return False
        if self._add_measured is not None:
            for m in view.measured:
                self._add_measured(dataclasses.replace(m, name=f"identify {m.name}"), browser)
        tuning.set_nominal(view.nominal)
        fit = view.fit
        wn = f" (f<sub>n</sub> {fit.natural_freq_hz:.3f} Hz, &zeta; {fit.zeta:.3f})" if fit else ""
        self.use_result.content = (
            "<div class='dt-id-use dt-id-used' style='font-size:12px;border:2px solid #1f77b4;"
            "padding:4px;border-radius:4px'>The tuning candidate of the browser that pressed "
            "<i>Use as nominal model</i> now uses the fitted Mn Pn"
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
        if self._chart_n != spec.positions:
            self._make_charts(spec.positions)
        self._publish_charts(None)

        def on_position(r: IdentifyResult) -> None:
            self.curves.append(curve_of(r.positions[0]))
            self._publish_charts(None)

        try:
            run = run_offline(spec, cfg, self._abort, pace, self._rig_factory,
                              self._on_progress, on_position)
        except Exception as exc:  # show it; the worker must not die silently
            self._finish(FAILED, None, f"{type(exc).__name__}: {exc}", spec)
            return
        self._finish(DONE if run.complete else ABORTED, run.result, run.reason, spec)

    def _run_remote(self, spec: IdentifySpec, cfg: LoopConfig, _pace: float) -> None:
        """Start the run on the controller, poll its status until it is over."""
        client = self._run_client
        assert client is not None
        n = spec.positions
        if self._chart_n != n:
            self._make_charts(n)
        self._publish_charts(None)
        try:
            prev = _query_identify(client).run_id
            reply = self._leased(client, lambda: client.command(proto.IdentifyStart(spec=spec)))
            if not reply.ok:
                self._show_end(FAILED, None, f"refused by the controller: {reply.message}", n)
                return
            sent_abort = False
            drawn: tuple[int, ...] = ()
            while True:
                if self._closing.is_set():
                    return  # the dashboard closes; the run goes on in the controller
                if self._abort.is_set() and not sent_abort:
                    r = self._leased(client, lambda: client.command(proto.IdentifyAbort()))
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
                + ("Identification complete" if done else f"<b>INCOMPLETE</b> ({esc(text)})")
                + f" &middot; {esc(self.where_note)}</div>")
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

