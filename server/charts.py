"""Chart data (pure): analysis and experiment results -> uPlot data tuples and options.

No viser, no I/O: the app creates one uPlot per chart from `ChartSpec` once and afterwards only
assigns new `data` tuples built here. Frequency axes are logarithmic (uPlot `distr: 3`);
magnitudes are in dB, phases in degrees, times in seconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = [
    "BODE_CHARTS",
    "LIVE_CHARTS",
    "PREVIEW_CHART",
    "BodeCurves",
    "ChartSpec",
    "bode_data",
    "db",
    "live_data",
    "minmax_decimate",
    "preview_data",
]

FloatArray = npt.NDArray[np.float64]

CANDIDATE = "#1f77b4"
ACTIVE = "#9aa5b1"
NO_DOB = "#e8871e"
BOUND = "#d62728"
MEASURED = "#2ca02c"


def db(x: npt.ArrayLike) -> FloatArray:
    """20 log10 |x|, with zeros clipped to -300 dB (uPlot cannot draw -inf)."""
    mag = np.abs(np.asarray(x))
    return np.asarray(20.0 * np.log10(np.maximum(mag, 1e-15)), dtype=np.float64)


@dataclass(frozen=True)
class BodeCurves:
    """Frequency responses of one configuration on one grid (dB / deg), for drawing."""

    freq_hz: FloatArray
    open_loop_db: FloatArray
    open_loop_phase_deg: FloatArray
    closed_dob_db: FloatArray
    closed_nodob_db: FloatArray
    dist_dob_db: FloatArray
    dist_nodob_db: FloatArray
    noise_dob_db: FloatArray
    noise_nodob_db: FloatArray
    q_db: FloatArray
    rejection_db: FloatArray | None = None
    inv_delta_db: FloatArray | None = None
    inv_delta_measured_db: FloatArray | None = None


@dataclass(frozen=True)
class ChartSpec:
    """Static uPlot options of one chart (series count and order never change)."""

    key: str
    title: str
    series: tuple[dict[str, Any], ...]
    scales: dict[str, dict[str, Any]]
    axes: tuple[dict[str, Any], ...]
    height: int = 220
    extra: dict[str, Any] = field(default_factory=dict)


def _line(label: str, stroke: str, *, dash: Sequence[float] = (), width: float = 1.5,
          scale: str = "y") -> dict[str, Any]:
    s: dict[str, Any] = {"label": label, "stroke": stroke, "width": width, "scale": scale}
    if dash:
        s["dash"] = tuple(dash)
    return s


_LOG_X: dict[str, dict[str, Any]] = {
    "x": {"time": False, "distr": 3, "log": 10},
    "y": {"auto": True},
}


def _bode_spec(key: str, title: str, *series: dict[str, Any], y_label: str = "dB",
               scales: dict[str, dict[str, Any]] | None = None,
               axes: tuple[dict[str, Any], ...] | None = None) -> ChartSpec:
    return ChartSpec(
        key=key,
        title=title,
        series=({"label": "f (Hz)"}, *series),
        scales=scales or _LOG_X,
        axes=axes or ({"label": "Hz", "scale": "x"}, {"label": y_label, "scale": "y"}),
    )


BODE_CHARTS: tuple[ChartSpec, ...] = (
    _bode_spec(
        "open_loop",
        "Open loop Cv M P (speed loop)",
        _line("|L| candidate", CANDIDATE),
        _line("|L| active", ACTIVE, dash=(6, 4)),
        _line("phase candidate", CANDIDATE, dash=(2, 3), width=1.0, scale="deg"),
        _line("phase active", ACTIVE, dash=(2, 3), width=1.0, scale="deg"),
        scales={**_LOG_X, "deg": {"auto": True}},
        axes=(
            {"label": "Hz", "scale": "x"},
            {"label": "dB", "scale": "y"},
            {"label": "deg", "scale": "deg", "side": 1, "grid": {"show": False}},
        ),
    ),
    _bode_spec(
        "closed_loop",
        "Closed loop r -> w (15) vs (18)",
        _line("with DOB", CANDIDATE),
        _line("without DOB", NO_DOB, dash=(4, 3)),
        _line("active", ACTIVE, dash=(6, 4)),
    ),
    _bode_spec(
        "disturbance",
        "Disturbance d -> w: (16) with DOB vs (18) without",
        _line("(16) with DOB", CANDIDATE),
        _line("(18) without DOB", NO_DOB, dash=(4, 3)),
        _line("(16) active", ACTIVE, dash=(6, 4)),
    ),
    _bode_spec(
        "noise",
        "Noise zeta -> w (17)",
        _line("(17) with DOB", CANDIDATE),
        _line("(18) without DOB", NO_DOB, dash=(4, 3)),
        _line("(17) active", ACTIVE, dash=(6, 4)),
    ),
    _bode_spec(
        "rejection",
        "DOB rejection gain |E_without / E_with| (23): > 0 dB where the DOB helps",
        _line("candidate", CANDIDATE),
        _line("active", ACTIVE, dash=(6, 4)),
    ),
    _bode_spec(
        "small_gain",
        "Small gain: |Q| vs 1/|Delta|",
        _line("|Q| candidate", CANDIDATE),
        _line("|Q| active", ACTIVE, dash=(6, 4)),
        _line("1/|Delta| bound", BOUND, dash=(4, 3)),
        _line("1/|Delta| measured", MEASURED, width=2.0),
    ),
)


def bode_data(key: str, cand: BodeCurves, active: BodeCurves | None) -> tuple[FloatArray, ...]:
    """The uPlot data tuple of chart `key`; the active curves must share the candidate's grid."""
    act = active if active is not None and active.freq_hz.shape == cand.freq_hz.shape else cand
    nan = np.full_like(cand.freq_hz, np.nan)
    cols: tuple[FloatArray, ...]
    if key == "open_loop":
        cols = (cand.open_loop_db, act.open_loop_db, cand.open_loop_phase_deg,
                act.open_loop_phase_deg)
    elif key == "closed_loop":
        cols = (cand.closed_dob_db, cand.closed_nodob_db, act.closed_dob_db)
    elif key == "disturbance":
        cols = (cand.dist_dob_db, cand.dist_nodob_db, act.dist_dob_db)
    elif key == "noise":
        cols = (cand.noise_dob_db, cand.noise_nodob_db, act.noise_dob_db)
    elif key == "rejection":
        cols = (
            cand.rejection_db if cand.rejection_db is not None else nan,
            act.rejection_db if act.rejection_db is not None else nan,
        )
    elif key == "small_gain":
        bound = cand.inv_delta_db if cand.inv_delta_db is not None else nan
        meas = cand.inv_delta_measured_db if cand.inv_delta_measured_db is not None else nan
        cols = (cand.q_db, act.q_db, bound, meas)
    else:
        raise KeyError(key)
    return (cand.freq_hz, *(np.asarray(c, dtype=np.float64) for c in cols))


