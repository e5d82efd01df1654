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

The spec's fields on the panel (`server.panels.identify_form`) are generated from the metadata
of `controller.ident.spec.IdentifySpec` (label, unit, range, help); the charts are
`server.panels.identify_charts`; what the panel shows of a run comes from `server.identify_view`.

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

import threading
import time
from collections.abc import Callable, Sequence

import viser

from controller import protocol as proto
from controller.client import ControllerClient, ControllerUnavailable
from controller.core.config import LoopConfig, NominalModel
from controller.core.errors import ConfigError
from controller.gate.knowledge import MeasuredResponse
from controller.ident.engine import RigLike
from controller.ident.offline import run_offline, sim_rig
from controller.ident.plan import check_rate, plan_text
from controller.ident.result import IdentifyResult
from controller.ident.spec import IdentifySpec
from server.escape import esc
from server.gui import on_press, set_value
from server.http_access import Refused
from server.identify_view import (
    IdentifyView,
    curve_of,
    format_result_html,
    view_from_result,
    view_from_status,
)
from server.panels.identify_charts import IdentifyCharts
from server.panels.identify_form import (
    DASHBOARD_FIELDS,
    OFFLINE_NOTE,
    WHERE_CONTROLLER,
    WHERE_OFFLINE,
    IdentifyForm,
    IdentifySettings,
)
from server.panels.identify_use import UseFit
from server.panels.nominal_tuning import NominalTuningPanel
from server.panels.widgets import confirm
from server.session import tell

__all__ = [
    "ABORTED",
    "DASHBOARD_FIELDS",
    "DONE",
    "FAILED",
    "IDLE",
    "RUNNING",
    "WHERE_CONTROLLER",
    "WHERE_OFFLINE",
    "IdentifyPanel",
    "IdentifySettings",
]

IDLE, RUNNING, DONE, ABORTED, FAILED = "idle", "running", "done", "aborted", "failed"

#: The browser that pressed a control (None: the API, a script or a test).
Browser = viser.ClientHandle | None
#: `act()` under a client's operator lease (`server.session.leased`).
Leased = Callable[[ControllerClient, Callable[[], proto.CommandReply]], proto.CommandReply]


# -- pure helpers -------------------------------------------------------------------------------


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


def end_text(state: str, view: IdentifyView | None, reason: str | None, n: int) -> str:
    """How a run of `n` positions ended, in a line: done (with the fit's f_n), or why not, and
    what an aborted one kept."""
    if state == DONE:
        fit = None if view is None else view.fit
        return "done" + (f": fit f_n {fit.natural_freq_hz:.3f} Hz" if fit is not None else "")
    text = f"{reason or state}"
    if state == ABORTED:
        kept = 0 if view is None else view.positions_done
        text = f"INCOMPLETE, {text}: {kept} of {n} position(s) kept"
    return text


def run_as_planned(spec: IdentifySpec, cfg: LoopConfig, latest: dict[str, float] | None) -> str:
    """The run as planned, in the progress text's words (the amplitude the plan allows, not
    the one asked; the band; the duration from where the load is now: `latest`'s position)."""
    start_deg = latest["pos_deg"] if latest is not None else spec.centers_deg[0]
    return plan_text(spec, cfg, start_deg)


def _as_is(client: ControllerClient | None) -> ControllerClient:
    """The client that acts for every browser (one identity)."""
    assert client is not None
    return client


# -- the panel ----------------------------------------------------------------------------------


