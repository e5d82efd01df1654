"""The recommended maximum Q cut-off: the top of the accepted region from the lowest cut-off."""

from __future__ import annotations

import math

import numpy as np

from controller.core.config import LoopConfig
from controller.core.qfilter import Q_TYPES, QType, check_q_type
from controller.gate.analysis import GateLimits, analyse
from controller.gate.knowledge import (
    PlantKnowledge,
)


def recommended_max_cutoff_hz(
    cfg: LoopConfig,
    plant: PlantKnowledge | None = None,
    limits: GateLimits | None = None,
    q_type: str | None = None,
    *,
    lowest_hz: float = 0.02,
    highest_hz: float | None = None,
    coarse_points: int = 16,
    rel_tol: float = 0.01,
) -> float | None:
    """Largest Q cut-off (Hz) the gate accepts for `q_type` (default cfg.q_type), DOB on.

    Acceptance is assumed to hold on an interval from low cut-offs up to a limit (robustness
    and margins degrade as the Q bandwidth grows), though not strictly monotone. Guard: scan
    `coarse_points` log-spaced cut-offs from `lowest_hz` to `highest_hz` (default: a tenth of
    the loop rate), take the first accept -> reject transition from below, then bisect it in
    log cut-off to `rel_tol`. None if `lowest_hz` is already rejected.
    """
    qt: QType = check_q_type(q_type if q_type is not None else cfg.q_type)
    assert qt in Q_TYPES
    top = highest_hz if highest_hz is not None else 0.1 * cfg.rate_hz
    top = min(top, 0.45 * cfg.rate_hz)
    base = cfg.with_(dob_on=True, q_type=qt)

    def ok(fc: float) -> bool:
        return analyse(base.with_(q_cutoff_hz=fc), plant, limits).accepted

    grid = np.geomspace(lowest_hz, top, coarse_points)
    if not ok(float(grid[0])):
        return None
    lo = float(grid[0])
    hi: float | None = None
    for fc in grid[1:]:
        if ok(float(fc)):
            lo = float(fc)
        else:
            hi = float(fc)
            break
    if hi is None:
        return lo
    while hi / lo > 1.0 + rel_tol:
        mid = math.sqrt(lo * hi)
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return lo
