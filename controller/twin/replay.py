"""A recorded run replayed on the rig's twin (pure): the same configuration and reference run
on the twin through the compiled offline loop, its position error against the one measured
(`ReplayFit`: RMSE and peak, measured and predicted); and the disturbance the DOB estimated
on the rig that the twin lacks (`disturbance_lacking`: the recorded d_hat against the twin's
own for the same run), put into the twin as the drive's speed offset (`with_disturbance`)."""

from __future__ import annotations

from dataclasses import replace

import msgspec
import numpy as np

from controller.core.arrays import FloatArray
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.sim import offline
from controller.sim.disturbance import Disturbance
from controller.sim.experiment import default_settle_s, run_experiment
from controller.twin.fit import disturbance_estimate
from controller.twin.model import DisturbanceEstimate, ReplayFit, RigTwin

__all__ = ["disturbance_lacking", "replay", "with_disturbance"]

#: The mean's deviation comes from this many blocks of the window.
BLOCKS = 10
#: Seconds of the trajectory the twin runs before a window that starts later (its loop's
#: start-up and the DOB's settling; the article's Q31 0.5 Hz settles in about 1 s).
LEAD_S = 3.0


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


def disturbance_lacking(twin: RigTwin, cfg: LoopConfig, trajectory: Trajectory,
                        d_hat_deg_s: FloatArray, *, disturbance: Disturbance | None = None,
                        seed: int = 0, settle_s: float | None = None,
                        start_tick: int = 0) -> DisturbanceEstimate:
    """The disturbance the DOB estimated on the rig that the twin lacks: the recorded run's
    d_hat (one per tick from the trajectory's tick `start_tick`, `cfg` with its DOB on) less
    the d_hat of the same configuration and reference run on the twin, from `settle_s` on
    (default: the experiments' window): its mean (with the deviation of the mean from ten
    blocks), level and spectrum. From a later `start_tick` (a window of the controller's
    running), the twin's run starts `LEAD_S` before it (at the trajectory's start at the
    earliest, the window's first samples then skipped up to `LEAD_S` after it). ValueError
    for a non-finite window, a DOB that is off, or fewer than 10 blocks of 16 samples."""
    d = np.asarray(d_hat_deg_s, dtype=np.float64)
    if d.ndim != 1 or not np.all(np.isfinite(d)):
        raise ValueError("d_hat_deg_s: one finite value per tick")
    if not cfg.dob_on:
        raise ValueError("cfg: the DOB is off (d_hat is not estimated)")
    if start_tick < 0:
        raise ValueError(f"start_tick: {start_tick} is before the trajectory's start")
    if start_tick > 0:
        want = round(LEAD_S * cfg.rate_hz)
        lead = min(start_tick, want)
        skip = want - lead
    else:
        lead, skip = 0, round((default_settle_s(trajectory) if settle_s is None else settle_s)
                              * cfg.rate_hz)
    if d.size - skip < 16 * BLOCKS:
        raise ValueError(f"d_hat_deg_s: {d.size} samples, the window starts at {skip}")
    period = 1.0 / cfg.rate_hz
    rig = twin.sim_rig(seed=seed, disturbance=disturbance, rate_hz=cfg.rate_hz,
                       initial_position_deg=trajectory.at((start_tick - lead) * period)[0])
    if start_tick > 0:
        run = offline.run_ticks(ServoLoop(LoopCoefficients.build(cfg)), rig, trajectory,
                                lead + d.size, traj_tick=start_tick - lead, period_s=period)
        own_d = np.asarray(run.d_hat_deg_s, dtype=np.float64)[lead:]
    else:
        own_d = np.asarray(run_experiment(cfg, trajectory, d.size / cfg.rate_hz,
                                          rig=rig).d_hat_deg_s, dtype=np.float64)
    diff = d[skip:] - own_d[skip: d.size]
    est = disturbance_estimate(diff, 1.0 / cfg.rate_hz)
    blocks = np.array([b.mean() for b in np.array_split(diff, BLOCKS)])
    return msgspec.structs.replace(
        est, mean_std_deg_s=float(np.std(blocks, ddof=1) / np.sqrt(BLOCKS)),
        relative_to=f"the twin's own d_hat for the same run ({cfg.q_type} "
                    f"{cfg.q_cutoff_hz:g} Hz, {trajectory.kind})")


def with_disturbance(twin: RigTwin, est: DisturbanceEstimate) -> RigTwin:
    """`twin` with the disturbance `est` states: its mean, a rate at P's input, added to the
    drive's speed offset (motor side: x gear ratio, deg/s -> rpm), which the offline loop
    runs; the estimate kept in the twin (`disturbance`) and said in its notes."""
    p = twin.params
    rpm = est.mean_deg_s * p.gear_ratio / 6.0
    sd = (f" +- {est.mean_std_deg_s * p.gear_ratio / 6.0:.2g}" if est.mean_std_deg_s is not None
          else "")
    what = f"d_hat less {est.relative_to}" if est.relative_to else "d_hat"
    note = (f"drive offset {p.drive_offset_rpm + rpm:.3g} rpm: {p.drive_offset_rpm:.3g} + "
            f"{rpm:.3g}{sd} rpm, the mean of {what} over {est.window_s:.3g} s")
    return msgspec.structs.replace(
        twin, params=replace(p, drive_offset_rpm=p.drive_offset_rpm + rpm), disturbance=est,
        notes=(*twin.notes, note))
