"""A recorded run replayed on the rig's twin (pure): the same configuration and reference run
on the twin through the compiled offline loop, its position error against the one measured
(`ReplayFit`: RMSE and peak, measured and predicted)."""

from __future__ import annotations

import numpy as np

from controller.core.arrays import FloatArray
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.sim.disturbance import Disturbance
from controller.sim.experiment import default_settle_s, run_experiment
from controller.twin.model import ReplayFit, RigTwin

__all__ = ["replay"]


def replay(twin: RigTwin, cfg: LoopConfig, trajectory: Trajectory,
           measured_error_deg: FloatArray, *, label: str = "recorded run",
           disturbance: Disturbance | None = None, seed: int = 0,
           settle_s: float | None = None) -> ReplayFit:
    """Run `cfg` on the twin following `trajectory` for as many ticks as
    `measured_error_deg` holds (the recorded run's position error, reference minus position,
    one per tick from the trajectory's start), with the load torque `disturbance`; the
    twin-predicted error against the measured one, both from `settle_s` on (default: the
    experiments' window, `default_settle_s`). ValueError for fewer than 2 finite samples
    in it."""
    e = np.asarray(measured_error_deg, dtype=np.float64)
    if e.ndim != 1 or not np.all(np.isfinite(e)):
        raise ValueError("measured_error_deg: one finite value per tick")
    duration_s = e.size / cfg.rate_hz
    skip = round((default_settle_s(trajectory) if settle_s is None else settle_s) * cfg.rate_hz)
    if e.size - skip < 2:
        raise ValueError(f"measured_error_deg: {e.size} samples, the window starts at {skip}")
    rig = twin.sim_rig(seed=seed, disturbance=disturbance,
                       initial_position_deg=trajectory.at(0.0)[0], rate_hz=cfg.rate_hz)
    pred = run_experiment(cfg, trajectory, duration_s, rig=rig)
    p = np.asarray(pred.error_deg, dtype=np.float64)[skip: e.size]
    e = e[skip:]
    return ReplayFit(label=label, duration_s=duration_s,
                     measured_rmse_deg=float(np.sqrt(np.mean(e * e))),
                     predicted_rmse_deg=float(np.sqrt(np.mean(p * p))),
                     measured_peak_deg=float(np.max(np.abs(e))),
                     predicted_peak_deg=float(np.max(np.abs(p))))
