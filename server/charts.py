"""Chart data (pure): analysis and experiment results -> uPlot data tuples and options.

No viser, no I/O: the app creates one uPlot per chart from `ChartSpec` once and afterwards only
assigns new `data` tuples built here. Frequency axes are logarithmic (uPlot `distr: 3`);
magnitudes are in dB, phases in degrees, times in seconds.

The charts by topic: `charts_base` (colours, `ChartSpec`, the curves), this module (the
Bode charts), `charts_time` (preview, steps, live), `charts_identify`, `charts_nyquist`;
everything is importable from here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controller.core.arrays import FloatArray
from server.charts_base import (
    ACTIVE,
    BOUND,
    CANDIDATE,
    DASH_ACTIVE,
    DASH_NO_DOB,
    GM_COLOR,
    HZ_AXIS,
    LOG_X,
    MARK_SCALE,
    MEASURED,
    NO_DOB,
    PLANT_POSITIONS,
    PM_COLOR,
    SPREAD_FLOOR,
    VERSION_INCRS,
    BodeCurves,
    ChartDict,
    ChartSpec,
    NyquistLoop,
    PlantCurves,
    band_edge,
    bode_spec,
    crossing_marks,
    db,
    dob_spec,
    freq_chart,
    line_series,
    marker_series,
    measured_points,
    ranged_scales,
    rgba_of,
    settled_scales,
    spread_band_db,
)
from server.charts_identify import (
    FIT,
    POSITION_COLORS,
    MeasuredCurve,
    identify_chart_specs,
    identify_data,
    points_series,
)
from server.charts_nyquist import (
    NYQUIST_FOOTER_PX,
    NYQUIST_HEADER_PX,
    NYQUIST_INSET_PX,
    NYQUIST_RADIUS,
    fmt_margin,
    nyquist_segments,
    nyquist_svg,
    open_loop_response,
)
from server.charts_time import (
    LIVE_CHARTS,
    LIVE_COLUMNS,
    LIVE_EMPTY_T,
    LIVE_WINDOW_S,
    PREVIEW_CHART,
    PREVIEW_SETTLE_FRAC,
    STEP_CHART,
    T_AXIS,
    live_data,
    live_scales,
    minmax_decimate,
    preview_data,
)

__all__ = [
    "ACTIVE",
    "BODE_CHARTS",
    "BOUND",
    "CANDIDATE",
    "DASH_ACTIVE",
    "DASH_NO_DOB",
    "FIT",
    "GM_COLOR",
    "GM_DOWN_LABEL",
    "GM_MARKS",
    "GM_UP_LABEL",
    "HZ_AXIS",
    "LIVE_CHARTS",
    "LIVE_COLUMNS",
    "LIVE_EMPTY_T",
    "LIVE_WINDOW_S",
    "LOOP_CURSOR",
    "LOOP_MAG_CHART",
    "LOOP_PHASE_CHART",
    "MARK_SCALE",
    "MEASURED",
    "NO_DOB",
    "NYQUIST_FOOTER_PX",
    "NYQUIST_HEADER_PX",
    "NYQUIST_INSET_PX",
    "NYQUIST_RADIUS",
    "PLANT_CHART",
    "PLANT_MODEL",
    "PLANT_POSITIONS",
    "PM_COLOR",
    "POSITION_COLORS",
    "PREVIEW_CHART",
    "PREVIEW_SETTLE_FRAC",
    "SMALL_DB_AXIS",
    "SPREAD_FLOOR",
    "STEP_CHART",
    "T_AXIS",
    "VERSION_INCRS",
    "Y_STEPS",
    "BodeCurves",
    "ChartSpec",
    "MarginMark",
    "MeasuredCurve",
    "NyquistLoop",
    "PlantCurves",
    "band_edge",
    "bode_data",
    "bode_spec",
    "crossing_marks",
    "db",
    "dob_spec",
    "fmt_hz",
    "fmt_margin",
    "freq_chart",
    "identify_chart_specs",
    "identify_data",
    "line_series",
    "live_data",
    "live_scales",
    "loop_bode_data",
    "loop_margins_html",
    "margin_marks",
    "marker_series",
    "measured_points",
    "minmax_decimate",
    "nyquist_segments",
    "nyquist_svg",
    "open_loop_response",
    "points_series",
    "preview_data",
    "ranged_scales",
    "rgba_of",
    "settled_scales",
    "spread_band_db",
]


# -- the classic Bode of the speed loop ----------------------------------------------------------

#: The two charts of the loop's Bode share one cursor (uPlot's cursor sync: hovering one shows
#: the same frequency on the other; web_assets/dashboard.js reads both there and labels the
#: margin markers) and one x grid (`loop_bode_data`), so one frequency axis.
LOOP_CURSOR: ChartDict = {"sync": {"key": "dt-loop-bode"}}
#: The magnitude chart marks at most this many phase crossovers (a conditionally stable loop
#: has a lower one, where a gain reduction destabilises, and an upper one).
GM_MARKS = 2
#: The y steps the Bode charts' fixed ranges are rounded out to (dB, deg): a candidate that
#: moves a curve a little keeps its chart's scales (a new range re-creates the chart).
Y_STEPS = {"y": 10.0, "deg": 45.0}
#: Tick steps of the loop's Bode axes (uPlot picks the first whose ticks are `space` px apart):
#: dB in tens, degrees in multiples of 15 (so -180 is a tick). The magnitude's ticks 16 px
#: apart: its ~180 dB over ~80 px had 3 ticks (-60, 0, 60) at 20 px; now 5 (every 40 dB).
_DB_INCRS = (10, 20, 40, 60, 100, 200)
_DEG_INCRS = (15, 30, 45, 90, 180, 360)


#: The gain-margin markers' legend names, as the verdict's headline names the two figures: up
#: where |L| < 1 at the -180 deg crossing, down where |L| > 1 (conditionally stable).
GM_UP_LABEL = "gain margin (up)"
GM_DOWN_LABEL = "gain-reduction margin (down)"


def _margin_line(label: str, color: str, scale: str = "y") -> ChartDict:
    """A margin marker: one vertical segment (two points at one frequency) from the reference
    (0 dB or -180 deg) to the curve, NaN elsewhere."""
    return {"label": label, "stroke": color, "width": 3.0, "scale": scale}


LOOP_MAG_CHART = bode_spec(
    "loop_mag",
    "Open loop L (speed loop): magnitude; gain margin = 0 dB - |L| where the phase is -180 deg",
    (line_series("|L| candidate", CANDIDATE, width=2.0), "cand.open_loop_db"),
    (line_series("|L| active", ACTIVE, dash=DASH_ACTIVE), "act.open_loop_db"),
    (line_series("0 dB line", "#555555", width=1.0), "ref.0"),
    (_margin_line(GM_UP_LABEL, GM_COLOR), "mark.gm1"),
    (_margin_line(GM_DOWN_LABEL, GM_COLOR), "mark.gm2"),
    axes=(HZ_AXIS, {"label": "dB", "scale": "y", "space": 16, "incrs": _DB_INCRS}),
    height=135,  # (with 125 below: Decide fits 1080 px over the E-STOP's strip)
    cursor=LOOP_CURSOR,
)
LOOP_PHASE_CHART = bode_spec(
    "loop_phase",
    "Open loop L (speed loop): phase; phase margin = phase + 180 deg where |L| = 0 dB",
    (line_series("phase candidate", CANDIDATE, width=2.0, scale="deg"), "cand.open_loop_phase_deg"),
    (line_series("phase active", ACTIVE, dash=DASH_ACTIVE, scale="deg"), "act.open_loop_phase_deg"),
    (line_series("-180 deg line", "#d62728", width=1.0, scale="deg"), "ref.-180"),
    (_margin_line("phase margin", PM_COLOR, scale="deg"), "mark.pm"),
    scales={"x": LOG_X["x"], "deg": {"auto": True}},
    axes=(HZ_AXIS, {"label": "deg", "scale": "deg", "space": 20, "incrs": _DEG_INCRS}),
    height=125,
    cursor=LOOP_CURSOR,
)
_LOOP_KEYS = (LOOP_MAG_CHART.key, LOOP_PHASE_CHART.key)


@dataclass(frozen=True)
class MarginMark:
    """Where a margin is read on the Bode: at `freq_hz`, from `start` (on the reference line
    for a phase margin, on |L| for a gain margin) to `end`; `value` = end - start (dB, deg)."""

    freq_hz: float
    start: float
    end: float

    @property
    def value(self) -> float:
        return self.end - self.start


def margin_marks(c: BodeCurves) -> tuple[tuple[MarginMark, ...], MarginMark | None]:
    """The gain-margin marks (the reported GM's crossing first, then the others by frequency,
    at most GM_MARKS) and the phase-margin mark (the reported PM's crossing) of the drawn
    loop, from its refined crossings (`NyquistLoop`): the same numbers as the verdict."""
    loop = c.loop
    if loop is None:
        return (), None
    gms = -20.0 * np.log10(np.abs(loop.phase_crossings))
    finite = [i for i in range(len(gms)) if np.isfinite(gms[i])]
    # The headline's two figures (issue 33): the gain margin up, the smallest over the
    # crossings where |L| < 1, then the gain-reduction margin down, the smallest over those
    # where |L| > 1 (a conditionally stable loop); each drawn in the column named for it.
    up = [i for i in finite if gms[i] >= 0.0]
    down = [i for i in finite if gms[i] < 0.0]
    picks = ([min(up, key=lambda i: gms[i])] if up else []) + \
        ([max(down, key=lambda i: gms[i])] if down else [])
    gm = tuple(MarginMark(float(loop.phase_crossover_hz[i]), -float(gms[i]), 0.0)
               for i in picks)
    pm = None
    if len(loop.gain_crossings):
        pms = np.degrees(np.angle(loop.gain_crossings)) % 360.0 - 180.0
        i = int(np.argmin(np.abs(pms - loop.phase_margin_deg)))
        f = float(loop.gain_crossover_hz[i])
        drawn = float(np.interp(np.log(f), np.log(c.freq_hz), c.open_loop_phase_deg))
        # The -180 + k 360 line the drawn (unwrapped) phase is read against.
        ref = -180.0 + 360.0 * round((drawn - pms[i] + 180.0) / 360.0)
        pm = MarginMark(f, ref, ref + float(pms[i]))
    return gm, pm


def loop_bode_data(cand: BodeCurves, active: BodeCurves | None,
                   ) -> tuple[tuple[FloatArray, ...], tuple[FloatArray, ...]]:
    """The data of LOOP_MAG_CHART and LOOP_PHASE_CHART, on one x grid: the curves' grid with
    each margin mark's frequency in it twice (the mark's two points; the curves are
    interpolated there, linearly in log f). A mark's column is NaN but at its two points."""
    act = active if active is not None and active.freq_hz.shape == cand.freq_hz.shape else cand
    gm, pm = margin_marks(cand)
    marks = [*gm, *([pm] if pm is not None else [])]
    f0 = cand.freq_hz
    extra = np.array([m.freq_hz for m in marks for _ in (0, 1)], dtype=np.float64)
    x = np.sort(np.concatenate([f0, extra]))
    lx, lf = np.log(x), np.log(f0)

    def on_x(y: FloatArray) -> FloatArray:
        return np.asarray(np.interp(lx, lf, y), dtype=np.float64)

    def mark_column(m: MarginMark | None) -> FloatArray:
        col = np.full(x.size, np.nan)
        if m is not None:
            i = int(np.searchsorted(x, m.freq_hz, side="left"))
            col[i], col[i + 1] = m.start, m.end
        return col

    # Column 1 the gain margin up, column 2 the gain-reduction margin down (their legends).
    gm_cols = [mark_column(next((m for m in gm if (m.value < 0) == down), None))
               for down in (False, True)]
    mag = (x, on_x(cand.open_loop_db), on_x(act.open_loop_db), np.zeros(x.size), *gm_cols)
    phase = (x, on_x(cand.open_loop_phase_deg), on_x(act.open_loop_phase_deg),
             np.full(x.size, -180.0), mark_column(pm))
    return mag, phase


