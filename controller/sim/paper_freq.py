"""Frequency-domain results of the article (continuous time, control.md's formulas).

- Disturbance responses, eqs. (16) and (18): E2 = Gdw with the DOB = P (1 - Q) / D,
  D = 1 + Cv M P + (P Pn^-1 - 1) Q (eq. 19); E1 = Gdw without it = P / (1 + Cv M P).
- Disturbance suppression, eq. (23), with the article's names: E1/E2 = Gdw(without DOB) /
  Gdw(with DOB) = D / ((1 - Q)(1 + Cv M P)); with P = Pn it is 1/(1 - Q). |E1/E2| > 1
  (positive dB): the DOB rejects better; < 1: it rejects worse (the waterbed near the cut-off).
- Parameter sensitivity, eqs. (28)-(29): the relative change of the reference-to-rate transfer
  function per relative change of P, at the plant P':
  S_P'^W1 = 1 / (1 + Cv M P')                 (no DOB, W1 = Cv M P / (1 + Cv M P))
  S_P'^W2 = (1 - Q) / D(P')                   (DOB, W2 = Cv M P / D)

M = Mn (the drive is modelled exactly), Cv = kp (1 + ki/s), Q by its -3 dB cut-off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controller.core.arrays import ComplexArray, FloatArray
from controller.core.config import LoopConfig
from controller.core.qfilter import design_q
from controller.sim.linear_rig import PlantVariant

__all__ = [
    "DisturbanceResponses",
    "SensitivityCurves",
    "SuppressionCurve",
    "disturbance_responses",
    "loop_parts",
    "sensitivity_curves",
    "suppression_curve",
]

NOMINAL = PlantVariant("nominal")


def _grid(freq_hz: FloatArray | None) -> FloatArray:
    """`freq_hz`, or the default grid of the curves: 2000 points log-spaced over 0.01-100 Hz."""
    return np.geomspace(0.01, 100.0, 2000) if freq_hz is None else np.asarray(freq_hz, float)


def loop_parts(
    cfg: LoopConfig, q_type: str, cutoff_hz: float, variant: PlantVariant, freq_hz: FloatArray
) -> tuple[ComplexArray, ComplexArray, ComplexArray, ComplexArray]:
    """Responses at `freq_hz`: (Cv M P', P' Pn^-1, Q, Cv)."""
    s = 1j * 2.0 * math.pi * np.asarray(freq_hz, float)
    nom = cfg.nominal
    cv = cfg.cv_kp * (1.0 + cfg.cv_ki_per_s / s)
    m = 1.0 / np.polyval(nom.mn_den, s)
    pn = np.polyval(nom.pn_num, s) / np.polyval(nom.pn_den, s)
    p = variant.response(nom, freq_hz)
    qn, qd = design_q(q_type, cutoff_hz=cutoff_hz).tf()  # type: ignore[arg-type]
    q = np.polyval(qn, s) / np.polyval(qd, s)
    return cv * m * p, p / pn, q, cv


@dataclass(frozen=True)
class SuppressionCurve:
    q_type: str
    cutoff_hz: float
    plant: str
    freq_hz: FloatArray
    gain_db: FloatArray
    """20 log10 |E1/E2| (eq. 23): > 0 where the DOB rejects better."""

    @property
    def waterbed_db(self) -> float:
        """The lowest |E1/E2| in dB: how much worse the DOB rejects at its worst."""
        return float(np.min(self.gain_db))

    @property
    def waterbed_hz(self) -> float:
        return float(self.freq_hz[int(np.argmin(self.gain_db))])

    def at(self, f_hz: float) -> float:
        """|E1/E2| in dB at `f_hz` (interpolated on log f)."""
        return float(np.interp(math.log(f_hz), np.log(self.freq_hz), self.gain_db))

    @property
    def crossover_hz(self) -> float:
        """Lowest frequency where |E1/E2| falls to 0 dB: below it the DOB helps."""
        below = np.nonzero(self.gain_db <= 0.0)[0]
        return float(self.freq_hz[below[0]]) if below.size else math.inf


def suppression_curve(
    cfg: LoopConfig,
    q_type: str,
    cutoff_hz: float,
    variant: PlantVariant = NOMINAL,
    freq_hz: FloatArray | None = None,
) -> SuppressionCurve:
    f = _grid(freq_hz)
    r = disturbance_responses(cfg, q_type, cutoff_hz, variant, f)
    return SuppressionCurve(q_type, cutoff_hz, variant.label, f, r.e1_db - r.e2_db)


@dataclass(frozen=True)
class DisturbanceResponses:
    q_type: str
    cutoff_hz: float
    plant: str
    freq_hz: FloatArray
    e1_db: FloatArray
    """|Gdw| without the DOB, eq. (18), in dB."""
    e2_db: FloatArray
    """|Gdw| with the DOB, eq. (16), in dB."""

    def peak(self, which: str) -> tuple[float, float]:
        """(peak dB, its frequency Hz) of 'e1' or 'e2'."""
        g = self.e1_db if which == "e1" else self.e2_db
        i = int(np.argmax(g))
        return float(g[i]), float(self.freq_hz[i])


def disturbance_responses(
    cfg: LoopConfig,
    q_type: str,
    cutoff_hz: float,
    variant: PlantVariant = NOMINAL,
    freq_hz: FloatArray | None = None,
) -> DisturbanceResponses:
    """Eqs. (16) and (18) at `freq_hz` (default 0.01-100 Hz)."""
    f = _grid(freq_hz)
    lp, ppn, q, _ = loop_parts(cfg, q_type, cutoff_hz, variant, f)
    p = variant.response(cfg.nominal, f)
    e2 = p * (1.0 - q) / (1.0 + lp + (ppn - 1.0) * q)
    e1 = p / (1.0 + lp)
    return DisturbanceResponses(q_type, cutoff_hz, variant.label, f,
                                20.0 * np.log10(np.abs(e1)), 20.0 * np.log10(np.abs(e2)))


@dataclass(frozen=True)
class SensitivityCurves:
    plant: str
    freq_hz: FloatArray
    s1_db: FloatArray
    """|S_P'^W1| in dB (no DOB)."""
    s2_db: FloatArray
    """|S_P'^W2| in dB (DOB)."""

    def at(self, f_hz: float) -> tuple[float, float]:
        lf = np.log(self.freq_hz)
        x = math.log(f_hz)
        return float(np.interp(x, lf, self.s1_db)), float(np.interp(x, lf, self.s2_db))

    @property
    def dob_less_sensitive_below_hz(self) -> float:
        """Highest frequency up to which |S2| <= |S1| holds without a break from the lowest."""
        worse = np.nonzero(self.s2_db > self.s1_db)[0]
        return float(self.freq_hz[worse[0]]) if worse.size else math.inf

    @property
    def worst_excess_db(self) -> float:
        """max(|S2| - |S1|) in dB: how much more sensitive the DOB loop gets anywhere."""
        return float(np.max(self.s2_db - self.s1_db))


def sensitivity_curves(
    cfg: LoopConfig, variant: PlantVariant, freq_hz: FloatArray | None = None
) -> SensitivityCurves:
    f = _grid(freq_hz)
    lp, ppn, q, _ = loop_parts(cfg, cfg.q_type, cfg.q_cutoff_hz, variant, f)
    d = 1.0 + lp + (ppn - 1.0) * q
    s1 = 1.0 / (1.0 + lp)
    s2 = (1.0 - q) / d
    return SensitivityCurves(
        variant.label, f, 20.0 * np.log10(np.abs(s1)), 20.0 * np.log10(np.abs(s2))
    )
