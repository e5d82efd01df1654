"""What the gate's analysis returns: each piece of evidence's result and the whole analysis of
a candidate (plain data; `controller.gate.analysis` computes them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from controller.core.arrays import ComplexArray, FloatArray
from controller.core.config import LoopConfig
from controller.core.verdict import VerdictKind
from controller.gate.margins import (
    LoopCrossings,
    Margins,
)

__all__ = [
    "Analysis",
    "SourceResult",
]


@dataclass(frozen=True, eq=False)
class SourceResult:
    """What one piece of evidence says about the candidate.

    kind "model": the plant model (exact closed-loop poles) with its stated bound as the
    allowance; "measured": a measured response (winding number on a refined grid) with the
    allowance between its points and the bound beyond its band.
    """

    name: str
    kind: Literal["model", "measured", "bound"]
    small_gain_peak: float
    """Robust-stability figure max |a T| with the speed loop alone (nan: no allowance)."""
    small_gain_freq_hz: float
    small_gain_full_peak: float
    """The same with the position loop closed."""
    small_gain_full_freq_hz: float
    delta_q_peak: float
    """max |a Q| (display only; not a sufficient condition)."""
    delta_q_freq_hz: float
    base_loop_stable: bool
    """The loop with this evidence's plant (model: exact poles; measured: the interpolated
    response, argument principle), speed loop alone and whole servo."""
    margins: Margins | None
    """Margins of the speed loop at the plant input with this evidence's plant."""
    inv_delta_db: FloatArray
    """20 log10 (1 / a) on the analysis grid: the plant change this evidence allows."""
    margins_full: Margins | None = None
    """Margins of the whole servo (position loop closed) at the plant input."""
    band_hz: tuple[float, float] | None = None
    """The measured band (measured responses only)."""


@dataclass(frozen=True, eq=False)
class Analysis:
    """Everything the dashboard plots and the gate decides on, for one candidate."""

    config: LoopConfig
    tau_s: float
    freq_hz: FloatArray
    open_loop: ComplexArray
    """L_u on the grid (plant model; DOB off: G Cv)."""
    open_loop_mag_db: FloatArray
    open_loop_phase_deg: FloatArray
    """Unwrapped."""
    closed_loop: ComplexArray
    """Gyw with the configured DOB state (eq. 15, or eq. 18 when the DOB is off)."""
    closed_loop_dob: ComplexArray
    """Gyw with the DOB on (eq. 15), whatever cfg.dob_on."""
    closed_loop_no_dob: ComplexArray
    """Gyw without the DOB (eq. 18)."""
    disturbance_dob: ComplexArray
    """Gdw with the DOB (eq. 16)."""
    disturbance_no_dob: ComplexArray
    """Gdw without the DOB (eq. 18)."""
    noise_dob: ComplexArray
    """Gzw with the DOB (eq. 17)."""
    noise_no_dob: ComplexArray
    q_mag_db: FloatArray
    """|F2| (the implemented Q) in dB."""
    rejection_db: FloatArray
    """eq. 23: 20 log10 |E_without / E_with|; > 0 where the DOB helps."""
    margins: Margins
    """Speed loop at the plant input, plant model."""
    bandwidth_hz: float
    """-3 dB bandwidth of the speed closed loop Gyw (configured DOB state)."""
    poles: ComplexArray
    """Closed-loop eigenvalues of the whole discrete servo with the plant model."""
    max_pole_radius: float
    """Over the whole servo and the speed loop alone."""
    sources: tuple[SourceResult, ...]
    small_gain_peak: float
    """Largest robust-stability figure over all evidence and both loops (nan without)."""
    verdict: VerdictKind
    reasons: tuple[str, ...]
    """Rejections first, then cautions."""
    noise_to_command_peak_db: float = math.nan
    """max |(Cv + F1)/D| in dB: how much speed-measurement noise reaches the command."""
    rejections: tuple[str, ...] = ()
    cautions: tuple[str, ...] = ()
    margins_full: Margins | None = None
    """The whole servo (position loop closed) at the plant input, plant model."""
    knowledge: str = ""
    """Which plant knowledge the verdict used (`PlantKnowledge.describe`)."""
    open_loop_full: ComplexArray | None = None
    """The whole servo's loop at the plant input, G (C_tot + F1) / (1 - F2 z^-1), plant model."""
    crossings: LoopCrossings | None = None
    """Where `margins` are read: the speed loop's refined crossings (plant model)."""

    @property
    def accepted(self) -> bool:
        """Accepted without reservation."""
        return self.verdict == "accept"

    @property
    def applicable(self) -> bool:
        """Accepted, or `caution` (applied only with confirmation)."""
        return self.verdict != "reject"

    @property
    def gain_margin_db(self) -> float:
        return self.margins.gain_margin_db

    @property
    def phase_margin_deg(self) -> float:
        return self.margins.phase_margin_deg

    @property
    def peak_sensitivity_db(self) -> float:
        return self.margins.peak_sensitivity_db

    @property
    def delay_margin_s(self) -> float:
        return self.margins.delay_margin_s
