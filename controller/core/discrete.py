"""Discretisation (off the tick) and the scalar filter runtime (on the tick).

Method: Tustin (bilinear) with frequency prewarping at a chosen frequency (for the DOB filters:
the Q cut-off), applied to poles and zeros directly (`lti.bilinear_zpk`, scipy's bit for bit)
and realised as second-order sections (`lti.zpk2sos`, scipy's 'nearest' pairing) in float64.
No high-order polynomial is ever formed, so a Q31 triple pole near z = 1 keeps its exact DC
gain (control.md, mistake 3).
"""

from __future__ import annotations

import math
from collections.abc import MutableSequence, Sequence

import numpy as np

from controller.core import lti

SosArray = np.ndarray  # shape (n_sections, 6): b0 b1 b2 a0(=1) a1 a2


def prewarped_fs(rate_hz: float, prewarp_hz: float | None) -> float:
    """The 'fs' to hand to the bilinear map so that the response matches at `prewarp_hz`."""
    if prewarp_hz is None:
        return rate_hz
    w = 2.0 * math.pi * prewarp_hz
    return w / (2.0 * math.tan(w / (2.0 * rate_hz)))


def tustin_zpk(
    zeros: Sequence[complex],
    poles: Sequence[complex],
    gain: float,
    rate_hz: float,
    prewarp_hz: float | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    fs = prewarped_fs(rate_hz, prewarp_hz)
    zd, pd, kd = lti.bilinear_zpk(np.asarray(zeros, complex), np.asarray(poles, complex), gain, fs)
    return zd, pd, float(np.real(kd))


def zpk_to_sos(zd: np.ndarray, pd: np.ndarray, kd: float) -> SosArray:
    sos = lti.zpk2sos(zd, pd, kd)
    return np.ascontiguousarray(sos, dtype=np.float64)


def sos_dc_gain(sos: SosArray) -> float:
    g = 1.0
    for b0, b1, b2, _a0, a1, a2 in sos:
        g *= (b0 + b1 + b2) / (1.0 + a1 + a2)
    return float(g)


def sos_response(sos: SosArray, freq_hz: np.ndarray, rate_hz: float) -> np.ndarray:
    """Complex frequency response of the sections at `freq_hz` (vectorised, off the tick)."""
    return sos_responses((sos,), freq_hz, rate_hz)[0]


def sos_responses(soss: Sequence[SosArray], freq_hz: np.ndarray, rate_hz: float
                  ) -> list[np.ndarray]:
    """`sos_response` of each filter in `soss` at the same frequencies (z^-1 computed once)."""
    zinv = np.exp(-2j * np.pi * np.asarray(freq_hz, float) / rate_hz)
    out = []
    for sos in soss:
        h = np.ones_like(zinv)
        for b0, b1, b2, _a0, a1, a2 in sos:
            h *= (b0 + zinv * (b1 + zinv * b2)) / (1.0 + zinv * (a1 + zinv * a2))
        out.append(h)
    return out


# -- the tick's filter arithmetic: plain functions of flat sequences (a tuple and a list in the
# live loop, float64 arrays in the compiled offline loop, `controller.sim.offline`), so that
# both run this one definition.

#: Coefficients b0 b1 b2 a1 a2 per section, and two states per section.
SosCoefficients = Sequence[float] | np.ndarray
SosStates = MutableSequence[float] | np.ndarray


def sos_step(c: SosCoefficients, s: SosStates, n: int, x: float) -> float:
    """One sample through `n` second-order sections, transposed direct form II: `c` holds
    b0 b1 b2 a1 a2 of each section in turn, `s` its two states (updated in place)."""
    j = 0
    m = 0
    for _ in range(n):
        y = c[j] * x + s[m]
        s[m] = c[j + 1] * x - c[j + 3] * y + s[m + 1]
        s[m + 1] = c[j + 2] * x - c[j + 4] * y
        x = y
        j += 5
        m += 2
    return x


def sos_set_steady(c: SosCoefficients, s: SosStates, n: int, x: float) -> float:
    """Put the states `s` at the steady state for a constant input x; returns the output."""
    for i in range(n):
        j = 5 * i
        b0 = c[j]
        b1 = c[j + 1]
        b2 = c[j + 2]
        a1 = c[j + 3]
        a2 = c[j + 4]
        y = x * (b0 + b1 + b2) / (1.0 + a1 + a2)
        s[2 * i + 1] = b2 * x - a2 * y
        s[2 * i] = y - b0 * x
        x = y
    return x


class SosFilter:
    """Cascade of second-order sections, transposed direct form II, scalar float64 arithmetic.

    `step` is the hot-path call; `set_steady` puts every state at the steady state for a
    constant input (used for bumpless coefficient changes).
    """

    __slots__ = ("_c", "_n", "_s")

    def __init__(self, sos: SosArray) -> None:
        arr = np.asarray(sos, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 6 or not np.all(np.isfinite(arr)):
            raise ValueError("sos: expected a finite (n, 6) array")
        if not np.allclose(arr[:, 3], 1.0):
            raise ValueError("sos: a0 of every section must be 1")
        flat: list[float] = []
        for b0, b1, b2, _a0, a1, a2 in arr:
            flat += [float(b0), float(b1), float(b2), float(a1), float(a2)]
        self._c = tuple(flat)
        self._n = len(arr)
        self._s = [0.0] * (2 * self._n)

    @property
    def n_sections(self) -> int:
        return self._n

    def step(self, x: float) -> float:
        return sos_step(self._c, self._s, self._n, x)

    def dc_gain(self) -> float:
        c = self._c
        g = 1.0
        for i in range(self._n):
            j = 5 * i
            g *= (c[j] + c[j + 1] + c[j + 2]) / (1.0 + c[j + 3] + c[j + 4])
        return g

    def set_steady(self, x: float) -> float:
        """States for a constant input x held forever; returns the steady output."""
        return sos_set_steady(self._c, self._s, self._n, x)

    @property
    def coefficients(self) -> tuple[float, ...]:
        """b0 b1 b2 a1 a2 of each section in turn (what `sos_step` takes)."""
        return self._c

    @property
    def states(self) -> list[float]:
        """The two states of each section in turn, live (what `sos_step` updates)."""
        return self._s

    def reset(self) -> None:
        for i in range(len(self._s)):
            self._s[i] = 0.0
