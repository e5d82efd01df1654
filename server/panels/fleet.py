"""The fleet overview: every rig reachable through the dashboard's Zenoh endpoints (a router).

`FleetMonitor` (no GUI) follows the rigs' liveliness tokens (`dobtune/<rig>/alive`: a rig
whose controller dies leaves at once) and their status and state streams, and keeps per rig
the latest status and a short, decimated trace of the position error. `FleetPanel` shows it
in the dashboard: one row per rig (mode, the watch's drift state beside it, configuration
version, error RMS and a small live error trace, faults, lease holder), an E-STOP for any
rig, and a full view of any rig (another dashboard in this process, on its own port, opened
on demand).

Zenoh callbacks only decode and store under a lock; the panel redraws at a few hertz.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import viser

from controller.client.fleet import FleetMonitor, RigRow
from server.escape import esc, href
from server.gui import on_press, set_value
from server.panels.widgets import set_html
from server.workers import Periodic

__all__ = ["FleetMonitor", "FleetPanel", "RigRow", "sparkline_svg"]

log = logging.getLogger(__name__)


def sparkline_svg(trace: tuple[float, ...], width: int = 160, height: int = 28) -> str:
    """A small inline SVG of the error trace (symmetric about zero; the scale is printed)."""
    if len(trace) < 2:
        return f"<svg width='{width}' height='{height}'></svg>"
    peak = max(abs(v) for v in trace) or 1e-9
    step = width / (len(trace) - 1)
    mid = height / 2
    pts = " ".join(f"{i * step:.1f},{mid - v / peak * (mid - 1):.1f}" for i, v in enumerate(trace))
    return (f"<svg width='{width}' height='{height}' style='background:#fafafa'>"
            f"<line x1='0' y1='{mid}' x2='{width}' y2='{mid}' stroke='#ccc'/>"
            f"<polyline class='dt-spark' fill='none' stroke='#d62728' stroke-width='1' "
            f"points='{pts}'/></svg>")


def fleet_table_html(rows: list[RigRow]) -> str:
    if not rows:
        return ("<div class='dt-fleet'>No rig reachable (yet) through this dashboard's "
                "endpoints.</div>")
    body = []
    for r in rows:
        state = (r.mode or "?") if r.alive else "gone"
        color = {"running": "#2e7d32", "estop": "#d62728", "fault": "#e67e22"}.get(
            r.mode if r.alive else "gone", "#555")
        rms = "-" if r.error_rms_deg is None else f"{r.error_rms_deg:.4f}"
        peak = max((abs(v) for v in r.trace), default=0.0)
        ver = "-" if r.config_version is None else f"v{r.config_version}"
        body.append(
            f"<tr class='dt-fleet-row' data-rig='{esc(r.rig)}'><td><b>{esc(r.rig)}</b><br>"
            f"<span style='color:#888'>{esc(r.plant)}</span></td>"
            f"<td style='color:{color}'><b class='dt-fleet-mode'>{esc(state)}</b></td>"
            f"<td class='dt-fleet-drift' style='color:{'#d62728' if r.drift_alarm else '#333'}'"
            f">{esc(r.drift) or 'no watch heard'}</td>"
            f"<td>{ver}</td><td>{rms}</td><td>{sparkline_svg(r.trace)}<br>"
            f"<span style='color:#888'>&plusmn;{peak:.3g} deg</span></td>"
            f"<td>{esc(r.operator) or '-'}</td>"
            f"<td style='color:#d62728'>{esc('; '.join(r.faults)) or '-'}"
            + (f"<br><span class='dt-fleet-unread'>status not read: {esc(r.unread)}</span>"
               if r.unread else "") + "</td></tr>")
    return ("<div class='dt-fleet' style='font-size:12px'><table><tr><th>rig</th><th>state</th>"
            "<th>plant drift (the watch)</th><th>config</th><th>error RMS (deg)</th>"
            "<th>error, last 3 s</th><th>lease</th>"
            "<th>faults</th></tr>" + "".join(body) + "</table></div>")


class FleetPanel:
    """The Fleet tab: the table, an E-STOP for any rig, a full view of any rig."""

    def __init__(self, gui: viser.GuiApi, monitor: FleetMonitor,
                 open_view: Callable[[str, viser.ClientHandle | None], str],
                 rate_hz: float = 2.0) -> None:
        """`open_view(rig, browser)`: the URL of `rig`'s full view for that browser's user."""
        self.gui = gui
        self.monitor = monitor
        self._open_view = open_view
        self._updater = Periodic(self._refresh, 1.0 / rate_hz, name="fleet-updater")
        self.refreshes = 0

    def build(self) -> None:
        gui = self.gui
        self.table = gui.add_html(fleet_table_html([]))
        self.pick = gui.add_dropdown("Rig", ("-",), initial_value="-")
        self.estop_button = gui.add_button("E-STOP this rig", color="red")
        self.open_button = gui.add_button("Open its full view", color="gray")
        self.result = gui.add_html("<div class='dt-fleet-result'></div>")
        on_press(self.estop_button, lambda _browser: self.estop(str(self.pick.value)))
        on_press(self.open_button, lambda browser: self.open(str(self.pick.value), browser))

    def start(self) -> None:
        self._updater.start()

    def stop(self) -> None:
        self._updater.stop()

    def _refresh(self, _k: int = 0) -> None:
        rows = self.monitor.rows()
        set_html(self.table, fleet_table_html(rows))
        options = tuple(r.rig for r in rows if r.alive) or ("-",)
        if tuple(self.pick.options) != options:
            keep = self.pick.value if self.pick.value in options else options[0]
            self.pick.options = options
            set_value(self.pick, keep)
        self.refreshes += 1

    def estop(self, rig: str) -> bool:
        if rig not in self.monitor.rigs():
            self.result.content = ("<div class='dt-fleet-result' style='color:#d62728'>No such "
                                   f"rig alive: {esc(rig)}</div>")
            return False
        self.monitor.estop(rig)
        log.warning("E-STOP of rig %s from the fleet overview", rig)
        self.result.content = (f"<div class='dt-fleet-result' style='color:#d62728'>E-STOP sent "
                               f"to {esc(rig)}.</div>")
        return True

    def open(self, rig: str, browser: viser.ClientHandle | None = None) -> str:
        """Open (or find) the full view of `rig`; its address is shown as a link."""
        if rig not in self.monitor.rigs():
            self.result.content = ("<div class='dt-fleet-result' style='color:#d62728'>No such "
                                   f"rig alive: {esc(rig)}</div>")
            return ""
        try:
            url = self._open_view(rig, browser)
            link = href(url)
        except Exception as exc:  # shown and logged: the overview goes on
            log.exception("full view of %s not opened", rig)
            self.result.content = (f"<div class='dt-fleet-result' style='color:#d62728'>Full "
                                   f"view of {esc(rig)} not opened: {esc(str(exc))}</div>")
            return ""
        self.result.content = (f"<div class='dt-fleet-result'>Full view of {esc(rig)}: "
                               f"<a href='{link}' target='_blank' rel='noopener'>open it</a>"
                               "</div>")
        return url

