"""Design of the rate-difference DOB filters (control.md, "The rate-difference DOB").

    d_hat[k] = F1(z) w[k] - F2(z) u[k-1],   F1 ~ Q (Mn Pn)^-1,  F2 ~ Q

Both are the Tustin images (prewarped at the Q cut-off) of the continuous filters, built from
poles and zeros: zeros of F1 are Q's zeros and the roots of mn_den and pn_den, its poles are
Q's poles and the roots of pn_num; common roots (the article's Pn numerator equals Mn's
denominator) are cancelled exactly before discretising.
"""

from __future__ import annotations

from dataclasses import dataclass

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
    q = design_q(cfg.q_type, cutoff_hz=cfg.q_cutoff_hz)  # type: ignore[arg-type]
    prewarp = cfg.q_cutoff_hz
    z1, p1, k1 = f1_continuous_zpk(q, cfg.nominal)
    f1 = zpk_to_sos(*tustin_zpk(z1, p1, k1, cfg.rate_hz, prewarp))
    qz, qp, qk = q.zpk()
    f2 = zpk_to_sos(*tustin_zpk(qz, qp, qk, cfg.rate_hz, prewarp))
    return DobDesign(q=q, rate_hz=cfg.rate_hz, f1_sos=f1, f2_sos=f2)
