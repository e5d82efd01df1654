"""What every chart shares (pure): colours, dB, the curves an analysis gives a chart
(`BodeCurves`, `PlantCurves`, `NyquistLoop`), `ChartSpec` and the series' options
(`server.charts`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np
import numpy.typing as npt

from controller.core.arrays import ComplexArray, FloatArray

#: What a chart's options are made of (uPlot's JSON: series, scales, axes; sent to the page as
#: JSON, never read back here): `object`, as server/gui.py's `add_uplot` takes them.
JsonValue: TypeAlias = object
ChartDict: TypeAlias = dict[str, JsonValue]

__all__ = [
    "ACTIVE",
    "BOUND",
    "CANDIDATE",
    "DASH_ACTIVE",
    "DASH_NO_DOB",
    "GM_COLOR",
    "HZ_AXIS",
    "LOG_X",
    "MARK_SCALE",
    "MEASURED",
    "NO_DOB",
    "PLANT_POSITIONS",
    "PM_COLOR",
    "SPREAD_FLOOR",
    "VERSION_INCRS",
    "BodeCurves",
    "ChartSpec",
    "NyquistLoop",
    "PlantCurves",
    "band_edge",
    "bode_spec",
    "crossing_marks",
    "db",
    "dob_spec",
    "freq_chart",
    "line_series",
    "marker_series",
    "measured_points",
    "ranged_scales",
    "rgba_of",
    "settled_scales",
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


def rgba_of(hex_color: str, alpha: float) -> str:
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
        return crossing_marks(np.log(self.freq_hz) - np.log(self.divergence_hz))


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


def crossing_marks(crossing: FloatArray) -> FloatArray:
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
                  steps: dict[str, float] | None = None) -> dict[str, ChartDict]:
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
        step = spec.y_step if name == "y" else None
        step = step or (steps or {}).get(name)
        if step and vals.size:
            lo, hi = step * math.floor(lo / step), step * math.ceil(hi / step)
            if hi <= lo:
                lo, hi = lo - step, hi + step
        else:
            pad = 0.05 * (hi - lo) if hi > lo else max(abs(lo), 1.0) * 0.05
            lo, hi = lo - pad, hi + pad
        clip = spec.y_clip if name == "y" else None
        if clip is not None and vals.size:
            # What the chart is read for stays legible (|S|'s 3 dB peak, the rejection's -2 dB
            # waterbed): the range held within `clip`, the rest runs off the chart.
            lo, hi = max(lo, clip[0]), min(hi, clip[1])
            if hi <= lo:
                lo, hi = clip
        out[name] = {**spec.scales[name], "auto": False, "range": (lo, hi)}
    return out


def settled_scales(spec: ChartSpec, data: Sequence[npt.ArrayLike],
                   settle_frac: float) -> tuple[dict[str, ChartDict], float, float]:
    """`ranged_scales` of the settled part of a time chart: from `settle_frac` of its time span
    on (a start-up transient set the preview's scale: 0.23 deg over a 0.05 deg error), with
    how the part before it is left out: (scales, the time it ends, its peak |y| when that
    runs off the scale, else NaN)."""
    x = np.asarray(data[0], dtype=np.float64)
    if x.size < 2:
        return ranged_scales(spec, data), math.nan, math.nan
    t_end = float(x[0] + settle_frac * (x[-1] - x[0]))
    keep = x >= t_end
    scales = ranged_scales(spec, [x[keep], *(np.asarray(c, dtype=np.float64)[keep]
                                            for c in data[1:])])
    rng = scales["y"]["range"]
    assert isinstance(rng, tuple)  # ranged_scales sets every y range as (lo, hi)
    lo, hi = rng
    early = np.concatenate([np.asarray(c, dtype=np.float64)[~keep] for c in data[1:]])
    early = early[np.isfinite(early)]
    off = early.size and (early.min() < lo or early.max() > hi)
    return scales, t_end, float(np.abs(early).max()) if off else math.nan


def marker_series(label: str, color: str) -> ChartDict:
    return {"label": label, "stroke": color, "width": 2, "scale": MARK_SCALE, "dash": (3, 3)}


@dataclass(frozen=True)
class ChartSpec:
    """Static uPlot options of one chart (series count and order never change)."""

    key: str
    title: str
    series: tuple[ChartDict, ...]
    scales: dict[str, ChartDict]
    axes: tuple[ChartDict, ...]
    height: int = 220
    y_step: float | None = None
    """The y scale rounded out to whole steps of this (dB)."""
    y_clip: tuple[float, float] | None = None
    """The y range held within this: what the chart is read for stays legible."""
    cursor: JsonValue = None
    """uPlot's cursor options (a shared key syncs the cursors of charts read together)."""
    bands: JsonValue = None
    """uPlot's bands (filled between two series)."""
    #: What each series after x draws, in series order: for a Bode chart "cand.<field>" or
    #: "act.<field>" of BodeCurves; for a live chart the ring column.
    columns: tuple[str, ...] = ()

    def placeholder(self, x: npt.ArrayLike) -> tuple[FloatArray, ...]:
        """Data to create the chart with: `x` and zeros for every series."""
        xs = np.asarray(x, dtype=np.float64)
        return (xs, *([np.zeros_like(xs)] * (len(self.series) - 1)))


def line_series(label: str, stroke: str, *, dash: Sequence[float] = (), width: float = 1.5,
          scale: str = "y") -> ChartDict:
    s: ChartDict = {"label": label, "stroke": stroke, "width": width, "scale": scale}
    if dash:
        s["dash"] = tuple(dash)
    return s


LOG_X: dict[str, ChartDict] = {
    "x": {"time": False, "distr": 3, "log": 10},
    "y": {"auto": True},
}
#: The frequency axis, compact (the tick values and "Hz" in 44 px, uPlot's default 80: the
#: Bode tab's Decide view fits a 1080 px screen).
HZ_AXIS: ChartDict = {"label": "Hz", "scale": "x", "size": 28, "labelSize": 16, "labelGap": 0}
DASH_ACTIVE = (6, 4)
DASH_NO_DOB = (4, 3)


def freq_chart(key: str, title: str, series: Sequence[ChartDict], *, y_label: str = "dB",
                scales: dict[str, ChartDict] | None = None,
                axes: tuple[ChartDict, ...] | None = None, height: int = 220,
                y_step: float | None = None, y_clip: tuple[float, float] | None = None,
                cursor: JsonValue = None, bands: JsonValue = None,
                columns: tuple[str, ...] = ()) -> ChartSpec:
    """A chart over a log frequency axis."""
    return ChartSpec(
        key=key,
        title=title,
        series=({"label": "f (Hz)"}, *series),
        scales=scales or dict(LOG_X),
        axes=axes or (HZ_AXIS, {"label": y_label, "scale": "y"}),
        height=height,
        y_step=y_step,
        y_clip=y_clip,
        cursor=cursor,
        bands=bands,
        columns=columns,
    )


def bode_spec(key: str, title: str, *series: tuple[ChartDict, str], y_label: str = "dB",
              scales: dict[str, ChartDict] | None = None,
              axes: tuple[ChartDict, ...] | None = None, height: int = 220,
              y_step: float | None = None, y_clip: tuple[float, float] | None = None,
              cursor: JsonValue = None) -> ChartSpec:
    """A Bode chart; each series comes with the BodeCurves column it draws."""
    return freq_chart(key, title, [s for s, _ in series], y_label=y_label, scales=scales,
                      axes=axes, height=height, y_step=y_step, y_clip=y_clip, cursor=cursor,
                      columns=tuple(c for _, c in series))


def dob_spec(key: str, title: str, dob: str, no_dob: str, labels: tuple[str, str, str],
              ) -> ChartSpec:
    """Candidate with and without the DOB, and the active configuration with it."""
    with_dob, without_dob, active = labels
    return bode_spec(
        key,
        title,
        (line_series(with_dob, CANDIDATE), f"cand.{dob}"),
        (line_series(without_dob, NO_DOB, dash=DASH_NO_DOB), f"cand.{no_dob}"),
        (line_series(active, ACTIVE, dash=DASH_ACTIVE), f"act.{dob}"),
    )


def measured_points(label: str, stroke: str, scale: str = "y") -> ChartDict:
    """Measured points joined across the grid points between them (spanGaps). uPlot's own
    rule shows the points once they are sparse on screen (zoomed in)."""
    s = line_series(label, stroke, width=2.0, scale=scale)
    s["spanGaps"] = True
    return s


def band_edge(label: str) -> ChartDict:
    """One edge of a measured band, as a dashed line. Not a filled uPlot band: the data
    reach uPlot as Float64Array, where a gap is NaN, not null, and uPlot closes a band's fill
    at the last non-null x, so the fill of a band that ends before the chart does runs on
    to the chart's end (seen in Chromium: a wedge past the last measured point)."""
    s = line_series(label, rgba_of(MEASURED, 0.8), dash=(4, 3), width=1.0)
    s["spanGaps"] = True
    return s


#: A configuration version is a whole number: its axis is ticked in whole steps (uPlot's own
#: choice put ticks at 2.5).
VERSION_INCRS = tuple(m * 10**e for e in range(17) for m in (1, 2, 5))
