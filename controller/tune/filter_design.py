"""The speed-command filter designed with the speed PI (pure): where a measured resonance
limits the speed loop, a notch at the mode (or a second-order low-pass below it) on Cv's
output (`controller.core.command_filter`) lets the PI cross over higher.

Procedure (`design_filter`):
1. The modes: each measured position's first resonance (`measured_modes_hz`), with the
   uncertainty of its frequency (half the measured grid's step there). None: no filter.
2. The band the filter must cover: from the lowest mode less its uncertainty to the highest
   plus its own. Notches are centred on the band (geometric mean), their width (pole
   damping) at least delta / sqrt(d) for the band's half-width delta and the depth's linear
   gain d (so every position's mode is cut by at least half the depth in dB), and wider;
   low-passes have their corner at 0.4 and 0.6 of the band's bottom (for a mode too uncertain
   or spread for a notch to cover well).
3. Only where the mode limits the speed loop: the first target the PI designed without a
   filter missed (a gain margin at a phase crossover, a phase margin at a gain crossover) was
   missed near the mode (`NEAR_MODE`: the mode's peak and its phase drop set the gain the PI
   may have). Otherwise no filter (it would only add lag at the crossover).
4. Every filter's speed PI is designed by the same rule as without one
   (`controller.tune.loop_design.design_speed` on N G); the filter whose PI crosses over
   highest is proposed, if it crosses at least `MIN_RAISE` times higher than the PI alone.
   Whether it is kept is for the whole-loop tune (the gate on the whole loop, the objective on
   the plant): `controller.tune.whole_loop`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from controller.core.command_filter import NOTCH_WIDTH_RANGE, CommandFilter
from controller.gate.knowledge import PlantKnowledge
from controller.tune.loop_design import (
    DesignTargets,
    NoSpeedDesign,
    SpeedDesign,
    design_speed,
    measured_modes_hz,
)

__all__ = ["MIN_RAISE", "FilterDesign", "candidate_filters", "design_filter", "mode_band_hz",
           "mode_limits", "plain_crossover_hz"]

NEAR_MODE = 0.7
#: A filter is proposed only if the speed loop crosses over at least this much higher with it.
MIN_RAISE = 1.1
NOTCH_DEPTHS_DB = (10.0, 20.0, 30.0)
WIDTH_FACTORS = (1.0, 2.0)
#: Wider notches tried too (a non-collocated mode lags well below its peak).
WIDE_NOTCHES = (0.3, 0.6, 1.0, 1.5)
MIN_NOTCH_WIDTH = 0.05
LOWPASS_FRACTIONS = (0.4, 0.6)
LOWPASS_DAMPINGS = (0.5, 0.7)


@dataclass(frozen=True)
class FilterDesign:
    """A filter that lets the speed loop cross over higher, and what it was weighed against."""

    command_filter: CommandFilter
    speed: SpeedDesign
    """The speed PI designed with the filter."""
    plain: SpeedDesign | NoSpeedDesign
    """The speed PI designed without one (or why there is none)."""
    modes_hz: tuple[float, ...]
    """Each measured position's mode."""
    band_hz: tuple[float, float]
    """The band the filter covers (the modes with their uncertainty)."""
    tried: int
    kept: bool = True
    """Whether the whole-loop tune kept it (the gate accepted the loop with it and it scored
    better on the plant than the loop without it)."""


def mode_band_hz(knowledge: PlantKnowledge) -> tuple[tuple[float, ...], tuple[float, float]] | None:
    """(the modes, the band they lie in with their uncertainty), or None when the measured
    responses show no resonance."""
    modes = measured_modes_hz(knowledge)
    if not modes:
        return None
    lo = min(f / (1.0 + u) for f, u in modes)
    hi = max(f * (1.0 + u) for f, u in modes)
    return tuple(f for f, _ in modes), (lo, hi)


def plain_crossover_hz(plain: SpeedDesign | NoSpeedDesign) -> float:
    """The crossover of the PI alone (0: none meets the targets)."""
    return plain.crossover_hz if isinstance(plain, SpeedDesign) else 0.0


def mode_limits(plain: SpeedDesign | NoSpeedDesign, band_hz: tuple[float, float]) -> bool:
    """Step 3: whether the first target the PI alone missed was missed near the mode (its
    crossing at or above `NEAR_MODE` x the band's bottom, at most `1 / NEAR_MODE` x its top)."""
    f = plain.limit_hz
    return NEAR_MODE * band_hz[0] <= f <= band_hz[1] / NEAR_MODE  # nan: False


def candidate_filters(band_hz: tuple[float, float], rate_hz: float) -> list[CommandFilter]:
    """The notches and low-passes of step 2 for a mode band (those the loop rate allows)."""
    lo, hi = band_hz
    centre = math.sqrt(lo * hi)
    half = 0.5 * (hi - lo) / centre
    out: list[CommandFilter] = []
    top = 0.45 * rate_hz
    if centre < top:
        for depth in NOTCH_DEPTHS_DB:
            need = max(half / math.sqrt(10.0 ** (-depth / 20.0)), MIN_NOTCH_WIDTH)
            widths = sorted({round(need * k, 3) for k in WIDTH_FACTORS}
                            | {w for w in WIDE_NOTCHES if w > need})
            for width in widths:
                if width <= NOTCH_WIDTH_RANGE[1]:
                    out.append(CommandFilter(kind="notch", notch_hz=round(centre, 2),
                                             notch_depth_db=depth, notch_width=width))
    for frac in LOWPASS_FRACTIONS:
        corner = frac * lo
        if corner < top:
            for damping in LOWPASS_DAMPINGS:
                out.append(CommandFilter(kind="lowpass", lowpass_hz=round(corner, 2),
                                         lowpass_damping=damping))
    return out


def design_filter(knowledge: PlantKnowledge, rate_hz: float,
                  plain: SpeedDesign | NoSpeedDesign, targets: DesignTargets | None = None,
                  ) -> FilterDesign | None:
    """The procedure of the module docstring; `plain` is the speed PI designed without a
    filter, or why none meets the targets (then any filter that lets one meet them is a
    raise). None: no measured resonance, one that does not limit `plain`, or no filter that
    raises the crossover `MIN_RAISE`-fold."""
    found = mode_band_hz(knowledge)
    if found is None:
        return None
    modes, band = found
    if not mode_limits(plain, band):
        return None
    cands = candidate_filters(band, rate_hz)
    best: SpeedDesign | None = None
    for cf in cands:
        try:
            sp = design_speed(knowledge, rate_hz, targets, command_filter=cf)
        except ValueError:  # nothing meets the targets with this filter
            continue
        if best is None or sp.crossover_hz > best.crossover_hz:
            best = sp
    if best is None or not best.crossover_hz >= MIN_RAISE * plain_crossover_hz(plain):
        return None
    return FilterDesign(best.command_filter, best, plain, modes, band, len(cands))
