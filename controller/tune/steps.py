"""Step responses of the linear loop: the controller's own tick (`ServoLoop`) against the exact
sampled plant model (`controller.gate.loop_model.discrete_plant`: ZOH of M P with the
backward-difference rate), no friction, backlash or saturation. A reference step of 1 deg, and
a load-disturbance step: 1 deg/s added to the speed command at the plant input (what the DOB
estimates and cancels), both from rest.
"""

from __future__ import annotations

import numpy as np

from controller.core.arrays import FloatArray
from controller.core.config import LoopConfig, NominalModel
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.gate.loop_model import discrete_plant

__all__ = ["step_responses"]



def _run(cfg: LoopConfig, model: NominalModel, n: int, ref_deg: float, d_deg_s: float,
         ) -> FloatArray:
    pl = discrete_plant(model, cfg.rate_hz)
    a, b, cw, ct = (np.asarray(m) for m in (pl.a, pl.b, pl.cw, pl.ct))
    # The limit would make this a nonlinear response: lift it (the linear model's view).
    loop = ServoLoop(LoopCoefficients.build(cfg.with_(command_limit_deg_s=1e4)))
    x = np.zeros(a.shape[0])
    out = np.empty(n)
    for k in range(n):
        pos = float(ct @ x)
        w = float(cw @ x)
        out[k] = pos
        u = loop.tick(ref_deg, 0.0, pos, w)
        x = a @ x + b * (u + d_deg_s)
    return out


def step_responses(
    cfg: LoopConfig, model: NominalModel, duration_s: float = 2.0
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(t_s, theta for a 1 deg reference step, theta for a 1 deg/s load-disturbance step)."""
    n = max(2, round(duration_s * cfg.rate_hz))
    t = np.arange(n) / cfg.rate_hz
    return t, _run(cfg, model, n, 1.0, 0.0), _run(cfg, model, n, 0.0, 1.0)
