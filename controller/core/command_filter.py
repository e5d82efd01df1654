"""The optional filter on the speed command: a notch or a low-pass on Cv's output.

Where a resonance of the mechanics limits the speed loop, a notch at the resonance (or a
second-order low-pass well above the speed crossover) on the speed controller's output lets
the crossover stay where the rigid-body plant allows. The filter sits between Cv and the DOB
(control.md): v_f = N(z) Cv(z) e, u = sat(v_f - d_hat). It is off by default, and off it is no
element of the tick at all (zero sections: the command passes through unchanged, bit for bit).

Continuous prototypes (w0 = 2 pi f0):

    notch   N(s) = (s^2 + 2 zeta_z w0 s + w0^2) / (s^2 + 2 zeta_p w0 s + w0^2),
            zeta_p = notch_width, zeta_z = zeta_p 10^(-notch_depth_db / 20):
            unity gain at DC and far above, |N(j w0)| = -notch_depth_db dB;
    lowpass N(s) = w0^2 / (s^2 + 2 zeta w0 s + w0^2), zeta = lowpass_damping.

Discretised off the tick by Tustin prewarped at f0 (the notch's centre or the low-pass's
corner is exactly where it was asked for) into one biquad, run on the tick by
`controller.core.discrete.sos_step` on preallocated plain-float state.
"""

from __future__ import annotations

import math

import msgspec
import numpy as np

from controller.core.discrete import SosArray
from controller.core.errors import ConfigError
from controller.core.validate import in_range, number

FILTER_KINDS = ("off", "notch", "lowpass")
#: The filter's frequency may be at most this fraction of the loop rate (below Nyquist, with
#: room for the prewarp: tan(pi f0 / rate) stays finite and well conditioned).
MAX_FRACTION_OF_RATE = 0.45
NOTCH_DEPTH_DB_RANGE = (1.0, 60.0)
NOTCH_WIDTH_RANGE = (0.02, 2.0)
LOWPASS_DAMPING_RANGE = (0.1, 2.0)


class CommandFilter(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The speed-command filter's settings (only those of `kind` are used)."""

    kind: str = "off"
    notch_hz: float = 50.0
    notch_depth_db: float = 20.0
    notch_width: float = 0.3
    lowpass_hz: float = 200.0
    lowpass_damping: float = 0.707

    def __post_init__(self) -> None:
        if self.kind not in FILTER_KINDS:
            raise ConfigError(
                "command_filter.kind",
                f"unknown filter {self.kind!r}; expected one of {', '.join(FILTER_KINDS)}",
            )
        for name in ("notch_hz", "lowpass_hz"):
            f = number(getattr(self, name), f"command_filter.{name}")
            if not f > 0.0:
                raise ConfigError(f"command_filter.{name}", f"must be > 0 Hz, got {f}")
        in_range(self.notch_depth_db, "command_filter.notch_depth_db", *NOTCH_DEPTH_DB_RANGE)
        in_range(self.notch_width, "command_filter.notch_width", *NOTCH_WIDTH_RANGE)
        in_range(self.lowpass_damping, "command_filter.lowpass_damping", *LOWPASS_DAMPING_RANGE)

    @property
    def frequency_hz(self) -> float:
        return self.notch_hz if self.kind == "notch" else self.lowpass_hz

    def check_rate(self, rate_hz: float) -> None:
        """The frequency in use must lie below Nyquist (with margin) at `rate_hz`."""
        if self.kind == "off":
            return
        name = "notch_hz" if self.kind == "notch" else "lowpass_hz"
        f = self.frequency_hz
        top = MAX_FRACTION_OF_RATE * rate_hz
        if f >= top:
            raise ConfigError(
                f"command_filter.{name}",
                f"{f} Hz is at or above {top:g} Hz ({MAX_FRACTION_OF_RATE} x the loop rate; "
                f"Nyquist is {rate_hz / 2:g} Hz)",
            )

    def describe(self) -> str:
        if self.kind == "notch":
            return (f"notch at {self.notch_hz:.4g} Hz, {self.notch_depth_db:.3g} dB deep, "
                    f"width (pole damping) {self.notch_width:.3g}")
        if self.kind == "lowpass":
            return (f"2nd-order low-pass at {self.lowpass_hz:.4g} Hz, damping "
                    f"{self.lowpass_damping:.3g}")
        return "off"


Poly2 = tuple[float, float, float]


def continuous_tf(cf: CommandFilter) -> tuple[Poly2, Poly2]:
    """(num, den) of N(s), coefficients of s^2, s, 1; (1), (1) when off."""
    if cf.kind == "off":
        return (0.0, 0.0, 1.0), (0.0, 0.0, 1.0)
    w0 = 2.0 * math.pi * cf.frequency_hz
    if cf.kind == "notch":
        zp = cf.notch_width
        zz = zp * 10.0 ** (-cf.notch_depth_db / 20.0)
        return (1.0, 2.0 * zz * w0, w0 * w0), (1.0, 2.0 * zp * w0, w0 * w0)
    z = cf.lowpass_damping
    return (0.0, 0.0, w0 * w0), (1.0, 2.0 * z * w0, w0 * w0)


def biquad(cf: CommandFilter, rate_hz: float) -> tuple[float, float, float, float, float]:
    """b0 b1 b2 a1 a2 (a0 = 1) of the Tustin-prewarped biquad of N(s) (not for 'off')."""
    cf.check_rate(rate_hz)
    (b2, b1, b0), (a2, a1, a0) = continuous_tf(cf)
    w0 = 2.0 * math.pi * cf.frequency_hz
    k = w0 / math.tan(w0 / (2.0 * rate_hz))  # s = k (1 - z^-1) / (1 + z^-1), prewarped at f0
    kk = k * k
    n0, n1, n2 = b2 * kk + b1 * k + b0, 2.0 * (b0 - b2 * kk), b2 * kk - b1 * k + b0
    d0, d1, d2 = a2 * kk + a1 * k + a0, 2.0 * (a0 - a2 * kk), a2 * kk - a1 * k + a0
    return n0 / d0, n1 / d0, n2 / d0, d1 / d0, d2 / d0


def command_filter_sos(cf: CommandFilter, rate_hz: float) -> SosArray:
    """The filter as second-order sections (n, 6): none when off, one biquad otherwise."""
    if cf.kind == "off":
        return np.zeros((0, 6))
    b0, b1, b2, a1, a2 = biquad(cf, rate_hz)
    return np.array([[b0, b1, b2, 1.0, a1, a2]])


def command_filter_response(cf: CommandFilter, freq_hz: np.ndarray, rate_hz: float) -> np.ndarray:
    """N(e^{jwT}) of the implemented biquad at `freq_hz` (ones when off)."""
    f = np.asarray(freq_hz, dtype=np.float64)
    if cf.kind == "off":
        return np.ones(f.shape, dtype=np.complex128)
    b0, b1, b2, a1, a2 = biquad(cf, rate_hz)
    zinv = np.exp(-2j * np.pi * f / rate_hz)
    out: np.ndarray = (b0 + zinv * (b1 + zinv * b2)) / (1.0 + zinv * (a1 + zinv * a2))
    return out
