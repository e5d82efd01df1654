"""The gate's nonlinear check: a candidate on the simulated timing-belt rig (backlash, Stribeck
and static friction, the drive's torque limit, the command limit, encoder quantisation and
noise) through a velocity reversal, a stop and a hold, looking for what the linear analysis
cannot see: ringing after the reversal, chatter and hunting at standstill.

The loop is the controller's own (`controller.core.loop.ServoLoop`), ticked against `SimRig`
exactly as `controller.sim.experiment` does (compiled: `controller.sim.offline`). The scenario
(2.5 s simulated):

    0 - 1.571 s   reference 5 sin(2 t) deg: up to the reversal at 0.785 s, back to 0
    1.571 - 4.5 s hold at 0 deg (a stop from 10 deg/s; stick-slip chatter needs seconds)

Figures (the speed command u band-passed 4-150 Hz, as the loop watchdog does: what the
trajectory asks for is below the band, chatter and ringing are in it):

* `reversal_rms_deg_s`: band RMS of u in the 0.4 s after the reversal;
* `hold_rms_deg_s`: band RMS of u over the last 1 s of the hold;
* `hold_error_p2p_deg`: peak-to-peak position error over the last 1 s (hunting);
* the frequency of each oscillation from the zero crossings of the band-passed u.

Thresholds, from measurements on the simulated rig (`tests/bench/bench_nonlinear_check.py`
prints the sweep): the article's configuration (Q31 at 0.5 Hz) gives 0.85 deg/s RMS after the
reversal and 0.66 deg/s at hold, and hunts: a stick-slip limit cycle of 0.12 deg peak to peak
(the hold preview's "hunting even at 0.5 Hz"; also without the DOB: it is the position loop's
integrator against static friction, not a DOB finding). Q31 from ~4 Hz and Q20 from ~4 Hz
chatter at standstill (2.6-6 deg/s RMS, 3-6 Hz) and hunt up to 0.32 deg. A finding is a band
RMS above `OSCILLATION_RMS_DEG_S` (2 deg/s: the watchdog's own oscillation threshold, so a
configuration flagged here is one the watchdog would roll back) or hunting above
`HUNTING_P2P_DEG` (0.25 deg: twice the article configuration's own limit cycle).

Each finding says whether the oscillation is sustained: chatter at standstill whose band RMS
over the last 0.5 s is still at least `SUSTAINED_RATIO` (0.7) of the 0.5 s before it (it does
not decay: a limit cycle, 2.9-4.5 s after the stop; Q31 at 10-15 Hz on the default loop holds
its RMS within 2 % there) is sustained; the gate rejects a candidate with a sustained
oscillation (`controller.gate.verdict.judge`). Ringing after the reversal (a transient),
chatter that decays and hunting (a slow position limit cycle of the size the article's own
configuration shows) stay cautions. The plant's
gain follows the plant knowledge's model (its DC gain relative to the simulated rig's), the
rest is the simulated rig's.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from controller.core.config import LoopConfig, NominalModel
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.lti import butter_sos, sosfilt
from controller.core.trajectory import Trajectory
from controller.sim.offline import ROWS, OfflineRun, run_ticks
from controller.sim.sim_rig import RigFaults, RigParams, SimRig

__all__ = [
    "HUNTING_P2P_DEG",
    "OSCILLATION_RMS_DEG_S",
    "SUSTAINED_RATIO",
    "Finding",
    "NonlinearResult",
    "findings",
    "nonlinear_check",
]

OSCILLATION_RMS_DEG_S = 2.0
HUNTING_P2P_DEG = 0.25
SUSTAINED_RATIO = 0.7
_AMPLITUDE_DEG = 5.0
_OMEGA_RAD_S = 2.0
_DURATION_S = 4.5
_BAND_HZ = (4.0, 150.0)


@dataclass(frozen=True)
class Finding:
    """One finding of the nonlinear check (`controller.gate.verdict.NonlinearFinding`)."""

    text: str
    sustained: bool
    """An oscillation that does not decay (the gate rejects); False: a transient or a slow
    limit cycle (a caution)."""


@dataclass(frozen=True)
class NonlinearResult:
    reversal_rms_deg_s: float
    reversal_freq_hz: float | None
    hold_rms_deg_s: float
    hold_freq_hz: float | None
    hold_error_p2p_deg: float
    peak_command_deg_s: float
    run_time_s: float
    reasons: tuple[str, ...]
    """One sentence per finding with its figures; empty when nothing was found."""
    findings: tuple[Finding, ...] = ()
    """The reasons with whether each oscillation is sustained."""
    hold_decay_ratio: float = float("nan")
    """Band RMS of u over the last 0.5 s over that of the 0.5 s before (< 1: decaying)."""


def _freq(x: np.ndarray, rate_hz: float) -> float | None:
    s = np.signbit(x)
    crossings = int(np.count_nonzero(s[1:] != s[:-1]))
    if crossings < 4:
        return None
    return 0.5 * crossings * rate_hz / x.size


@lru_cache(maxsize=4)
def _band_sos(rate_hz: float) -> np.ndarray:
    """The 4-150 Hz band-pass (second order) at the loop rate: the same for every candidate."""
    sos = butter_sos(2, _BAND_HZ, "bandpass", rate_hz)
    sos.flags.writeable = False
    return sos


def nonlinear_check(
    cfg: LoopConfig,
    model: NominalModel | None = None,
    *,
    rig_params: RigParams | None = None,
    seed: int = 0,
) -> NonlinearResult:
    """Run `cfg` through the scenario on the simulated rig; deterministic for a seed."""
    if not isinstance(cfg, LoopConfig):
        raise ValueError("cfg: must be a LoopConfig")
    t0 = time.perf_counter()
    rate = cfg.rate_hz
    ts = 1.0 / rate
    n = round(_DURATION_S * rate)
    t_stop = math.pi / _OMEGA_RAD_S
    gain = 1.0
    if model is not None:
        gain = model.dc_gain / NominalModel().dc_gain
        if not (math.isfinite(gain) and 0.0 < gain <= 100.0):
            raise ValueError(f"model: DC gain ratio {gain!r} to the simulated rig is out of range")
    rig = SimRig(rig_params or RigParams(), rate_hz=rate, seed=seed)
    if gain != 1.0:
        rig.set_faults(RigFaults(plant_gain=gain))
    loop = ServoLoop(LoopCoefficients.build(cfg))
    # The sine up to the stop (the ticks whose time k ts is before t_stop), then a hold at 0.
    k_stop = min(n, math.ceil(t_stop * rate))
    while k_stop > 0 and (k_stop - 1) * ts >= t_stop:
        k_stop -= 1
    while k_stop < n and k_stop * ts < t_stop:
        k_stop += 1
    run = OfflineRun(np.empty((len(ROWS), n)))
    sine = Trajectory(kind="sine", amplitude_deg=_AMPLITUDE_DEG, omega_rad_s=_OMEGA_RAD_S)
    run_ticks(loop, rig, sine, k_stop, out=run, period_s=ts)
    run_ticks(loop, rig, Trajectory(kind="hold", offset_deg=0.0), n - k_stop, out=run,
              at=k_stop, period_s=ts)
    cmd = run.command_deg_s
    err = run.ref_deg - run.pos_deg
    band = sosfilt(_band_sos(rate), cmd)
    k_rev = round(0.5 * t_stop * rate)
    rev = band[k_rev : k_rev + round(0.4 * rate)]
    hold = band[n - round(1.0 * rate) :]
    half = hold.size // 2
    early = float(np.sqrt(np.mean(hold[:half] ** 2)))
    late = float(np.sqrt(np.mean(hold[half:] ** 2)))
    decay = late / early if early > 0.0 else 0.0
    hold_err = err[n - round(1.0 * rate) :]
    rev_rms = float(np.sqrt(np.mean(rev * rev)))
    hold_rms = float(np.sqrt(np.mean(hold * hold)))
    p2p = float(np.ptp(hold_err))
    rev_f, hold_f = _freq(rev, rate), _freq(hold, rate)
    found: list[Finding] = []

    def at(f: float | None) -> str:
        return f" at {f:.3g} Hz" if f is not None else ""

    if not rev_rms < OSCILLATION_RMS_DEG_S:
        found.append(Finding(
            f"ringing after a velocity reversal: the speed command oscillates{at(rev_f)}, "
            f"{rev_rms:.3g} deg/s RMS (4-150 Hz) > {OSCILLATION_RMS_DEG_S:g}", False))
    if not hold_rms < OSCILLATION_RMS_DEG_S:
        sustained = decay >= SUSTAINED_RATIO
        found.append(Finding(
            f"chatter at standstill: the speed command oscillates{at(hold_f)}, "
            f"{hold_rms:.3g} deg/s RMS (4-150 Hz) > {OSCILLATION_RMS_DEG_S:g}"
            + (f", sustained: it does not decay ({decay:.2f} of its RMS 0.5 s earlier,"
               f" 3-4.5 s after the stop)" if sustained
               else f", decaying ({decay:.2f} of its RMS 0.5 s earlier)"),
            sustained))
    if not p2p < HUNTING_P2P_DEG:
        found.append(Finding(
            f"hunting at hold: the position error swings {p2p:.3g} deg peak to peak "
            f"> {HUNTING_P2P_DEG:g} deg (backlash and friction limit cycle)", False))
    return NonlinearResult(
        reversal_rms_deg_s=rev_rms,
        reversal_freq_hz=rev_f,
        hold_rms_deg_s=hold_rms,
        hold_freq_hz=hold_f,
        hold_error_p2p_deg=p2p,
        peak_command_deg_s=float(np.max(np.abs(cmd))),
        run_time_s=time.perf_counter() - t0,
        reasons=tuple(x.text for x in found),
        findings=tuple(found),
        hold_decay_ratio=decay,
    )


@lru_cache(maxsize=128)
def findings(cfg: LoopConfig, model: NominalModel) -> tuple[Finding, ...]:
    """The findings of `nonlinear_check` (the gate's `judge(..., nonlinear=findings)`), cached
    per (configuration, plant model): everything the run depends on (the simulated rig's
    parameters and the seed are the defaults). A candidate judged again, or on new plant
    knowledge with the same model (new measured responses), is not simulated again."""
    return nonlinear_check(cfg, model).findings