def fmt_hz(f: float) -> str:
    return f"{f:.3g} Hz"


def loop_margins_html(c: BodeCurves) -> str:
    """One line over the loop's Bode: every margin the markers show, with its frequency."""
    gm, pm = margin_marks(c)
    parts = []
    both = any(m.value < 0 for m in gm) and any(m.value >= 0 for m in gm)
    named: set[str] = set()
    for m in gm:
        # Both positive and named (issue 33): up where |L| < 1, down (a conditionally stable
        # loop: a gain reduction destabilises) where |L| > 1.
        down = m.value < 0
        what = "gain-reduction margin" if down else "gain margin"
        value = (f"{-m.value:.1f} dB down" if down else
                 f"{m.value:.1f} dB up" if both else f"{m.value:.1f} dB")
        label = what if what not in named else "another -180 deg crossing"
        named.add(what)
        parts.append(f"<span class='dt-gm' style='color:{GM_COLOR}'><b>{label}</b> "
                     f"{value} at {fmt_hz(m.freq_hz)}</span>")
    if not gm:
        parts.append(f"<span class='dt-gm' style='color:{GM_COLOR}'><b>gain margin</b> none "
                     "(the phase never crosses -180 deg)</span>")
    if pm is not None:
        parts.append(f"<span class='dt-pm' style='color:{PM_COLOR}'><b>phase margin</b> "
                     f"{pm.value:.1f} deg at {fmt_hz(pm.freq_hz)}</span>")
    else:
        parts.append(f"<span class='dt-pm' style='color:{PM_COLOR}'><b>phase margin</b> none "
                     "(|L| never crosses 0 dB)</span>")
    return ("<div class='dt-loop-margins' style='font-size:13px'>"
            + " &middot; ".join(parts) + "</div>")