# -- time domain --------------------------------------------------------------------------------


def minmax_decimate(
    x: FloatArray, ys: Sequence[FloatArray], max_points: int
) -> tuple[FloatArray, list[FloatArray]]:
    """Reduce to <= max_points samples keeping each bucket's min and max (spikes survive).

    Buckets are equal index ranges; each yields its first x twice with the (min, max) of every
    series, so the drawn envelope matches the full-rate trace at chart resolution.
    """
    n = len(x)
    if n <= max_points or max_points < 4:
        return np.asarray(x, dtype=np.float64), [np.asarray(y, dtype=np.float64) for y in ys]
    buckets = max_points // 2
    size = n // buckets
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


_T_AXIS = {"label": "s", "scale": "x"}
_LIN_X: dict[str, dict[str, Any]] = {"x": {"time": False, "auto": True}, "y": {"auto": True}}

PREVIEW_CHART = ChartSpec(
    key="preview",
    title="Preview: position error, simulated test",
    series=(
        {"label": "t (s)"},
        _line("candidate", CANDIDATE),
        _line("active", ACTIVE, dash=(6, 4)),
    ),
    scales=_LIN_X,
    axes=(_T_AXIS, {"label": "deg", "scale": "y"}),
)


def preview_data(
    t_s: FloatArray, cand_error_deg: FloatArray, active_error_deg: FloatArray | None,
    max_points: int = 1500,
) -> tuple[FloatArray, ...]:
    act = active_error_deg if active_error_deg is not None else np.full_like(t_s, np.nan)
    n = min(len(t_s), len(cand_error_deg), len(act))
    x, ys = minmax_decimate(t_s[:n], [cand_error_deg[:n], act[:n]], max_points)
    return (x, *ys)


def _live_spec(key: str, title: str, unit: str, *series: dict[str, Any]) -> ChartSpec:
    return ChartSpec(
        key=key,
        title=title,
        series=({"label": "t (s)"}, *series, _line("config v", "#8e44ad", width=1.0,
                                                     scale="ver")),
        scales={**_LIN_X, "ver": {"auto": True}},
        axes=(
            _T_AXIS,
            {"label": unit, "scale": "y"},
            {"label": "config v", "scale": "ver", "side": 1, "grid": {"show": False}},
        ),
        height=170,
    )


#: Live charts; the last series of each is the active config version (a step marks a change).
LIVE_CHARTS: tuple[ChartSpec, ...] = (
    _live_spec("error", "Position error", "deg", _line("error", "#c0392b")),
    _live_spec(
        "speed",
        "Load speed vs speed reference",
        "deg/s",
        _line("speed w", CANDIDATE),
        _line("reference r", NO_DOB, dash=(4, 3)),
    ),
    _live_spec("d_hat", "Disturbance estimate d_hat", "deg/s", _line("d_hat", "#16a085")),
    _live_spec("command", "Speed command u", "deg/s", _line("u", "#34495e")),
)

#: Ring-buffer columns used by each live chart, in series order.
LIVE_COLUMNS: dict[str, tuple[str, ...]] = {
    "error": ("error_deg",),
    "speed": ("speed_deg_s", "speed_ref_deg_s"),
    "d_hat": ("d_hat_deg_s",),
    "command": ("command_deg_s",),
}


def live_data(
    t_s: FloatArray, columns: dict[str, FloatArray], version: FloatArray, max_points: int = 1000
) -> dict[str, tuple[FloatArray, ...]]:
    """Per live chart, its decimated data with time relative to the newest sample (<= 0)."""
    if len(t_s) == 0:
        z = np.zeros(2)
        empty: dict[str, tuple[FloatArray, ...]] = {}
        for spec in LIVE_CHARTS:
            empty[spec.key] = (np.array([-1.0, 0.0]), *([z] * (len(spec.series) - 1)))
        return empty
    t_rel = t_s - t_s[-1]
    names = [c for cols in LIVE_COLUMNS.values() for c in cols]
    x, ys = minmax_decimate(t_rel, [columns[c] for c in names] + [version], max_points)
    by_name = dict(zip([*names, "version"], ys, strict=True))
    return {
        key: (x, *(by_name[c] for c in cols), by_name["version"])
        for key, cols in LIVE_COLUMNS.items()
    }
