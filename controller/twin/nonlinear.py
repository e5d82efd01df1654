"""The twin's friction, backlash and sensor noise, estimated from a recorded window of normal
running (pure), each with its standard deviation.

- **Encoder noise** (`noise_estimate`): the second difference of the measured position over
  the window's slow samples (|rate| below `SLOW_DEG_S`: there the motion's own second
  difference and the encoder's interpolation error are next to nothing), its spread by the
  median absolute deviation (robust to the few ticks where the load breaks away), less the
  quantisation of the encoder (LSB^2/12): var(d2) = 6 sigma^2 for white noise. The speed
  sensor's noise is the backward difference's, sqrt(2) sigma x the loop rate.
- **Load Coulomb friction and backlash** (`friction_fit`): the twin is fed the speed command
  the loop sent over the window, in open loop, from the window's first position (the same
  kernel the offline loop runs, `SimRig.run_commands`), and its load rate is compared with the
  measured one below `BAND_HZ` (zero-phase low-pass), less its mean (a speed offset the
  twin lacks, which the DOB's d_hat tells: `controller.twin.replay.disturbance_lacking`, is
  not friction). At each reversal the load stops while
  the motor crosses the dead zone and winds the belt up to the static friction, and through
  the drive's droop the friction sets the speed error in each direction: the rate there tells
  the Coulomb friction (the static friction scaled with it, in the twin's ratio) and the total
  dead zone (belt and gearbox in series; the gearbox's share kept, the belt's fitted). A
  coarse grid first (the cost is rugged: stick and slip move in steps with the parameters),
  then least squares from its best three points; the deviation of each is its bias bound (the
  Jacobian with wide differences and the whole fitted residual: how far a model error that
  large, shaped like the part's own effect, would move it).
- **Viscous friction** comes from the responses (`controller.twin.fit`: the load's viscous
  factor, with its deviation from that fit's Jacobian).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import msgspec
import numpy as np
from scipy.optimize import least_squares
from scipy.signal import butter, sosfiltfilt

from controller.core.arrays import FloatArray
from controller.core.samples import TickSamples
from controller.sim.sim_rig import RigFaults, RigParams, SimRig
from controller.twin.model import NonlinearEstimate, RigTwin

__all__ = [
    "BAND_HZ",
    "FrictionFit",
    "NoiseFit",
    "RunningFit",
    "RunningWindow",
    "friction_fit",
    "noise_estimate",
    "running_fit",
    "with_friction",
    "with_running",
]

#: Samples slower than this (deg/s, the measured rate low-passed) are the noise estimate's.
SLOW_DEG_S = 0.3
#: The friction fit compares the rates below this frequency.
BAND_HZ = 40.0
#: Seconds at the start of a window the twin (started at rest) needs to catch up.
SETTLE_S = 0.5
#: The Coulomb factor's grid (on the twin's) and the dead zone's beyond the gearbox's (deg).
GRID_FACTORS = tuple(float(v) for v in np.geomspace(0.25, 4.0, 11))
GRID_BACKLASH_DEG = (0.0, 0.02, 0.05, 0.08, 0.12, 0.18, 0.26, 0.36)
#: Bounds of the fit: Coulomb factor (log) and total dead zone (deg).
LOG_FACTOR_BOUND = math.log(8.0)
BACKLASH_MAX_DEG = 0.6
#: Finite-difference steps of the refinement and of the deviations (log factor, deg): wide
#: enough to average over what moves in steps with the parameters.
DIFF_STEPS = (0.05, 0.005)
MAX_NFEV = 10
#: Least squares runs from this many of the grid's best points.
STARTS = 3


@dataclass(frozen=True)
class RunningWindow(TickSamples):
    """A window of normal running, one sample per tick as the state stream carries them: the
    measured position and rate before the tick's command, and the command sent."""

    rate_hz: float
    pos_deg: FloatArray
    speed_deg_s: FloatArray
    command_deg_s: FloatArray
    label: str = "recorded running"

    def __post_init__(self) -> None:
        n = self.command_deg_s.size
        if not (self.pos_deg.size == self.speed_deg_s.size == n):
            raise ValueError("window: pos_deg, speed_deg_s and command_deg_s differ in length")
        if n < round(4 * SETTLE_S * self.rate_hz):
            raise ValueError(f"window: {n} samples, need {round(4 * SETTLE_S * self.rate_hz)}")
        for name in ("pos_deg", "speed_deg_s", "command_deg_s"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f"window: {name} has a non-finite sample")

    @classmethod
    def of_columns(cls, rate_hz: float, columns: Mapping[str, FloatArray],
                   label: str = "recorded running") -> RunningWindow:
        """A window from the state stream's columns (`controller.core.samples.STATE_COLUMNS`
        names: `pos_deg`, `speed_deg_s`, `command_deg_s`; a recording's or the history's);
        ValueError naming a missing column."""
        got = {}
        for name in ("pos_deg", "speed_deg_s", "command_deg_s"):
            if name not in columns:
                raise ValueError(f"window: no column {name!r}")
            got[name] = np.asarray(columns[name], dtype=np.float64)
        return cls(rate_hz, got["pos_deg"], got["speed_deg_s"], got["command_deg_s"], label)


