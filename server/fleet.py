"""The fleet overview: every rig reachable through the dashboard's Zenoh endpoints (a router).

`FleetMonitor` (no GUI) follows the rigs' liveliness tokens (`dobtune/<rig>/alive`: a rig
whose controller dies leaves at once) and their status and state streams, and keeps per rig
the latest status and a short, decimated trace of the position error. `FleetPanel` shows it
in the dashboard: one row per rig (mode, configuration version, error RMS and a small live
error trace, faults, lease holder), an E-STOP for any rig, and a full view of any rig (another
dashboard in this process, on its own port, opened on demand).

Zenoh callbacks only decode and store under a lock; the panel redraws at a few hertz.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from controller import protocol as proto
from server.escape import esc, href
from server.panels.widgets import set_html
from server.workers import Periodic, run_logged

__all__ = ["FleetMonitor", "FleetPanel", "RigRow", "sparkline_svg"]

log = logging.getLogger(__name__)

#: Error trace kept per rig: every DECIMATE-th sample, TRACE_POINTS of them (3 s at 1 kHz).
DECIMATE = 10
TRACE_POINTS = 300


@dataclass(frozen=True)
class RigRow:
    rig: str
    alive: bool  #: its liveliness token is present
    mode: str
    plant: str
    config_version: int | None
    error_rms_deg: float | None  #: over the trace
    faults: tuple[str, ...]
    operator: str
    status_age_s: float | None
    trace: tuple[float, ...]  #: the latest error samples (decimated), oldest first


@dataclass
class _Rig:
    status: proto.Status | None = None
    status_at: float = 0.0
    trace: deque[float] | None = None
    next_keep: int = 0  #: the next sequence number kept in the trace


class FleetMonitor:
    """Liveliness, status and state of every rig through one Zenoh session (not owned)."""

    def __init__(self, session: Any, estop_key: Callable[[str], str] = proto.key_estop) -> None:
        self._session = session
        self._estop_key = estop_key
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._rigs: dict[str, _Rig] = {}
        self._entities: list[Any] = []
        self.decode_errors = 0

    def __enter__(self) -> FleetMonitor:
        import zenoh

        s, p = self._session, proto.KEY_PREFIX
        try:
            self._entities.append(s.liveliness().declare_subscriber(
                f"{p}/*/alive", zenoh.handlers.Callback(self._on_alive), history=True))
            self._entities.append(s.declare_subscriber(
                f"{p}/*/status", zenoh.handlers.Callback(self._on_status)))
            self._entities.append(s.declare_subscriber(
                f"{p}/*/state", zenoh.handlers.Callback(self._on_state)))
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for e in self._entities:
            run_logged(e.undeclare, what="undeclaring a fleet subscriber")
        self._entities = []

    # -- Zenoh callbacks (short) ---------------------------------------------------------------

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        parts = str(sample.key_expr).split("/")
        if len(parts) != 3:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._alive.discard(parts[1])
            else:
                self._alive.add(parts[1])

    def _on_status(self, sample: Any) -> None:
        rig = _rig_of(sample)
        try:
            st = proto.decode(sample.payload.to_bytes(), proto.Status)
        except proto.ProtocolError:
            self.decode_errors += 1
            return
        if st.rig != rig:  # a rig speaking for another (the key is what the access control
            self.decode_errors += 1  # checks: a controller may put on its own rig's keys only)
            return
        with self._lock:
            r = self._rigs.setdefault(rig, _Rig())
            r.status, r.status_at = st, time.monotonic()

    def _on_state(self, sample: Any) -> None:
        rig = _rig_of(sample)
        try:
            b = proto.decode(sample.payload.to_bytes(), proto.StateBatch)
        except proto.ProtocolError:
            self.decode_errors += 1
            return
        if b.rig != rig:
            self.decode_errors += 1
            return
        with self._lock:
            r = self._rigs.setdefault(rig, _Rig())
            if r.trace is None:
                r.trace = deque(maxlen=TRACE_POINTS)
            n = len(b.error_deg)
            i = max(0, r.next_keep - b.seq0)
            if i > n + DECIMATE or r.next_keep - b.seq0 > 10 * TRACE_POINTS * DECIMATE:
                i = 0  # the controller restarted (its sequence began again)
            while i < n:
                r.trace.append(b.error_deg[i])
                i += DECIMATE
            r.next_keep = b.seq0 + i

    # -- reading -------------------------------------------------------------------------------

    def rigs(self) -> list[str]:
        """The rigs alive now (liveliness), sorted."""
        with self._lock:
            return sorted(self._alive)

    def rows(self) -> list[RigRow]:
        """One row per rig alive (and per rig heard of that is no longer: alive False)."""
        now = time.monotonic()
        with self._lock:
            names = sorted(self._alive | set(self._rigs))
            out = []
            for name in names:
                r = self._rigs.get(name, _Rig())
                st = r.status
                trace = tuple(r.trace) if r.trace else ()
                rms = math.sqrt(sum(e * e for e in trace) / len(trace)) if trace else None
                out.append(RigRow(
                    rig=name, alive=name in self._alive, mode=st.mode if st else "",
                    plant=st.plant if st else "",
                    config_version=st.config_version if st else None,
                    error_rms_deg=rms, faults=tuple(st.faults) if st else (),
                    operator=st.operator if st else "",
                    status_age_s=(now - r.status_at) if st else None, trace=trace))
        return out

    def estop(self, rig: str) -> None:
        """The e-stop put on `rig` (any payload stops its loop; no reply needed)."""
        proto.check_rig_name(rig)
        msg = proto.Command(body=proto.EStop(), client="dashboard fleet overview")
        self._session.put(self._estop_key(rig), proto.encode(msg))


def _rig_of(sample: Any) -> str:
    """The rig of a `dobtune/<rig>/<what>` sample: its key (what the access control checks)."""
    return str(sample.key_expr).split("/")[1]


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
            f"<td>{ver}</td><td>{rms}</td><td>{sparkline_svg(r.trace)}<br>"
            f"<span style='color:#888'>&plusmn;{peak:.3g} deg</span></td>"
            f"<td>{esc(r.operator) or '-'}</td>"
            f"<td style='color:#d62728'>{esc('; '.join(r.faults)) or '-'}</td></tr>")
    return ("<div class='dt-fleet' style='font-size:12px'><table><tr><th>rig</th><th>state</th>"
            "<th>config</th><th>error RMS (deg)</th><th>error, last 3 s</th><th>lease</th>"
            "<th>faults</th></tr>" + "".join(body) + "</table></div>")


class FleetPanel:
    """The Fleet tab: the table, an E-STOP for any rig, a full view of any rig."""

    def __init__(self, gui: Any, monitor: FleetMonitor,
                 open_view: Callable[[str, Any], str], rate_hz: float = 2.0) -> None:
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
        self.estop_button.on_click(lambda _e: self.estop(str(self.pick.value)))
        self.open_button.on_click(lambda e: self.open(str(self.pick.value), e.client))

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
            self.pick.value = keep
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

    def open(self, rig: str, browser: Any = None) -> str:
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

