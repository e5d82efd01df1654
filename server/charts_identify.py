"""The identification charts (pure): measured responses building up, position by position
(`server.charts`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from controller.core.arrays import FloatArray
from server.charts_base import (
    DASH_ACTIVE,
    LOG_X,
    ChartDict,
    ChartSpec,
    JsonValue,
    db,
    freq_chart,
    line_series,
    rgba_of,
)

__all__ = [
    "FIT",
    "POSITION_COLORS",
    "MeasuredCurve",
    "identify_chart_specs",
    "identify_data",
    "points_series",
]


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


def points_series(label: str, stroke: str, **extra: JsonValue) -> ChartDict:
    s = line_series(label, stroke)
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
    mag: list[ChartDict] = []
    bands: list[ChartDict] = []
    for k, c in enumerate(colors):
        i = 1 + 3 * k
        mag.append(points_series(f"pos {k + 1} |G|", c))
        mag.append(line_series(f"pos {k + 1} +std", rgba_of(c, 0.35), width=0.5))
        mag.append(line_series(f"pos {k + 1} -std", rgba_of(c, 0.35), width=0.5))
        bands.append({"series": (i + 1, i + 2), "fill": rgba_of(c, 0.15)})
    fit = line_series("fit Mn Pn", FIT, dash=DASH_ACTIVE, width=1.5)
    fit["spanGaps"] = True
    phase = [points_series(f"pos {k + 1} phase", c) for k, c in enumerate(colors)]
    coh = [points_series(f"pos {k + 1} coherence", c) for k, c in enumerate(colors)]
    return (
        freq_chart("identify_mag", "Measured |G| = |w/u| with +-1 std band, and the fit",
                    (*mag, fit), height=240, bands=tuple(bands)),
        freq_chart("identify_phase", "Measured phase of w/u, and the fit",
                    (*phase, dict(fit, label="fit phase")), y_label="deg", height=200),
        freq_chart("identify_coherence", "Coherence", coh, y_label="", height=150,
                    scales={"x": LOG_X["x"], "y": {"auto": False, "range": (0.0, 1.05)}}),
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