PLANT_MODEL = "#34495e"

#: The plant itself: the model the gate judges on, and the measured responses with their
#: spread as a band between the "+spread" and "-spread" series.
_POSITION_COLORS = ("#8c564b", "#e377c2", "#17becf", "#bcbd22")

PLANT_CHART = bode_spec(
    "plant",
    "Plant u -> speed: model and measured (band: measured |H| (1 +- spread)); each position, "
    "the spread between positions (max - min, dB) and where they diverge (> 1 dB)",
    (line_series("|M P| model", PLANT_MODEL), "plant.model_db"),
    (measured_points("|H| measured", MEASURED), "plant.measured_db"),
    (band_edge("|H| (1 + spread)"), "plant.upper_db"),
    (band_edge("|H| (1 - spread)"), "plant.lower_db"),
    (line_series("phase model", PLANT_MODEL, dash=(2, 3), width=1.0, scale="deg"),
     "plant.model_phase_deg"),
    (measured_points("phase measured", "#7fbf7f", scale="deg"), "plant.measured_phase_deg"),
    *((measured_points(f"|H| position {i + 1}", c), f"plant.pos{i + 1}_db")
      for i, c in enumerate(_POSITION_COLORS[:PLANT_POSITIONS])),
    (measured_points("spread between positions (dB)", "#d62728"), "plant.spread_db"),
    (marker_series("responses diverge (> 1 dB)", "#d62728"), "plant.divergence_marks"),
    scales={**LOG_X, "deg": {"auto": True}, MARK_SCALE: {"auto": False, "range": (0.0, 1.0)}},
    axes=(
        HZ_AXIS,
        {"label": "dB", "scale": "y"},
        {"label": "deg", "scale": "deg", "side": 1, "grid": {"show": False}},
    ),
)

