"""Loop health against a stated normal range (pure).

The controller's status carries its timing: period percentiles over the last status interval
and counters since start (ticks, overruns, skipped ticks). A counter since start only grows:
judged as it is, one late tick an hour after start made the health box red for good, and on a
loaded machine it was red all the time. What is judged here is the recent rate, over the last
`window_s` of statuses, against `LoopNormal`:

* late ticks (overruns: a tick that ended after the next deadline) per 100 ticks run,
* lost ticks (whole periods skipped instead of running ticks back to back) per 100 due,
* jitter: the period's p99 minus its p50 (the median over the window of the per-status values,
  so one spike does not decide), against a fraction of the period.

The defaults are what the simulated rig's 1 kHz loop does on a quiet 2-core machine with room to
spare (measured: late 0.2-1.3 %, lost 0-1.1 %, jitter 0-120 us; with 6 busy processes beside it
late ~12 %, lost ~20 %, jitter 4-9 ms, which is outside), and what the loop tolerates: a lost
tick holds the command one more period, rare ones do not show in the tracking error.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from controller import protocol as proto
from server.escape import esc

__all__ = ["HealthJudgement", "LoopNormal", "TimingHistory", "health_html", "judge_timing"]


@dataclass(frozen=True)
class LoopNormal:
    """The normal range of the loop's timing (each an upper bound)."""

    late_pct: float = 2.0
    lost_pct: float = 2.0
    jitter_periods: float = 0.5
    """p99 - p50 of the period, in periods (500 us at 1 kHz)."""


@dataclass(frozen=True)
class _Sample:
    t_s: float
    ticks: int
    overruns: int
    skipped: int
    jitter_us: float


class TimingHistory:
    """The statuses' timing of the last `window_s` seconds (by the statuses' own clock)."""

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_s = window_s
        self._samples: deque[_Sample] = deque()

    def add(self, st: proto.Status) -> None:
        tm = st.timing
        s = _Sample(st.t_s, tm.ticks, tm.overruns, tm.skipped_ticks,
                    tm.period_p99_us - tm.period_p50_us)
        q = self._samples
        if q and (s.t_s < q[-1].t_s or s.ticks < q[-1].ticks):
            q.clear()  # a restarted controller: its counters start again
        if q and s.t_s == q[-1].t_s:
            return
        q.append(s)
        while len(q) > 2 and q[-1].t_s - q[1].t_s >= self.window_s:
            q.popleft()

    def rates(self) -> tuple[float, float, float, float]:
        """(late %, lost %, median jitter us, seconds covered); NaN while fewer than two
        statuses are known."""
        q = self._samples
        if len(q) < 2:
            return math.nan, math.nan, math.nan, 0.0
        a, b = q[0], q[-1]
        ran = b.ticks - a.ticks
        lost = b.skipped - a.skipped
        late_pct = 100.0 * (b.overruns - a.overruns) / ran if ran > 0 else math.nan
        lost_pct = 100.0 * lost / (ran + lost) if ran + lost > 0 else math.nan
        jit = sorted(s.jitter_us for s in list(q)[1:])
        return late_pct, lost_pct, jit[len(jit) // 2], b.t_s - a.t_s


@dataclass(frozen=True)
class HealthJudgement:
    normal: bool
    outside: tuple[str, ...]
    """What is outside the normal range, each with its number and the bound."""
    late_pct: float
    lost_pct: float
    jitter_us: float
    span_s: float


def judge_timing(history: TimingHistory, rate_hz: float,
                 normal: LoopNormal = LoopNormal()) -> HealthJudgement:
    late, lost, jitter, span = history.rates()
    jitter_max = normal.jitter_periods * 1e6 / rate_hz
    outside = []
    if late > normal.late_pct:
        outside.append(f"late ticks {late:.1f} % (normal up to {normal.late_pct:g} %)")
    if lost > normal.lost_pct:
        outside.append(f"lost ticks {lost:.1f} % (normal up to {normal.lost_pct:g} %)")
    if jitter > jitter_max:
        outside.append(f"jitter {jitter:.0f} us (normal up to {jitter_max:.0f} us)")
    return HealthJudgement(not outside, tuple(outside), late, lost, jitter, span)


def _pct(v: float) -> str:
    return "n/a" if math.isnan(v) else f"{v:.1f} %"


def health_html(st: proto.Status, j: HealthJudgement, rate_hz: float, stream: str,
                normal: LoopNormal = LoopNormal()) -> str:
    """The loop-health box: red only when a fault is in force or the recent timing is outside
    its normal range (which it names, with the numbers); else quiet, saying it is normal."""
    tm = st.timing
    faults = esc(", ".join(st.faults)) if st.faults else "none"
    jitter_max = normal.jitter_periods * 1e6 / rate_hz
    bad = bool(st.faults) or not j.normal
    if st.faults:
        state = "<b class='dt-health-state'>FAULT</b>"
    elif math.isnan(j.late_pct):
        state = "<b class='dt-health-state'>timing: waiting for statuses</b>"
    elif j.normal:
        state = (f"<b class='dt-health-state' style='color:#2e7d32'>timing normal</b> over the "
                 f"last {j.span_s:.0f} s")
    else:
        state = ("<b class='dt-health-state'>timing OUTSIDE its normal range</b>: "
                 + esc(", ".join(o.split(" (")[0] for o in j.outside)))
    jit = "n/a" if math.isnan(j.jitter_us) else f"{j.jitter_us:.0f} us"
    # Which window each figure covers, said beside it: "lost ticks 22.1 %" (recent) beside
    # "76159 lost of 2458638" (since start, 3 %) read as a contradiction.
    recent = ("over the last " + (f"{j.span_s:.0f} s" if math.isfinite(j.span_s) else "statuses")
              + ": ")
    due = tm.ticks + tm.skipped_ticks
    start_pct = (f" ({100.0 * tm.skipped_ticks / due:.1f} % lost)" if due > 0 else "")
    style = "color:#d62728" if bad else ""
    cls = "dt-health dt-health-bad" if bad else "dt-health dt-health-ok"
    return (
        f"<div class='{cls}' style='font-size:12px;{style}'>"
        f"mode <b>{esc(st.mode)}</b>, plant {esc(st.plant)}, trajectory "
        f"{esc(st.trajectory.kind)}<br>{state}<br>"
        f"{recent}late ticks {_pct(j.late_pct)} (normal &le; {normal.late_pct:g} %), lost ticks "
        f"{_pct(j.lost_pct)} (&le; {normal.lost_pct:g} %), jitter p99&minus;p50 {jit} "
        f"(&le; {jitter_max:.0f} us)<br>"
        f"<span style='color:#777'>period p50 {tm.period_p50_us:.0f} us, p99 "
        f"{tm.period_p99_us:.0f} us, max {tm.period_max_us:.0f} us; compute p99 "
        f"{tm.compute_p99_us:.0f} us; since the loop started: {tm.overruns} late of {tm.ticks} "
        f"ticks run, {tm.skipped_ticks} lost of {due} due{start_pct}</span><br>"
        f"faults: {faults}<br>{stream}</div>"
    )
