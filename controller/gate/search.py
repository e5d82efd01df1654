"""The recommended maximum Q cut-off: the top of the accepted region from the lowest cut-off,
and, with responses measured at several turntable positions, below where they diverge.

The second limit is the article's argument (Fig. 13): the responses measured at different
positions agree only at low frequency, so a single model of the plant is trusted only there,
and Q must roll off before the responses part. The spread between them (`PositionSpread`,
relative: |H_i / H_ref - 1|) is a multiplicative plant error Delta that the DOB's model must
allow wherever the turntable stands; the DOB's small-gain figure with it, max_f |Delta(f)|
|Q(f)|, must stay at or below 1 / `SPREAD_MARGIN` (the agreement level, 1 dB). (The figure
alone is not sufficient for stability, control.md: the gate's own analysis is the other
limit, and the smaller wins.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from controller.core.config import LoopConfig
from controller.core.qfilter import Q_TYPES, QType, check_q_type, design_q
from controller.gate.analysis import GateLimits, analyse
from controller.gate.knowledge import (
    DIVERGENCE_FRACTION,
    MeasuredResponse,
    PlantKnowledge,
    PositionSpread,
    position_spread,
)
from controller.gate.loop_model import TWO_PI, ComplexArray, discrete_equivalent

__all__ = [
    "SPREAD_MARGIN",
    "Recommendation",
    "knowledge_spread",
    "recommend",
    "recommended_max_cutoff_hz",
    "spread_figure",
    "spread_limited_cutoff_hz",
]

#: The position spread's figure max |Delta Q| is held at or below 1 / SPREAD_MARGIN =
#: `DIVERGENCE_FRACTION` (1 dB): Q passes no more model error than the level at which the
#: responses still count as agreeing, so it rolls off where they diverge (the article's
#: argument). That is 18 dB from the small-gain limit |Delta Q| = 1: the spread at a few
#: positions is a sample of the plant's variation, not its bound.
SPREAD_MARGIN = 1.0 / DIVERGENCE_FRACTION


@dataclass(frozen=True)
class Recommendation:
    """The recommended maximum cut-off for one Q type and what limits it."""

    q_type: str
    recommended_hz: float | None
    """min(gate_hz, spread_hz); None when the gate accepts not even the lowest cut-off."""
    gate_hz: float | None
    """The top of the gate's accepted region from the lowest cut-off."""
    spread_hz: float | None
    """The largest cut-off with max |Delta Q| <= 1 / margin (None: no spread evidence, or even
    the lowest cut-off exceeds it)."""
    spread: PositionSpread | None
    margin: float

    @property
    def limited_by_spread(self) -> bool:
        return (
            self.spread is not None
            and self.gate_hz is not None
            and self.recommended_hz is not None
            and self.recommended_hz < self.gate_hz
        )

    def describe(self) -> str:
        """One line: the recommendation and its limits."""
        def hz(v: float | None) -> str:
            return "none" if v is None else f"{v:.3g} Hz"

        if self.spread is None:
            return f"{self.q_type}: {hz(self.recommended_hz)} (gate; no position spread)"
        div = self.spread.divergence_hz
        where = (
            f"the {len(self.spread.names)} responses diverge above {div:.3g} Hz"
            if div is not None
            else f"the {len(self.spread.names)} responses agree on their whole band"
        )
        return (
            f"{self.q_type}: {hz(self.recommended_hz)} (gate alone {hz(self.gate_hz)}; "
            f"position spread |Delta Q| <= {1.0 / self.margin:.3g}: {hz(self.spread_hz)}; {where})"
        )


def knowledge_spread(plant: PlantKnowledge, rate_hz: float) -> PositionSpread | None:
    """The spread across the knowledge's measured responses (None with fewer than two)."""

    def continuous(m: MeasuredResponse) -> ComplexArray:
        if not m.sampled:
            return m.response
        return m.response / discrete_equivalent(np.ones(m.freq_hz.size), m.freq_hz, rate_hz)

    return position_spread(plant.measured, continuous)


def _q_mag(q_type: QType, cutoff_hz: float, freq_hz: np.ndarray) -> np.ndarray:
    num, den = design_q(q_type, cutoff_hz=cutoff_hz).tf()
    s = 1j * TWO_PI * freq_hz
    return np.asarray(np.abs(np.polyval(num, s) / np.polyval(den, s)), dtype=np.float64)


def _spread_grid(spread: PositionSpread) -> np.ndarray:
    """The spread's own points, a dense log grid over its band and a decade above it (the
    spread held at the edge there)."""
    lo, hi = float(spread.freq_hz[0]), float(spread.freq_hz[-1])
    return np.union1d(spread.freq_hz, np.geomspace(lo, 10.0 * hi, 1200))


def spread_figure(q_type: str, cutoff_hz: float, spread: PositionSpread) -> float:
    """max_f |Delta(f)| |Q(f)| with Delta the position spread (continuous Q)."""
    qt = check_q_type(q_type)
    f = _spread_grid(spread)
    return float(np.max(spread.at(f) * _q_mag(qt, cutoff_hz, f)))