@dataclass(frozen=True)
class NoiseFit:
    """The encoder's position noise (deg, one standard deviation per sample) and its standard
    error, from `samples` slow samples; the speed sensor's noise it makes (deg/s)."""

    position_noise_deg: float
    std_deg: float
    samples: int
    rate_noise_deg_s: float


@dataclass(frozen=True)
class FrictionFit:
    """The load's Coulomb friction (N m) and the total dead zone (deg, belt and gearbox), each
    with its standard deviation; the plant's residual (rms deg/s below `BAND_HZ`) with the
    twin's values and with the fitted ones."""

    coulomb_n_m: float
    coulomb_std_n_m: float
    backlash_deg: float
    backlash_std_deg: float
    residual_rms_deg_s: float
    fitted_rms_deg_s: float
    evaluations: int


def noise_estimate(win: RunningWindow, params: RigParams) -> NoiseFit:
    """See the module docstring; ValueError when the window has fewer than 200 slow
    samples."""
    band = butter(2, 5.0, fs=win.rate_hz, output="sos")
    slow = np.abs(sosfiltfilt(band, win.speed_deg_s)) < SLOW_DEG_S
    d2 = win.pos_deg[2:] - 2.0 * win.pos_deg[1:-1] + win.pos_deg[:-2]
    d2 = d2[slow[2:] & slow[1:-1] & slow[:-2]]
    if d2.size < 200:
        raise ValueError(f"window: {d2.size} slow samples (|rate| < {SLOW_DEG_S} deg/s), "
                         "need 200 (record a hold or a slower trajectory)")
    mad_sd = 1.4826 * float(np.median(np.abs(d2 - np.median(d2))))
    lsb = 360.0 / 2.0**params.load_encoder_bits
    var = max(0.0, mad_sd**2 / 6.0 - lsb**2 / 12.0)
    sigma = math.sqrt(var)
    # The MAD's standard error is 1.67 sigma / sqrt(2 n) for normal samples; a second
    # difference's neighbours are correlated (-2/3, +1/6): about n/3 independent ones.
    n_eff = d2.size / 3.0
    std = 1.67 * mad_sd / math.sqrt(6.0) / math.sqrt(2.0 * n_eff)
    return NoiseFit(sigma, std, int(d2.size), math.sqrt(2.0) * sigma * win.rate_hz)