#: The dB axis of a short chart (~50 px of plot): ticks every 10 dB, at least 14 px apart
#: (uPlot's default 30 px left |S| with ticks at 0 and -100 only, the rejection at 0 and 50;
#: 5 dB steps at 10 px were crowded), on a range rounded out to 10 dB (SMALL_DB_STEP) so that
#: it holds 4 ticks or more (the rejection's -5..20 had only 0, 10, 20).
SMALL_DB_AXIS = {"label": "dB", "scale": "y", "space": 14, "incrs": (10, 20, 50, 100)}
SMALL_DB_STEP = 10.0

BODE_CHARTS: tuple[ChartSpec, ...] = (
    LOOP_MAG_CHART,
    LOOP_PHASE_CHART,
    # Titles say what each curve is; the article's equation numbers come after, named as such
    # ("(15) vs (18)" alone read as a riddle).
    dob_spec("closed_loop", "Closed loop, reference r -> speed w: candidate with and without "
             "the DOB, active (article eqs. 15, 18)", "closed_dob_db",
             "closed_nodob_db", ("with DOB", "without DOB", "active")),
    dob_spec("disturbance", "Disturbance d -> speed w: candidate with and without the DOB, "
             "active (article eqs. 16, 18)", "dist_dob_db",
             "dist_nodob_db", ("with DOB", "without DOB", "active")),
    dob_spec("noise", "Sensor noise zeta -> speed w: candidate with and without the DOB, active "
             "(article eqs. 17, 18)", "noise_dob_db", "noise_nodob_db",
             ("with DOB", "without DOB", "active")),
    bode_spec(
        "rejection",
        "DOB rejection gain: |tracking error without DOB / with DOB| (article eq. 23), > 0 dB "
        "where the DOB helps, < 0 dB where it costs (waterbed)",
        (line_series("candidate", CANDIDATE), "cand.rejection_db"),
        (line_series("active", ACTIVE, dash=DASH_ACTIVE), "act.rejection_db"),
        height=105,
        axes=(HZ_AXIS, SMALL_DB_AXIS),
        y_step=SMALL_DB_STEP, y_clip=(-20.0, 20.0),  # the waterbed (-2 dB) legible
    ),
    bode_spec(
        "sensitivity",
        "Sensitivity |S| and complementary |T| at the plant input (whole servo dashed)",
        (line_series("|S| candidate", CANDIDATE), "cand.s_db"),
        (line_series("|T| candidate", NO_DOB), "cand.t_db"),
        (line_series("|S| whole servo", CANDIDATE, dash=DASH_NO_DOB, width=1.0), "cand.s_full_db"),
        (line_series("|T| whole servo", NO_DOB, dash=DASH_NO_DOB, width=1.0), "cand.t_full_db"),
        (line_series("|S| active", ACTIVE, dash=DASH_ACTIVE), "act.s_db"),
        height=110,
        axes=(HZ_AXIS, SMALL_DB_AXIS),
        y_step=SMALL_DB_STEP, y_clip=(-20.0, 20.0),  # the peak (~3 dB) legible
    ),
    bode_spec(
        "small_gain",
        "Small gain: |Q| vs 1/|Delta|",
        (line_series("|Q| candidate", CANDIDATE), "cand.q_db"),
        (line_series("|Q| active", ACTIVE, dash=DASH_ACTIVE), "act.q_db"),
        (line_series("1/|Delta| bound", BOUND, dash=DASH_NO_DOB), "cand.inv_delta_db"),
        (line_series("1/|Delta| measured", MEASURED, width=2.0), "cand.inv_delta_measured_db"),
    ),
    PLANT_CHART,
)
_BODE_BY_KEY = {spec.key: spec for spec in BODE_CHARTS}


