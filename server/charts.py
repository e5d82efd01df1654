"""Chart data (pure): analysis and experiment results -> uPlot data tuples and options.

No viser, no I/O: the app creates one uPlot per chart from `ChartSpec` once and afterwards only
assigns new `data` tuples built here. Frequency axes are logarithmic (uPlot `distr: 3`);
magnitudes are in dB, phases in degrees, times in seconds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from controller.core.arrays import ComplexArray, FloatArray

__all__ = [
    "BODE_CHARTS",
    "LIVE_CHARTS",
    "PLANT_CHART",
    "PREVIEW_CHART",
    "BodeCurves",
    "ChartSpec",
    "MeasuredCurve",
    "NyquistLoop",
    "PlantCurves",
    "bode_data",
    "db",
    "identify_chart_specs",
    "identify_data",
    "live_data",
    "loop_bode_data",
    "loop_margins_html",
    "margin_marks",
    "minmax_decimate",
    "nyquist_svg",
    "preview_data",
    "ranged_scales",
    "spread_band_db",
]


CANDIDATE = "#1f77b4"
ACTIVE = "#9aa5b1"
NO_DOB = "#e8871e"
BOUND = "#d62728"
MEASURED = "#2ca02c"
PM_COLOR = "#2ca02c"
GM_COLOR = "#9467bd"


def db(x: npt.ArrayLike) -> FloatArray:
    """20 log10 |x|, with zeros clipped to -300 dB (uPlot cannot draw -inf)."""
    mag = np.abs(np.asarray(x))
    return np.asarray(20.0 * np.log10(np.maximum(mag, 1e-15)), dtype=np.float64)


def _rgba(hex_color: str, alpha: float) -> str:
    r, g, b = (int(hex_color[i:i + 2], 16) for i in (1, 3, 5))
    return f"rgba({r},{g},{b},{alpha})"


@dataclass(frozen=True)
class NyquistLoop:
    """One open loop for the Nyquist view: L on the grid of its BodeCurves and the points,
    refined between grid points, where its margins are read (python-control's rules pick
    the reported PM and GM among them)."""

    response: ComplexArray
    gain_crossover_hz: FloatArray
    """Every |L| = 1 crossing (the phase margin is read there)."""
    gain_crossings: ComplexArray
    """L at those frequencies (on the unit circle)."""
    phase_crossover_hz: FloatArray
    """Every crossing of the negative real axis (the gain margin is read there)."""
    phase_crossings: ComplexArray
    phase_margin_deg: float
    """The reported PM (smallest |PM|; inf without a gain crossover)."""
    gain_margin_db: float
    """The reported GM (closest to 0 dB; inf without a phase crossover)."""


@dataclass(frozen=True)
class PlantCurves:
    """The plant u -> load rate for drawing: the plant knowledge's model M P and its measured
    responses with their spread, in the continuous basis, on one grid (the measured points
    merged in). Measured columns are NaN where no response has a point; with several
    responses a point shows their mean (dB, deg) and the band their envelope."""

    freq_hz: FloatArray
    model_db: FloatArray
    model_phase_deg: FloatArray
    measured_db: FloatArray
    measured_phase_deg: FloatArray
    upper_db: FloatArray
    """max over responses of 20 log10(|H| (1 + spread))."""
    lower_db: FloatArray
    """min over responses of 20 log10(|H| max(1 - spread, SPREAD_FLOOR))."""
    n_measured: int = 0
    positions_db: tuple[FloatArray, ...] = ()
    """20 log10 |H| of each of the first `PLANT_POSITIONS` responses (one per position)."""
    spread_db: FloatArray | None = None
    """The spread between the responses, max - min |H| in dB (`PositionSpread.mag_db`), on
    the band they share; None with fewer than two responses."""
    divergence_hz: float | None = None
    """Where the responses part by more than 1 dB (`PositionSpread.divergence_hz`)."""

    def _position(self, i: int) -> FloatArray | None:
        return self.positions_db[i] if i < len(self.positions_db) else None

    @property
    def pos1_db(self) -> FloatArray | None:
        return self._position(0)

    @property
    def pos2_db(self) -> FloatArray | None:
        return self._position(1)

    @property
    def pos3_db(self) -> FloatArray | None:
        return self._position(2)

    @property
    def pos4_db(self) -> FloatArray | None:
        return self._position(3)

    @property
    def divergence_marks(self) -> FloatArray | None:
        """A vertical line at the divergence frequency (the "mark" scale)."""
        if self.divergence_hz is None:
            return None
        return _marks(np.log(self.freq_hz) - np.log(self.divergence_hz))


#: The plant chart draws this many measured responses one by one (the article's Fig. 13 has
#: three positions); the mean and the band cover all of them.
PLANT_POSITIONS = 4


#: The lower edge of a measured band is drawn at most 20 dB below |H|: a spread near or
#: above 1 leaves the magnitude unbounded below (20 log10(1 - spread) -> -inf), which would
#: only stretch the chart's scale.
SPREAD_FLOOR = 0.1


def spread_band_db(h: npt.ArrayLike, spread: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """(upper, lower) edge of the band |H| (1 +- spread) in dB, the lower one clipped at
    SPREAD_FLOOR |H|."""
    mag = np.abs(np.asarray(h))
    sp = np.asarray(spread, dtype=np.float64)
    return db(mag * (1.0 + sp)), db(mag * np.maximum(1.0 - sp, SPREAD_FLOOR))


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
    s_db: FloatArray | None = None
    """Sensitivity 1/(1 + L) at the plant input, speed loop (plant model)."""
    t_db: FloatArray | None = None
    """Complementary sensitivity L/(1 + L), speed loop."""
    s_full_db: FloatArray | None = None
    """Sensitivity of the whole servo (position loop closed)."""
    t_full_db: FloatArray | None = None
    nyquist_dob: NyquistLoop | None = None
    """The speed loop with the DOB, G (Cv + F1) / (1 - F2 z^-1), whatever cfg.dob_on."""
    nyquist_nodob: NyquistLoop | None = None
    """The speed loop without the DOB, G Cv."""
    plant: PlantCurves | None = None
    """The plant the configuration is judged on (same for every configuration)."""

    dob_on: bool = True
    """The configuration's DOB switch: the drawn open loop (`open_loop_*`) is `nyquist_dob`
    with the DOB on, `nyquist_nodob` with it off."""

    @property
    def loop(self) -> NyquistLoop | None:
        """The drawn open loop's crossings and margins."""
        return self.nyquist_dob if self.dob_on else self.nyquist_nodob


