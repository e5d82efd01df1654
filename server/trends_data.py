"""A rig's trend for the Trends view (no viser): the hourly MCAP files of a time range read
into columns (`controller.recording.trend`), each closed hour read once (`TrendReader` keeps
it by size and modification time: a week's second look reads only the hour being written),
and the columns reduced to a chart's width (`time_decimate`: min and max per pixel of time,
so a spike of one window survives a week).

What is read (`TrendSpan`): the residuals, every estimated part (value, deviation, state, its
allowed range when the trend carries it), the loop's health (compute p99, skipped ticks per
window) and the alarms (the /drift/alarm channel; a part's entry into the alarm state where
the trend has no alarm record for it). What could not be read is said, never raised: no trend
directory, no file in the range, a file that is not a trend, a file cut short.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from controller.core.arrays import FloatArray
from controller.recording.trend import HourRead, read_hour, trend_files, trend_rigs

__all__ = ["RANGES", "TrendAlarm", "TrendReader", "TrendSpan", "find_rigs", "time_decimate"]

#: The time ranges offered, in seconds before now.
RANGES: dict[str, float] = {"last hour": 3600.0, "last day": 86400.0, "last week": 7 * 86400.0}

#: The residual and health columns the view draws (with their units).
RESIDUAL_COLUMNS = ("plant_residual_rms_deg_s", "fitted_residual_rms_deg_s",
                    "loop_residual_rms_deg", "loop_measured_rms_deg")
HEALTH_COLUMNS = ("compute_p99_us", "skipped_ticks")
#: A part's states as a number (the alarm and not-told points are series of their own).
STATES = ("ok", "note", "outside", "alarm", "not told")


@dataclass(frozen=True)
class TrendAlarm:
    epoch_s: float
    part: str
    text: str
    cleared: bool = False


@dataclass
class TrendSpan:
    """A rig's trend from t0 to t1: columns per channel (epoch seconds first), oldest first."""

    rig: str
    t0_epoch_s: float
    t1_epoch_s: float
    residual: dict[str, FloatArray] = field(default_factory=dict)
    parts: dict[str, FloatArray] = field(default_factory=dict)
    part_states: dict[str, np.ndarray] = field(default_factory=dict)
    """Per part, its state per window as an index into `STATES` (int8)."""
    health: dict[str, FloatArray] = field(default_factory=dict)
    alarms: list[TrendAlarm] = field(default_factory=list)
    files: int = 0
    problems: list[str] = field(default_factory=list)
    sources: tuple[tuple[str, int, int], ...] = ()
    """(name, size, mtime ns) of every file read: the same sources, the same data."""
    """Files not read (not a trend) or cut short, each with why."""

    @property
    def windows(self) -> int:
        return int(self.parts.get("t", np.empty(0)).size)

    @property
    def empty(self) -> bool:
        return self.windows == 0 and int(self.residual.get("t", np.empty(0)).size) == 0

    def part_names(self) -> list[str]:
        """The estimated parts, in the watch's order (value columns, not _std/_low/_high)."""
        return [k for k in self.parts if k != "t" and not k.endswith(("_std", "_low", "_high"))]


def find_rigs(dirs: tuple[Path, ...]) -> dict[str, Path]:
    """Every rig with a trend in `dirs` and the directory it is in (the first one wins)."""
    out: dict[str, Path] = {}
    for d in dirs:
        for rig in trend_rigs(d):
            out.setdefault(rig, d)
    return out


def _columns(times: list[float], datas: list[dict[str, object]],
             names: tuple[str, ...] | None = None) -> dict[str, FloatArray]:
    """The numeric fields of `datas` as float columns (NaN where a window lacks one), "t"
    (`times`) first; `names`: only these (else every numeric field seen, in the order first
    seen)."""
    if names is None:
        first: dict[str, object] = {}
        for d in datas[:1]:
            first.update(d)
        for k in sorted(set().union(*datas) - first.keys()):  # a field not in the first one
            first[k] = next(d[k] for d in datas if k in d)
        names = tuple(k for k, v in first.items()
                      if isinstance(v, int | float) and not isinstance(v, bool))
    out = {"t": np.array(times, dtype=np.float64)}
    for k in names:
        col = [d.get(k) for d in datas]
        try:
            out[k] = np.array(col, dtype=np.float64)  # None (absent) becomes NaN
        except (TypeError, ValueError):  # a window with text there: that window's is NaN
            out[k] = np.array([_num(v) for v in col], dtype=np.float64)
    return out


def _states(datas: list[dict[str, object]], key: str) -> np.ndarray:
    """A part's state per window as an index into `STATES` (an unknown one: "ok")."""
    col = np.array([str(d.get(key, "ok")) for d in datas])
    out = np.zeros(col.size, dtype=np.int8)
    for i, name in enumerate(STATES[1:], start=1):
        out[col == name] = i
    return out


def _num(v: object) -> float:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else math.nan


