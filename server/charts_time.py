"""Time-domain charts (pure): the preview and step charts, the live traces and their
decimation (`server.charts`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from controller.core.arrays import FloatArray
from server.charts_base import (
    ACTIVE,
    CANDIDATE,
    DASH_ACTIVE,
    DASH_NO_DOB,
    NO_DOB,
    VERSION_INCRS,
    ChartDict,
    ChartSpec,
    line_series,
)

__all__ = [
    "LIVE_CHARTS",
    "LIVE_COLUMNS",
    "LIVE_EMPTY_T",
    "LIVE_WINDOW_S",
    "PREVIEW_CHART",
    "PREVIEW_SETTLE_FRAC",
    "STEP_CHART",
    "T_AXIS",
    "live_data",
    "live_scales",
    "minmax_decimate",
    "preview_data",
]


# -- time domain --------------------------------------------------------------------------------


def minmax_decimate(
    x: FloatArray, ys: Sequence[FloatArray], max_points: int
) -> tuple[FloatArray, list[FloatArray]]:
    """Reduce to <= max_points samples keeping each bucket's min and max (spikes survive).

    Buckets are equal index ranges; each yields its first x twice with the (min, max) of every
    series, so the drawn envelope matches the full-rate trace at chart resolution. The buckets
    cover all but fewer than one bucket's oldest samples (a bucket size rounded down dropped
    up to a third of a series a little longer than `max_points`: a 26 s comparison drew from
    its 6.3 s on).
    """
    n = len(x)
    if n <= max_points or max_points < 4:
        return np.asarray(x, dtype=np.float64), [np.asarray(y, dtype=np.float64) for y in ys]
    size = -(-n // (max_points // 2))  # ceil: at most max_points // 2 buckets
    buckets = n // size
    m = buckets * size
    start = n - m  # keep the newest samples aligned to the end
    xb = np.asarray(x[start:], dtype=np.float64).reshape(buckets, size)
    x_out = np.repeat(xb[:, 0], 2)
    x_out[1::2] = xb[:, -1]
    out: list[FloatArray] = []
    for y in ys:
        yb = np.asarray(y[start:], dtype=np.float64).reshape(buckets, size)
        lo = yb.min(axis=1)
        hi = yb.max(axis=1)
        # Order each pair by where the extremes occur so the line does not zigzag backwards.
        lo_first = yb.argmin(axis=1) <= yb.argmax(axis=1)
        pair = np.empty(2 * buckets)
        pair[0::2] = np.where(lo_first, lo, hi)
        pair[1::2] = np.where(lo_first, hi, lo)
        out.append(pair)
    return x_out, out


T_AXIS: ChartDict = {"label": "s", "scale": "x"}
_LIN_X: dict[str, ChartDict] = {"x": {"time": False, "auto": True}, "y": {"auto": True}}

PREVIEW_CHART = ChartSpec(
    key="preview",
    title="Preview: position error, simulated test",
    series=(
        {"label": "t (s)"},
        line_series("candidate", CANDIDATE),
        line_series("active", ACTIVE, dash=DASH_ACTIVE),
        line_series("candidate, DOB off", NO_DOB, dash=DASH_NO_DOB),
    ),
    scales=_LIN_X,
    axes=(T_AXIS, {"label": "deg", "scale": "y", "space": 14}),
)
#: The preview's y scale is of its settled part: from this fraction of its time span on
#: (`charts.settled_scales`; the start-up before it is said when it runs off the scale).
PREVIEW_SETTLE_FRAC = 0.15


STEP_CHART = ChartSpec(
    key="steps",
    title="Linear model: 1 deg reference step (left) and 1 deg/s load-disturbance step (right)",
    series=(
        {"label": "t (s)"},
        line_series("ref step candidate", CANDIDATE),
        line_series("ref step active", ACTIVE, dash=DASH_ACTIVE),
        line_series("load step candidate", NO_DOB, scale="d"),
        line_series("load step active", ACTIVE, dash=DASH_NO_DOB, scale="d"),
    ),
    scales={**_LIN_X, "d": {"auto": True}},
    axes=(T_AXIS, {"label": "deg", "scale": "y"},
          {"label": "deg (load step)", "scale": "d", "side": 1, "grid": {"show": False}}),
)


def preview_data(
    t_s: FloatArray, cand_error_deg: FloatArray, active_error_deg: FloatArray | None,
    no_dob_error_deg: FloatArray | None = None, max_points: int = 1500,
) -> tuple[FloatArray, ...]:
    """The preview chart's columns: t, the candidate's error, the active's, the candidate's
    with the DOB off (NaN when a run is missing)."""
    act = active_error_deg if active_error_deg is not None else np.full_like(t_s, np.nan)
    off = no_dob_error_deg if no_dob_error_deg is not None else np.full_like(t_s, np.nan)
    n = min(len(t_s), len(cand_error_deg), len(act), len(off))
    x, ys = minmax_decimate(t_s[:n], [cand_error_deg[:n], act[:n], off[:n]], max_points)
    return (x, *ys)


#: The time axis of a live chart before any sample arrived, s.
LIVE_EMPTY_T = (-1.0, 0.0)
#: The live charts' time window when the page opens, s (the Window slider's initial value).
LIVE_WINDOW_S = 10.0


def live_scales(window_s: float) -> dict[str, ChartDict]:
    """The scales of a live chart showing the last `window_s` seconds: x fixed at
    [-window_s, 0] (the newest sample at 0), y and the config version auto-ranged.

    The x range is fixed, not auto: viser's uPlot component keeps an auto x scale's bounds
    relative to the previous data's range, and a chart drawn once while its tab was hidden (or
    before its first data) kept 0..1 s for good, one sample of the window on the axis
    (issue 22)."""
    return {"x": {"time": False, "auto": False, "range": (-float(window_s), 0.0)},
            "y": {"auto": True}, "ver": {"auto": True}}


def _live_spec(key: str, title: str, unit: str, *series: tuple[ChartDict, str]
               ) -> ChartSpec:
    """A live chart; each series comes with its ring column; the config version comes last."""
    version = line_series("config v", "#8e44ad", width=1.0, scale="ver")
    return ChartSpec(
        key=key,
        title=title,
        series=({"label": "t (s)"}, *(s for s, _ in series), version),
        scales=live_scales(LIVE_WINDOW_S),
        axes=(
            T_AXIS,
            # Ticks 14 px apart at least (uPlot's 30 px left the position error's 60 px with
            # one tick, "0").
            {"label": unit, "scale": "y", "space": 14},
            {"label": "config v", "scale": "ver", "side": 1, "grid": {"show": False},
             "incrs": VERSION_INCRS},
        ),
        height=170,
        columns=tuple(c for _, c in series),
    )


#: Live charts; the last series of each is the active config version (a step marks a change).
LIVE_CHARTS: tuple[ChartSpec, ...] = (
    _live_spec("error", "Position error", "deg", (line_series("error", "#c0392b"), "error_deg")),
    _live_spec(
        "speed",
        "Load speed vs speed reference",
        "deg/s",
        (line_series("speed w", CANDIDATE), "speed_deg_s"),
        (line_series("reference r", NO_DOB, dash=DASH_NO_DOB), "speed_ref_deg_s"),
    ),
    _live_spec("d_hat", "Disturbance estimate d_hat", "deg/s",
               (line_series("d_hat", "#16a085"), "d_hat_deg_s")),
    _live_spec("command", "Speed command u", "deg/s",
               (line_series("u", "#34495e"), "command_deg_s")),
)

#: Ring-buffer columns used by each live chart, in series order (before the version).
LIVE_COLUMNS: dict[str, tuple[str, ...]] = {spec.key: spec.columns for spec in LIVE_CHARTS}


def live_data(
    t_s: FloatArray, columns: dict[str, FloatArray], version: FloatArray, max_points: int = 1000
) -> dict[str, tuple[FloatArray, ...]]:
    """Per live chart, its decimated data with time relative to the newest sample (<= 0)."""
    if len(t_s) == 0:
        return {spec.key: spec.placeholder(LIVE_EMPTY_T) for spec in LIVE_CHARTS}
    t_rel = t_s - t_s[-1]
    names = [c for cols in LIVE_COLUMNS.values() for c in cols]
    x, ys = minmax_decimate(t_rel, [columns[c] for c in names] + [version], max_points)
    by_name = dict(zip([*names, "version"], ys, strict=True))
    return {
        key: (x, *(by_name[c] for c in cols), by_name["version"])
        for key, cols in LIVE_COLUMNS.items()
    }