def spread_limited_cutoff_hz(
    q_type: str,
    spread: PositionSpread,
    margin: float = SPREAD_MARGIN,
    *,
    lowest_hz: float = 0.01,
    highest_hz: float = 100.0,
    rel_tol: float = 1e-3,
) -> float | None:
    """The largest cut-off whose `spread_figure` stays <= 1 / margin, searched from
    `lowest_hz` up (the first crossing, bisected in log cut-off to `rel_tol`); `highest_hz`
    if it never crosses; None if `lowest_hz` already exceeds it."""
    if not (margin >= 1.0 and math.isfinite(margin)):
        raise ValueError(f"margin: {margin!r} must be >= 1")
    limit = 1.0 / margin

    def ok(fc: float) -> bool:
        return spread_figure(q_type, fc, spread) <= limit

    return _top_of(ok, np.geomspace(lowest_hz, highest_hz, 60), rel_tol)


def recommend(
    cfg: LoopConfig,
    plant: PlantKnowledge | None = None,
    limits: GateLimits | None = None,
    q_type: str | None = None,
    *,
    spread_margin: float | None = SPREAD_MARGIN,
    lowest_hz: float = 0.02,
    highest_hz: float | None = None,
    coarse_points: int = 16,
    rel_tol: float = 0.01,
) -> Recommendation:
    """The gate's top cut-off and, with two or more measured responses, the position spread's
    limit (`spread_margin` None: the gate alone)."""
    qt: QType = check_q_type(q_type if q_type is not None else cfg.q_type)
    gate_hz = _gate_top_hz(cfg, plant, limits, qt, lowest_hz, highest_hz, coarse_points,
                           rel_tol)
    spread = None
    spread_hz = None
    if spread_margin is not None and plant is not None:
        spread = knowledge_spread(plant, cfg.rate_hz)
    if spread is not None:
        assert spread_margin is not None
        spread_hz = spread_limited_cutoff_hz(qt, spread, spread_margin)
    rec = gate_hz
    if rec is not None and spread is not None:
        rec = None if spread_hz is None else min(rec, spread_hz)
    return Recommendation(qt, rec, gate_hz, spread_hz, spread,
                          spread_margin if spread_margin is not None else math.nan)


def recommended_max_cutoff_hz(
    cfg: LoopConfig,
    plant: PlantKnowledge | None = None,
    limits: GateLimits | None = None,
    q_type: str | None = None,
    *,
    spread_margin: float | None = SPREAD_MARGIN,
    lowest_hz: float = 0.02,
    highest_hz: float | None = None,
    coarse_points: int = 16,
    rel_tol: float = 0.01,
) -> float | None:
    """Largest Q cut-off (Hz) recommended for `q_type` (default cfg.q_type), DOB on: the top of
    the gate's accepted region, and below the position spread's limit when the knowledge
    holds responses measured at two or more positions (`recommend`)."""
    return recommend(
        cfg, plant, limits, q_type, spread_margin=spread_margin, lowest_hz=lowest_hz,
        highest_hz=highest_hz, coarse_points=coarse_points, rel_tol=rel_tol,
    ).recommended_hz


def _gate_top_hz(
    cfg: LoopConfig, plant: PlantKnowledge | None, limits: GateLimits | None, qt: QType,
    lowest_hz: float, highest_hz: float | None, coarse_points: int, rel_tol: float,
) -> float | None:
    """Largest Q cut-off (Hz) the gate accepts, DOB on.

    Acceptance is assumed to hold on an interval from low cut-offs up to a limit (robustness
    and margins degrade as the Q bandwidth grows), though not strictly monotone. Guard: scan
    `coarse_points` log-spaced cut-offs from `lowest_hz` to `highest_hz` (default: a tenth of
    the loop rate), take the first accept -> reject transition from below, then bisect it in
    log cut-off to `rel_tol`. None if `lowest_hz` is already rejected.
    """
    assert qt in Q_TYPES
    top = highest_hz if highest_hz is not None else 0.1 * cfg.rate_hz
    top = min(top, 0.45 * cfg.rate_hz)
    base = cfg.with_(dob_on=True, q_type=qt)

    def ok(fc: float) -> bool:
        return analyse(base.with_(q_cutoff_hz=fc), plant, limits).accepted

    return _top_of(ok, np.geomspace(lowest_hz, top, coarse_points), rel_tol)


def _top_of(ok: Callable[[float], bool], grid: np.ndarray, rel_tol: float) -> float | None:
    """The first ok -> not ok transition on `grid` from below, bisected in log to `rel_tol`
    (the grid's top if there is none; None if its first point is not ok)."""
    if not ok(float(grid[0])):
        return None
    lo = float(grid[0])
    hi: float | None = None
    for fc in grid[1:]:
        if ok(float(fc)):
            lo = float(fc)
        else:
            hi = float(fc)
            break
    if hi is None:
        return lo
    while hi / lo > 1.0 + rel_tol:
        mid = math.sqrt(lo * hi)
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return lo