def with_friction(params: RigParams, coulomb_factor: float, backlash_deg: float) -> RigParams:
    """`params` with the load's Coulomb and static friction x `coulomb_factor` and a total dead
    zone of `backlash_deg` (the gearbox's share kept, the belt's the rest, at least 0)."""
    return replace(params, coulomb_torque_n_m=params.coulomb_torque_n_m * coulomb_factor,
                   static_torque_n_m=params.static_torque_n_m * coulomb_factor,
                   backlash_deg=max(0.0, backlash_deg - params.gearbox_backlash_deg))


def friction_fit(params: RigParams, faults: RigFaults, win: RunningWindow) -> FrictionFit:
    """See the module docstring. The twin `params` must have some Coulomb friction (its
    static-to-Coulomb ratio is kept); ValueError otherwise, or for a window whose load never
    reverses (nothing there tells friction from backlash)."""
    if params.coulomb_torque_n_m <= 0.0:
        raise ValueError("twin: no Coulomb friction to scale")
    if not (np.any(win.command_deg_s > 0.05) and np.any(win.command_deg_s < -0.05)):
        raise ValueError("window: the speed command never reverses")
    quiet = replace(params, position_noise_deg=0.0)
    skip = min(win.n - 2, round(SETTLE_S * win.rate_hz))
    band = butter(2, BAND_HZ, fs=win.rate_hz, output="sos")
    meas = sosfiltfilt(band, win.speed_deg_s[1:])[skip:]
    total0 = params.backlash_deg + params.gearbox_backlash_deg
    evals = 0

    def residual(x: FloatArray) -> FloatArray:
        nonlocal evals
        evals += 1
        rig = SimRig(with_friction(quiet, math.exp(float(x[0])), float(x[1])),
                     rate_hz=win.rate_hz, initial_position_deg=float(win.pos_deg[0]))
        if faults.active:
            rig.set_faults(faults)
        _, w = rig.run_commands(win.command_deg_s)
        r = meas - sosfiltfilt(band, w[:-1])[skip:]
        return np.asarray(r - np.mean(r), dtype=np.float64)  # a speed offset is not friction

    r0 = residual(np.array([0.0, total0]))
    floor = params.gearbox_backlash_deg  # the gearbox's share is kept: the total's least
    grid = [(0.0, total0)] + [(math.log(f), floor + b) for f in GRID_FACTORS
                              for b in GRID_BACKLASH_DEG]
    costs = [float(np.sum(r0**2))] + [float(np.sum(residual(np.array(x)) ** 2))
                                      for x in grid[1:]]
    lo = np.array([-LOG_FACTOR_BOUND, floor])
    hi = np.array([LOG_FACTOR_BOUND, floor + BACKLASH_MAX_DEG])
    # The cost's valley runs diagonally (more friction, less dead zone: the same lost motion at
    # a reversal), narrower than the grid's step: least squares from the best STARTS points.
    x, best = np.array(grid[int(np.argmin(costs))]), min(costs)
    for i in np.argsort(costs)[:STARTS]:
        x0 = np.clip(np.array(grid[int(i)]), lo + 1e-6, hi - 1e-6)
        sol = least_squares(residual, x0, bounds=(lo, hi), x_scale=np.array(DIFF_STEPS),
                            diff_step=np.array(DIFF_STEPS), jac="3-point", max_nfev=MAX_NFEV,
                            xtol=1e-4, ftol=1e-6)
        cost = float(np.sum(sol.fun**2))
        if cost < best:
            x, best = sol.x, cost
    r = residual(x)
    # The deviation stated is the bias bound (as the watch's): how far a model error as large
    # as the whole fitted residual, shaped like each part's own effect, would move it. The
    # noise alone (the residual's variance over its independent samples) gives far less, and
    # the twin's own errors (its fitted dynamics, what it does not model) are not noise.
    jac = np.empty((r.size, 2))
    for i, h in enumerate(DIFF_STEPS):
        e = np.zeros(2)
        e[i] = h
        up, down = x + e, x - e
        if down[i] < lo[i]:  # at the bound: one-sided
            jac[:, i] = (residual(up) - r) / h
        else:
            jac[:, i] = (residual(up) - residual(down)) / (2.0 * h)
    try:
        cov = float(np.sum(r * r)) * np.linalg.inv(jac.T @ jac)
        std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        std = np.array([math.inf, math.inf])
    factor = math.exp(float(x[0]))
    fc = params.coulomb_torque_n_m * factor
    return FrictionFit(coulomb_n_m=fc, coulomb_std_n_m=fc * float(std[0]),
                       backlash_deg=float(x[1]), backlash_std_deg=float(std[1]),
                       residual_rms_deg_s=float(np.sqrt(np.mean(r0 * r0))),
                       fitted_rms_deg_s=float(np.sqrt(np.mean(r * r))), evaluations=evals)


