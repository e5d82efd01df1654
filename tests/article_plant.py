"""The article's M(s) P(s) (7.0 Hz, damping 0.707) ZOH-discretised at the 1 kHz loop rate: the
discrete plant the estimator tests (tests/test_frd_estimate.py, tests/test_ident_lines.py)
excite, its exact response (scipy's freqz, independent of the estimators), and the odd
random-phase multisine the line estimator excites it with (tests/test_excitation.py checks its
lines)."""

from __future__ import annotations

import numpy as np
import scipy.signal as sig

from controller.ident.excitation import MultisineSpec

__all__ = ["A_G", "B_G", "FS", "odd_multisine_spec", "plant_response"]

FS = 1000.0
_num, _den, _ = sig.cont2discrete(([1935.0], [1.0, 62.2, 1935.0]), 1.0 / FS, method="zoh")
B_G = np.ravel(_num)
A_G = np.ravel(_den)


def plant_response(freq_hz: np.ndarray) -> np.ndarray:
    """Exact response of the discrete plant at `freq_hz`."""
    return np.asarray(sig.freqz(B_G, A_G, worN=freq_hz, fs=FS)[1])


def odd_multisine_spec(**kw: object) -> MultisineSpec:
    """An odd random-phase multisine, 10 lines a decade, measured from its first period after a
    1000-sample faded lead-in, its spread from the detection lines; `kw` sets any field."""
    odd: dict[str, object] = dict(transient_periods=0, points_per_decade=10, harmonics="odd",
                                  phases="random", lead_samples=1000, spread_from="lines")
    return MultisineSpec(**{**odd, **kw})  # type: ignore[arg-type]