def _marks(crossing: FloatArray) -> FloatArray:
    """0 and 1 on the two grid points around each zero crossing of `crossing` (a sign change
    between neighbours of less than 180: a wrap of the phase is not a crossing), NaN
    elsewhere: on a fixed 0..1 scale, a line across the whole chart there. The canvas joins
    the marks across the gaps, so they alternate up and down: the joins run along the chart's
    top or bottom edge."""
    c = np.asarray(crossing, dtype=np.float64)
    out = np.full(len(c), np.nan)
    a, b = c[:-1], c[1:]
    with np.errstate(invalid="ignore"):
        sign_change = ((a <= 0.0) & (b > 0.0)) | ((b <= 0.0) & (a > 0.0))
        hit = np.isfinite(a) & np.isfinite(b) & sign_change & (np.abs(b - a) < 180.0)
    i = np.nonzero(hit)[0]
    up = np.arange(i.size) % 2 == 0  # alternately up (0 then 1) and down (1 then 0)
    # Second points first: where two crossings are neighbours, the later crossing's first
    # point wins, as in a pass from low to high frequency.
    out[i + 1] = np.where(up, 1.0, 0.0)
    out[i] = np.where(up, 0.0, 1.0)
    return out


#: The scale of the crossover marks: fixed 0..1 (no auto range, so gaps cannot upset it).
MARK_SCALE = "mark"


def ranged_scales(spec: ChartSpec, data: Sequence[npt.ArrayLike],
                  steps: dict[str, float] | None = None) -> dict[str, dict[str, Any]]:
    """`spec.scales` with every y scale fixed (auto off) to the finite range of its series in
    `data` (5 % margin, or rounded out to whole `steps[scale]`; 0..1 with no finite value): on
    a fixed scale uPlot draws a NaN as nothing, where an auto scale takes a series' first
    non-null value for its range (a NaN first value gave the scale a NaN range: the chart
    drew nothing), so no column needs a stand-in value (an empty chart's red "suggested"
    dot at (0.1 Hz, 0))."""
    out = dict(spec.scales)
    for name in spec.scales:
        if name == "x" or name == MARK_SCALE:
            continue
        cols = [np.asarray(c, dtype=np.float64) for c, ser in zip(data[1:], spec.series[1:],
                                                                    strict=False)
                if ser.get("scale", "y") == name]
        vals = np.concatenate(cols) if cols else np.empty(0)
        vals = vals[np.isfinite(vals)]
        lo, hi = (float(vals.min()), float(vals.max())) if vals.size else (0.0, 1.0)
        step = (steps or {}).get(name)
        if step and vals.size:
            lo, hi = step * math.floor(lo / step), step * math.ceil(hi / step)
            if hi <= lo:
                lo, hi = lo - step, hi + step
        else:
            pad = 0.05 * (hi - lo) if hi > lo else max(abs(lo), 1.0) * 0.05
            lo, hi = lo - pad, hi + pad
        out[name] = {**spec.scales[name], "auto": False, "range": (lo, hi)}
    return out


def _marker(label: str, color: str) -> dict[str, Any]:
    return {"label": label, "stroke": color, "width": 2, "scale": MARK_SCALE, "dash": (3, 3)}


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
    #: What each series after x draws, in series order: for a Bode chart "cand.<field>" or
    #: "act.<field>" of BodeCurves; for a live chart the ring column.
    columns: tuple[str, ...] = ()

    def placeholder(self, x: npt.ArrayLike) -> tuple[FloatArray, ...]:
        """Data to create the chart with: `x` and zeros for every series."""
        xs = np.asarray(x, dtype=np.float64)
        return (xs, *([np.zeros_like(xs)] * (len(self.series) - 1)))


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
#: The frequency axis, compact (the tick values and "Hz" in 44 px, uPlot's default 80: the
#: Bode tab's Decide view fits a 1080 px screen).
_HZ_AXIS = {"label": "Hz", "scale": "x", "size": 28, "labelSize": 16, "labelGap": 0}
_DASH_ACTIVE = (6, 4)
_DASH_NO_DOB = (4, 3)