class IdentifyPanel:
    """Settings, Start/Abort, progress and result (`build_controls`) and the response charts
    (`build_charts`); the run happens in one worker thread at a time."""

    def __init__(
        self,
        gui: viser.GuiApi,
        tuning_for: Callable[[Browser], NominalTuningPanel | None] | None,
        config_fn: Callable[[], LoopConfig] | None = None,
        rig_factory: Callable[[LoopConfig, int], RigLike] | None = None,
        add_measured: Callable[[Sequence[MeasuredResponse], Browser], None] | None = None,
        client: ControllerClient | None = None,
        client_for: Callable[[Browser, str], ControllerClient] | None = None,
        leased: Leased | None = None,
        authorize: Callable[[Browser, str], object] | None = None,
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
        self._client_for = client_for or (lambda _browser, _action: _as_is(client))
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
        self._last_publish = 0.0
        self.responses = IdentifyCharts(gui)
        """The measured responses' charts (built by `build_charts`)."""

    # -- building --------------------------------------------------------------------------

    def build_controls(self) -> None:
        gui = self.gui
        self.form = IdentifyForm(gui, with_controller=self.client is not None)
        self.start_button = gui.add_button("Start identification", color="green")
        self.abort_button = gui.add_button("Abort", color="red", disabled=True)
        self.progress_bar = gui.add_progress_bar(0.0)
        self.status = gui.add_html(_status_html(IDLE, self.text))
        self.result_html = gui.add_html(format_result_html(None))
        self.use = UseFit(gui, self._tuning_for, self._add_measured)
        self.start_button.on_click(lambda e: self.ask_start(e.client))
        on_press(self.abort_button, self.abort)
        on_press(self.use.button, self.use_as_nominal)

    def build_charts(self) -> None:
        self.responses.build(self.n_positions)

    def stop(self) -> None:
        """Dashboard shutdown: an offline run stops; a run on the controller goes on there."""
        self._closing.set()
        self._abort.set()
        t = self._thread
        if t is not None:
            t.join(timeout=5.0)

    def settings(self) -> IdentifySettings:
        """What the controls ask for (`IdentifyForm.settings`: ConfigError naming a field)."""
        return self.form.settings()

    # -- events (short) ----------------------------------------------------------------------

    def ask_start(self, browser: Browser) -> None:
        """On the controller the rig moves: asked first, in the browser that pressed Start."""
        try:
            s = self.settings()
        except ConfigError as exc:
            self._tell(browser, f"not started: {exc}")
            return
        if s.where != WHERE_CONTROLLER or self.client is None:
            self.start(s, browser)
            return
        try:
            what = run_as_planned(s.spec(), self._config_fn(), self.client.ring.latest())
        except ConfigError as exc:
            self._tell(browser, f"not started: {exc}")
            return
        confirm(self.gui, browser, "Start the identification?",
                f"<b>The rig moves</b> (rig {esc(self.client.opts.rig_name)}): {esc(what)}; "
                "within the position window and the duration limit; E-STOP aborts.",
                "Start identification", lambda who: self.start(s, who), ok_color="green")

    def start(self, settings: IdentifySettings | None = None, browser: Browser = None) -> bool:
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
            self.responses.curves = []
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
        self.use.clear()
        self.result_html.content = format_result_html(None)
        set_value(self.progress_bar, 0.0)
        self.progress_bar.animated = True
        self.status.content = _status_html(RUNNING, self.text, self.where_note)
        self.responses.start(spec.positions)  # the last run's curves off before this one runs
        self._thread.start()
        return True

    def _tell(self, browser: Browser, text: str) -> None:
        """The outcome of one browser's press, to that browser only (the status box is every
        browser's: the run's state); without a browser (the API), in the status box."""
        if browser is None:
            self.status.content = _status_html(self.state, text, self.where_note)
            return
        tell(browser, "Identification", text, "orange")

    def abort(self, browser: Browser = None) -> bool:
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

    def use_as_nominal(self, browser: Browser = None) -> bool:
        """Put the fitted nominal into the tuning candidate (never sent from here)."""
        with self._lock:
            view = self.view if self.state == DONE else None
        return self.use.put(view, browser)

    # -- the worker ----------------------------------------------------------------------------

    def wait_done(self, timeout_s: float = 30.0) -> bool:
        t = self._thread
        if t is not None:
            t.join(timeout=timeout_s)
        return self.state != RUNNING

    def _run(self, spec: IdentifySpec, cfg: LoopConfig, pace: float) -> None:
        def on_position(r: IdentifyResult) -> None:
            self.responses.curves.append(curve_of(r.positions[0]))
            self.responses.publish(None)

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
        self.responses.curves = list(view_from_status(st, n, base).curves)
        self.responses.publish(None)
        return now

    def _on_progress(self, fraction: float, text: str) -> None:
        now = time.monotonic()
        self.progress, self.text = fraction, text
        if now - self._last_publish < 0.1:
            return
        self._last_publish = now
        set_value(self.progress_bar, round(100.0 * min(max(fraction, 0.0), 1.0), 1))
        self.status.content = _status_html(
            RUNNING, f"{100 * fraction:.0f} % {text}", self.where_note)

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
            self.responses.curves = list(view.curves)
        self.responses.publish(None if view is None else view.fit)
        text = end_text(state, view, reason, n)
        self.result_html.content = format_result_html(view)
        self.responses.show_end(state, text, self.where_note)
        self.progress_bar.animated = False
        if state == DONE:
            set_value(self.progress_bar, 100.0)
        with self._lock:
            self.view = view
            self.state = state
            self.text = text
        self.status.content = _status_html(state, text, self.where_note)
        self.start_button.disabled = False
        self.abort_button.disabled = True
        self.use.button.disabled = not (
            state == DONE and view is not None and view.nominal is not None
        )

