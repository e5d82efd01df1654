"""Live panel: rolling traces, metrics, loop health, connection banner, trajectory, e-stop.

The GUI is built once; one thread (`server.workers.Periodic`) refreshes the charts at
`rate_hz` from the client's ring buffer (their data to the browsers `audience` names: those
that show them) and the slower texts at a few Hz, assigning only changed properties.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import viser

from controller import protocol as proto
from controller.client import ControllerClient, StateRing
from controller.core.trajectory import TRAJECTORY_KINDS, Trajectory, default_trajectory
from controller.core.verdict import kind_of
from server import charts
from server.alarms import AlarmBoard, alarms_html
from server.escape import esc
from server.gui import Browser, on_press
from server.health import HealthJudgement, TimingHistory, health_html, judge_timing
from server.http_access import Refused
from server.panels.widgets import add_chart, confirm, send_data, set_html
from server.workers import Periodic, run_logged

__all__ = ["LivePanel", "LiveStats", "banner_html", "window_metrics"]

log = logging.getLogger(__name__)

#: How often the live texts (metrics, loop health) are refreshed.
TEXT_RATE_HZ = 2.0


def window_metrics(error_deg: np.ndarray) -> tuple[float, float]:
    """(peak |error|, RMSE) in deg; NaN for an empty window."""
    if len(error_deg) == 0:
        return math.nan, math.nan
    return float(np.max(np.abs(error_deg))), float(np.sqrt(np.mean(error_deg**2)))


def metrics_window(chart_window_s: float, period_s: float | None) -> tuple[float, str]:
    """The live metrics' window (s) and its name: for a periodic trajectory a whole number of
    its periods (as many as fit the charts' window, at least one), else the charts' window. A
    10 s window over the sine's 12.6 s period cut the sine in a different place each second:
    the RMSE of a steady loop wandered 0.0272-0.0315 deg."""
    if period_s is None or not (math.isfinite(period_s) and period_s > 0):
        return chart_window_s, f"last {chart_window_s:.0f} s"
    n = max(1, int(chart_window_s / period_s + 1e-9))
    return n * period_s, f"last {n} period{'s' if n > 1 else ''} ({n * period_s:.1f} s)"


def banner_html(client: ControllerClient) -> str:
    """The connection / mode banner: red when the controller is gone or e-stopped."""
    st = client.status
    mismatch = client.counters.version_mismatch
    if st is None and mismatch:
        return _banner(
            "#b71c1c",
            f"CONTROLLER OF ANOTHER VERSION &mdash; rig '{esc(client.opts.rig_name)}' on "
            f"{esc(', '.join(client.opts.connect))} sends messages this dashboard cannot "
            f"read ({esc(mismatch)}). Nothing can be applied.",
            "dt-banner dt-gone dt-version",
        )
    if st is None:
        return _banner(
            "#616161",
            f"CONTROLLER STARTING &mdash; waiting for rig '{esc(client.opts.rig_name)}' on "
            f"{esc(', '.join(client.opts.connect))}"
            + (f" as user {esc(client.opts.user)}" if client.opts.user else "")
            + ": no status yet (it may still be starting: seconds, longer on a busy machine; "
            "or it is not reachable). The dashboard keeps waiting and connects when it "
            "answers; nothing can be applied until then.",
            "dt-banner dt-starting",
        )
    if not client.connected:
        return _banner(
            "#b71c1c",
            f"CONTROLLER NOT REACHABLE (no status for {client.status_age_s:.1f} s) &mdash; "
            f"rig '{esc(client.opts.rig_name)}' on "
            f"{esc(', '.join(client.opts.connect))}"
            + (f" as user {esc(client.opts.user)} (wrong credentials look the same)"
               if client.opts.user else "")
            + ". Traces are frozen; nothing can be applied.",
            "dt-banner dt-gone",
        )
    if st.mode == "estop" or client.ring.mode == "estop":  # the stream says it first
        return _banner("#d62728", "E-STOP ACTIVE: speed command 0, drive disabled. "
                       "Reset fault, then Start.", "dt-banner dt-estop")
    if st.mode == "fault" or st.faults:
        faults = "; ".join(st.faults) or "fault"
        return _banner("#e67e22", f"FAULT: {esc(faults)}. Reset fault, then Start.",
                       "dt-banner dt-fault")
    auth = f"authenticated as {esc(client.opts.user)}" if st.auth else "no authentication"
    lease = f", lease: {esc(st.operator)}" if st.operator else ""
    # (What the watchdog did is an alarm of its own, server/alarms.py: never in green.)
    return _banner(
        "#2e7d32",
        f"Connected: rig <b>{esc(st.rig)}</b> ({esc(st.plant)}), {esc(st.mode)}, config "
        f"v{st.config_version} ({esc(_judged(st))}); {auth}{lease}",
        "dt-banner dt-ok",
    )


def _judged(st: proto.Status) -> str:
    """The running configuration's verdict and the knowledge it was judged on."""
    v, now = st.verdict, st.knowledge or "-"
    if v is None or v.knowledge_version == st.knowledge_version:
        return f"{kind_of(v)} on knowledge {now}"
    return f"{v.verdict} on knowledge v{v.knowledge_version}; the knowledge is now {now}"


def _banner(bg: str, html: str, cls: str) -> str:
    return (f"<div class='{cls}' style='background:{bg};color:white;padding:6px 8px;"
            f"border-radius:4px;font-size:13px;font-weight:600'>{html}</div>")


@dataclass
class LiveStats:
    """Measured by the updater, for benchmarks and the health box."""

    frames: int = 0
    chart_pushes: int = 0
    last_frame_s: float = 0.0
    started_at: float = 0.0

    def push_rate_hz(self) -> float:
        dt = time.monotonic() - self.started_at
        return self.chart_pushes / dt if dt > 0 else 0.0


class LivePanel:
    """Live controls and charts; `tick()` is called by the updater thread."""

    def __init__(
        self,
        gui: viser.GuiApi,
        client: ControllerClient,
        send_command: Callable[[proto.CommandBody, Browser], None],
        on_status: Callable[[proto.Status], None] | None = None,
        on_frame: Callable[[dict[str, float] | None], None] | None = None,
        rate_hz: float = 25.0,
        max_points: int = 1000,
        audience: Callable[[], list[viser.ClientHandle]] | None = None,
        authorize: Callable[[Browser, str], object] | None = None,
        loop: asyncio.AbstractEventLoop | None = None,
    ) -> None:
        """`authorize(browser, action)`: raises `Refused` (told to that browser) unless the
        user at `browser` may change the rig (operators): acknowledging the alarms clears
        them for every browser. None: anyone may (one identity).

        `loop`: viser's event loop (`ViserServer.get_event_loop()`): the refresh's charts and
        texts are assigned on it (viser wakes its senders with an `asyncio.Event`, which is not
        thread-safe: set from this refresh's thread it raised "deque mutated during iteration"
        now and then, and that refresh was lost). None: in the refresh's own thread."""
        self._loop = loop
        self.gui = gui
        self._authorize = authorize
        self.client = client
        self._send = send_command
        self._on_status = on_status
        self._on_frame = on_frame
        self.rate_hz = rate_hz
        self.max_points = max_points
        self._audience = audience
        """The browsers the charts' data goes to (those that show them); None: every one."""
        self.stats = LiveStats()
        self._charts: dict[str, Any] = {}
        self._last_total = -1
        self._last_window = -1.0
        self._last_status_seen: proto.Status | None = None
        self._banner_sent = ""
        self._controller_traj_kind = ""
        self.trajectory: Any = None
        self.alarm_board = AlarmBoard()
        self.timing_history = TimingHistory()
        self.timing_judgement: HealthJudgement | None = None
        """The latest judgement of the loop's timing (None: no status yet)."""
        self._alarm_lock = threading.Lock()
        self._drift_raw: list[bytes] = []
        """Drift alarms received, not yet on the board (appended by a Zenoh thread)."""
        # The texts (metrics, loop health, alarms) twice a second: each change of an HTML box is
        # a message and a re-render in every page (the banner goes at every refresh).
        self._slow_every = max(1, int(rate_hz / TEXT_RATE_HZ))
        self._updater = Periodic(self._refresh, 1.0 / rate_hz, name="live-updater")

    # -- building --------------------------------------------------------------------------

    def build_banner(self) -> None:
        """The connection banner, and under it the alarms not yet acknowledged (a rollback
        amber, a fault or an e-stop red, each with its reason and time) and their
        Acknowledge button."""
        self.banner = self.gui.add_html(banner_html(self.client))
        self.alarms = self.gui.add_html(alarms_html(self.alarm_board))
        self.ack_button = self.gui.add_button(
            "Acknowledge alarms", color="yellow", visible=False,
            hint="the alarms above are seen: clear them (History keeps every change)")
        on_press(self.ack_button, self.acknowledge_alarms)
        # The watch's drift alarms join the board (decoded and shown at the next slow tick:
        # the Zenoh callback only keeps the bytes).
        self._drift_sub = self.client.session.declare_subscriber(
            proto.key_drift_alarm(self.client.opts.rig_name),
            lambda sample: self._drift_raw.append(sample.payload.to_bytes()))

    def acknowledge_alarms(self, browser: Browser = None) -> bool:
        """Clear the alarms for every browser: an operator's press (a viewer's is refused,
        told to that browser: the alarms stay for everyone). False: refused."""
        if self._authorize is not None:
            try:
                self._authorize(browser, "Acknowledge alarms")
            except Refused:
                return False
        with self._alarm_lock:
            self.alarm_board.acknowledge()
            self._show_alarms()
        return True

    def observe_alarms(self, st: proto.Status) -> None:
        """Note the alarms a status raises (each status once, by `tick`) and show them."""
        with self._alarm_lock:
            if self.alarm_board.observe(st):
                self._show_alarms()

    def observe_drift_alarms(self) -> None:
        """The drift alarms received since the last call onto the board (one that does not
        decode is logged, not shown as an alarm)."""
        while self._drift_raw:
            raw = self._drift_raw.pop(0)
            try:
                alarm = proto.decode(raw, proto.DriftAlarm)
            except proto.ProtocolError as exc:
                log.warning("a drift alarm not read: %s", exc)
                continue
            with self._alarm_lock:
                if self.alarm_board.observe_drift(alarm):
                    self._show_alarms()

    def _show_alarms(self) -> None:
        set_html(self.alarms, alarms_html(self.alarm_board))
        self.ack_button.visible = bool(self.alarm_board.alarms)

    def build_estop(self) -> None:
        self.estop_button = self.gui.add_button(
            "E-STOP", color="red", icon=None, hint="speed command 0 and drive disabled, at once"
        )
        self.estop_button.on_click(lambda e: self._send(proto.EStop(), e.client))

    def build_controls(self) -> None:
        gui = self.gui
        self.window_s = gui.add_slider("Window (s)", min=2.0, max=60.0, step=1.0,
                                       initial_value=charts.LIVE_WINDOW_S)
        self.trajectory = gui.add_dropdown("Trajectory", TRAJECTORY_KINDS, initial_value="sine",
                                           hint="5 sin(0.5 t) deg, 5 deg step, 1 deg/s ramp, "
                                                "hold at 40 deg")
        self.set_traj = gui.add_button("Set trajectory")
        self.run_buttons = gui.add_button_group("Run", ("Start", "Stop", "Reset fault"))
        self.set_traj.on_click(lambda e: self._confirm_trajectory(e.client))
        self.run_buttons.on_click(self._on_run)
        self.command_result = gui.add_html("<div class='dt-cmd'></div>")
        self.metrics = gui.add_html("<div class='dt-metrics'>metrics: waiting for data</div>")
        self.health = gui.add_html("<div class='dt-health'>loop health: waiting</div>")

    def _on_run(self, event: viser.GuiEvent[viser.GuiButtonGroupHandle]) -> None:
        v = event.target.value
        if v == "Start":  # the axis moves: asked first, in the browser that pressed it
            # The trajectory Start runs (while stopped the loop follows a hold).
            run = _run_trajectory(self.client.status)
            traj = f"<b class='dt-start-traj'>{esc(run.kind)}</b>" if run else "the set trajectory"
            confirm(self.gui, event.client, "Start the loop?",
                    f"<b>The axis moves</b>: from its present position onto {traj} (speed and "
                    "acceleration bounded).", "Start", lambda who: self._send(proto.Start(), who))
            return
        # A reset acknowledges the latest e-stop the dashboard shows: the controller refuses
        # it when a newer one exists (pressed meanwhile, in another session).
        st = self.client.status
        body: proto.CommandBody = proto.Stop() if v == "Stop" else proto.ResetFault(
            estop_seq=None if st is None else st.estop_seq
        )
        self._send(body, event.client)

    def _confirm_trajectory(self, browser: Browser) -> None:
        kind = str(self.trajectory.value)
        body = proto.SetTrajectory(trajectory=default_trajectory(kind))
        st = self.client.status
        if st is None or st.mode != "running":
            self._send(body, browser)  # nothing moves until Start (which asks)
            return
        confirm(self.gui, browser, "Change the trajectory?",
                f"<b>The axis moves</b>: the running loop follows {esc(kind)} from now.",
                "Set trajectory", lambda who: self._send(body, who))

    def build_charts(self) -> None:
        for spec in charts.LIVE_CHARTS:
            self._charts[spec.key] = add_chart(
                self.gui, spec, spec.placeholder(charts.LIVE_EMPTY_T), aspect=2.5,
                cursor={"show": True, "drag": {"x": False, "y": False}},
            )

    def show_in(self, browser: viser.ClientHandle) -> None:
        """The charts' data cut now to `browser` (its page shows them from now on)."""
        data = _window_data(self.client.ring, float(self.window_s.value), self.max_points)[1]
        for key, handle in self._charts.items():
            send_data(handle, data[key], [browser])

    # -- running -----------------------------------------------------------------------------

    def start(self) -> None:
        self.stats.started_at = time.monotonic()
        self._updater.start()

    def stop(self) -> None:
        self._updater.stop()

    def _refresh(self, k: int) -> None:
        t0 = time.perf_counter()
        try:
            self.tick(slow=(k % self._slow_every == 0))
        finally:
            self.stats.last_frame_s = time.perf_counter() - t0

    def tick(self, slow: bool = True) -> None:
        """One refresh: charts when new samples arrived, texts when `slow`."""
        self.stats.frames += 1
        ring = self.client.ring
        window = float(self.window_s.value)
        total = ring.total
        cols: dict[str, np.ndarray] | None = None
        if total != self._last_total or window != self._last_window:
            scales = None
            if window != self._last_window:  # the time axis spans the window
                scales = charts.live_scales(window)
                self._last_window = window
            if self._audience is not None and not self._audience():
                # None shows them: none cut for nobody (`show_in` cuts them for a page).
                if scales is not None:
                    in_loop(self._loop, self._show_charts, {}, scales)
            else:
                self._last_total = total
                cols, data = _window_data(ring, window, self.max_points)
                in_loop(self._loop, self._show_charts, data, scales)
                self.stats.chart_pushes += 1
            if self._on_frame is not None:
                self._on_frame(ring.latest())
        banner = banner_html(self.client)
        if not slow:
            # The banner at every refresh (an E-STOP shows at once), the rest a few times a
            # second.
            if banner != self._banner_sent:
                self._banner_sent = banner
                in_loop(self._loop, set_html, self.banner, banner)
            return
        self._banner_sent = banner
        self.observe_drift_alarms()
        st = self.client.status
        if st is not None and st is not self._last_status_seen:
            self._last_status_seen = st
            self.observe_alarms(st)
            run = _run_trajectory(st)
            kind = run.kind if run is not None else ""
            if kind != self._controller_traj_kind and kind in TRAJECTORY_KINDS:
                # The drop-down follows the controller's trajectory when that changes (a
                # selection not yet sent stays until then).
                self._controller_traj_kind = kind
                if self.trajectory is not None:
                    self.trajectory.value = kind
            if self._on_status is not None:
                self._on_status(st)
        if cols is None:
            cols, _ = ring.window(window)
        in_loop(self._loop, self._show_texts, banner, self._metrics_html(cols, window, st),
                self._health_html(st))

    def _show_charts(self, data: dict[str, tuple[np.ndarray, ...]],
                     scales: dict[str, charts.ChartDict] | None) -> None:
        """The charts' new data (of those in `data`) and time axis (when the window changed)
        to the browsers that show them (on viser's loop)."""
        for handle in self._charts.values() if scales is not None else ():
            handle.scales = scales
        if self._audience is None:
            for key, values in data.items():
                self._charts[key].data = values
            return
        browsers = self._audience()
        for key, values in data.items():
            send_data(self._charts[key], values, browsers)

    def _show_texts(self, banner: str, metrics: str, health: str) -> None:
        set_html(self.banner, banner)
        set_html(self.metrics, metrics)
        set_html(self.health, health)

    def _metrics_html(self, cols: dict[str, np.ndarray], window: float,
                      st: proto.Status | None) -> str:
        span, name = metrics_window(window, st.trajectory.period_s if st is not None else None)
        if span > window:
            cols, _ = self.client.ring.window(span)
        t = cols["t_s"]
        sel = t >= t[-1] - span if len(t) else np.zeros(0, dtype=bool)
        peak, rmse = window_metrics(cols["error_deg"][sel])
        have = float(t[-1] - t[0]) if len(t) else 0.0
        if have < span - 0.05:
            name += f", {have:.1f} s so far"
        rows = [f"<tr><td class='dt-metrics-window'>{name}</td><td>{_num(peak)}</td>"
                f"<td>{_num(rmse)}</td></tr>"]
        marks = self.client.counters.version_marks
        changes = ""
        if marks and len(cols["t_s"]):
            t_now = cols["t_s"][-1]
            recent = [m for m in marks if t_now - m.t_s <= 60.0]
            if recent:
                changes = "<div style='color:#8e44ad'>config changes: " + ", ".join(
                    f"v{m.version} at {m.t_s - t_now:+.1f} s" for m in recent[-4:]) + "</div>"
        return (
            "<div class='dt-metrics' style='font-size:12px'><table style='width:100%'>"
            "<tr><th></th><th>peak |e| (deg)</th><th>RMSE (deg)</th></tr>"
            + "".join(rows) + "</table>" + changes + "</div>"
        )

    def _health_html(self, st: proto.Status | None) -> str:
        """Loop health: the recent timing against its normal range (server/health.py): red
        only outside it or with a fault, never for a count since start."""
        ring = self.client.ring
        c = self.client.counters
        stream = (f"stream: {ring.batches} batches, {ring.gaps} samples lost, "
                  f"{c.decode_errors} bad messages; refresh {self.stats.push_rate_hz():.0f} Hz")
        if st is None:
            return f"<div class='dt-health' style='font-size:12px'>{stream}</div>"
        self.timing_history.add(st)
        j = self.timing_judgement = judge_timing(self.timing_history, st.config.rate_hz)
        return health_html(st, j, st.config.rate_hz, stream)


def in_loop(loop: asyncio.AbstractEventLoop | None, fn: Callable[..., None],
            *args: object) -> None:
    """`fn(*args)` on viser's event loop `loop` (logged if it fails), or here without one."""
    if loop is None:
        fn(*args)
        return
    # A closed loop (RuntimeError): the server stopped, nobody to show it to.
    with contextlib.suppress(RuntimeError):
        loop.call_soon_threadsafe(functools.partial(run_logged, fn, *args, what="live refresh"))


def _window_data(ring: StateRing, window_s: float, max_points: int
                 ) -> tuple[dict[str, np.ndarray], dict[str, tuple[np.ndarray, ...]]]:
    """The ring's last `window_s` seconds (its columns) and the live charts' data of them."""
    cols, version = ring.window(window_s)
    return cols, charts.live_data(cols["t_s"], cols, version, max_points)


def _run_trajectory(st: proto.Status | None) -> Trajectory | None:
    """The trajectory Start runs (a controller without `run_trajectory`: the present one)."""
    if st is None:
        return None
    return st.run_trajectory if st.run_trajectory is not None else st.trajectory


def _num(v: float) -> str:
    return "n/a" if math.isnan(v) else f"{v:.4f}"
