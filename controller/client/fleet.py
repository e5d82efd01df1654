"""The fleet watcher: every rig reachable through one Zenoh session (a router), no GUI.

`FleetMonitor` follows the rigs' liveliness tokens (`dobtune/<rig>/alive`: a rig whose
controller dies leaves at once) and their status, state and drift streams, and keeps per rig
the latest status, the watch's latest drift state, and a short, decimated trace of the
position error. The dashboard's Fleet tab
(`server/fleet.py`) and `dobtune ctl rigs` show it. Zenoh callbacks only decode and store under
a lock.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from controller import protocol as proto
from controller.client.controller_client import quietly
from controller.client.session import put_estop

__all__ = ["DECIMATE", "TRACE_POINTS", "FleetMonitor", "RigRow", "drift_summary"]

M = TypeVar("M", proto.Status, proto.StateBatch, proto.DriftState)

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
    #: Why its latest status could not be read ("" it could): e.g. a controller of another
    #: protocol version ("v: unsupported protocol version 1; this side speaks 2 ...").
    unread: str = ""
    #: The watch's drift state in a few words ("" no watch heard: `drift_summary`), and
    #: whether a part is in alarm.
    drift: str = ""
    drift_alarm: bool = False


def drift_summary(d: proto.DriftState) -> str:
    """The watch's latest window in a few words: the parts in alarm (value and range), else
    the parts moved (notes), else ok; the parts the window did not tell."""
    alarm = [f"{p.name} x{p.value:.3g} (range {p.low:.3g}-{p.high:.3g})"
             for p in d.parts if p.state == "alarm"]
    moved = [f"{p.name} x{p.value:.3g}" for p in d.parts if p.state in ("note", "outside")]
    untold = [p.name for p in d.parts if p.state == "not told"]
    head = ("ALARM: " + ", ".join(alarm) if alarm else
            "moved, inside the bound: " + ", ".join(moved) if moved else "ok")
    return head + (f"; not told: {', '.join(untold)}" if untold else "")


@dataclass
class _Rig:
    status: proto.Status | None = None
    drift: proto.DriftState | None = None
    status_at: float = 0.0
    unread: str = ""
    trace: deque[float] | None = None
    next_keep: int = 0  #: the next sequence number kept in the trace


def _keep_status(r: _Rig, st: proto.Status) -> None:
    r.status, r.status_at, r.unread = st, time.monotonic(), ""


def _keep_drift(r: _Rig, d: proto.DriftState) -> None:
    r.drift = d


def _keep_state(r: _Rig, b: proto.StateBatch) -> None:
    """Every DECIMATE-th error sample of the batch into the rig's trace."""
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

        s, every = self._session, "*"
        try:
            self._entities.append(s.liveliness().declare_subscriber(
                proto.key_alive(every), zenoh.handlers.Callback(self._on_alive), history=True))
            self._entities.append(s.declare_subscriber(
                proto.key_status(every), zenoh.handlers.Callback(self._on_status)))
            self._entities.append(s.declare_subscriber(
                proto.key_state(every), zenoh.handlers.Callback(self._on_state)))
            self._entities.append(s.declare_subscriber(
                proto.key_drift(every), zenoh.handlers.Callback(self._on_drift)))
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for e in self._entities:
            quietly("undeclaring a fleet subscriber", e.undeclare)
        self._entities = []

    # -- Zenoh callbacks (short) ---------------------------------------------------------------

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        try:
            rig = proto.rig_of_key(sample.key_expr)
        except ValueError:
            return
        if str(sample.key_expr) != proto.key_alive(rig):
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._alive.discard(rig)
            else:
                self._alive.add(rig)

    def _take(self, sample: Any, kind: type[M], keep: Callable[[_Rig, M], None]) -> None:
        """`keep` a status or state sample in its rig's record (made on the rig's first word),
        under the lock; a sample that does not decode, or a rig speaking for another (the key
        is what the access control checks: a controller may put on its own rig's keys only),
        is counted in `decode_errors` and not kept."""
        rig = proto.rig_of_key(sample.key_expr)
        try:
            msg = proto.decode(sample.payload.to_bytes(), kind)
        except proto.ProtocolError as exc:
            self.decode_errors += 1
            if kind is proto.Status:
                with self._lock:
                    self._rigs.setdefault(rig, _Rig()).unread = str(exc)[:300]
            return
        if msg.rig != rig:
            self.decode_errors += 1
            return
        with self._lock:
            keep(self._rigs.setdefault(rig, _Rig()), msg)

    def _on_status(self, sample: Any) -> None:
        self._take(sample, proto.Status, _keep_status)

    def _on_state(self, sample: Any) -> None:
        self._take(sample, proto.StateBatch, _keep_state)

    def _on_drift(self, sample: Any) -> None:
        self._take(sample, proto.DriftState, _keep_drift)

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
                    status_age_s=(now - r.status_at) if st else None, trace=trace,
                    unread=r.unread, drift=drift_summary(r.drift) if r.drift else "",
                    drift_alarm=bool(r.drift and r.drift.alarms)))
        return out

    def estop(self, rig: str) -> None:
        """The e-stop put on `rig` (any payload stops its loop; no reply needed)."""
        proto.check_rig_name(rig)
        put_estop(self._session, self._estop_key(rig), "dashboard fleet overview")
