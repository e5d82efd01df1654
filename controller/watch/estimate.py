"""What changed in the plant, estimated from the loop's own samples (pure).

The twin (its `RigParams` + `RigFaults`: the rig's twin when one was built, else the model the
controller runs on) is fed the speed command the loop actually sent over a window, in open
loop, from the window's first position (`SimRig.run_commands`: the same kernel, no load-torque
profile, no encoder noise): its load rate against the measured one is the **plant's residual**.
The twin's parameters are then fitted to the window by least squares on that residual
(`fit_window`): drive gain, belt stiffness and load inertia as log factors, the motor's
Coulomb friction in N m; the command delay by trying whole ticks beside the twin's. Each
estimate has a standard deviation from the fit's Jacobian and the residual's variance
(inflated for the residual's correlation from tick to tick): where the window's command does
not excite a part, its deviation is large and the part is reported as not told, never guessed.
Each also has a bias bound (`PartEstimate.bias`): how far a model error as large as the whole
fitted residual, shaped like that part's own effect, would move it. More samples shrink the
deviation, not this: on a constant-speed ramp the command barely moves the belt's stiffness and
the load's inertia, the deviation still looks small, and the estimate follows what the twin does
not model (the judge takes a part as told only when its bias bound is inside the part's range).

The **loop's residual** (`loop_residual`): the active configuration run on the twin in closed
loop over the window's measured reference (the tick's own `ServoLoop`, compiled with the twin by
`controller.sim.offline.run_ref_ticks`, bit for bit the Python tick; the rate reference by a
central difference of the reference) gives the error the twin predicts; against the measured
error, it says whether the loop still does what it was approved for.

The first `settle_s` of each run is left out: the twin starts at rest while the rig moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import butter, sosfiltfilt

from controller.core.arrays import FloatArray
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.samples import TickSamples
from controller.sim.offline import run_ref_ticks
from controller.sim.sim_rig import RigFaults, RigParams, SimRig

__all__ = [
    "MODE_PARTS",
    "PARTS",
    "DriftFit",
    "LoopResidual",
    "PartEstimate",
    "Window",
    "drifted",
    "fit_window",
    "friction_scale_n_m",
    "loop_residual",
    "plant_residual",
]

#: The parts estimated, in the fit's order: drive gain, belt stiffness, load inertia (factors
#: on the twin's), the motor's Coulomb friction (N m, motor side; stated as a factor when the
#: twin has some).
PARTS: tuple[str, ...] = ("gain", "stiffness", "inertia", "motor_friction")
#: With an extra mode in the twin (`RigFaults.resonance_hz`, a measured resonance): its
#: natural frequency and damping ratio, as factors on the twin's, fitted after `PARTS`.
MODE_PARTS: tuple[str, ...] = ("resonance", "resonance_damping")
#: The mode's damping is told when its relative deviation is below this (a damping ratio is
#: known far less closely than a frequency).
DAMPING_TOLD_REL_STD = 0.25
#: Seconds at the start of a window that the twin (starting at rest) needs to catch up.
SETTLE_S = 0.5
#: Whole ticks of extra command delay tried beside the twin's.
DELAY_TRIED = 2
#: A part is told by a window when its relative standard deviation is below this.
TOLD_REL_STD = 0.05
#: The motor friction's scale (N m) when the twin has none: its deviation is judged on it.
FRICTION_SCALE_N_M = 0.004
#: The motor friction is told when its deviation is below this share of its scale.
FRICTION_TOLD_STD = 0.15
#: The fit's finite-difference step (central differences, on the log factors): wide enough
#: to average over what moves in steps with the parameters (the drive's encoder counts, the
#: moments the load sticks and slips), which a narrow step takes for the slope.
DIFF_STEP = 0.05
#: Iterations of one window's fit at most; the next window starts where this one ended.
MAX_NFEV = 12
#: Another delay than the twin's is taken only if it lowers the cost by this share.
DELAY_GAIN = 0.2
#: The residual is compared below this frequency (zero-phase low-pass): the plant's parts show
#: there; above it the drive's encoder quantisation and the rig's noise, which no parameter
#: explains, would only roughen the fit.
BAND_HZ = 40.0
#: Residuals beyond this (deg/s, after the low-pass) weigh less than squared (soft L1): the
#: moments where the twin, started at rest, sticks or slips otherwise than the rig (reversals
#: under a heavier load) must not pull every part.
F_SCALE_DEG_S = 0.01


@dataclass(frozen=True)
class Window(TickSamples):
    """One window of the loop's samples (one per tick, as the state stream carries them):
    the measured position and rate *before* the tick's command, the command sent, the
    reference and the error."""

    t0_s: float
    rate_hz: float
    pos_deg: FloatArray
    speed_deg_s: FloatArray
    command_deg_s: FloatArray
    ref_deg: FloatArray
    error_deg: FloatArray


@dataclass(frozen=True)
class PartEstimate:
    """One part's estimate: `value` (a factor on the twin's; N m for the motor friction when
    the twin has none), its standard deviation, and whether the window tells it."""

    name: str
    value: float
    std: float
    told: bool
    unit: str = "x"
    bias: float = 0.0
    """How far a model error as large as the fit's residual could move the estimate (the same
    unit as `std`): the bias bound, which more samples do not shrink."""


@dataclass(frozen=True)
class DriftFit:
    """A window's fit: each part, the command delay (ticks), the plant's residual with the
    twin as it is and with the fitted parameters (rms, deg/s), samples used."""

    parts: tuple[PartEstimate, ...]
    delay_ticks: int
    twin_delay_ticks: int
    residual_rms_deg_s: float
    fitted_rms_deg_s: float
    samples: int
    evaluations: int
    x: tuple[float, ...] = ()
    """The fit's variables (log factors, friction in `friction_scale_n_m`) for the parts it
    tells, the twin's for the others: the next window's start."""

    def part(self, name: str) -> PartEstimate:
        for p in self.parts:
            if p.name == name:
                return p
        raise KeyError(name)


@dataclass(frozen=True)
class LoopResidual:
    """The measured error against the one the twin predicts for the configuration (rms,
    deg) over the window after `SETTLE_S`."""

    measured_rms_deg: float
    predicted_rms_deg: float
    residual_rms_deg: float


def _quiet(params: RigParams) -> RigParams:
    """The twin as a predictor: no encoder noise, interpolation error nor quantisation (the
    measured rate carries the rig's own; a quantised predictor's answer moves in steps with
    its parameters, which a least-squares fit cannot follow)."""
    return replace(params, position_noise_deg=0.0, encoder_cyclic_error_deg=0.0,
                   load_encoder_bits=48,
                   motor_encoder_counts_per_rev=params.motor_encoder_counts_per_rev * 256)


def friction_scale_n_m(params: RigParams) -> float:
    """The unit of the fit's friction variable: the twin's motor friction, or
    `FRICTION_SCALE_N_M` when it has none."""
    f0 = params.motor_coulomb_n_m
    return f0 if f0 > 0.0 else FRICTION_SCALE_N_M


def drifted(params: RigParams, faults: RigFaults, x: FloatArray, delay_ticks: int
            ) -> tuple[RigParams, RigFaults]:
    """The twin with the fit's values `x` (log gain, log stiffness, log inertia factors, motor
    friction in units of `friction_scale_n_m`; then, when `x` has them and the twin has an
    extra mode, the log factors on its frequency and damping) and `delay_ticks`."""
    scale = friction_scale_n_m(params)
    g, k, j = (math.exp(float(v)) for v in x[:3])
    p = replace(params, belt_stiffness_n_m_rad=params.belt_stiffness_n_m_rad * k,
                load_inertia_kg_m2=params.load_inertia_kg_m2 * j,
                motor_coulomb_n_m=max(0.0, float(x[3]) * scale), command_delay_ticks=delay_ticks)
    fl = replace(faults, plant_gain=min(99.0, faults.plant_gain * g))
    if len(x) > 4 and faults.resonance_hz > 0.0:
        fl = replace(fl, resonance_hz=faults.resonance_hz * math.exp(float(x[4])),
                     resonance_damping=min(1.0, faults.resonance_damping * math.exp(float(x[5]))))
    return p, fl


def _rate(params: RigParams, faults: RigFaults, win: Window) -> FloatArray:
    """The twin's rate after each of the window's commands (open loop, from rest)."""
    rig = SimRig(params, rate_hz=win.rate_hz, initial_position_deg=float(win.pos_deg[0]))
    if faults.active:
        rig.set_faults(faults)
    _, w = rig.run_commands(win.command_deg_s)
    return w


def _skip(win: Window) -> int:
    return min(win.n - 2, round(SETTLE_S * win.rate_hz))


def plant_residual(params: RigParams, faults: RigFaults, win: Window) -> FloatArray:
    """Measured rate minus the twin's answer to the same commands, from `SETTLE_S` on (the
    rate read at tick k+1 answers the command of tick k)."""
    w_twin = _rate(_quiet(params), faults, win)
    s = _skip(win)
    return np.asarray(win.speed_deg_s[1 + s:] - w_twin[s:-1], dtype=np.float64)


def fit_window(params: RigParams, faults: RigFaults, win: Window,
               start: FloatArray | None = None) -> DriftFit:
    """The twin's parameters fitted to `win` (see the module docstring); `start`: the
    previous window's values (`DriftFit.x`), else the twin's own."""
    if win.n < round(2 * SETTLE_S * win.rate_hz):
        raise ValueError(f"window: {win.n} samples, need {round(2 * SETTLE_S * win.rate_hz)}")
    quiet = _quiet(params)
    twin_delay = params.command_delay_ticks
    f0 = params.motor_coulomb_n_m
    scale_f = friction_scale_n_m(params)
    mode = faults.resonance_hz > 0.0
    x_twin = np.array([0.0, 0.0, 0.0, f0 / scale_f] + ([0.0, 0.0] if mode else []))
    s = _skip(win)
    band = butter(2, BAND_HZ, fs=win.rate_hz, output="sos")
    meas = sosfiltfilt(band, win.speed_deg_s[1:])[s:]
    evals = 0

    def residual(x: FloatArray, delay: int) -> FloatArray:
        nonlocal evals
        evals += 1
        p, fl = drifted(quiet, faults, x, delay)
        w = sosfiltfilt(band, _rate(p, fl, win)[:-1])[s:]
        return np.asarray(meas - w, dtype=np.float64)

    def solve(x: FloatArray, d: int) -> object:
        return least_squares(residual, x, args=(d,), bounds=(lo, hi), x_scale=xs,
                             diff_step=DIFF_STEP, jac="3-point", xtol=1e-4, ftol=1e-6,
                             max_nfev=MAX_NFEV,
                             loss="soft_l1", f_scale=F_SCALE_DEG_S)

    x0 = x_twin if start is None or len(start) != x_twin.size else np.array(start, dtype=np.float64)
    lo = np.array([-1.5, -1.5, -1.5, 0.0] + ([-0.7, -2.5] if mode else []))
    hi = np.array([1.5, 1.5, 1.5, 20.0] + ([0.7, 2.5] if mode else []))
    x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
    r0 = residual(x_twin, twin_delay)
    xs = np.array([0.05, 0.05, 0.05, 0.25] + ([0.05, 0.2] if mode else []))

    # The twin's delay first; whole ticks more are tried at its solution (a delay is not a
    # least-squares variable) and fitted again only if one answers better.
    delay = twin_delay
    sol = solve(x0, delay)
    best = float(np.sum(sol.fun ** 2))  # type: ignore[attr-defined]
    for d in range(twin_delay + 1, twin_delay + DELAY_TRIED + 1):
        c = float(np.sum(residual(sol.x, d) ** 2))  # type: ignore[attr-defined]
        if c < (1.0 - DELAY_GAIN) * best:
            trial = solve(sol.x, d)  # type: ignore[attr-defined]
            ct = float(np.sum(trial.fun ** 2))  # type: ignore[attr-defined]
            if ct < (1.0 - DELAY_GAIN) * best:
                delay, best, sol = d, ct, trial
    r = np.asarray(sol.fun, dtype=np.float64)  # type: ignore[attr-defined]
    x = np.asarray(sol.x, dtype=np.float64)  # type: ignore[attr-defined]
    n, m = r.size, x.size
    jac = np.asarray(sol.jac, dtype=np.float64)  # type: ignore[attr-defined]
    s2 = float(np.sum(r * r)) / max(1, n - m)
    # Filtered residuals are correlated over about rate / (2 band) ticks: that many fewer
    # independent samples than ticks.
    s2 *= win.rate_hz / (2.0 * BAND_HZ)
    std = _std(jac, s2)
    bias = _std(jac, float(np.sum(r * r)))
    parts = []
    for i, name in enumerate(PARTS[:3]):
        v = math.exp(float(x[i]))
        sd = v * float(std[i])
        parts.append(PartEstimate(name, v, sd, bool(sd < TOLD_REL_STD), bias=v * float(bias[i])))
    fc, fsd = float(x[3]), float(std[3])
    told = bool(fsd < FRICTION_TOLD_STD)
    if f0 > 0.0:
        parts.append(PartEstimate("motor_friction", fc, fsd, told, bias=float(bias[3])))
    else:
        parts.append(PartEstimate("motor_friction", fc * scale_f, fsd * scale_f, told,
                                  unit="N m", bias=float(bias[3]) * scale_f))
    if mode:
        for i, (name, rel) in enumerate(zip(MODE_PARTS, (TOLD_REL_STD, DAMPING_TOLD_REL_STD),
                                            strict=True), start=4):
            v = math.exp(float(x[i]))
            sd = v * float(std[i])
            parts.append(PartEstimate(name, v, sd, bool(sd < rel), bias=v * float(bias[i])))
    # The next window starts from this one's told parts; a part not told starts again from
    # the twin's value (where a window that barely moved it left it says nothing).
    x_next = np.where([p.told for p in parts], x, x_twin)
    return DriftFit(parts=tuple(parts), delay_ticks=delay, twin_delay_ticks=twin_delay,
                    residual_rms_deg_s=float(np.sqrt(np.mean(r0 * r0))),
                    fitted_rms_deg_s=float(np.sqrt(np.mean(r * r))), samples=n,
                    evaluations=evals, x=tuple(float(v) for v in x_next))


def _std(jac: FloatArray, s2: float) -> FloatArray:
    """Each variable's standard deviation from the fit's Jacobian; a variable the window does
    not move (a mode the trajectory does not excite: its column is next to nothing) gets an
    infinite one and the others are taken without it, not from a near-singular inverse."""
    m = jac.shape[1]
    norms = np.sqrt(np.sum(jac * jac, axis=0))
    live = norms > 1e-6 * max(float(np.max(norms)), 1e-300)
    std = np.full(m, math.inf)
    if not np.any(live):
        return std
    j = jac[:, live]
    try:
        cov = s2 * np.linalg.inv(j.T @ j)
    except np.linalg.LinAlgError:
        return std
    d = np.diag(cov)
    std[live] = np.where(d > 0.0, np.sqrt(np.abs(d)), math.inf)
    return std


def loop_residual(cfg: LoopConfig, params: RigParams, faults: RigFaults, win: Window
                  ) -> LoopResidual:
    """The configuration on the twin over the window's reference (see the module docstring)."""
    ref = np.asarray(win.ref_deg, dtype=np.float64)
    rate = np.gradient(ref) * win.rate_hz
    loop = ServoLoop(LoopCoefficients.build(cfg, 0))
    rig = SimRig(_quiet(params), rate_hz=win.rate_hz, initial_position_deg=float(win.pos_deg[0]))
    if faults.active:
        rig.set_faults(faults)
    run = run_ref_ticks(loop, rig, ref, rate)  # the tick's arithmetic, compiled
    err = run.ref_deg - run.pos_deg
    s = round(2.0 * SETTLE_S * win.rate_hz)
    e_meas = np.asarray(win.error_deg[s:], dtype=np.float64)
    e_pred = err[s:]
    d = e_meas - e_pred
    return LoopResidual(measured_rms_deg=float(np.sqrt(np.mean(e_meas**2))),
                        predicted_rms_deg=float(np.sqrt(np.mean(e_pred**2))),
                        residual_rms_deg=float(np.sqrt(np.mean(d * d))))
