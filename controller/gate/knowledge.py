"""What the gate knows about the plant: measured responses and uncertainty bounds.

Plain data, validated on construction; the stability analysis (`controller.gate.analysis`)
judges a candidate against a `PlantKnowledge`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

TWO_PI = 2.0 * math.pi

__all__ = [
    "MeasuredResponse",
    "PlantKnowledge",
    "SampledBound",
    "UncertaintyBound",
    "WeightBound",
    "readonly",
]


def readonly(a: np.ndarray) -> np.ndarray:
    """Mark an array read-only (the records are shared between threads)."""
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class MeasuredResponse:
    """A measured (or model-variant) plant response from speed command u to load rate.

    `response` is continuous, G_c(j 2 pi f), unless `sampled` is true: then it is already the
    response of the sampled loop u[k] -> w[k] (what an FRF test run by the loop itself gives).
    """

    name: str
    freq_hz: FloatArray
    response: ComplexArray
    sampled: bool = False

    def __post_init__(self) -> None:
        f = np.array(self.freq_hz, dtype=np.float64)
        h = np.array(self.response, dtype=np.complex128)
        if not isinstance(self.name, str) or not self.name:
            raise ValueError("measured response: a non-empty name is required")
        if f.ndim != 1 or f.size < 2 or h.shape != f.shape:
            raise ValueError(f"measured response {self.name!r}: need >= 2 points, equal sizes")
        if not (np.all(np.isfinite(f)) and np.all(f > 0) and np.all(np.diff(f) > 0)):
            raise ValueError(
                f"measured response {self.name!r}: freq_hz must be > 0 and strictly increasing"
            )
        if not np.all(np.isfinite(h)) or np.any(h == 0):
            raise ValueError(f"measured response {self.name!r}: response must be finite, != 0")
        object.__setattr__(self, "freq_hz", readonly(f))
        object.__setattr__(self, "response", readonly(h))


@dataclass(frozen=True, eq=False)
class WeightBound:
    """Multiplicative uncertainty bound |Delta(jw)| <= |W(jw)|, W first order plus a mode.

    W1(s) = (tau s + r0) / (tau s / r_inf + 1): r0 = `low_freq_fraction` at DC, |W1| = 1 at
    `unity_freq_hz`, r_inf = `high_freq_fraction` at high frequency. An optional unmodelled
    mode (a resonance at `mode_hz` with damping `mode_damping` missing from the model) adds
    its relative error |s^2 + 2 z wm s| / |s^2 + 2 z wm s + wm^2| to |W1|.
    """

    low_freq_fraction: float
    unity_freq_hz: float
    high_freq_fraction: float = 2.0
    mode_hz: float | None = None
    mode_damping: float = 0.05
    name: str = "bound"

    def __post_init__(self) -> None:
        r0, rinf = self.low_freq_fraction, self.high_freq_fraction
        if not (0.0 <= r0 < 1.0):
            raise ValueError(f"low_freq_fraction must be in [0, 1), got {r0}")
        if not (rinf > 1.0 and math.isfinite(rinf)):
            raise ValueError(f"high_freq_fraction must be > 1, got {rinf}")
        if not (self.unity_freq_hz > 0 and math.isfinite(self.unity_freq_hz)):
            raise ValueError(f"unity_freq_hz must be > 0, got {self.unity_freq_hz}")
        if self.mode_hz is not None and not (self.mode_hz > 0 and math.isfinite(self.mode_hz)):
            raise ValueError(f"mode_hz must be > 0, got {self.mode_hz}")
        if not (0.0 < self.mode_damping < 1.0):
            raise ValueError(f"mode_damping must be in (0, 1), got {self.mode_damping}")

    @property
    def tau_s(self) -> float:
        r0, rinf = self.low_freq_fraction, self.high_freq_fraction
        w1 = TWO_PI * self.unity_freq_hz
        return math.sqrt((1.0 - r0 * r0) / (1.0 - 1.0 / (rinf * rinf))) / w1

    def transfer_function(self) -> tuple[list[float], list[float]]:
        """(num, den) of W1(s), highest power first."""
        tau = self.tau_s
        return [tau, self.low_freq_fraction], [tau / self.high_freq_fraction, 1.0]

    def magnitude(self, freq_hz: ArrayLike) -> FloatArray:
        s = 1j * TWO_PI * np.asarray(freq_hz, dtype=np.float64)
        tau = self.tau_s
        mag = np.abs((tau * s + self.low_freq_fraction) / (tau / self.high_freq_fraction * s + 1))
        if self.mode_hz is not None:
            wm = TWO_PI * self.mode_hz
            a = s * s + 2.0 * self.mode_damping * wm * s
            mag = mag + np.abs(a / (a + wm * wm))
        return np.asarray(mag, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class SampledBound:
    """|W| given at frequencies (interpolated log-log; held constant outside the range)."""

    freq_hz: FloatArray
    mag: FloatArray
    name: str = "bound"

    def __post_init__(self) -> None:
        f = np.array(self.freq_hz, dtype=np.float64)
        m = np.array(self.mag, dtype=np.float64)
        if f.ndim != 1 or f.size < 1 or m.shape != f.shape:
            raise ValueError("sampled bound: freq_hz and mag must be 1-D of equal size")
        if not (np.all(np.isfinite(f)) and np.all(f > 0) and np.all(np.diff(f) > 0)):
            raise ValueError("sampled bound: freq_hz must be > 0 and strictly increasing")
        if not (np.all(np.isfinite(m)) and np.all(m > 0)):
            raise ValueError("sampled bound: mag must be finite and > 0")
        object.__setattr__(self, "freq_hz", readonly(f))
        object.__setattr__(self, "mag", readonly(m))

    def magnitude(self, freq_hz: ArrayLike) -> FloatArray:
        x = np.log(np.asarray(freq_hz, dtype=np.float64))
        return np.exp(np.interp(x, np.log(self.freq_hz), np.log(self.mag)))


UncertaintyBound = WeightBound | SampledBound


@dataclass(frozen=True, eq=False)
class PlantKnowledge:
    """What is known of the real plant besides the nominal model (which is cfg.nominal)."""

    measured: tuple[MeasuredResponse, ...] = ()
    bound: UncertaintyBound | None = None

    def __post_init__(self) -> None:
        names = [m.name for m in self.measured]
        if len(set(names)) != len(names):
            raise ValueError(f"measured responses need distinct names, got {names}")


