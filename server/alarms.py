"""Alarms: what the controller did that an operator must see and acknowledge (a watchdog
rollback, a fault, an e-stop), found in the stream of its status messages, and the plant's
drift the watch alarms on (`dobtune/<rig>/drift/alarm`).

Pure: `AlarmBoard.observe(status, now)` and `observe_drift(alarm, now)` keep the alarms not
yet acknowledged; `alarms_html` draws them. The live panel feeds it and shows the board.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from controller import protocol as proto
from server.escape import esc

__all__ = ["Alarm", "AlarmBoard", "alarms_html"]

#: (border, background, text) per level.
_LEVEL_COLORS = {"amber": ("#b26a00", "#fff4e0", "#6b3f00"),
                 "red": ("#b71c1c", "#fdecea", "#7f0000")}


@dataclass(frozen=True)
class Alarm:
    kind: str  # "rollback" | "fault" | "estop" | "drift"
    level: str  # "amber" | "red"
    title: str
    reason: str
    at_s: float  # wall-clock time it was seen (time.time())


@dataclass
class AlarmBoard:
    """The alarms not yet acknowledged, newest last."""

    alarms: list[Alarm] = field(default_factory=list)
    _rollbacks: int | None = None
    _estop_seq: int | None = None
    _fault_key: tuple[str, ...] | None = None
    _mode: str = ""

    def observe(self, st: proto.Status, now_s: float | None = None) -> bool:
        """Note the alarms `st` raises against the previous status; True if any was added.
        The first status sets what counts as known, except an e-stop or a fault in force,
        which is an alarm at once."""
        now = time.time() if now_s is None else now_s
        added = False
        first = self._rollbacks is None
        if not first and st.rollbacks > (self._rollbacks or 0):
            self.alarms.append(Alarm(
                "rollback", "amber", f"WATCHDOG ROLLBACK to v{st.config_version}",
                st.watchdog or "the watchdog rolled the configuration back", now))
            added = True
        self._rollbacks = st.rollbacks
        if st.mode == "estop" and (self._mode != "estop" or st.estop_seq != self._estop_seq):
            # A new e-stop while the latch stands and its alarm is still shown is that alarm
            # (one press is two e-stops: the put on the e-stop key, then the EStop command,
            # each a new estop_seq); once acknowledged, a new press is a new alarm.
            shown = self._mode == "estop" and any(a.kind == "estop" for a in self.alarms)
            if not shown:
                self.alarms.append(Alarm("estop", "red", "E-STOP",
                                         "speed command 0, drive disabled", now))
                added = True
        faults = tuple(st.faults)
        fault_key = faults if st.mode != "estop" and (st.mode == "fault" or faults) else None
        if fault_key is not None and fault_key != self._fault_key:
            self.alarms.append(Alarm("fault", "red", "FAULT",
                                     "; ".join(faults) or "the controller is in fault", now))
            added = True
        self._fault_key = fault_key
        self._mode = st.mode
        self._estop_seq = st.estop_seq
        return added

    def observe_drift(self, alarm: proto.DriftAlarm, now_s: float | None = None) -> bool:
        """A part of the plant left its range (amber: the loop still runs what the gate
        passed; what it means and what to do are in the reason). Its clearing adds nothing:
        an acknowledged drift stays in the trend. True if added."""
        if alarm.cleared:
            return False
        now = time.time() if now_s is None else now_s
        self.alarms.append(Alarm("drift", "amber", f"PLANT DRIFT: {alarm.part}",
                                 f"{alarm.text}. {alarm.action}".strip(), now))
        return True

    def acknowledge(self) -> int:
        """Clear the alarms shown; returns how many."""
        n = len(self.alarms)
        self.alarms.clear()
        return n


def _clock(at_s: float) -> str:
    return time.strftime("%H:%M:%S", time.localtime(at_s))


def alarms_html(board: AlarmBoard) -> str:
    """The unacknowledged alarms, one box per kind (newest kind first): the newest of that
    kind, and how many since the last acknowledgement with the first one's time. Three e-stops
    were three boxes that pushed the controls down the page."""
    if not board.alarms:
        return "<div class='dt-alarms'></div>"
    kinds: dict[str, list[Alarm]] = {}
    for a in reversed(board.alarms):
        kinds.setdefault(a.kind, []).append(a)
    rows = []
    for kind, same in kinds.items():
        a = same[0]  # the newest
        border, bg, ink = _LEVEL_COLORS[a.level]
        count = (f" <span class='dt-alarm-count'>&times;{len(same)} (first at "
                 f"{_clock(same[-1].at_s)})</span>" if len(same) > 1 else "")
        rows.append(
            f"<div class='dt-alarm dt-alarm-{kind} dt-alarm-{a.level}' style='border:2px "
            f"solid {border};background:{bg};color:{ink};padding:5px 7px;border-radius:4px;"
            f"margin:3px 0;font-size:13px'><b>&#9888; {esc(a.title)}</b> "
            f"<span class='dt-alarm-time'>at {_clock(a.at_s)}</span>{count}<br>"
            f"<span class='dt-alarm-reason'>{esc(a.reason)}</span></div>")
    return "<div class='dt-alarms'>" + "".join(rows) + "</div>"
