"""The gate's reasons as text: margins below the limits, no distance from -1, robust-stability
figures (each naming its loop, its evidence and where to measure).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from controller.core.arrays import FloatArray
from controller.gate.limits import GateLimits
from controller.gate.margins import (
    Margins,
    RefineTask,
)

__all__ = [
    "distance_reasons",
    "fmt_hz",
    "margin_reasons",
    "on_grid",
    "robust_reasons",
    "round_up",
]


def fmt_hz(f: float) -> str:
    return f"{f:.3g} Hz"




def margin_reasons(m: Margins, limits: GateLimits, where: str, out: list[str]) -> None:
    """Cautions for margins below the limits (`where` names the loop and the evidence)."""
    if not m.phase_margin_deg >= limits.phase_margin_min_deg:
        out.append(
            f"phase margin {m.phase_margin_deg:.1f} deg < {limits.phase_margin_min_deg:g} deg"
            f" (at {fmt_hz(m.gain_crossover_hz)}; {where})"
        )
    # Both gain margins, each positive: up (|L| < 1 at a phase crossover) and, in a
    # conditionally stable loop, the gain reduction (|L| > 1). (Both >= the limit exactly
    # when python-control's pick, the one closest to 0 dB, is >= it in magnitude.)
    if not m.gain_margin_up_db >= limits.gain_margin_min_db:
        out.append(
            f"gain margin {m.gain_margin_up_db:.1f} dB up < {limits.gain_margin_min_db:g} dB"
            f" (at {fmt_hz(m.gain_margin_up_hz)}; {where})"
        )
    if not m.gain_reduction_margin_db >= limits.gain_margin_min_db:
        out.append(
            f"conditionally stable: a gain reduction of {m.gain_reduction_margin_db:.1f} dB "
            f"(< {limits.gain_margin_min_db:g} dB, as a saturating command gives) "
            f"destabilises it (gain-reduction margin {m.gain_reduction_margin_db:.1f} dB down"
            f" at {fmt_hz(m.gain_reduction_margin_hz)}; {where})"
        )
    if not m.peak_sensitivity_db <= limits.peak_sensitivity_max_db:
        out.append(
            f"peak sensitivity {m.peak_sensitivity_db:.1f} dB > "
            f"{limits.peak_sensitivity_max_db:g} dB (at {fmt_hz(m.peak_sensitivity_hz)}; {where})"
        )


def distance_reasons(m: Margins, limits: GateLimits, where: str, out: list[str]) -> None:
    """A rejection when the Nyquist curve passes closer to -1 than the stated margin."""
    sm = 10.0 ** (-m.peak_sensitivity_db / 20.0)
    if not sm >= limits.stability_margin_min:
        out.append(
            f"no margin from instability: the Nyquist curve passes within {sm:.3g} of -1"
            f" (< {limits.stability_margin_min:g}; peak sensitivity"
            f" {m.peak_sensitivity_db:.1f} dB at {fmt_hz(m.peak_sensitivity_hz)}; {where})"
        )


def robust_reasons(
    task: RefineTask, which: str, evidence: str, limits: GateLimits,
    band_top_hz: float | None, a_of: Callable[[FloatArray], FloatArray],
    t_of: Callable[[FloatArray], FloatArray], f: FloatArray,
    rejections: list[str], cautions: list[str], symbol: str = "|a T|",
    sparse: tuple[float, float, float] | None = None,
) -> None:
    """Reject when max |a T| >= 1 (not proven stable for every plant the evidence allows),
    caution at >= small_gain_max. Beyond a measured band the reason says how far to measure;
    inside it, where the allowance comes from the interpolation between two measured points
    (`sparse`: the interval and the change across it), that the points do not resolve the
    response there and where to measure denser."""
    v = task.value
    if v < limits.small_gain_max:
        return
    text = (
        f"robust stability ({which}): {symbol} peaks at {v:.3g} at {fmt_hz(task.freq_hz)}"
        f" for {evidence}"
    )
    if v < 1.0:
        cautions.append(text + f" (>= {limits.small_gain_max:g}: little room for plant error)")
        return
    if band_top_hz is not None and task.freq_hz > band_top_hz:
        # Where does the loop stop depending on the unmeasured plant?
        fine = np.geomspace(band_top_hz, f[-1], 400)
        over = fine[a_of(fine) * t_of(fine) >= 1.0]
        top = float(over[-1]) if over.size else task.freq_hz
        rejections.append(
            text + f": the loop depends on the plant above the measured band "
            f"({fmt_hz(band_top_hz)}), known there only within the bound; "
            f"measure up to {round_up(top)} Hz first"
        )
        return
    if sparse is not None:
        lo, hi, change = sparse
        rejections.append(
            text + f" >= 1: the measured points do not resolve the response there (it changes"
            f" by a factor {math.exp(change):.3g} between {fmt_hz(lo)} and {fmt_hz(hi)},"
            f" a sharp mode may sit between them): measure denser between {fmt_hz(lo)} and"
            f" {fmt_hz(hi)} first"
        )
        return
    rejections.append(text + " >= 1: not proven stable for every plant this evidence allows")


def on_grid(x: FloatArray, vals: FloatArray) -> Callable[[FloatArray], FloatArray]:
    """vals (given at log frequencies x) as a function of frequency, linear in log f."""

    def at(ff: FloatArray) -> FloatArray:
        return np.asarray(np.interp(np.log(ff), x, vals), dtype=np.float64)

    return at


def round_up(f: float) -> str:
    """A frequency rounded up to two significant digits."""
    e = 10.0 ** (math.floor(math.log10(f)) - 1)
    return f"{math.ceil(f / e) * e:.3g}"
