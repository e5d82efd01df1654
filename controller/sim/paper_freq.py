"""Frequency-domain results of the article (continuous time, control.md's formulas).

- Disturbance suppression, eq. (23): E1/E2 = Gdw(with DOB) / Gdw(without DOB)
  = (1 - Q)(1 + Cv M P) / D, D = 1 + Cv M P + (P Pn^-1 - 1) Q (eq. 19). With P = Pn it is 1 - Q.
  |E1/E2| < 1 (negative dB): the DOB rejects better; > 1: it amplifies (the waterbed).
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
import numpy.typing as npt

from controller.core.config import LoopConfig
from controller.core.qfilter import QType, design_q
from controller.sim.linear_rig import PlantVariant

__all__ = [
    "SensitivityCurves",
    "SuppressionCurve",
    "cutoff_for_waterbed_at",
    "loop_parts",
    "sensitivity_curves",
    "suppression_curve",
]

FloatArray = npt.NDArray[np.float64]
ComplexArray = npt.NDArray[np.complex128]
NOMINAL = PlantVariant("nominal")


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
    """20 log10 |E1/E2| (eq. 23)."""

    @property
    def peak_db(self) -> float:
        return float(np.max(self.gain_db))

    @property
    def peak_hz(self) -> float:
        return float(self.freq_hz[int(np.argmax(self.gain_db))])

    def at(self, f_hz: float) -> float:
        """|E1/E2| in dB at `f_hz` (interpolated on log f)."""
        return float(np.interp(math.log(f_hz), np.log(self.freq_hz), self.gain_db))

    @property
    def crossover_hz(self) -> float:
        """Lowest frequency where |E1/E2| reaches 0 dB: below it the DOB helps."""
        above = np.nonzero(self.gain_db >= 0.0)[0]
        return float(self.freq_hz[above[0]]) if above.size else math.inf


def suppression_curve(
    cfg: LoopConfig,
    q_type: str,
    cutoff_hz: float,
    variant: PlantVariant = NOMINAL,
    freq_hz: FloatArray | None = None,
) -> SuppressionCurve:
    f = np.geomspace(0.01, 100.0, 2000) if freq_hz is None else np.asarray(freq_hz, float)
    lp, ppn, q, _ = loop_parts(cfg, q_type, cutoff_hz, variant, f)
    d = 1.0 + lp + (ppn - 1.0) * q
    ratio = (1.0 - q) * (1.0 + lp) / d
    return SuppressionCurve(q_type, cutoff_hz, variant.label, f, 20.0 * np.log10(np.abs(ratio)))


def cutoff_for_waterbed_at(q_type: QType, peak_hz: float, cfg: LoopConfig) -> float:
    """The cut-off whose eq. (23) peak (P = Pn: 1 - Q) lies at `peak_hz`: the peak scales
    with 1/tau, so one curve gives the ratio peak/cut-off."""
    ref = suppression_curve(cfg, q_type, 1.0, freq_hz=np.geomspace(0.05, 50.0, 20001))
    return peak_hz / ref.peak_hz


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
    f = np.geomspace(0.01, 100.0, 2000) if freq_hz is None else np.asarray(freq_hz, float)
    lp, ppn, q, _ = loop_parts(cfg, cfg.q_type, cfg.q_cutoff_hz, variant, f)
    d = 1.0 + lp + (ppn - 1.0) * q
    s1 = 1.0 / (1.0 + lp)
    s2 = (1.0 - q) / d
    return SensitivityCurves(
        variant.label, f, 20.0 * np.log10(np.abs(s1)), 20.0 * np.log10(np.abs(s2))
    )
