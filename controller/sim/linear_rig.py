"""A linear rig: the article's block diagram w = P (M u + d) with a perturbed P, sampled exactly.

For the article's robustness cases (Figs. 8-9: "40 % low-frequency model uncertainty and an
unmodelled 5 Hz mode"): the true plant is

    P'(s) = gain * Pn(s) * R(s),   R(s) = (s^2/wz^2 + 2 zz s/wz + 1) / (s^2/wp^2 + 2 zp s/wp + 1)

(an extra pair of conjugate poles at `mode_hz` and zeros at `antimode_hz`; gain 1.4 or 0.6 is
the 40 % error), M = Mn. d is a rate disturbance at P's input (control.md), in deg/s. The
command u and d are held over each period (ZOH, exact matrix exponential); the rate is the
backward difference of the position over one period, as on the simulated and the real rig.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
import numpy.typing as npt

from controller.core.config import NominalModel
from controller.core.errors import ConfigError
from controller.core.lti import tf2ss
from controller.core.validate import check_fields, nonnegative, positive

__all__ = ["BacklashRig", "LinearRig", "PlantVariant", "backlash_period", "linear_period"]

_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True, slots=True)
class PlantVariant:
    """P' = gain Pn R: see the module docstring. mode_hz = 0: no extra mode."""

    label: str
    gain: Annotated[float, positive] = 1.0
    mode_hz: float = 0.0
    mode_damping: float = 0.05
    antimode_hz: float = 0.0
    antimode_damping: float = 0.05

    def __post_init__(self) -> None:
        check_fields(self)
        if self.mode_hz < 0.0 or (self.mode_hz > 0.0 and self.antimode_hz <= 0.0):
            raise ConfigError("antimode_hz", "a mode needs its pair of zeros (antimode_hz > 0)")

    def mode_polys(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(numerator, denominator) of R(s), highest power first."""
        if self.mode_hz == 0.0:
            return np.array([1.0]), np.array([1.0])
        wz = _TWO_PI * self.antimode_hz
        wp = _TWO_PI * self.mode_hz
        num = np.array([1.0 / wz**2, 2.0 * self.antimode_damping / wz, 1.0])
        den = np.array([1.0 / wp**2, 2.0 * self.mode_damping / wp, 1.0])
        return num, den

    def p_polys(
        self, nominal: NominalModel
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(numerator, denominator) of P'(s)."""
        rn, rd = self.mode_polys()
        num = self.gain * np.polymul(np.asarray(nominal.pn_num, float), rn)
        den = np.polymul(np.asarray(nominal.pn_den, float), rd)
        return num, den

    def response(self, nominal: NominalModel, freq_hz: npt.ArrayLike) -> npt.NDArray[np.complex128]:
        """P'(j 2 pi f)."""
        s = 1j * _TWO_PI * np.asarray(freq_hz, float)
        num, den = self.p_polys(nominal)
        return np.asarray(np.polyval(num, s) / np.polyval(den, s), dtype=np.complex128)


def _ss(num: npt.NDArray[np.float64], den: npt.NDArray[np.float64]) -> tuple[np.ndarray, ...]:
    a, b, c, d = tf2ss(num, den)
    return tuple(np.atleast_2d(np.asarray(m, float)) for m in (a, b, c, d))


FlatModel = tuple[npt.NDArray[np.float64], ...]


def _flat_model(ad: np.ndarray, bd: np.ndarray, c: np.ndarray, d: float) -> FlatModel:
    """(state, A row-major, B's first column, C, [D], scratch) as float64 arrays."""
    n = ad.shape[0]
    return (np.zeros(n), np.ascontiguousarray(ad, dtype=np.float64).ravel(),
            np.ascontiguousarray(bd[:, 0], dtype=np.float64),
            np.ascontiguousarray(c, dtype=np.float64), np.array([d]), np.zeros(n))


def ss_step(x: np.ndarray, a: np.ndarray, b: np.ndarray, u: float, tmp: np.ndarray) -> None:
    """x <- A x + b u, in place (sums in index order)."""
    n = len(x)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += a[i * n + j] * x[j]
        tmp[i] = acc + b[i] * u
    for i in range(n):
        x[i] = tmp[i]


def ss_out(x: np.ndarray, c: np.ndarray) -> float:
    acc = 0.0
    for i in range(len(x)):
        acc += c[i] * x[i]
    return acc


def linear_period(u: float, d: float, pos: float, args: Any) -> float:
    """One period of `LinearRig` (exact ZOH; a plain function of floats and float64 arrays
    updated in place): returns the new load position. args: (x, A row-major, B's u column,
    B's d column, scratch, index of the position in x)."""
    x, a, bu, bd, tmp, cth = args
    n = len(x)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += a[i * n + j] * x[j]
        tmp[i] = acc + (bu[i] * u + bd[i] * d)
    for i in range(n):
        x[i] = tmp[i]
    return float(x[cth])


def backlash_period(u: float, d: float, pos: float, args: Any) -> float:
    """One period of `BacklashRig` (a plain function of floats and float64 arrays updated in
    place): returns the new load position. args: see `BacklashRig.__init__`."""
    sub, dt, half, th, xm, am, bm, cm, dm, tm, xp, ap, bp, cp, dp, tp = args
    th_m = th[0]
    th_in = th[1]
    for _ in range(sub):
        v = ss_out(xm, cm) + dm[0] * u + d  # motor rate + d (P's input)
        ss_step(xm, am, bm, u, tm)
        th_m_new = th_m + v * dt
        th_in_new = min(max(th_in, th_m_new - half), th_m_new + half)
        v_in = (th_in_new - th_in) / dt
        th_m = th_m_new
        th_in = th_in_new
        w = ss_out(xp, cp) + dp[0] * v_in
        ss_step(xp, ap, bp, v_in, tp)
        pos += w * dt
    th[0] = th_m
    th[1] = th_in
    return pos


class _SpeedRig:
    """What the linear rigs share: `read()` / `step(u)` like SimRig, the rate disturbance d
    (deg/s) sampled per period, and one period as a plain function `period(u, d, pos, args)`
    of the rig's arrays (the compiled offline loop, `controller.sim.offline`, runs it too)."""

    __slots__ = ("_args", "_d", "_k", "_pos", "_rate", "_ts")

    @staticmethod
    def period(u: float, d: float, pos: float, args: Any) -> float:
        raise NotImplementedError

    def __init__(self, rate_hz: float, speed_disturbance: Callable[[float], float] | None) -> None:
        self._ts = 1.0 / rate_hz
        self._d = speed_disturbance
        self._k = 0
        self._pos = 0.0
        self._rate = 0.0
        self._args: tuple[Any, ...] = ()

    @property
    def period_s(self) -> float:
        return self._ts

    @property
    def args(self) -> tuple[Any, ...]:
        """The rig's arrays (updated in place by `period`) and constants."""
        return self._args

    def read(self) -> tuple[float, float]:
        return self._pos, self._rate

    def step(self, command_deg_s: float) -> None:
        d = 0.0 if self._d is None else self._d(self._k * self._ts)
        pos = self.period(command_deg_s, d, self._pos, self._args)
        self._rate = (pos - self._pos) / self._ts
        self._pos = pos
        self._k += 1

    # -- for the compiled offline loop

    def disturbances(self, n: int) -> npt.NDArray[np.float64]:
        """d of the next `n` steps, sampled as `step` samples it."""
        k0, ts = self._k, self._ts
        if self._d is None:
            return np.zeros(n)
        return np.array([self._d(k * ts) for k in range(k0, k0 + n)], dtype=np.float64)

    def advanced(self, n: int, pos_deg: float, rate_deg_s: float) -> None:
        """`period` was run outside for `n` steps, the last reading (pos, rate)."""
        self._k += n
        self._pos = pos_deg
        self._rate = rate_deg_s


class LinearRig(_SpeedRig):
    """`read()` / `step(u)` like SimRig, for the linear plant Mn, P'. `speed_disturbance(t)`
    gives d (deg/s) per period."""

    __slots__ = ()

    period = staticmethod(linear_period)

    def __init__(
        self,
        variant: PlantVariant,
        nominal: NominalModel | None = None,
        *,
        rate_hz: float = 1000.0,
        speed_disturbance: Callable[[float], float] | None = None,
    ) -> None:
        super().__init__(rate_hz, speed_disturbance)
        (a1, b1, c1, d1), (a2, b2, c2, d2) = _m_and_p(variant, nominal)
        n1, n2 = a1.shape[0], a2.shape[0]
        n = n1 + n2 + 1
        # x = [x1 (M); x2 (P'); theta], inputs [u, d]: v = C1 x1 + D1 u + d, w = C2 x2 + D2 v.
        a = np.zeros((n, n))
        b = np.zeros((n, 2))
        a[:n1, :n1] = a1
        b[:n1, 0] = b1[:, 0]
        a[n1 : n1 + n2, :n1] = b2 @ c1
        a[n1 : n1 + n2, n1 : n1 + n2] = a2
        b[n1 : n1 + n2, 0] = (b2 * d1[0, 0])[:, 0]
        b[n1 : n1 + n2, 1] = b2[:, 0]
        a[n - 1, :n1] = d2[0, 0] * c1[0]
        a[n - 1, n1 : n1 + n2] = c2[0]
        b[n - 1, 0] = d2[0, 0] * d1[0, 0]
        b[n - 1, 1] = d2[0, 0]
        ad, bd = _zoh(a, b, self._ts)
        self._args = (np.zeros(n), np.ascontiguousarray(ad, dtype=np.float64).ravel(),
                      np.ascontiguousarray(bd[:, 0]), np.ascontiguousarray(bd[:, 1]),
                      np.zeros(n), n - 1)


def _expm(m: np.ndarray) -> np.ndarray:
    # scipy.linalg on first use: importing this module (the compiled offline loop does, for
    # the nonlinear check before an apply) does not pay for it.
    from scipy import linalg

    return np.asarray(linalg.expm(m))


def _m_and_p(
    variant: PlantVariant, nominal: NominalModel | None
) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """State spaces (A, B, C, D) of the nominal motor model Mn and of the variant's plant P'."""
    nominal = nominal or NominalModel()
    return _ss(np.array([1.0]), np.asarray(nominal.mn_den, float)), _ss(*variant.p_polys(nominal))


def _zoh(a: np.ndarray, b: np.ndarray, ts: float) -> tuple[np.ndarray, np.ndarray]:
    n, m = a.shape[0], b.shape[1]
    big = np.zeros((n + m, n + m))
    big[:n, :n] = a
    big[:n, n:] = b
    e = _expm(big * ts)
    return e[:n, :n], e[:n, n:]


class BacklashRig(_SpeedRig):
    """The linear rig with backlash at P's input: the motor angle (integral of M u + d) drives
    P's input angle through a play of total width `backlash_deg` (the input stays put until
    the motor has crossed the gap, then follows it), the article's backlash as a rate
    disturbance at P's input. Integrated with `substeps` ZOH sub-steps per period (M and P
    exact per sub-step, P's input rate held over a sub-step); the rate is the backward
    difference of the load position over one period, as on the other rigs."""

    __slots__ = ()

    period = staticmethod(backlash_period)

    def __init__(
        self,
        variant: PlantVariant,
        nominal: NominalModel | None = None,
        *,
        backlash_deg: float,
        rate_hz: float = 1000.0,
        substeps: int = 10,
        speed_disturbance: Callable[[float], float] | None = None,
    ) -> None:
        nonnegative(backlash_deg, "backlash_deg")
        super().__init__(rate_hz, speed_disturbance)
        dt = self._ts / substeps
        (a1, b1, c1, d1), (a2, b2, c2, d2) = _m_and_p(variant, nominal)
        # substeps, dt, half the play, [motor angle, P's input angle], M's arrays, P's arrays
        self._args = (substeps, dt, 0.5 * backlash_deg, np.zeros(2),
                      *_flat_model(*_zoh(a1, b1, dt), c1[0], float(d1[0, 0])),
                      *_flat_model(*_zoh(a2, b2, dt), c2[0], float(d2[0, 0])))