@dataclass(frozen=True)
class _Hour:
    """One file's windows as columns (what `TrendReader` keeps per file)."""

    residual: dict[str, FloatArray]
    parts: dict[str, FloatArray]
    states: dict[str, np.ndarray]
    health: dict[str, FloatArray]
    alarms: list[TrendAlarm]
    cut_short: str


def _hour_columns(hr: HourRead) -> _Hour:
    datas = hr.data["/drift/parts"]
    parts = _columns(hr.epoch_s["/drift/parts"], datas)
    seen = dict.fromkeys(k for d in datas[:1] for k in d)
    seen.update(dict.fromkeys(sorted(set().union(*datas) - seen.keys())))
    states = {k[:-len("_state")]: _states(datas, k) for k in seen if k.endswith("_state")}
    health = _columns(hr.epoch_s["/drift/health"], hr.data["/drift/health"], HEALTH_COLUMNS)
    alarms = [TrendAlarm(p.epoch_s, str(p.data.get("part", "?")),
                         str(p.data.get("text", "")), bool(p.data.get("cleared", False)))
              for p in hr.points("/drift/alarm")]
    residual = _columns(hr.epoch_s["/drift/residual"], hr.data["/drift/residual"],
                        RESIDUAL_COLUMNS)
    return _Hour(residual, parts, states, health, alarms, hr.cut_short)


def _concat(cols: list[dict[str, FloatArray]]) -> dict[str, FloatArray]:
    """Columns of several hours end to end (a column an hour lacks is NaN there)."""
    names: dict[str, None] = {}
    for c in cols:
        names.update(dict.fromkeys(c))
    out: dict[str, FloatArray] = {}
    for k in names:
        out[k] = np.concatenate([c[k] if k in c else np.full(c["t"].size, np.nan)
                                 for c in cols]) if cols else np.empty(0)
    return out


def _in(cols: dict[str, FloatArray], t0: float, t1: float) -> dict[str, FloatArray]:
    if "t" not in cols:
        return {"t": np.empty(0)}
    keep = (cols["t"] >= t0) & (cols["t"] <= t1)
    return {k: v[keep] for k, v in cols.items()}