@dataclass(frozen=True)
class RunningFit:
    """What a window of normal running tells: the twin's `params` with the estimates in
    them, the fits, and each estimate in words (with its deviation and its source)."""

    params: RigParams
    friction: FrictionFit
    noise: NoiseFit
    window: str
    how: tuple[str, ...]


def running_fit(params: RigParams, faults: RigFaults, win: RunningWindow) -> RunningFit:
    """The encoder noise, the load's Coulomb friction and the backlash of the twin
    (`params`, `faults`) estimated from `win` (`noise_estimate`, `friction_fit`)."""
    nf = noise_estimate(win, params)
    fr = friction_fit(params, faults, win)
    out = replace(with_friction(params, fr.coulomb_n_m / params.coulomb_torque_n_m,
                                fr.backlash_deg), position_noise_deg=nf.position_noise_deg)
    window = f"{win.label}, {win.duration_s:.3g} s"
    how = (f"Coulomb friction {fr.coulomb_n_m:.3g} +- {fr.coulomb_std_n_m:.2g} N m (static "
           f"{out.static_torque_n_m:.3g}: the base rig's ratio) and backlash "
           f"{fr.backlash_deg:.3g} +- {fr.backlash_std_deg:.2g} deg: estimated from {window} "
           f"(the plant's residual {fr.residual_rms_deg_s:.3g} -> {fr.fitted_rms_deg_s:.3g} "
           f"deg/s rms below {BAND_HZ:g} Hz)",
           f"encoder noise {nf.position_noise_deg:.3g} +- {nf.std_deg:.2g} deg: estimated "
           f"from {nf.samples} slow samples of {window}")
    return RunningFit(out, fr, nf, window, how)


def with_running(twin: RigTwin, win: RunningWindow) -> RigTwin:
    """`twin` (its fitted dynamics kept, not fitted again) with the friction, backlash and
    noise `win` tells (`running_fit`), in its parameters (what the offline loop runs) and in
    its `nonlinear` estimate; the viscous friction's from the responses is kept."""
    rf = running_fit(twin.params, twin.faults, win)
    p, old = rf.params, twin.nonlinear
    keep = tuple(h for h in (old.how if old is not None else ())
                 if h.startswith("viscous") or h.startswith("drive offset"))
    est = NonlinearEstimate(
        coulomb_torque_n_m=p.coulomb_torque_n_m, static_torque_n_m=p.static_torque_n_m,
        backlash_deg=p.backlash_deg + p.gearbox_backlash_deg,
        position_noise_deg=p.position_noise_deg, how=(*rf.how, *keep),
        viscous_n_m_s_rad=p.load_viscous_n_m_s_rad,
        coulomb_std_n_m=rf.friction.coulomb_std_n_m,
        backlash_std_deg=rf.friction.backlash_std_deg,
        position_noise_std_deg=rf.noise.std_deg,
        viscous_std_n_m_s_rad=old.viscous_std_n_m_s_rad if old is not None else None,
        rate_noise_deg_s=rf.noise.rate_noise_deg_s, window=rf.window)
    return msgspec.structs.replace(twin, params=p, nonlinear=est)