def _freq_chart(key: str, title: str, series: Sequence[dict[str, Any]], *, y_label: str = "dB",
                scales: dict[str, dict[str, Any]] | None = None,
                axes: tuple[dict[str, Any], ...] | None = None, height: int = 220,
                extra: dict[str, Any] | None = None, columns: tuple[str, ...] = ()) -> ChartSpec:
    """A chart over a log frequency axis."""
    return ChartSpec(
        key=key,
        title=title,
        series=({"label": "f (Hz)"}, *series),
        scales=scales or dict(_LOG_X),
        axes=axes or (_HZ_AXIS, {"label": y_label, "scale": "y"}),
        height=height,
        extra=extra or {},
        columns=columns,
    )


def _bode_spec(key: str, title: str, *series: tuple[dict[str, Any], str],
               **options: Any) -> ChartSpec:
    """A Bode chart; each series comes with the BodeCurves column it draws."""
    return _freq_chart(key, title, [s for s, _ in series], columns=tuple(c for _, c in series),
                       **options)


def _dob_spec(key: str, title: str, dob: str, no_dob: str, labels: tuple[str, str, str],
              ) -> ChartSpec:
    """Candidate with and without the DOB, and the active configuration with it."""
    with_dob, without_dob, active = labels
    return _bode_spec(
        key,
        title,
        (_line(with_dob, CANDIDATE), f"cand.{dob}"),
        (_line(without_dob, NO_DOB, dash=_DASH_NO_DOB), f"cand.{no_dob}"),
        (_line(active, ACTIVE, dash=_DASH_ACTIVE), f"act.{dob}"),
    )


def _measured_points(label: str, stroke: str, scale: str = "y") -> dict[str, Any]:
    """Measured points joined across the grid points between them (spanGaps). uPlot's own
    rule shows the points once they are sparse on screen (zoomed in)."""
    s = _line(label, stroke, width=2.0, scale=scale)
    s["spanGaps"] = True
    return s


def _band_edge(label: str) -> dict[str, Any]:
    """One edge of a measured band, as a dashed line. Not a filled uPlot band: the data
    reach uPlot as Float64Array, where a gap is NaN, not null, and uPlot closes a band's fill
    at the last non-null x, so the fill of a band that ends before the chart does runs on
    to the chart's end (seen in Chromium: a wedge past the last measured point)."""
    s = _line(label, _rgba(MEASURED, 0.8), dash=(4, 3), width=1.0)
    s["spanGaps"] = True
    return s


# -- the classic Bode of the speed loop ----------------------------------------------------------

#: The two charts of the loop's Bode share one cursor (uPlot's cursor sync: hovering one shows
#: the same frequency on the other; web_assets/dashboard.js reads both there and labels the
#: margin markers) and one x grid (`loop_bode_data`), so one frequency axis.
LOOP_CURSOR: dict[str, Any] = {"sync": {"key": "dt-loop-bode"}}
#: The magnitude chart marks at most this many phase crossovers (a conditionally stable loop
#: has a lower one, where a gain reduction destabilises, and an upper one).
GM_MARKS = 2
#: The y steps the Bode charts' fixed ranges are rounded out to (dB, deg): a candidate that
#: moves a curve a little keeps its chart's scales (a new range re-creates the chart).
Y_STEPS = {"y": 10.0, "deg": 45.0}
#: Tick steps of the loop's Bode axes (uPlot picks the first whose ticks are `space` px apart):
#: dB in tens, degrees in multiples of 15 (so -180 is a tick).
_DB_INCRS = (10, 20, 40, 60, 100, 200)
_DEG_INCRS = (15, 30, 45, 90, 180, 360)
#: A configuration version is a whole number: its axis is ticked in whole steps (uPlot's own
#: choice put ticks at 2.5).
VERSION_INCRS = tuple(m * 10**e for e in range(17) for m in (1, 2, 5))


def _margin_line(label: str, color: str, scale: str = "y") -> dict[str, Any]:
    """A margin marker: one vertical segment (two points at one frequency) from the reference
    (0 dB or -180 deg) to the curve, NaN elsewhere."""
    return {"label": label, "stroke": color, "width": 3.0, "scale": scale}