class TrendReader:
    """Reads a rig's trend for a time range, keeping each file's columns by (size, mtime):
    an hour already read is not read again until it changes (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._hours: dict[Path, tuple[tuple[int, int], _Hour]] = {}
        self.files_read = 0
        """Files read from disk so far (a cached hour does not count)."""

    def _hour(self, path: Path) -> _Hour:
        st = path.stat()
        key = (st.st_size, st.st_mtime_ns)
        with self._lock:
            hit = self._hours.get(path)
        if hit is not None and hit[0] == key:
            return hit[1]
        hour = _hour_columns(read_hour(path))
        with self._lock:
            self._hours[path] = (key, hour)
            self.files_read += 1
        return hour

    def read(self, root: Path, rig: str, t0_epoch_s: float, t1_epoch_s: float) -> TrendSpan:
        span = TrendSpan(rig, t0_epoch_s, t1_epoch_s)
        paths = trend_files(root, rig, t0_epoch_s, t1_epoch_s)
        hours: list[_Hour] = []
        paths_read: list[Path] = []
        for path in paths:
            try:
                hours.append(self._hour(path))
                paths_read.append(path)
            except (OSError, ValueError) as exc:
                span.problems.append(f"{path.name}: not read ({exc})")
        with self._lock:  # files gone from the disk go from the cache
            for gone in [p for p in self._hours if p.parent == Path(root) / rig
                         and not p.exists()]:
                del self._hours[gone]
        span.files = len(hours)
        span.sources = tuple(_source(p) for p in paths_read)
        span.problems += [h.cut_short for h, p in zip(hours, paths_read, strict=True)
                          if h.cut_short and not _being_written(p)]
        span.residual = _in(_concat([h.residual for h in hours]), t0_epoch_s, t1_epoch_s)
        parts = _concat([h.parts for h in hours])
        states = _concat([{"t": h.parts["t"], **{k: v.astype(np.float64)
                                                 for k, v in h.states.items()}}
                          for h in hours])
        span.parts = _in(parts, t0_epoch_s, t1_epoch_s)
        in_states = _in(states, t0_epoch_s, t1_epoch_s)
        span.part_states = {k: np.nan_to_num(v, nan=0.0).astype(np.int8)
                            for k, v in in_states.items() if k != "t"}
        health = _in(_concat([h.health for h in hours]), t0_epoch_s, t1_epoch_s)
        if "skipped_ticks" in health:
            health["skipped_ticks"] = per_window(health["skipped_ticks"])
        span.health = health
        recorded = [a for h in hours for a in h.alarms if t0_epoch_s <= a.epoch_s <= t1_epoch_s]
        span.alarms = sorted(recorded + entered_alarm(span, recorded), key=lambda a: a.epoch_s)
        return span


#: A file written to this recently is the hour the watch is writing: its end cut short is a
#: chunk on its way to the disk, not a fault to report.
BEING_WRITTEN_S = 120.0


def _source(path: Path) -> tuple[str, int, int]:
    try:
        st = path.stat()
    except OSError:
        return (path.name, -1, -1)
    return (path.name, st.st_size, st.st_mtime_ns)


def _being_written(path: Path) -> bool:
    try:
        return time.time() - path.stat().st_mtime < BEING_WRITTEN_S
    except OSError:
        return False


def per_window(total: FloatArray) -> FloatArray:
    """A count since the controller started (skipped ticks) as its increase per window; a
    restart (the count fell) counts from zero."""
    out = np.diff(total, prepend=total[:1])
    fell = out < 0
    out[fell] = total[fell]
    return out


def entered_alarm(span: TrendSpan, recorded: list[TrendAlarm]) -> list[TrendAlarm]:
    """The windows where a part entered the alarm state with no alarm record of that part
    within a minute (a trend written before the watch recorded its alarms)."""
    out: list[TrendAlarm] = []
    t = span.parts.get("t", np.empty(0))
    alarm = STATES.index("alarm")
    for part, st in span.part_states.items():
        now = st == alarm
        # Entries only: a part already in alarm at the range's first window entered it before.
        starts = np.flatnonzero(now & ~np.concatenate(([True], now[:-1])))
        for i in starts:
            e = float(t[i])
            if not any(a.part == part and abs(a.epoch_s - e) <= 60.0 for a in recorded):
                value = span.parts.get(part, np.full(t.size, np.nan))[i]
                out.append(TrendAlarm(e, part, f"{part} x{value:.3g}: in alarm (the window's "
                                      "state; no alarm record in the trend)"))
    return out


def time_decimate(t: FloatArray, ys: list[FloatArray], t0: float, t1: float, width_px: int,
                  gap_s: float | None = None) -> tuple[FloatArray, list[FloatArray]]:
    """`ys` against `t` reduced to at most two points per pixel of a `width_px` chart of t0..t1:
    in each pixel's time, the min and the max of each series (NaN ignored), in the order they
    occur, at the pixel's first and last time. A gap in `t` longer than `gap_s` (default: 3
    times the median spacing) stays a gap: a NaN row between (the line breaks, never a line
    drawn across hours the watch did not run). Fewer points than pixels: returned as they are,
    with the gaps' NaN rows."""
    t = np.asarray(t, dtype=np.float64)
    ys = [np.asarray(y, dtype=np.float64) for y in ys]
    n = t.size
    if n == 0:
        return t, ys
    dt = np.diff(t)
    if gap_s is None:
        gap_s = 3.0 * float(np.median(dt)) if dt.size else math.inf
    gap_after = np.flatnonzero(dt > gap_s)  # a gap between i and i + 1
    px = np.floor((t - t0) / max(t1 - t0, 1e-9) * width_px).astype(np.int64)
    new = np.ones(n, dtype=bool)
    new[1:] = px[1:] != px[:-1]
    new[gap_after + 1] = True
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], n) - 1
    if starts.size * 2 >= n:  # no fewer points to gain: the samples, the gaps broken
        return _with_breaks(t, ys, gap_after)
    x_out = np.empty(2 * starts.size)
    x_out[0::2] = t[starts]
    x_out[1::2] = t[ends]
    out: list[FloatArray] = []
    for y in ys:
        with np.errstate(invalid="ignore"):
            lo = np.fmin.reduceat(y, starts)
            hi = np.fmax.reduceat(y, starts)
            lo_first = _argfirst(y, starts, ends, lo) <= _argfirst(y, starts, ends, hi)
        pair = np.empty(2 * starts.size)
        pair[0::2] = np.where(lo_first, lo, hi)
        pair[1::2] = np.where(lo_first, hi, lo)
        out.append(pair)
    # The groups that end at a gap: a NaN row after their pair.
    gap_groups = np.searchsorted(starts, gap_after + 1) - 1
    return _with_breaks(x_out, out, 2 * gap_groups + 1)


def _argfirst(y: FloatArray, starts: np.ndarray, ends: np.ndarray, v: FloatArray) -> np.ndarray:
    """Per group, the index where `y` first equals its group's value `v` (n for none)."""
    n = y.size
    group = np.repeat(np.arange(starts.size), ends - starts + 1)
    hit = np.flatnonzero(y == v[group])
    first = np.full(starts.size, n, dtype=np.int64)
    np.minimum.at(first, group[hit], hit)
    return first


def _with_breaks(x: FloatArray, ys: list[FloatArray], after: np.ndarray
                 ) -> tuple[FloatArray, list[FloatArray]]:
    """A NaN row inserted after each index in `after` (x: the midpoint, so x stays sorted)."""
    if after.size == 0:
        return x, ys
    mid = (x[after] + x[after + 1]) / 2.0
    xs = np.insert(x, after + 1, mid)
    return xs, [np.insert(y, after + 1, np.nan) for y in ys]
