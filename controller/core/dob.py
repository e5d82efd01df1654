"""Design of the rate-difference DOB filters (control.md, "The rate-difference DOB").

    d_hat[k] = F1(z) w[k] - F2(z) u[k-1],   F1 ~ Q (Mn Pn)^-1,  F2 ~ Q

Both are the Tustin images (prewarped at the Q cut-off) of the continuous filters, built from
poles and zeros: zeros of F1 are Q's zeros and the roots of mn_den and pn_den, its poles are
Q's poles and the roots of pn_num; common roots (the article's Pn numerator equals Mn's
denominator) are cancelled exactly before discretising.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from controller.core.config import LoopConfig, NominalModel, Poly2
from controller.core.discrete import SosArray, tustin_zpk, zpk_to_sos
from controller.core.qfilter import QFilter, design_q


def poly_roots_gain(p: Poly2) -> tuple[list[complex], float]:
    """Roots and leading coefficient of a2 s^2 + a1 s + a0 (degree may drop)."""
    coeffs = np.trim_zeros(np.asarray(p, float), "f")
    return list(np.roots(coeffs).astype(complex)), float(coeffs[0])


def cancel_common_roots(zeros: list[complex], poles: list[complex], rtol: float = 1e-9) -> None:
    """Remove the roots `zeros` and `poles` have in common (within `rtol`), in place."""
    for z in list(zeros):
        for i, p in enumerate(poles):
            if abs(z - p) <= rtol * max(1.0, abs(p)):
                zeros.remove(z)
                del poles[i]
                break


def f1_continuous_zpk(
    q: QFilter, nominal: NominalModel
) -> tuple[list[complex], list[complex], float]:
    """Q(s) (Mn Pn)^-1(s) = Q(s) mn_den(s) pn_den(s) / pn_num(s) as zeros, poles, gain."""
    qz, qp, qk = q.zpk()
    rm, km = poly_roots_gain(nominal.mn_den)
    rd, kd = poly_roots_gain(nominal.pn_den)
    rn, kn = poly_roots_gain(nominal.pn_num)
    zeros = [complex(z) for z in qz] + rm + rd
    poles = [complex(p) for p in qp] + rn
    cancel_common_roots(zeros, poles)
    return zeros, poles, qk * km * kd / kn


@dataclass(frozen=True)
class DobDesign:
    """The implemented DOB filters at the loop rate."""

    q: QFilter
    rate_hz: float
    f1_sos: SosArray
    f2_sos: SosArray


def design_dob(cfg: LoopConfig) -> DobDesign:
    """The DOB's filters for cfg's Q type, cut-off, rate and nominal model (cached on those:
    the gate's analysis and the loop's coefficients of one candidate share one design)."""
    return _design_dob(cfg.q_type, cfg.q_cutoff_hz, cfg.rate_hz, cfg.nominal)


@lru_cache(maxsize=128)
def _design_dob(q_type: str, cutoff_hz: float, rate_hz: float, nominal: NominalModel,
                ) -> DobDesign:
    q = design_q(q_type, cutoff_hz=cutoff_hz)  # type: ignore[arg-type]
    prewarp = cutoff_hz
    z1, p1, k1 = f1_continuous_zpk(q, nominal)
    f1 = zpk_to_sos(*tustin_zpk(z1, p1, k1, rate_hz, prewarp))
    qz, qp, qk = q.zpk()
    f2 = zpk_to_sos(*tustin_zpk(qz, qp, qk, rate_hz, prewarp))
    f1.flags.writeable = False  # shared by every user of the cached design
    f2.flags.writeable = False
    return DobDesign(q=q, rate_hz=rate_hz, f1_sos=f1, f2_sos=f2)
