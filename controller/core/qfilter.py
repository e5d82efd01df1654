"""Q-filters of the rate-difference DOB (control.md eqs. 30-32), designed by -3 dB cut-off.

    Q20(s) = 1 / (tau s + 1)^2
    Q31(s) = (3 tau s + 1) / (tau s + 1)^3

The cut-off is the half-power (-3 dB) frequency f_c = k / tau with k = x / (2 pi), where x is the
root of |Q(j x / tau)|^2 = 1/2; x is computed here from the closed form, not hard-coded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from controller.core.errors import ConfigError
from controller.core.validate import positive

QType = Literal["q20", "q31"]
Q_TYPES: tuple[QType, ...] = ("q20", "q31")


def _q31_half_power_x() -> float:
    # |Q31(jx)|^2 = (1 + 9 y) / (1 + y)^3 = 1/2 with y = x^2  <=>  y^3 + 3 y^2 - 15 y - 1 = 0.
    # Newton from y = 2.7 (the only positive root is ~2.6977).
    y = 2.7
    for _ in range(50):
        f = y**3 + 3 * y**2 - 15 * y - 1
        y -= f / (3 * y**2 + 6 * y - 15)
    return math.sqrt(y)


#: omega * tau at the -3 dB point.
HALF_POWER_OMEGA_TAU: dict[QType, float] = {
    "q20": math.sqrt(math.sqrt(2.0) - 1.0),  # 0.643594
    "q31": _q31_half_power_x(),  # 1.642474
}
#: f_c * tau (Hz * s): 0.10243 for Q20, 0.26141 for Q31.
CUTOFF_TAU_PRODUCT: dict[QType, float] = {
    k: v / (2.0 * math.pi) for k, v in HALF_POWER_OMEGA_TAU.items()
}


def check_q_type(q_type: object, field: str = "q_type") -> QType:
    if q_type not in Q_TYPES:
        raise ConfigError(field, f"unknown Q type {q_type!r}; expected one of {', '.join(Q_TYPES)}")
    return q_type  # type: ignore[return-value]


def tau_from_cutoff(q_type: QType, cutoff_hz: float) -> float:
    """Time constant tau (s) whose -3 dB frequency is `cutoff_hz`."""
    check_q_type(q_type)
    return CUTOFF_TAU_PRODUCT[q_type] / positive(cutoff_hz, "cutoff_hz")


def cutoff_from_tau(q_type: QType, tau_s: float) -> float:
    check_q_type(q_type)
    return CUTOFF_TAU_PRODUCT[q_type] / positive(tau_s, "tau_s")


@dataclass(frozen=True, slots=True)
class QFilter:
    """A continuous Q-filter: zeros, poles and gain in s (rad/s), plus its polynomial form."""

    q_type: QType
    tau_s: float

    @property
    def cutoff_hz(self) -> float:
        return cutoff_from_tau(self.q_type, self.tau_s)

    def tf(self) -> tuple[list[float], list[float]]:
        """(numerator, denominator) coefficients in s, highest power first, eq. (31)/(32)."""
        t = self.tau_s
        if self.q_type == "q20":
            return [1.0], [t * t, 2.0 * t, 1.0]
        return [3.0 * t, 1.0], [t**3, 3.0 * t * t, 3.0 * t, 1.0]

    def zpk(self) -> tuple[list[float], list[float], float]:
        t = self.tau_s
        if self.q_type == "q20":
            return [], [-1.0 / t] * 2, 1.0 / (t * t)
        return [-1.0 / (3.0 * t)], [-1.0 / t] * 3, 3.0 / (t * t)

    @property
    def relative_degree(self) -> int:
        return 2


def design_q(
    q_type: QType, *, cutoff_hz: float | None = None, tau_s: float | None = None
) -> QFilter:
    """Q-filter from either its -3 dB cut-off in Hz or its time constant in s (exactly one)."""
    check_q_type(q_type)
    if (cutoff_hz is None) == (tau_s is None):
        raise ConfigError("cutoff_hz", "give exactly one of cutoff_hz or tau_s")
    if cutoff_hz is not None:
        return QFilter(q_type, tau_from_cutoff(q_type, cutoff_hz))
    assert tau_s is not None
    return QFilter(q_type, positive(tau_s, "tau_s"))
