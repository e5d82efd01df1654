"""The apply gate's limits: below a margin limit a caution, unstable or not proven stable a
rejection (`controller.gate.analysis`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = [
    "GateLimits",
]


@dataclass(frozen=True)
class GateLimits:
    """Limits of the apply gate (validated on construction).

    Below a margin limit the verdict is `caution` (stable on all evidence, applied only with
    confirmation); instability on any evidence, or a robust-stability test at or above 1, is
    `reject`.
    """

    phase_margin_min_deg: float = 30.0
    gain_margin_min_db: float = 6.0
    """Applies to |GM| in dB: an upper margin must exceed it, a gain-reduction margin too."""
    peak_sensitivity_max_db: float = 6.0
    small_gain_max: float = 0.8
    """Caution at or above this robust-stability figure (max |a T| over the evidence's
    allowance a); at or above 1 the loop is not proven stable: reject."""
    pole_radius_max: float = 1.0
    """Strict: every closed-loop pole radius with the plant model must be < this."""
    pole_time_constant_max_s: float = 100.0
    """The margin from instability on the model's poles: every closed-loop mode must decay
    with a time constant below this, radius < exp(-Ts / this) (1 - 1e-5 at 1 kHz); a pole
    at radius 1 - 1e-6 is as good as unstable (a 0.0001 % plant change moves it out)."""
    stability_margin_min: float = 0.1
    """The margin from instability on every loop and every piece of evidence that decides:
    the Nyquist curve must keep this distance from -1 (min |1 + L| at the plant input, the
    inverse of the peak sensitivity: 0.1 is 20 dB; a loop closer is rejected, not cautioned)."""
    check_measured_margins: bool = True
    """Also hold the margins computed with each measured response to the limits."""
    noise_to_command_max_db: float = 20.0
    """Peak gain from speed-measurement noise to the command, |(Cv + F1) / D|: a high Q
    cut-off makes F1 ~ Q (Mn Pn)^-1 differentiate twice and floods the drive with noise."""

    def __post_init__(self) -> None:
        def need(ok: bool, what: str) -> None:
            if not ok:
                raise ValueError(f"GateLimits: {what}")

        need(0.0 <= self.phase_margin_min_deg < 90.0, "phase_margin_min_deg in [0, 90)")
        need(0.0 <= self.gain_margin_min_db < 60.0, "gain_margin_min_db in [0, 60)")
        need(0.0 < self.peak_sensitivity_max_db < 60.0, "peak_sensitivity_max_db in (0, 60)")
        need(0.0 < self.small_gain_max <= 1.0, "small_gain_max in (0, 1]")
        need(0.0 < self.pole_radius_max <= 1.0, "pole_radius_max in (0, 1]")
        need(0.0 < self.pole_time_constant_max_s <= 1e6, "pole_time_constant_max_s in (0, 1e6]")
        need(0.0 <= self.stability_margin_min < 1.0, "stability_margin_min in [0, 1)")
        need(0.0 < self.noise_to_command_max_db <= 80.0, "noise_to_command_max_db in (0, 80]")

    def pole_radius_limit(self, rate_hz: float) -> float:
        """Every closed-loop pole radius must be strictly below this at `rate_hz`."""
        tau = self.pole_time_constant_max_s
        return min(self.pole_radius_max, math.exp(-1.0 / (rate_hz * tau)))