def bode_data(key: str, cand: BodeCurves, active: BodeCurves | None) -> tuple[FloatArray, ...]:
    """The uPlot data tuple of chart `key`; the active curves must share the candidate's grid.
    A curve the configuration does not have (no measured response, say) is all NaN, and a
    curve is NaN where it has no value: no stand-in values (the charts' y scales are fixed
    from the finite values, `ranged_scales`, so NaN draws nothing and upsets no scale). The
    plant chart ("plant.<field>" columns) draws `cand.plant` on its own grid; the loop's
    Bode charts are `loop_bode_data`."""
    if key in _LOOP_KEYS:
        return loop_bode_data(cand, active)[_LOOP_KEYS.index(key)]
    act = active if active is not None and active.freq_hz.shape == cand.freq_hz.shape else cand
    spec = _BODE_BY_KEY[key]
    x = cand.freq_hz
    sources: ChartDict = {"cand": cand, "act": act}
    if any(c.startswith("plant.") for c in spec.columns):
        if cand.plant is None:
            raise ValueError(f"chart {key!r}: BodeCurves.plant is None (no plant curves)")
        x = cand.plant.freq_hz
        sources["plant"] = cand.plant
    nan = np.full_like(x, np.nan)
    cols: list[FloatArray] = []
    for column in spec.columns:
        which, name = column.split(".")
        y = getattr(sources[which], name)
        cols.append(nan if y is None else np.asarray(y, dtype=np.float64))
    return (x, *cols)