LOOP_MAG_CHART = _bode_spec(
    "loop_mag",
    "Open loop L (speed loop): magnitude; gain margin = 0 dB - |L| where the phase is -180 deg",
    (_line("|L| candidate", CANDIDATE, width=2.0), "cand.open_loop_db"),
    (_line("|L| active", ACTIVE, dash=_DASH_ACTIVE), "act.open_loop_db"),
    (_line("0 dB line", "#555555", width=1.0), "ref.0"),
    (_margin_line("gain margin", GM_COLOR), "mark.gm1"),
    (_margin_line("gain margin, 2nd -180 deg crossing", GM_COLOR), "mark.gm2"),
    axes=(_HZ_AXIS, {"label": "dB", "scale": "y", "space": 20, "incrs": _DB_INCRS}),
    height=150,
    extra={"cursor": LOOP_CURSOR},
)
LOOP_PHASE_CHART = _bode_spec(
    "loop_phase",
    "Open loop L (speed loop): phase; phase margin = phase + 180 deg where |L| = 0 dB",
    (_line("phase candidate", CANDIDATE, width=2.0, scale="deg"), "cand.open_loop_phase_deg"),
    (_line("phase active", ACTIVE, dash=_DASH_ACTIVE, scale="deg"), "act.open_loop_phase_deg"),
    (_line("-180 deg line", "#d62728", width=1.0, scale="deg"), "ref.-180"),
    (_margin_line("phase margin", PM_COLOR, scale="deg"), "mark.pm"),
    scales={"x": _LOG_X["x"], "deg": {"auto": True}},
    axes=(_HZ_AXIS, {"label": "deg", "scale": "deg", "space": 20, "incrs": _DEG_INCRS}),
    height=140,
    extra={"cursor": LOOP_CURSOR},
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
    order = sorted(range(len(gms)), key=lambda i: (
        not np.isclose(gms[i], loop.gain_margin_db), loop.phase_crossover_hz[i]))
    gm = tuple(MarginMark(float(loop.phase_crossover_hz[i]), -float(gms[i]), 0.0)
               for i in order[:GM_MARKS] if np.isfinite(gms[i]))
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

    gm_cols = [mark_column(gm[k] if k < len(gm) else None) for k in range(GM_MARKS)]
    mag = (x, on_x(cand.open_loop_db), on_x(act.open_loop_db), np.zeros(x.size), *gm_cols)
    phase = (x, on_x(cand.open_loop_phase_deg), on_x(act.open_loop_phase_deg),
             np.full(x.size, -180.0), mark_column(pm))
    return mag, phase


def _fmt_hz(f: float) -> str:
    return f"{f:.3g} Hz"


def loop_margins_html(c: BodeCurves) -> str:
    """One line over the loop's Bode: every margin the markers show, with its frequency."""
    gm, pm = margin_marks(c)
    parts = []
    for k, m in enumerate(gm):
        what = "gain margin" if k == 0 else "2nd crossing"
        note = " (a gain <i>reduction</i> by this much destabilises)" if m.value < 0 else ""
        parts.append(f"<span class='dt-gm' style='color:{GM_COLOR}'><b>{what}</b> "
                     f"{m.value:.1f} dB at {_fmt_hz(m.freq_hz)}</span>{note}")
    if not gm:
        parts.append(f"<span class='dt-gm' style='color:{GM_COLOR}'><b>gain margin</b> none "
                     "(the phase never crosses -180 deg)</span>")
    if pm is not None:
        parts.append(f"<span class='dt-pm' style='color:{PM_COLOR}'><b>phase margin</b> "
                     f"{pm.value:.1f} deg at {_fmt_hz(pm.freq_hz)}</span>")
    else:
        parts.append(f"<span class='dt-pm' style='color:{PM_COLOR}'><b>phase margin</b> none "
                     "(|L| never crosses 0 dB)</span>")
    return ("<div class='dt-loop-margins' style='font-size:13px'>"
            + " &middot; ".join(parts) + "</div>")


PLANT_MODEL = "#34495e"

#: The plant itself: the model the gate judges on, and the measured responses with their
#: spread as a band between the "+spread" and "-spread" series.
_POSITION_COLORS = ("#8c564b", "#e377c2", "#17becf", "#bcbd22")

PLANT_CHART = _bode_spec(
    "plant",
    "Plant u -> speed: model and measured (band: measured |H| (1 +- spread)); each position, "
    "the spread between positions (max - min, dB) and where they diverge (> 1 dB)",
    (_line("|M P| model", PLANT_MODEL), "plant.model_db"),
    (_measured_points("|H| measured", MEASURED), "plant.measured_db"),
    (_band_edge("|H| (1 + spread)"), "plant.upper_db"),
    (_band_edge("|H| (1 - spread)"), "plant.lower_db"),
    (_line("phase model", PLANT_MODEL, dash=(2, 3), width=1.0, scale="deg"),
     "plant.model_phase_deg"),
    (_measured_points("phase measured", "#7fbf7f", scale="deg"), "plant.measured_phase_deg"),
    *((_measured_points(f"|H| position {i + 1}", c), f"plant.pos{i + 1}_db")
      for i, c in enumerate(_POSITION_COLORS[:PLANT_POSITIONS])),
    (_measured_points("spread between positions (dB)", "#d62728"), "plant.spread_db"),
    (_marker("responses diverge (> 1 dB)", "#d62728"), "plant.divergence_marks"),
    scales={**_LOG_X, "deg": {"auto": True}, MARK_SCALE: {"auto": False, "range": (0.0, 1.0)}},
    axes=(
        _HZ_AXIS,
        {"label": "dB", "scale": "y"},
        {"label": "deg", "scale": "deg", "side": 1, "grid": {"show": False}},
    ),
)

BODE_CHARTS: tuple[ChartSpec, ...] = (
    LOOP_MAG_CHART,
    LOOP_PHASE_CHART,
    _dob_spec("closed_loop", "Closed loop r -> w (15) vs (18)", "closed_dob_db",
              "closed_nodob_db", ("with DOB", "without DOB", "active")),
    _dob_spec("disturbance", "Disturbance d -> w: (16) with DOB vs (18) without", "dist_dob_db",
              "dist_nodob_db", ("(16) with DOB", "(18) without DOB", "(16) active")),
    _dob_spec("noise", "Noise zeta -> w (17)", "noise_dob_db", "noise_nodob_db",
              ("(17) with DOB", "(18) without DOB", "(17) active")),
    _bode_spec(
        "rejection",
        "DOB rejection gain |E_without / E_with| (23): > 0 dB where the DOB helps",
        (_line("candidate", CANDIDATE), "cand.rejection_db"),
        (_line("active", ACTIVE, dash=_DASH_ACTIVE), "act.rejection_db"),
        height=110,
    ),
    _bode_spec(
        "sensitivity",
        "Sensitivity |S| and complementary |T| at the plant input (whole servo dashed)",
        (_line("|S| candidate", CANDIDATE), "cand.s_db"),
        (_line("|T| candidate", NO_DOB), "cand.t_db"),
        (_line("|S| whole servo", CANDIDATE, dash=_DASH_NO_DOB, width=1.0), "cand.s_full_db"),
        (_line("|T| whole servo", NO_DOB, dash=_DASH_NO_DOB, width=1.0), "cand.t_full_db"),
        (_line("|S| active", ACTIVE, dash=_DASH_ACTIVE), "act.s_db"),
        height=120,
    ),
    _bode_spec(
        "small_gain",
        "Small gain: |Q| vs 1/|Delta|",
        (_line("|Q| candidate", CANDIDATE), "cand.q_db"),
        (_line("|Q| active", ACTIVE, dash=_DASH_ACTIVE), "act.q_db"),
        (_line("1/|Delta| bound", BOUND, dash=_DASH_NO_DOB), "cand.inv_delta_db"),
        (_line("1/|Delta| measured", MEASURED, width=2.0), "cand.inv_delta_measured_db"),
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
    sources: dict[str, Any] = {"cand": cand, "act": act}
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


_T_AXIS = {"label": "s", "scale": "x"}
_LIN_X: dict[str, dict[str, Any]] = {"x": {"time": False, "auto": True}, "y": {"auto": True}}

PREVIEW_CHART = ChartSpec(
    key="preview",
    title="Preview: position error, simulated test",
    series=(
        {"label": "t (s)"},
        _line("candidate", CANDIDATE),
        _line("active", ACTIVE, dash=_DASH_ACTIVE),
        _line("candidate, DOB off", NO_DOB, dash=_DASH_NO_DOB),
    ),
    scales=_LIN_X,
    axes=(_T_AXIS, {"label": "deg", "scale": "y"}),
)


STEP_CHART = ChartSpec(
    key="steps",
    title="Linear model: 1 deg reference step (left) and 1 deg/s load-disturbance step (right)",
    series=(
        {"label": "t (s)"},
        _line("ref step candidate", CANDIDATE),
        _line("ref step active", ACTIVE, dash=_DASH_ACTIVE),
        _line("load step candidate", NO_DOB, scale="d"),
        _line("load step active", ACTIVE, dash=_DASH_NO_DOB, scale="d"),
    ),
    scales={**_LIN_X, "d": {"auto": True}},
    axes=(_T_AXIS, {"label": "deg", "scale": "y"},
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


def live_scales(window_s: float) -> dict[str, dict[str, Any]]:
    """The scales of a live chart showing the last `window_s` seconds: x fixed at
    [-window_s, 0] (the newest sample at 0), y and the config version auto-ranged.

    The x range is fixed, not auto: viser's uPlot component keeps an auto x scale's bounds
    relative to the previous data's range, and a chart drawn once while its tab was hidden (or
    before its first data) kept 0..1 s for good, one sample of the window on the axis
    (issue 22)."""
    return {"x": {"time": False, "auto": False, "range": (-float(window_s), 0.0)},
            "y": {"auto": True}, "ver": {"auto": True}}


def _live_spec(key: str, title: str, unit: str, *series: tuple[dict[str, Any], str]
               ) -> ChartSpec:
    """A live chart; each series comes with its ring column; the config version comes last."""
    version = _line("config v", "#8e44ad", width=1.0, scale="ver")
    return ChartSpec(
        key=key,
        title=title,
        series=({"label": "t (s)"}, *(s for s, _ in series), version),
        scales=live_scales(LIVE_WINDOW_S),
        axes=(
            _T_AXIS,
            {"label": unit, "scale": "y"},
            {"label": "config v", "scale": "ver", "side": 1, "grid": {"show": False},
             "incrs": VERSION_INCRS},
        ),
        height=170,
        columns=tuple(c for _, c in series),
    )


#: Live charts; the last series of each is the active config version (a step marks a change).
LIVE_CHARTS: tuple[ChartSpec, ...] = (
    _live_spec("error", "Position error", "deg", (_line("error", "#c0392b"), "error_deg")),
    _live_spec(
        "speed",
        "Load speed vs speed reference",
        "deg/s",
        (_line("speed w", CANDIDATE), "speed_deg_s"),
        (_line("reference r", NO_DOB, dash=_DASH_NO_DOB), "speed_ref_deg_s"),
    ),
    _live_spec("d_hat", "Disturbance estimate d_hat", "deg/s",
               (_line("d_hat", "#16a085"), "d_hat_deg_s")),
    _live_spec("command", "Speed command u", "deg/s", (_line("u", "#34495e"), "command_deg_s")),
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


# -- identification (measured responses building up) ---------------------------------------------

#: One colour per measurement position (cycled).
POSITION_COLORS = ("#1f77b4", "#2ca02c", "#9467bd", "#e8871e", "#17becf", "#8c564b")
FIT = "#d62728"


@dataclass(frozen=True)
class MeasuredCurve:
    """One measured response to draw (plain arrays; NaN std where it is unknown)."""

    label: str
    freq_hz: FloatArray
    mag_db: FloatArray
    phase_deg: FloatArray
    mag_std_db: FloatArray
    coherence: FloatArray
    complete: bool = True


def _points(label: str, stroke: str, **extra: Any) -> dict[str, Any]:
    s = _line(label, stroke)
    s.update({"points": {"show": True, "size": 6}, "spanGaps": True, **extra})
    return s


def identify_chart_specs(n_positions: int) -> tuple[ChartSpec, ...]:
    """Magnitude (with the +-1 std band of each position and the fit), phase (with the fit) and
    coherence of `n_positions` measured responses on a log frequency axis.

    Series of the magnitude chart per position k: |G| k, |G|+std k, |G|-std k (the band is
    filled between the last two); then the fit. Phase: one per position, then the fit.
    Coherence: one per position.
    """
    n = max(1, int(n_positions))
    colors = [POSITION_COLORS[k % len(POSITION_COLORS)] for k in range(n)]
    mag: list[dict[str, Any]] = []
    bands: list[dict[str, Any]] = []
    for k, c in enumerate(colors):
        i = 1 + 3 * k
        mag.append(_points(f"pos {k + 1} |G|", c))
        mag.append(_line(f"pos {k + 1} +std", _rgba(c, 0.35), width=0.5))
        mag.append(_line(f"pos {k + 1} -std", _rgba(c, 0.35), width=0.5))
        bands.append({"series": (i + 1, i + 2), "fill": _rgba(c, 0.15)})
    fit = _line("fit Mn Pn", FIT, dash=_DASH_ACTIVE, width=1.5)
    fit["spanGaps"] = True
    phase = [_points(f"pos {k + 1} phase", c) for k, c in enumerate(colors)]
    coh = [_points(f"pos {k + 1} coherence", c) for k, c in enumerate(colors)]
    return (
        _freq_chart("identify_mag", "Measured |G| = |w/u| with +-1 std band, and the fit",
                    (*mag, fit), height=240, extra={"bands": tuple(bands)}),
        _freq_chart("identify_phase", "Measured phase of w/u, and the fit",
                    (*phase, dict(fit, label="fit phase")), y_label="deg", height=200),
        _freq_chart("identify_coherence", "Coherence", coh, y_label="", height=150,
                    scales={"x": _LOG_X["x"], "y": {"auto": False, "range": (0.0, 1.05)}}),
    )


def identify_data(
    n_positions: int,
    curves: Sequence[MeasuredCurve | None],
    fit_freq_hz: FloatArray | None = None,
    fit_response: npt.NDArray[np.complex128] | None = None,
) -> dict[str, tuple[FloatArray, ...]]:
    """Data tuples for `identify_chart_specs(n_positions)`.

    The x grid is the union of every curve's frequencies and the fit's; a series is NaN where
    it has no point (drawn with spanGaps). Curves missing so far (None) are all NaN. With no
    data at all, a two-point placeholder grid.
    """
    n = max(1, int(n_positions))
    have = [c for c in curves[:n] if c is not None and c.freq_hz.size > 0]
    grids = [c.freq_hz for c in have]
    if fit_freq_hz is not None and fit_response is not None and fit_freq_hz.size > 0:
        grids.append(np.asarray(fit_freq_hz, dtype=np.float64))
    x = np.unique(np.concatenate(grids)) if grids else np.array([0.1, 10.0])
    nan = np.full(x.size, np.nan)

    def on_grid(f: FloatArray, y: FloatArray) -> FloatArray:
        out = nan.copy()
        out[np.searchsorted(x, f)] = y
        return out

    mag: list[FloatArray] = []
    phase: list[FloatArray] = []
    coh: list[FloatArray] = []
    for k in range(n):
        c = curves[k] if k < len(curves) else None
        if c is None or c.freq_hz.size == 0:
            mag += [nan, nan, nan]
            phase.append(nan)
            coh.append(nan)
            continue
        std = np.nan_to_num(np.asarray(c.mag_std_db, dtype=np.float64), nan=0.0)
        m = on_grid(c.freq_hz, c.mag_db)
        mag += [m, on_grid(c.freq_hz, c.mag_db + std), on_grid(c.freq_hz, c.mag_db - std)]
        phase.append(on_grid(c.freq_hz, c.phase_deg))
        coh.append(on_grid(c.freq_hz, c.coherence))
    if fit_freq_hz is not None and fit_response is not None and fit_freq_hz.size > 0:
        fit_mag = on_grid(fit_freq_hz, db(fit_response))
        ph = np.degrees(np.unwrap(np.angle(fit_response)))
        fit_phase = on_grid(fit_freq_hz, ph)
    else:
        fit_mag = fit_phase = nan
    return {
        "identify_mag": (x, *mag, fit_mag),
        "identify_phase": (x, *phase, fit_phase),
        "identify_coherence": (x, *coh),
    }


# -- Nyquist -------------------------------------------------------------------------------------

#: The Nyquist view shows |L| <= this radius (the loop's integrators send L to infinity at
#: low frequency; what matters for margins is near the unit circle and -1).
NYQUIST_RADIUS = 3.0
#: A Nyquist panel's bands (viewBox px): the title and the formula above the square plot, the
#: tick labels inside its edge, the legend below it.
NYQUIST_HEADER_PX = 80
NYQUIST_INSET_PX = 30
NYQUIST_FOOTER_PX = 64


def open_loop_response(c: BodeCurves) -> ComplexArray:
    """L on the grid, back from the drawn magnitude (dB) and unwrapped phase (deg)."""
    return np.asarray(10.0 ** (c.open_loop_db / 20.0) * np.exp(
        1j * np.deg2rad(c.open_loop_phase_deg)), dtype=np.complex128)


def nyquist_segments(z: npt.ArrayLike, radius: float = NYQUIST_RADIUS) -> list[ComplexArray]:
    """The runs of consecutive grid points of the response `z` inside |z| <= radius (one
    polyline each)."""
    z = np.asarray(z, dtype=np.complex128)
    inside = np.isfinite(z) & (np.abs(z) <= radius)
    segments, start = [], None
    for i, ok in enumerate(inside):
        if ok and start is None:
            start = i
        elif not ok and start is not None:
            segments.append(z[start:i])
            start = None
    if start is not None:
        segments.append(z[start:])
    return [s for s in segments if len(s) >= 2]


def _fmt_margin(value: float, unit: str) -> str:
    return f"{value:.1f} {unit}" if np.isfinite(value) else "none"


def _nyquist_panel(cand: NyquistLoop | None, active: NyquistLoop | None, title: str,
                   formula: str, cls: str, loop: str, size: int, radius: float) -> str:
    """One Nyquist panel (an SVG): candidate solid, active dashed, unit circle, -1, and the
    candidate's margin points (PM on the unit circle, GM on the negative real axis)."""
    half = size / 2.0
    top = float(NYQUIST_HEADER_PX)
    cx0, cy0 = half, top + half  # the origin
    k = (half - NYQUIST_INSET_PX) / radius  # px per unit
    x0, y0, x1, y1 = cx0 - k * radius, cy0 - k * radius, cx0 + k * radius, cy0 + k * radius

    def xy(z: complex) -> tuple[str, str]:
        return f"{cx0 + k * z.real:.1f}", f"{cy0 - k * z.imag:.1f}"

    height = size + NYQUIST_HEADER_PX + NYQUIST_FOOTER_PX
    parts = [f"<svg class='{cls} dt-nyq-panel' data-loop='{loop}' viewBox='0 0 {size} {height}' "
             f"data-origin='{cx0:.1f} {cy0:.1f}' data-px-per-unit='{k:.4f}' "
             f"width='100%' style='display:block;height:auto;background:#fff'>",
             f"<rect class='dt-nyq-plot' x='{x0:.1f}' y='{y0:.1f}' width='{x1 - x0:.1f}' "
             f"height='{y1 - y0:.1f}' fill='none' stroke='#ccc'/>",
             f"<line x1='{x0:.1f}' y1='{cy0}' x2='{x1:.1f}' y2='{cy0}' stroke='#bbb'/>",
             f"<line x1='{cx0}' y1='{y0:.1f}' x2='{cx0}' y2='{y1:.1f}' stroke='#bbb'/>",
             f"<circle cx='{cx0}' cy='{cy0}' r='{k:.1f}' fill='none' stroke='#999' "
             "stroke-dasharray='4 3'/>"]
    # Ticks at every whole unit on both axes, labelled outside the plot's frame (real: under
    # it, imaginary: left of it), and the axes' names.
    for v in range(-int(radius), int(radius) + 1):
        px, py = cx0 + k * v, cy0 - k * v
        parts.append(f"<line class='dt-nyq-tick' x1='{px:.1f}' y1='{cy0 - 5}' x2='{px:.1f}' "
                     f"y2='{cy0 + 5}' stroke='#888'/>")
        parts.append(f"<line class='dt-nyq-tick' x1='{cx0 - 5}' y1='{py:.1f}' x2='{cx0 + 5}' "
                     f"y2='{py:.1f}' stroke='#888'/>")
        parts.append(f"<text class='dt-nyq-tick-re' x='{px:.1f}' y='{y1 + 15:.1f}' "
                     f"font-size='13' fill='#555' text-anchor='middle'>{v}</text>")
        parts.append(f"<text class='dt-nyq-tick-im' x='{x0 - 4:.1f}' y='{py:.1f}' "
                     f"font-size='13' fill='#555' text-anchor='end' "
                     f"dominant-baseline='central'>{v}</text>")
    parts.append(f"<text x='{x1:.1f}' y='{cy0 - 8}' font-size='13' fill='#555' "
                 "text-anchor='end'>Re L</text>")
    parts.append(f"<text x='{cx0 + 8}' y='{y0 + 13:.1f}' font-size='13' fill='#555'>Im L</text>")
    for nl, color, css, dash in ((active, ACTIVE, "dt-nyq-active", "6 4"),
                                 (cand, CANDIDATE, "dt-nyq-cand", "")):
        if nl is None:
            continue
        for seg in nyquist_segments(nl.response, radius):
            pts = " ".join(",".join(xy(complex(z))) for z in seg)
            parts.append(f"<polyline class='{css}' fill='none' stroke='{color}' "
                         f"stroke-width='2' stroke-dasharray='{dash}' points='{pts}'/>")
    if cand is not None:
        for zs, fs, color, css, what in (
                (cand.gain_crossings, cand.gain_crossover_hz, PM_COLOR, "dt-nyq-pm", "PM"),
                (cand.phase_crossings, cand.phase_crossover_hz, GM_COLOR, "dt-nyq-gm", "GM")):
            for z, f in zip(zs, fs, strict=True):
                if not abs(z) <= radius:
                    continue
                if what == "PM":
                    value = f"PM {np.degrees(np.angle(z)) % 360.0 - 180.0:.1f} deg"
                else:
                    value = f"GM {-20.0 * np.log10(abs(z)):.1f} dB"
                cx, cy = xy(complex(z))
                parts.append(f"<circle class='{css}' cx='{cx}' cy='{cy}' r='6' fill='{color}'>"
                             f"<title>{value} read here ({f:.3g} Hz)</title></circle>")
    cx, cy = xy(-1.0 + 0j)
    parts.append(f"<text class='dt-nyq-critical' x='{cx}' y='{cy}' fill='#d62728' "
                 "font-size='28' text-anchor='middle' dominant-baseline='central'>+</text>")
    if cand is None:
        summary = "not computed"
    else:
        gms = -20.0 * np.log10(np.abs(cand.phase_crossings))
        # The reported GM's point may lie outside the window (a gain-reduction margin).
        outside = bool(np.isfinite(cand.gain_margin_db) and gms.size and abs(
            cand.phase_crossings[int(np.argmin(np.abs(gms - cand.gain_margin_db)))]) > radius)
        summary = (f"PM {_fmt_margin(cand.phase_margin_deg, 'deg')}, "
                   f"GM {_fmt_margin(cand.gain_margin_db, 'dB')}"
                   + (" (read outside the view)" if outside else ""))
    # Sized for a panel drawn at about half its viewBox width (two side by side in the
    # dashboard's plot column): the title on two lines and the formula above the plot, the
    # legend on two lines under it (never over the curves).
    parts.append(f"<text class='dt-nyq-title' fill='#333'>"
                 f"<tspan x='8' y='24' font-size='22' font-weight='bold'>{title}:</tspan>"
                 f"<tspan x='8' y='48' font-size='19'> {summary}</tspan></text>")
    parts.append(f"<text x='8' y='70' font-size='15' fill='#555'>{formula}</text>")
    foot = y1 + 20
    parts.append(f"<text class='dt-nyq-foot' x='8' y='{foot + 16:.1f}' font-size='15' "
                 f"fill='#555'>|L| &#8804; {radius:g}, unit circle dashed, + = -1</text>")
    parts.append(f"<text class='dt-nyq-foot' x='8' y='{foot + 36:.1f}' font-size='15' "
                 "fill='#555'>candidate solid, active dashed; "
                 f"<tspan fill='{PM_COLOR}'>&#9679; PM</tspan> "
                 f"<tspan fill='{GM_COLOR}'>&#9679; GM</tspan> read here</text></svg>")
    return "".join(parts)


def nyquist_svg(cand: BodeCurves, active: BodeCurves | None, size: int = 460,
                radius: float = NYQUIST_RADIUS) -> str:
    """The speed loop's Nyquist plots (positive frequencies) side by side, as inline SVG:
    with the DOB (class `dt-nyquist`) and without it (class `dt-nyquist-nodob`); each draws
    the candidate and the active configuration, the unit circle, the critical point -1 and
    the candidate's own points where its PM and GM are read. The panels wrap one under the
    other when the container is narrower than two."""
    act_dob = active.nyquist_dob if active is not None else None
    act_nodob = active.nyquist_nodob if active is not None else None
    panels = (
        _nyquist_panel(cand.nyquist_dob, act_dob, "with DOB",
                       "speed loop L = G (Cv + F1) / (1 - F2 z^-1)", "dt-nyquist", "dob",
                       size, radius),
        _nyquist_panel(cand.nyquist_nodob, act_nodob, "without DOB", "speed loop L = G Cv",
                       "dt-nyquist-nodob", "nodob", size, radius),
    )
    return ("<div class='dt-nyq-pair' style='display:flex;flex-wrap:wrap;gap:8px'>"
            + "".join(f"<div style='flex:1 1 260px;max-width:{size}px'>{p}</div>"
                      for p in panels)
            + "</div>")
