"""Offline closed-loop experiments: ServoLoop on the simulated rig, faster than real time.

The loop and the rig are the same objects the live controller uses; here they run back to
back with no clock, compiled (`controller.sim.offline`: the tick's own functions and the rig's
kernel in one numba loop, bit for bit the Python tick's result); a loop variant
(`controller.sim.position_dob`) or another rig is ticked in Python. Metrics follow the
article: peak |error| and RMSE of the position error (deg) over the metrics window, plus rise
time / overshoot for steps and the static error for hold.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.sim import offline
from controller.sim.disturbance import Disturbance
from controller.sim.rig_disturbances import ScheduledRig
from controller.sim.sim_rig import RigParams, SimRig

#: The article's figures (Yu et al. 2022, Table in control.md) for the 5 sin(0.5 t) deg test.
ARTICLE_SINE: dict[str, dict[str, float | None]] = {
    "no DOB": {"peak_error_deg": 0.1, "rmse_deg": 0.0231},
    "DOB": {"peak_error_deg": 0.05, "rmse_deg": 0.0207},
    "DOB + FF": {"peak_error_deg": None, "rmse_deg": 0.0052},
}


@dataclass(frozen=True)
class Metrics:
    peak_error_deg: float
    rmse_deg: float
    window_s: tuple[float, float]
    rise_time_s: float | None = None
    overshoot_pct: float | None = None
    static_error_deg: float | None = None
    peak_command_deg_s: float = 0.0
    saturated_fraction: float = 0.0


@dataclass(frozen=True)
class ExperimentResult:
    config: LoopConfig
    trajectory: Trajectory
    duration_s: float
    seed: int
    disturbance: str
    t_s: np.ndarray
    ref_deg: np.ndarray
    pos_deg: np.ndarray
    speed_deg_s: np.ndarray
    speed_ref_deg_s: np.ndarray
    command_deg_s: np.ndarray
    d_hat_deg_s: np.ndarray
    metrics: Metrics
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def error_deg(self) -> np.ndarray:
        return self.ref_deg - self.pos_deg

    @property
    def peak_error_deg(self) -> float:
        return self.metrics.peak_error_deg

    @property
    def rmse_deg(self) -> float:
        return self.metrics.rmse_deg


def default_settle_s(trajectory: Trajectory) -> float:
    """Start of the metrics window: tracking tests skip the start-up transient, steps and holds
    are measured from t = 0 (their transient is the point)."""
    return 2.0 if trajectory.kind in ("sine", "ramp") else 0.0


def compute_metrics(
    t_s: np.ndarray,
    ref_deg: np.ndarray,
    pos_deg: np.ndarray,
    command_deg_s: np.ndarray,
    trajectory: Trajectory,
    command_limit_deg_s: float,
    settle_s: float,
) -> Metrics:
    mask = t_s >= settle_s
    if not np.any(mask):
        raise ConfigError("duration_s", f"no samples after the settle time {settle_s} s")
    err = (ref_deg - pos_deg)[mask]
    rise = overshoot = static = None
    if trajectory.kind == "step":
        t_step = trajectory.step_time_s
        after = t_s >= t_step
        y = pos_deg[after] - trajectory.offset_deg
        a = trajectory.amplitude_deg
        if a != 0.0 and len(y):
            yn = y / a
            i10 = np.argmax(yn >= 0.1)
            i90 = np.argmax(yn >= 0.9)
            if yn[i90] >= 0.9 and yn[i10] >= 0.1:
                rise = float((i90 - i10) / (1.0 / (t_s[1] - t_s[0])))
            overshoot = float(max(0.0, (yn.max() - 1.0) * 100.0))
    if trajectory.kind in ("hold", "step"):
        tail = t_s >= t_s[-1] - (t_s[-1] - t_s[0]) / 4.0
        static = float(np.mean(np.abs((ref_deg - pos_deg)[tail])))
    cmd = command_deg_s[mask]
    return Metrics(
        peak_error_deg=float(np.max(np.abs(err))),
        rmse_deg=float(math.sqrt(float(np.mean(err * err)))),
        window_s=(float(t_s[mask][0]), float(t_s[-1])),
        rise_time_s=rise,
        overshoot_pct=overshoot,
        static_error_deg=static,
        peak_command_deg_s=float(np.max(np.abs(cmd))),
        saturated_fraction=float(np.mean(np.abs(cmd) >= command_limit_deg_s * (1 - 1e-12))),
    )


ProgressFn = Callable[[float], None]


class Loop(Protocol):
    """What an experiment needs of a loop: ServoLoop, or a simulation-only variant."""

    d_hat: float
    speed_ref_deg_s: float

    def tick(
        self, ref_deg: float, ref_rate_deg_s: float, pos_deg: float, speed_deg_s: float
    ) -> float: ...


class Rig(Protocol):
    """What the loop needs of a rig: the simulated one, or the real one over CAN."""

    def read(self) -> tuple[float, float]: ...

    def step(self, command_deg_s: float) -> None: ...


def _python_run(
    loop: Loop, rig: Rig, trajectory: Trajectory, n: int, ts: float,
    progress: ProgressFn | None,
) -> tuple[np.ndarray, ...]:
    """The loop ticked in Python: for a loop variant or a rig the compiled loop does not run."""
    ref = np.empty(n)
    pos = np.empty(n)
    spd = np.empty(n)
    sref = np.empty(n)
    cmd = np.empty(n)
    dh = np.empty(n)
    at = trajectory.at
    tick = loop.tick
    read = rig.read
    step = rig.step
    chunk = max(1, n // 100)
    for k in range(n):
        r, rr = at(k * ts)
        p, w = read()
        u = tick(r, rr, p, w)
        step(u)
        ref[k] = r
        pos[k] = p
        spd[k] = w
        cmd[k] = u
        dh[k] = loop.d_hat
        sref[k] = loop.speed_ref_deg_s
        if progress is not None and k % chunk == 0:
            progress(k / n)
    return ref, pos, spd, sref, cmd, dh


def run_experiment(
    cfg: LoopConfig,
    trajectory: Trajectory,
    duration_s: float,
    *,
    seed: int = 0,
    disturbance: Disturbance | None = None,
    disturbance_name: str = "none",
    rig_params: RigParams | None = None,
    settle_s: float | None = None,
    progress: ProgressFn | None = None,
    rig: Rig | None = None,
    loop: Loop | None = None,
) -> ExperimentResult:
    """Run the loop against the simulated rig for `duration_s` simulated seconds (`loop`: a
    loop variant instead of the runtime's ServoLoop built from `cfg`)."""
    if not (isinstance(duration_s, (int, float)) and math.isfinite(duration_s)):
        raise ConfigError("duration_s", f"expected a finite number, got {duration_s!r}")
    if not 0.0 < duration_s <= 3600.0:
        raise ConfigError("duration_s", f"{duration_s} is out of range (0, 3600] s")
    rate = cfg.rate_hz
    ts = 1.0 / rate
    n = round(duration_s * rate)
    p0, _ = trajectory.at(0.0)
    if rig is None:
        rig = SimRig(
            rig_params or RigParams(),
            rate_hz=rate,
            seed=seed,
            disturbance=disturbance,
            initial_position_deg=p0,
        )
    if loop is None:
        loop = ServoLoop(LoopCoefficients.build(cfg))
    t_s = np.arange(n) * ts
    if offline.supported(loop, rig):
        assert isinstance(loop, ServoLoop) and isinstance(rig, SimRig | ScheduledRig)
        run = offline.OfflineRun(np.empty((len(offline.ROWS), n)))
        pieces = 1 if progress is None else 100
        for i in range(pieces):
            a, b = n * i // pieces, n * (i + 1) // pieces
            if progress is not None:
                progress(a / n)
            offline.run_ticks(loop, rig, trajectory, b - a, traj_tick=a, out=run, at=a,
                              period_s=ts)
        ref, pos, spd = run.ref_deg, run.pos_deg, run.speed_deg_s
        sref, cmd, dh = run.speed_ref_deg_s, run.command_deg_s, run.d_hat_deg_s
    else:
        ref, pos, spd, sref, cmd, dh = _python_run(loop, rig, trajectory, n, ts, progress)
    if progress is not None:
        progress(1.0)
    metrics = compute_metrics(
        t_s,
        ref,
        pos,
        cmd,
        trajectory,
        cfg.command_limit_deg_s,
        default_settle_s(trajectory) if settle_s is None else settle_s,
    )
    return ExperimentResult(
        config=cfg,
        trajectory=trajectory,
        duration_s=n * ts,
        seed=seed,
        disturbance=disturbance_name,
        t_s=t_s,
        ref_deg=ref,
        pos_deg=pos,
        speed_deg_s=spd,
        speed_ref_deg_s=sref,
        command_deg_s=cmd,
        d_hat_deg_s=dh,
        metrics=metrics,
    )
