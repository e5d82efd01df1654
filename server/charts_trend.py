"""The Trends view's charts (pure): a rig's trend (`server.trends_data.TrendSpan`) as uPlot
charts over a fixed time range, reduced to the chart's width.

One chart for the residuals (the plant's, deg/s, left; the loop's, deg, right), one per
estimated part (its value, its allowed range as a band when the trend carries it, the windows
in alarm and those that did not tell the part as points of their own) and one for the loop's
health (compute p99, us, left; skipped ticks per window, right). Every chart marks the alarms
as a vertical row of red points at their time (the "alarm" series, on a fixed 0..1 scale of
its own), and every y scale is fixed to its data with a margin and never collapses to one
value (a chart whose only y tick is "0" cannot be read)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controller.core.arrays import FloatArray
from server.charts_base import BOUND, CANDIDATE, MARK_SCALE, ChartDict, ChartSpec, line_series
from server.trends_data import STATES, TrendSpan, time_decimate

__all__ = ["ALARM_LABEL", "TrendChart", "alarm_rows", "readable_range", "trend_charts"]

ALARM_LABEL = "alarm"
ALARM_COLOR = "#d62728"
#: Points per alarm marker (a dotted vertical line from the chart's bottom to its top).
ALARM_DOTS = 15
_TIME_X: ChartDict = {"label": "time (this browser's time zone)", "scale": "x", "space": 70}
_MARK: ChartDict = {"auto": False, "range": (0.0, 1.0)}
#: No hover points: a series with no value under the cursor (the alarm, in-alarm and not-told
#: points are NaN in most windows) had its hover point drawn at the plot's top-left corner, a
#: stray red dot; the legend reads every value under the cursor.
_CURSOR: ChartDict = {"points": {"show": False}}
#: The residuals drawn (in milli-units: uPlot labels its ticks with at most 3 decimals, so a
#: residual of 0.003 deg on ticks 0.0005 apart read "0.003, 0.003, 0.002, 0.002...").
RESIDUALS = ("plant_residual_rms_deg_s", "fitted_residual_rms_deg_s", "loop_residual_rms_deg")


@dataclass(frozen=True)
class TrendChart:
    """One chart: its options, its columns (x first) and its scales for this data."""

    spec: ChartSpec
    data: tuple[FloatArray, ...]
    scales: dict[str, ChartDict]


def _points(label: str, color: str, size: float = 6.0) -> ChartDict:
    """Points only (no line, nothing filled under them)."""
    return {"label": label, "stroke": color, "width": 0, "scale": "y",
            "points": {"show": True, "size": size, "fill": color, "stroke": color},
            "spanGaps": False}


def _alarm_series() -> ChartDict:
    s = _points(ALARM_LABEL, ALARM_COLOR, 4.0)
    s["scale"] = MARK_SCALE
    return s


def _y_axis(label: str, scale: str = "y", side: int = 3) -> ChartDict:
    ax: ChartDict = {"label": label, "scale": scale, "space": 22, "size": 60}
    if side != 3:
        ax.update(side=side, grid={"show": False})
    return ax


def readable_range(vals: FloatArray, from_zero: bool = False) -> tuple[float, float]:
    """The finite values' range with a 10 % margin; never a single value (a flat trend of
    1.0 spans 0.95..1.05, of 0 spans -1..1), 0..1 with no value. `from_zero`: a quantity
    that cannot be negative (an rms, a time, a count) from 0 (a flat 0.003 then reads on
    ticks 0, 0.001, 0.002, 0.003, not on 0.003 three times)."""
    v = vals[np.isfinite(vals)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    if from_zero and lo >= 0.0:
        return 0.0, (1.15 * hi if hi > 0.0 else 1.0)
    span = hi - lo
    if span <= 1e-12 * max(abs(lo), abs(hi), 1.0):
        half = 0.05 * abs(lo) if lo != 0.0 else 1.0
        return lo - half, hi + half
    return lo - 0.1 * span, hi + 0.1 * span


def _merge_alarms(x: FloatArray, ys: list[FloatArray], alarms: list[float]
                  ) -> tuple[FloatArray, list[FloatArray], FloatArray]:
    """`ALARM_DOTS` rows per alarm time added (the series NaN there) and the marker column
    (NaN elsewhere); x kept sorted, a data row first where times are equal."""
    if not alarms:
        return x, ys, np.full(x.size, np.nan)
    ax = np.repeat(np.asarray(alarms, dtype=np.float64), ALARM_DOTS)
    am = np.tile(np.linspace(0.0, 1.0, ALARM_DOTS), len(alarms))
    order = np.argsort(np.concatenate((x, ax)), kind="stable")
    xs = np.concatenate((x, ax))[order]
    pad = np.full(ax.size, np.nan)
    out = [np.concatenate((y, pad))[order] for y in ys]
    mark = np.concatenate((np.full(x.size, np.nan), am))[order]
    return xs, out, mark


def _chart(key: str, title: str, series: list[ChartDict], axes: list[ChartDict],
           t: FloatArray, cols: list[FloatArray], span: TrendSpan, width_px: int,
           alarm_times: list[float], height: int, bands: object = None,
           extra_scales: tuple[str, ...] = (), from_zero: bool = False) -> TrendChart:
    x, ys = time_decimate(t, cols, span.t0_epoch_s, span.t1_epoch_s, width_px)
    x, ys, mark = _merge_alarms(x, ys, alarm_times)
    scales: dict[str, ChartDict] = {
        "x": {"time": True, "auto": False, "range": (span.t0_epoch_s, span.t1_epoch_s)},
        MARK_SCALE: _MARK}
    for name in ("y", *extra_scales):
        vals = [y for y, s in zip(ys, series, strict=True) if s.get("scale", "y") == name]
        lo, hi = readable_range(np.concatenate(vals) if vals else np.empty(0), from_zero)
        scales[name] = {"auto": False, "range": (lo, hi)}
    spec = ChartSpec(key=key, title=title, series=({"label": "time"}, *series, _alarm_series()),
                     scales=scales, axes=(_TIME_X, *axes), height=height, bands=bands,
                     cursor=_CURSOR)
    return TrendChart(spec, (x, *ys, mark), scales)


def trend_charts(span: TrendSpan, width_px: int) -> list[TrendChart]:
    """The residuals, each estimated part and the loop's health of `span`, each reduced to
    `width_px` (a chart draws at most two points per pixel)."""
    alarms = [a.epoch_s for a in span.alarms if not a.cleared]
    out: list[TrendChart] = []
    r = span.residual
    rt = r.get("t", np.empty(0))

    def col(cols: dict[str, FloatArray], name: str, n: int) -> FloatArray:
        return cols.get(name, np.full(n, np.nan))

    out.append(_chart(
        "trend_residuals", "Residuals: plant (measured rate - twin's answer) and loop "
        "(measured error - twin's predicted error)",
        [line_series("plant residual (mdeg/s rms)", CANDIDATE),
         line_series("plant residual, fitted parts (mdeg/s rms)", "#17becf", dash=(4, 3)),
         line_series("loop residual (mdeg rms)", "#e8871e", scale="mdeg")],
        [_y_axis("mdeg/s"), _y_axis("mdeg", "mdeg", 1)], rt,
        [1e3 * col(r, name, rt.size) for name in RESIDUALS], span, width_px, alarms, 250,
        extra_scales=("mdeg",), from_zero=True))
    p = span.parts
    pt = p.get("t", np.empty(0))
    for name in span.part_names():
        value = p[name]
        st = span.part_states.get(name, np.zeros(pt.size, dtype=np.int8))
        in_alarm = np.where(st == STATES.index("alarm"), value, np.nan)
        untold = np.where(st == STATES.index("not told"), value, np.nan)
        has_range = f"{name}_low" in p and bool(np.isfinite(p[f"{name}_low"]).any())
        series = [line_series(f"{name} (x)", CANDIDATE)]
        cols = [value]
        bands = None
        if has_range:
            series += [line_series("range high", "rgba(44,160,44,0.6)", width=1),
                       line_series("range low", "rgba(44,160,44,0.6)", width=1)]
            cols += [p[f"{name}_high"], p[f"{name}_low"]]
            bands = ({"series": (2, 3), "fill": "rgba(44,160,44,0.12)"},)
        series += [_points("in alarm", BOUND), _points("not told", "#999999", 4.0)]
        cols += [in_alarm, untold]
        title = (f"{name}: estimated, factor on the twin's (x)"
                 + (", with its allowed range" if has_range else
                    " (this trend carries no range)"))
        out.append(_chart(f"trend_{name}", title, series, [_y_axis("x")], pt, cols, span,
                          width_px, alarms, 230, bands))
    h = span.health
    ht = h.get("t", np.empty(0))
    out.append(_chart(
        "trend_health", "Loop health: tick compute p99 and skipped ticks per window",
        [line_series("compute p99 (us)", CANDIDATE),
         line_series("skipped ticks per window", "#9467bd", scale="ticks")],
        [_y_axis("us"), _y_axis("ticks", "ticks", 1)], ht,
        [col(h, "compute_p99_us", ht.size), col(h, "skipped_ticks", ht.size)], span,
        width_px, alarms, 230, extra_scales=("ticks",), from_zero=True))
    return out


def alarm_rows(span: TrendSpan, limit: int = 20) -> list[tuple[str, str, str]]:
    """(UTC time, part, text) of the range's alarms, newest first, at most `limit`."""
    import time

    rows = []
    for a in sorted(span.alarms, key=lambda a: -a.epoch_s)[:limit]:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(a.epoch_s)) + " UTC"
        rows.append((when, a.part + (" (cleared)" if a.cleared else ""), a.text))
    return rows
