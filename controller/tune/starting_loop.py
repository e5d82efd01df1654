"""The starting speed PI: placed by a stated procedure on the nominal model, not fitted to the
article's results (the article gives no Cv). docs/starting_loop.md explains the choice.

Procedure, for Cv(s) = Kp (1 + w_i / s) on L(s) = Cv(s) Mn(s) Pn(s) exp(-s T_d):
1. The loop delay T_d is one control period (half from the command held over the tick, half
   from the backward-difference rate the controller computes).
2. The integral corner sits at a fixed fraction of the crossover, w_i = w_c / r with r = 4
   (below the third a conventional PI keeps; the PI then costs atan(1/r) = 14 deg at w_c).
3. The crossover w_c is where the phase of L is -180 deg + the phase margin PM; Kp makes
   |L(j w_c)| = 1.
4. PM starts at the textbook 60 deg and rises in 5 deg steps until the whole servo (with the
   position loop and the DOB of the base configuration, judged by the gate) keeps ||W T|| <=
   0.7 for the article's own uncertainty statement (control.md: 20 % model error at low
   frequency, rising to 100 % at 15 Hz): robust stability with 30 % to spare (the gate
   cautions at 0.8). The model is trusted only at low frequency, so the crossover must stay
   clear of 15 Hz.
Kp and w_i are rounded to three significant figures. On the article's model (eqs. 33-34) at
1 kHz: PM 60 gives ||W T|| 0.87, 65 0.78, 70 0.72, 75 0.66: Cv = 1.35 (1 + 10.8/s), crossover
6.9 Hz, integral corner 1.7 Hz (tests/test_starting_loop.py checks them with python-control).

The position loop keeps Cp = 9 (1 + 3.5/s): with this speed loop closed it crosses over near
1.4 Hz, five times below the speed loop, with ~50 deg phase margin.
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass

from controller.core.config import LoopConfig, NominalModel
from controller.gate.analysis import analyse
from controller.gate.knowledge import PlantKnowledge, WeightBound

__all__ = ["StartingPI", "starting_loop", "starting_speed_pi"]

PHASE_MARGIN_DEG = 60.0
PHASE_MARGIN_STEP_DEG = 5.0
CORNER_RATIO = 4.0
#: control.md's first uncertainty case: 20 % at low frequency, |W| = 1 at 15 Hz.
ARTICLE_BOUND = WeightBound(0.2, 15.0)
ROBUST_PEAK_MAX = 0.7


@dataclass(frozen=True, slots=True)
class StartingPI:
    kp: float
    ki_per_s: float
    crossover_hz: float
    phase_margin_deg: float
    corner_ratio: float
    delay_s: float

    @property
    def corner_hz(self) -> float:
        return self.ki_per_s / (2.0 * math.pi)


def _mp(model: NominalModel, w: float) -> complex:
    s = 1j * w

    def poly(p: tuple[float, float, float]) -> complex:
        return p[0] * s * s + p[1] * s + p[2]

    return poly(model.pn_num) / (poly(model.mn_den) * poly(model.pn_den))


def _phase_deg(model: NominalModel, w: float, delay_s: float, ratio: float) -> float:
    """Phase of L(jw) with w_i = w / ratio, continuous (not wrapped): the model's factors are
    stable and minimum phase, so each quadratic's phase is a 0..180 deg arctan2."""
    s = 1j * w
    total = 0.0
    for p, sign in ((model.pn_num, 1.0), (model.mn_den, -1.0), (model.pn_den, -1.0)):
        z = p[0] * s * s + p[1] * s + p[2]
        total += sign * math.degrees(math.atan2(z.imag, z.real) % (2.0 * math.pi))
    pi = math.degrees(cmath.phase(1.0 + 1.0 / (1j * ratio)))
    return total + pi - math.degrees(w * delay_s)


def starting_speed_pi(
    model: NominalModel | None = None,
    rate_hz: float = 1000.0,
    phase_margin_deg: float = PHASE_MARGIN_DEG,
    corner_ratio: float = CORNER_RATIO,
) -> StartingPI:
    """The procedure of the module docstring (bisection on the continuous phase)."""
    model = model or NominalModel()
    delay = 1.0 / rate_hz
    target = -180.0 + phase_margin_deg
    lo, hi = 1e-3, math.pi * rate_hz
    if _phase_deg(model, lo, delay, corner_ratio) < target:
        raise ValueError(f"no crossover gives {phase_margin_deg} deg phase margin")
    for _ in range(200):
        mid = math.sqrt(lo * hi)
        if _phase_deg(model, mid, delay, corner_ratio) > target:
            lo = mid
        else:
            hi = mid
    wc = math.sqrt(lo * hi)
    kp = 1.0 / (abs(_mp(model, wc)) * abs(1.0 + 1.0 / (1j * corner_ratio)))
    return StartingPI(kp, wc / corner_ratio, wc / (2.0 * math.pi), phase_margin_deg,
                      corner_ratio, delay)


def _rounded(v: float) -> float:
    return float(f"{v:.3g}")


def starting_loop(base: LoopConfig | None = None) -> tuple[LoopConfig, StartingPI, float]:
    """Steps 1-4 of the module docstring on `base` (default: LoopConfig()): the configuration
    with the chosen Cv, the placement it came from, and its whole-servo ||W T||."""
    base = base or LoopConfig()
    knowledge = PlantKnowledge(bound=ARTICLE_BOUND)
    pm = PHASE_MARGIN_DEG
    while pm < 90.0:
        pi = starting_speed_pi(base.nominal, base.rate_hz, pm)
        cfg = base.with_(cv_kp=_rounded(pi.kp), cv_ki_per_s=_rounded(pi.ki_per_s))
        peak = analyse(cfg, knowledge).small_gain_peak
        if peak <= ROBUST_PEAK_MAX:
            return cfg, pi, peak
        pm += PHASE_MARGIN_STEP_DEG
    raise ValueError("no phase margin below 90 deg keeps ||W T|| <= 0.7")
