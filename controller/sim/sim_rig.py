"""Simulated timing-belt turntable: control.md's "reference rig model", stepped at the loop rate.

Physics (SI inside, load-side degrees at the interface), integrated with semi-implicit Euler at
`substeps` per control tick (default 10 -> 10 kHz):

- Drive: an I-P speed loop on the motor, torque = Ki * integral(ref - meas) - Kp * meas,
  clamped to the torque limit with conditional integration (no windup). ref = u * N * pi/180
  (u is the LOAD-side speed command in deg/s; control.md pitfall #2). meas is the drive's own
  speed estimate: the motor-encoder count difference over the last 1 ms (a sliding window over
  the sub-steps), so it is quantised (4000 counts/rev) and lags by half a millisecond.
- Gearbox: rigid, ratio N; the motor inertia sees the belt torque divided by N.
- Belt: spring-damper on the stretch (pulley angle + transmission error - load angle) with a
  dead zone of the backlash width; a slack belt transmits nothing and never pulls.
- Load: inertia, viscous friction, Stribeck friction Fc + (Fs - Fc) exp(-(w/ws)^2), a constant
  bias torque, tooth-ripple torque at `pulley_teeth` per rev, and an external disturbance.
  Friction is applied at the velocity level (time-stepping): if the friction available this
  sub-step can absorb the momentum the other torques would give, the load sticks at exactly
  zero speed, so standstill does not chatter numerically.
- Sensor: load encoder with 2^bits counts per revolution (counted multi-turn, never wrapped) and
  Gaussian position noise added before quantisation; the rate is the backward difference of
  that measured position over one tick, as the controller would compute it.

The model is control.md's table unchanged. Choices where the table is silent: the belt is
1:1, so tooth effects repeat `pulley_teeth` times per load revolution (transmission error as a
function of the pulley angle, ripple torque of the load angle); the bias torque pushes the
positive direction; the motor has no Coulomb friction; reset() restarts the noise stream, so a
seed gives the same run after every reset.

Checked against the article's identified M(s)P(s) = 1935/(s^2 + 62.2 s + 1935)
(tests/test_sim_rig.py): the linearised continuous model is within 0.28 dB / 1.9 deg up to
7 Hz (control.md's "0.15 dB" is not reproduced by its own table: -0.27 dB at 5 Hz). The stepped
rig measured through `read()` at 20 +- 2 deg/s, everything on, is within 0.28 dB / 2.3 deg at
0.2-5 Hz; of that phase, about one tick is sampling delay (half from the held command, half
from the backward-difference rate), i.e. -1.8 deg at 5 Hz.

Disturbances beyond the reference model (`controller.sim.rig_disturbances` names them): the
motor's cogging torque (`cogging_torque_n_m`, motor side, `cogging_periods_per_rev` per motor
revolution; 0 by default, and then the kernel skips it: runs are bit-identical to the model
without it) and friction changes while running (`SimRig.set_friction`).

Rate disturbances at P's input, the position-dependent belt and encoder errors (all 0 by
default; then the kernel skips them and runs bit-identically to the reference model, checked
against the kernel before they existed in tests/test_sim_rig_identity.py). The article's d is a
rate added to the motor rate at P's input; these put one there:
- motor and gearbox friction: Coulomb `motor_coulomb_n_m` plus `gearbox_friction_fraction` of
  the transmitted torque (1 - efficiency), on the motor inertia at the velocity level like the
  load's (the motor sticks at a reversal until the drive has built up the friction torque);
- gearbox backlash `gearbox_backlash_deg` (massless gearbox and pulley: in series with the
  belt's dead zone, so it adds to it);
- the drive's speed loop regulating to ref + `drive_offset_rpm` - droop * torque
  (`drive_droop_rpm_per_n_m`): a speed error that follows the load torque, flipping at each
  reversal of the friction;
- transmission-ratio ripple (`ratio_ripple_fraction`, `ratio_ripple_periods_per_rev` per load
  revolution): the pulley angle seen by the belt is theta + (a/n) sin(n theta).
The plant varies with the turntable's angle theta: belt stiffness k (1 + v_k cos theta) and
damping c (1 + v_c cos theta) (`belt_stiffness_variation`, `belt_damping_variation`: the tight
span and its tension change once per revolution). The load encoder adds an interpolation error
`encoder_cyclic_error_deg` sin(`encoder_cyclic_periods_per_rev` theta) before quantisation.
`controller.sim.rig_disturbances` names plausible values for each.

A transport delay of the command (`command_delay_ticks`, whole control ticks; 0 by default,
and then the kernel skips it): the drive acts on the command sent that many ticks before,
through a delay line in the state array (zeros after a reset).

The kernel is compiled with numba and works on two preallocated float64 arrays (parameters and
state); `SimRig` wraps it. The external disturbance is sampled once per tick and held. One
control tick is `advance_tick(x, p, command_deg_s, torque_n_m, noise_deg) -> (pos_deg, rate_deg_s)`
(x: state array, p: parameter array, both float64 and written in place; no allocation), callable
from other numba code.

Runtime faults (`RigFaults`, `SimRig.set_faults` and its shortcuts), for testing what watches
the loop: a plant-gain factor on the speed reference the drive receives (a wrong scaling in
the drive: the u -> w gain at all frequencies times the factor), extra backlash (the belt
loosens), and an extra mode: a payload of `resonance_mass_fraction` of the load inertia on a
torsional spring (natural frequency `resonance_hz` against a clamped hub, damping ratio
`resonance_damping`); friction, belt and ripple act on the hub, the load encoder reads the
payload (non-collocated: past the resonance the phase drops by 180 deg). With the belt the
pair resonates slightly above `resonance_hz` (about resonance_hz / sqrt(1 - mass fraction)
for a stiff hub). A fault is staged in the parameter array and taken over by the kernel at the
start of the next tick (a flag the kernel tests: no Python cost per tick, with or without
faults); adding or removing the mode conserves momentum. Faults survive `reset()`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Annotated

import numpy as np
import numpy.typing as npt

from controller.core.errors import ConfigError
from controller.core.numba_start import numba
from controller.core.validate import (
    check_fields,
    in_range,
    nonnegative,
    number,
    positive,
    within,
)
from controller.sim.disturbance import Disturbance, NoDisturbance

__all__ = ["RigFaults", "RigParams", "SimRig"]

_DEG = math.pi / 180.0
_TWO_PI = 2.0 * math.pi
_NOISE_BLOCK = 4096


def _integer(value: object, field: str) -> object:
    if not isinstance(value, int):
        raise ConfigError(field, f"must be an int, got {value!r}")
    return value


def _fraction(value: float, field: str) -> float:
    if abs(value) >= 0.9:
        raise ConfigError(field, f"must be in (-0.9, 0.9), got {value!r}")
    return value


def _delay_ticks(value: int, field: str) -> int:
    if not 0 <= value <= 100:
        raise ConfigError(field, f"must be in 0..100, got {value}")
    return value


def _encoder_bits(value: int, field: str) -> int:
    if not 1 <= value <= 48:
        raise ConfigError(field, f"must be in 1..48, got {value}")
    return value


@dataclass(frozen=True, slots=True)
class RigParams:
    """Physical parameters of the simulated rig; defaults are control.md's reference model."""

    gear_ratio: Annotated[float, positive] = 132.0
    """Motor revolutions per load revolution (gearbox; the belt is 1:1)."""
    motor_inertia_kg_m2: Annotated[float, positive] = 1.0e-5
    """Rotor inertia, motor side."""
    motor_viscous_n_m_s_rad: Annotated[float, nonnegative] = 1.0e-6
    """Motor viscous friction, motor side."""
    drive_kp_n_m_s_rad: Annotated[float, nonnegative] = 3.772e-3
    """Drive I-P speed loop: proportional gain on the measured motor speed."""
    drive_ki_n_m_rad: Annotated[float, positive] = 0.8217
    """Drive I-P speed loop: integral gain on the speed error."""
    drive_torque_limit_n_m: Annotated[float, positive] = 0.25
    """Drive output torque limit, motor side."""
    drive_speed_window_s: Annotated[float, positive] = 1.0e-3
    """Drive speed estimate: motor-encoder count difference over this window."""
    motor_encoder_counts_per_rev: Annotated[int, positive, _integer] = 4000
    """Motor encoder resolution (1000 lines x 4)."""
    belt_stiffness_n_m_rad: Annotated[float, positive] = 186.2
    """Belt stiffness, load side."""
    belt_damping_n_m_s_rad: Annotated[float, nonnegative] = 0.386
    """Belt damping, load side."""
    backlash_deg: Annotated[float, nonnegative] = 0.02
    """Total backlash (dead-zone width of the belt stretch), load side."""
    load_inertia_kg_m2: Annotated[float, positive] = 0.08
    """Turntable inertia."""
    load_viscous_n_m_s_rad: Annotated[float, nonnegative] = 5.54
    """Load viscous friction."""
    coulomb_torque_n_m: Annotated[float, nonnegative] = 0.25
    """Load Coulomb (sliding) friction."""
    static_torque_n_m: Annotated[float, number] = 0.35
    """Load static friction (breakaway); must be >= the Coulomb friction."""
    stribeck_speed_deg_s: Annotated[float, positive] = 0.2
    """Speed scale of the Stribeck decay from static to Coulomb friction."""
    bias_torque_n_m: Annotated[float, number] = 0.10
    """Constant torque on the load (imbalance), positive direction."""
    pulley_teeth: Annotated[int, positive, _integer] = 30
    """Teeth per revolution: frequency of transmission error and ripple, per rev."""
    transmission_error_deg: Annotated[float, nonnegative] = 0.01
    """Amplitude of the tooth-periodic transmission error, load side."""
    ripple_torque_n_m: Annotated[float, nonnegative] = 0.05
    """Amplitude of the tooth-periodic ripple torque on the load."""
    load_encoder_bits: Annotated[int, number, _integer, _encoder_bits] = 26
    """Load encoder resolution: 2**bits counts per revolution."""
    position_noise_deg: Annotated[float, nonnegative] = 1.0e-5
    """Standard deviation of Gaussian noise on the measured load position (~2 LSB)."""
    cogging_torque_n_m: Annotated[float, nonnegative] = 0.0
    """Amplitude of the motor's cogging torque, motor side (0 = none: the reference model)."""
    cogging_periods_per_rev: Annotated[int, positive, _integer] = 12
    """Cogging periods per MOTOR revolution (slots and poles of the motor)."""
    # -- rate disturbances at P's input (motor and gearbox side); 0 = off, the reference model
    motor_coulomb_n_m: Annotated[float, nonnegative] = 0.0
    """Coulomb friction of the motor and the gearbox input (no-load friction), motor side."""
    gearbox_friction_fraction: Annotated[float, nonnegative, _fraction] = 0.0
    """Load-dependent gearbox friction: this share of the transmitted torque (belt torque / N)
    is lost, motor side (1 - efficiency)."""
    gearbox_backlash_deg: Annotated[float, nonnegative] = 0.0
    """Gearbox backlash at its output, load side. The gearbox and pulley are massless here,
    so it is in series with the belt's dead zone and adds to it."""
    drive_offset_rpm: Annotated[float, number] = 0.0
    """Speed offset of the drive's speed loop, motor side: the motor turns at this speed when
    commanded zero (reference or speed-sensing offset)."""
    drive_droop_rpm_per_n_m: Annotated[float, nonnegative] = 0.0
    """Droop of the drive's speed loop, motor side: the regulated speed falls by this much per
    N m of drive torque (a drive tuned with droop, or a finite low-frequency speed-loop gain)."""
    ratio_ripple_fraction: Annotated[float, nonnegative, _fraction] = 0.0
    """Ripple of the transmission ratio (belt tension, pulley run-out), as a fraction: the
    pulley angle seen by the belt is theta + (a / n) sin(n theta), n = the periods below."""
    ratio_ripple_periods_per_rev: Annotated[int, positive, _integer] = 1
    """Ratio-ripple periods per LOAD revolution (1 = once per turn of the turntable)."""
    # -- plant varying with the turntable's position (belt span and tension)
    belt_stiffness_variation: Annotated[float, number, _fraction] = 0.0
    """Belt stiffness k(theta) = k (1 + v cos theta) with theta the load angle: the tight span
    and its tension change once per turntable revolution."""
    belt_damping_variation: Annotated[float, number, _fraction] = 0.0
    """Belt damping c(theta) = c (1 + v cos theta), like the stiffness."""
    # -- load encoder errors beyond noise and quantisation
    encoder_cyclic_error_deg: Annotated[float, nonnegative] = 0.0
    """Amplitude of the load encoder's interpolation (sub-divisional) error, load side."""
    encoder_cyclic_periods_per_rev: Annotated[int, positive, _integer] = 16384
    """Periods of that error per revolution (the encoder's signal periods)."""
    # -- transport delay of the command (a fieldbus, a drive's input filter)
    command_delay_ticks: Annotated[int, number, _integer, _delay_ticks] = 0
    """Whole control ticks the drive receives the speed command late (0 = none: the reference
    model; the kernel then skips the delay line and runs bit-identically)."""

    def __post_init__(self) -> None:
        check_fields(self)
        if self.static_torque_n_m < self.coulomb_torque_n_m:
            raise ConfigError(
                "static_torque_n_m",
                f"must be >= coulomb_torque_n_m ({self.coulomb_torque_n_m!r}), "
                f"got {self.static_torque_n_m!r}",
            )


@dataclass(frozen=True, slots=True)
class RigFaults:
    """Faults injected into a running simulated rig; the defaults are "no fault"."""

    plant_gain: Annotated[float, within(0.0, 100.0)] = 1.0
    """Factor on the speed reference the drive receives (1 = nominal, 0 = drive not moving)."""
    extra_backlash_deg: Annotated[float, within(0.0, 10.0)] = 0.0
    """Backlash added to `RigParams.backlash_deg` (the belt loosens), load side."""
    resonance_hz: Annotated[float, within(0.0, 1e4)] = 0.0
    """Natural frequency of an extra mode (payload on a spring, hub clamped); 0 = none."""
    resonance_damping: Annotated[float, within(0.0, 1.0, lo_open=True)] = 0.02
    """Damping ratio of the extra mode."""
    resonance_mass_fraction: Annotated[float, within(0.0, 0.9, lo_open=True)] = 0.2
    """Share of the load inertia that sits on the spring (the encoder reads it)."""

    def __post_init__(self) -> None:
        check_fields(self)

    @property
    def active(self) -> bool:
        return self != _NO_FAULTS


_NO_FAULTS = RigFaults()

# Parameter array layout (SI, load side unless noted). _P_JL is the hub's inertia (the whole
# load's without an extra mode); _P_RES_JP the payload's (0 = no extra mode). A fault change is
# staged at _P_NEW.. (the values for _FAULT_SLOTS, in order); the kernel takes it over when
# _P_PENDING is set.
_P_N, _P_JM, _P_BM, _P_KP, _P_KI, _P_TLIM, _P_CPR, _P_K, _P_C, _P_HALF_BL = range(10)
_P_JL, _P_BL, _P_FC, _P_FS, _P_WS, _P_BIAS, _P_Z, _P_TE, _P_RIP, _P_QDEG = range(10, 20)
_P_DT, _P_NSUB, _P_NWIN, _P_RATE = range(20, 24)
_P_GAIN, _P_RES_JP, _P_RES_W2, _P_RES_2ZW = range(24, 28)  # active fault values
_FAULT_SLOTS = (_P_GAIN, _P_HALF_BL, _P_JL, _P_RES_JP, _P_RES_W2, _P_RES_2ZW)
_P_NEW = 28
_P_PENDING = _P_NEW + len(_FAULT_SLOTS)
# Motor cogging torque (motor side) and its periods per motor revolution; 0 = none.
_P_COG = _P_PENDING + 1
_P_NCOG = _P_PENDING + 2
# Rate disturbances at P's input, position-dependent belt, encoder error (all 0 = off: the
# kernel skips them and runs bit-identically to the reference model). _P_MFRIC_ON is 1 when
# either motor-side friction is on, _P_DRIVE_ON when offset or droop is.
_P_MCOUL = _P_PENDING + 3  # motor + gearbox input Coulomb friction, N m motor side
_P_GFRAC = _P_PENDING + 4  # gearbox friction, share of the transmitted torque
_P_MFRIC_ON = _P_PENDING + 5
_P_DOFF = _P_PENDING + 6  # drive speed offset, rad/s motor side
_P_DROOP = _P_PENDING + 7  # drive droop, (rad/s) / (N m) motor side
_P_DRIVE_ON = _P_PENDING + 8
_P_RR = _P_PENDING + 9  # ratio ripple fraction
_P_NRR = _P_PENDING + 10  # its periods per load revolution
_P_KVAR = _P_PENDING + 11  # belt stiffness variation with the load angle
_P_CVAR = _P_PENDING + 12  # belt damping variation with the load angle
_P_ENC_CYC = _P_PENDING + 13  # encoder interpolation error amplitude, deg
_P_ENC_N = _P_PENDING + 14  # its periods per revolution
_P_DELAY = _P_PENDING + 15  # command delay, whole ticks (0 = none)
_P_LEN = _P_PENDING + 16

# State array layout; the motor-encoder ring buffer (counts) follows _X_RING (nwin entries),
# then the command delay line (`command_delay_ticks` entries, its next slot at _X_DIDX).
# _X_Q / _X_QD: deflection of the extra mode's payload relative to the hub, and its rate.
_X_THM, _X_WM, _X_THL, _X_WL, _X_XI, _X_TAU, _X_POSM, _X_RIDX, _X_Q, _X_QD, _X_DIDX = range(11)
_X_RING = 11


def _param_array(
    p: RigParams, rate_hz: float, substeps: int
) -> tuple[npt.NDArray[np.float64], int]:
    dt = 1.0 / (rate_hz * substeps)
    nwin = max(1, round(p.drive_speed_window_s / dt))
    a = np.zeros(_P_LEN)
    a[_P_N] = p.gear_ratio
    a[_P_JM] = p.motor_inertia_kg_m2
    a[_P_BM] = p.motor_viscous_n_m_s_rad
    a[_P_KP] = p.drive_kp_n_m_s_rad
    a[_P_KI] = p.drive_ki_n_m_rad
    a[_P_TLIM] = p.drive_torque_limit_n_m
    a[_P_CPR] = p.motor_encoder_counts_per_rev
    a[_P_K] = p.belt_stiffness_n_m_rad
    a[_P_C] = p.belt_damping_n_m_s_rad
    a[_P_HALF_BL] = 0.5 * p.backlash_deg * _DEG
    if p.gearbox_backlash_deg != 0.0:  # in series with the belt's dead zone
        a[_P_HALF_BL] = 0.5 * (p.backlash_deg + p.gearbox_backlash_deg) * _DEG
    a[_P_JL] = p.load_inertia_kg_m2
    a[_P_BL] = p.load_viscous_n_m_s_rad
    a[_P_FC] = p.coulomb_torque_n_m
    a[_P_FS] = p.static_torque_n_m
    a[_P_WS] = p.stribeck_speed_deg_s * _DEG
    a[_P_BIAS] = p.bias_torque_n_m
    a[_P_Z] = p.pulley_teeth
    a[_P_TE] = p.transmission_error_deg * _DEG
    a[_P_RIP] = p.ripple_torque_n_m
    a[_P_QDEG] = 360.0 / 2.0**p.load_encoder_bits
    a[_P_DT] = dt
    a[_P_NSUB] = substeps
    a[_P_NWIN] = nwin
    a[_P_RATE] = rate_hz
    a[_P_GAIN] = 1.0
    a[_P_COG] = p.cogging_torque_n_m
    a[_P_NCOG] = p.cogging_periods_per_rev
    a[_P_MCOUL] = p.motor_coulomb_n_m
    a[_P_GFRAC] = p.gearbox_friction_fraction
    a[_P_MFRIC_ON] = float(p.motor_coulomb_n_m > 0.0 or p.gearbox_friction_fraction > 0.0)
    a[_P_DOFF] = p.drive_offset_rpm * _TWO_PI / 60.0
    a[_P_DROOP] = p.drive_droop_rpm_per_n_m * _TWO_PI / 60.0
    a[_P_DRIVE_ON] = float(p.drive_offset_rpm != 0.0 or p.drive_droop_rpm_per_n_m != 0.0)
    a[_P_RR] = p.ratio_ripple_fraction
    a[_P_NRR] = p.ratio_ripple_periods_per_rev
    a[_P_KVAR] = p.belt_stiffness_variation
    a[_P_CVAR] = p.belt_damping_variation
    a[_P_ENC_CYC] = p.encoder_cyclic_error_deg
    a[_P_ENC_N] = p.encoder_cyclic_periods_per_rev
    a[_P_DELAY] = p.command_delay_ticks
    return a, nwin


def _fault_values(p: RigParams, f: RigFaults, substep_hz: float) -> tuple[float, ...]:
    """The kernel's values for `f`, in the order of _FAULT_SLOTS."""
    jp = w2 = zw2 = 0.0
    if f.resonance_hz > 0.0:
        if f.resonance_hz > substep_hz / 20.0:
            raise ConfigError(
                "resonance_hz",
                f"{f.resonance_hz} Hz is above {substep_hz / 20.0:g} Hz, the highest mode the "
                f"{substep_hz:g} Hz integration resolves",
            )
        w = _TWO_PI * f.resonance_hz
        jp = f.resonance_mass_fraction * p.load_inertia_kg_m2
        w2 = w * w
        zw2 = 2.0 * f.resonance_damping * w
    half = 0.5 * (p.backlash_deg + f.extra_backlash_deg) * _DEG
    if p.gearbox_backlash_deg != 0.0:  # in series with the belt's dead zone
        half = 0.5 * (p.backlash_deg + p.gearbox_backlash_deg + f.extra_backlash_deg) * _DEG
    return (f.plant_gain, half, p.load_inertia_kg_m2 - jp, jp, w2, zw2)


@numba.njit(cache=True)
def _measure_deg(x: np.ndarray, p: np.ndarray, noise_deg: float) -> float:
    q = p[_P_QDEG]
    th = x[_X_THL] + x[_X_Q]
    if p[_P_ENC_CYC] != 0.0:  # interpolation error, periodic in the true angle
        noise_deg += p[_P_ENC_CYC] * math.sin(p[_P_ENC_N] * th)
    return math.floor((th / _DEG + noise_deg) / q + 0.5) * q


@numba.njit(cache=True)
def _take_faults(x: np.ndarray, p: np.ndarray) -> None:
    """Take over the staged fault values. A changed extra mode first merges into the hub
    (momentum and centre of inertia kept), a new one starts at rest relative to the hub."""
    jp = p[_P_RES_JP]
    same_mode = True
    for i in range(3, len(_FAULT_SLOTS)):  # payload inertia, w^2, 2 zeta w
        same_mode = same_mode and p[_P_NEW + i] == p[_FAULT_SLOTS[i]]
    if jp > 0.0 and not same_mode:
        mu = jp / (p[_P_JL] + jp)
        x[_X_WL] += mu * x[_X_QD]
        x[_X_THL] += mu * x[_X_Q]
        x[_X_Q] = 0.0
        x[_X_QD] = 0.0
    for i in range(len(_FAULT_SLOTS)):
        p[_FAULT_SLOTS[i]] = p[_P_NEW + i]
    p[_P_PENDING] = 0.0


@numba.njit(cache=True)
def _run_commands(x: np.ndarray, p: np.ndarray, u: np.ndarray, noise: np.ndarray,
                  pos: np.ndarray, rate: np.ndarray) -> None:
    for i in range(u.size):
        pos[i], rate[i] = advance_tick(x, p, u[i], 0.0, noise[i])


@numba.njit(cache=True)
def _reset_kernel(x: np.ndarray, p: np.ndarray, position_deg: float, noise_deg: float) -> float:
    x[:] = 0.0
    x[_X_THL] = position_deg * _DEG
    x[_X_THM] = x[_X_THL] * p[_P_N]
    count = math.floor(x[_X_THM] * p[_P_CPR] / _TWO_PI)
    for i in range(int(p[_P_NWIN])):
        x[_X_RING + i] = count
    pos = _measure_deg(x, p, noise_deg)
    x[_X_POSM] = pos
    return pos


@numba.njit(cache=True)
def advance_tick(
    x: np.ndarray, p: np.ndarray, command_deg_s: float, torque_n_m: float, noise_deg: float
) -> tuple[float, float]:
    """Advance one control tick holding the command; return (measured pos deg, rate deg/s)."""
    if not math.isfinite(command_deg_s):
        raise ValueError("command_deg_s must be finite")
    if not math.isfinite(torque_n_m):
        raise ValueError("disturbance torque must be finite")
    if p[_P_PENDING] != 0.0:
        _take_faults(x, p)
    if p[_P_DELAY] != 0.0:  # the drive acts on the command of `delay` ticks ago
        slot = _X_RING + int(p[_P_NWIN]) + int(x[_X_DIDX])
        late = x[slot]
        x[slot] = command_deg_s
        x[_X_DIDX] = (x[_X_DIDX] + 1.0) % p[_P_DELAY]
        command_deg_s = late
    n = p[_P_N]
    jm = p[_P_JM]
    bm = p[_P_BM]
    kp = p[_P_KP]
    ki = p[_P_KI]
    tlim = p[_P_TLIM]
    cpr = p[_P_CPR]
    k = p[_P_K]
    c = p[_P_C]
    half = p[_P_HALF_BL]
    jl = p[_P_JL]
    bl = p[_P_BL]
    fc = p[_P_FC]
    dfs = p[_P_FS] - fc
    ws = p[_P_WS]
    z = p[_P_Z]
    te = p[_P_TE]
    rip = p[_P_RIP]
    dt = p[_P_DT]
    nsub = int(p[_P_NSUB])
    nwin = int(p[_P_NWIN])
    count_to_speed = _TWO_PI / cpr / (nwin * dt)
    ref = command_deg_s * n * _DEG * p[_P_GAIN]
    t_ext = p[_P_BIAS] + torque_n_m
    jp = p[_P_RES_JP]
    res_w2 = p[_P_RES_W2]
    res_zw2 = p[_P_RES_2ZW]
    cog = p[_P_COG]
    ncog = p[_P_NCOG]
    mfric_on = p[_P_MFRIC_ON] != 0.0
    mcoul = p[_P_MCOUL]
    gfrac = p[_P_GFRAC]
    drive_on = p[_P_DRIVE_ON] != 0.0
    doff = p[_P_DOFF]
    droop = p[_P_DROOP]
    rr = p[_P_RR]
    nrr = p[_P_NRR]
    kvar = p[_P_KVAR]
    cvar = p[_P_CVAR]

    thm = x[_X_THM]
    wm = x[_X_WM]
    thl = x[_X_THL]
    wl = x[_X_WL]
    xi = x[_X_XI]
    q = x[_X_Q]
    qd = x[_X_QD]
    ridx = int(x[_X_RIDX])
    tau = x[_X_TAU]  # the last sub-step's torque: the droop acts on it
    for _ in range(nsub):
        # Drive: speed from the count difference over the window, then I-P with clamping.
        count = math.floor(thm * cpr / _TWO_PI)
        meas = (count - x[_X_RING + ridx]) * count_to_speed
        x[_X_RING + ridx] = count
        ridx += 1
        if ridx == nwin:
            ridx = 0
        if drive_on:  # offset and droop: the speed the drive regulates to moves
            err = ref + doff - droop * tau - meas
        else:
            err = ref - meas
        xi_new = xi + err * dt
        tau = ki * xi_new - kp * meas
        if tau > tlim:
            tau = tlim
            if err > 0.0:
                xi_new = xi
        elif tau < -tlim:
            tau = -tlim
            if err < 0.0:
                xi_new = xi
        xi = xi_new

        # Belt: stretch through the backlash dead zone; a slack belt cannot pull.
        thp = thm / n
        wp = wm / n
        if rr != 0.0:  # transmission-ratio ripple: a kinematic error periodic in the angle
            arr = nrr * thp
            thp += rr / nrr * math.sin(arr)
            wp *= 1.0 + rr * math.cos(arr)
        zthp = z * thp
        stretch = thp + te * math.sin(zthp) - thl
        stretch_rate = wp * (1.0 + te * z * math.cos(zthp)) - wl
        kb = k
        cb = c
        if kvar != 0.0 or cvar != 0.0:  # span and tension change with the turntable's angle
            cos_l = math.cos(thl)
            kb = k * (1.0 + kvar * cos_l)
            cb = c * (1.0 + cvar * cos_l)
        tb = 0.0
        if stretch > half:
            tb = max(0.0, kb * (stretch - half) + cb * stretch_rate)
        elif stretch < -half:
            tb = min(0.0, kb * (stretch + half) + cb * stretch_rate)

        t_motor = tau - bm * wm - tb / n
        if cog != 0.0:  # skipped without cogging: the reference model stays bit-identical
            t_motor -= cog * math.sin(ncog * thm)
        if mfric_on:  # motor and gearbox friction, at the velocity level like the load's
            fm = mcoul + gfrac * abs(tb) / n
            mom_m = jm * wm + dt * t_motor
            if abs(mom_m) <= dt * fm:
                wm_new = 0.0
            else:
                wm_new = (mom_m - math.copysign(dt * fm, mom_m)) / jm
        else:
            wm_new = wm + dt / jm * t_motor

        # Load (hub): friction at the velocity level; stick when friction can absorb the
        # momentum. An extra mode's payload pulls through its spring; the payload's deflection
        # follows the hub's acceleration (semi-implicit, like the rest).
        t_mode = 0.0
        if jp > 0.0:
            t_mode = jp * (res_w2 * q + res_zw2 * qd)
        mom = jl * wl + dt * (tb + t_ext + t_mode + rip * math.sin(z * thl))
        r2 = (wl / ws) ** 2
        fmax = fc + dfs * math.exp(-r2) if r2 < 50.0 else fc
        if abs(mom) <= dt * fmax:
            wl_new = 0.0
        else:
            wl_new = (mom - math.copysign(dt * fmax, mom)) / (jl + dt * bl)
        if jp > 0.0:
            qd -= dt * t_mode / jp + (wl_new - wl)
            q += dt * qd

        wm = wm_new
        wl = wl_new
        thm += dt * wm
        thl += dt * wl

    x[_X_THM] = thm
    x[_X_WM] = wm
    x[_X_THL] = thl
    x[_X_WL] = wl
    x[_X_XI] = xi
    x[_X_Q] = q
    x[_X_QD] = qd
    x[_X_TAU] = tau
    x[_X_RIDX] = ridx
    pos = _measure_deg(x, p, noise_deg)
    rate = (pos - x[_X_POSM]) * p[_P_RATE]
    x[_X_POSM] = pos
    return pos, rate


class SimRig:
    """The simulated rig. Per tick: `pos, w = rig.read(); u = controller(...); rig.step(u)`."""

    __slots__ = (
        "_disturbance",
        "_faults",
        "_noise",
        "_noise_i",
        "_p",
        "_params",
        "_period_s",
        "_pos",
        "_rate",
        "_rng",
        "_seed",
        "_tick",
        "_x",
    )

    def __init__(
        self,
        params: RigParams = RigParams(),
        *,
        rate_hz: float = 1000.0,
        substeps: int = 10,
        seed: int = 0,
        disturbance: Disturbance | None = None,
        initial_position_deg: float = 0.0,
    ) -> None:
        if not isinstance(params, RigParams):
            raise ConfigError("params", f"must be RigParams, got {type(params).__name__}")
        positive(rate_hz, "rate_hz")
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise ConfigError("substeps", f"must be an int >= 1, got {substeps!r}")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError("seed", f"must be an int >= 0, got {seed!r}")
        number(initial_position_deg, "initial_position_deg")
        self._params = params
        self._p, nwin = _param_array(params, rate_hz, substeps)
        self._x = np.zeros(_X_RING + nwin + params.command_delay_ticks)
        self._faults = _NO_FAULTS
        self._period_s = 1.0 / rate_hz
        self._seed = seed
        self._disturbance: Disturbance | None = None
        self.set_disturbance(disturbance)
        self._rng = np.random.default_rng(seed)
        self._noise: list[float] = []
        self._noise_i = 0
        self._tick = 0
        self._pos = 0.0
        self._rate = 0.0
        self.reset(initial_position_deg)
        # The step's kernel is compiled (loaded from numba's cache) here, off the loop: on the
        # first `step` it was the controller's first tick (4.5 ms CPU, 13-34 ms at load 22: as
        # many missed ticks). A scratch copy of the state: nothing of this rig moves.
        advance_tick(self._x.copy(), self._p.copy(), 0.0, 0.0, 0.0)

    def reset(self, position_deg: float = 0.0) -> None:
        """Load at rest at `position_deg`, belt relaxed, drive idle; restart time and noise."""
        number(position_deg, "position_deg")
        self._rng = np.random.default_rng(self._seed)
        self._refill_noise()
        self._pos = float(_reset_kernel(self._x, self._p, position_deg, self._next_noise()))
        self._rate = 0.0
        self._tick = 0

    def read(self) -> tuple[float, float]:
        """(load position deg as the encoder reports it, backward-difference rate deg/s)."""
        return self._pos, self._rate

    def step(self, command_deg_s: float) -> None:
        """Hold the load-side speed command for one control period and advance."""
        d = self._disturbance
        torque = 0.0 if d is None else d.torque_n_m(self._tick * self._period_s)
        i = self._noise_i
        if i == _NOISE_BLOCK:
            self._refill_noise()
            i = 0
        self._noise_i = i + 1
        self._pos, self._rate = advance_tick(
            self._x, self._p, command_deg_s, torque, self._noise[i]
        )
        self._tick += 1

    # -- for the compiled offline loop (`controller.sim.offline`), which steps the kernel itself

    @property
    def tick(self) -> int:
        """Steps since the last reset (the load torque is sampled at tick x period_s)."""
        return self._tick

    @property
    def disturbance(self) -> Disturbance | None:
        """The external load-torque profile (None: none)."""
        return self._disturbance

    def torques(self, n: int) -> npt.NDArray[np.float64]:
        """The load torque of the next `n` steps, sampled as `step` samples it."""
        d = self._disturbance
        if d is None:
            return np.zeros(n)
        k0, ts = self._tick, self._period_s
        return np.array([d.torque_n_m(k * ts) for k in range(k0, k0 + n)], dtype=np.float64)

    def take_noise(self, n: int) -> npt.NDArray[np.float64]:
        """The encoder noise of the next `n` steps, consumed from the stream as `n` calls of
        `step` would consume it."""
        out = np.empty(n)
        done = 0
        i = self._noise_i
        while done < n:
            if i == _NOISE_BLOCK:
                self._refill_noise()
                i = 0
            m = min(n - done, _NOISE_BLOCK - i)
            out[done : done + m] = self._noise[i : i + m]
            i += m
            done += m
        self._noise_i = i
        return out

    def advanced(self, n: int, pos_deg: float, rate_deg_s: float) -> None:
        """The kernel was stepped `n` times outside (with `torques(n)` and `take_noise(n)`)
        and read (pos_deg, rate_deg_s) last: the rig's time and reading follow."""
        self._tick += n
        self._pos = pos_deg
        self._rate = rate_deg_s

    def set_disturbance(self, d: Disturbance | None) -> None:
        """Swap the external load-torque profile (None = no disturbance); time is the rig's."""
        if d is not None and not isinstance(d, Disturbance):
            raise ConfigError("disturbance", f"must have torque_n_m(time_s), got {d!r}")
        self._disturbance = None if isinstance(d, NoDisturbance) else d

    # -- runtime faults (take effect at the start of the next step) ---------------------------

    def set_faults(self, faults: RigFaults) -> None:
        """Replace every fault at once (RigFaults() clears them); effective from the next step.

        Staged in the parameter array and taken over by the kernel: safe to call between ticks
        from another thread than the one stepping (one caller at a time)."""
        if not isinstance(faults, RigFaults):
            raise ConfigError("faults", f"must be RigFaults, got {type(faults).__name__}")
        values = _fault_values(self._params, faults, 1.0 / float(self._p[_P_DT]))
        p = self._p
        p[_P_PENDING] = 0.0  # the kernel ignores the block while it is being written
        p[_P_NEW:_P_PENDING] = values
        p[_P_PENDING] = 1.0
        self._faults = faults

    def set_plant_gain(self, plant_gain: float) -> None:
        """Scale the speed reference the drive receives (drive/belt gain fault); 1 = nominal."""
        self.set_faults(replace(self._faults, plant_gain=plant_gain))

    def loosen_belt(self, extra_backlash_deg: float) -> None:
        """Backlash becomes `RigParams.backlash_deg + extra_backlash_deg` (not cumulative)."""
        self.set_faults(replace(self._faults, extra_backlash_deg=extra_backlash_deg))

    def add_resonance(
        self,
        resonance_hz: float,
        resonance_damping: float = 0.02,
        resonance_mass_fraction: float = 0.2,
    ) -> None:
        """Add (or replace) the extra mode: see `RigFaults.resonance_*`."""
        if resonance_hz == 0.0:
            raise ConfigError("resonance_hz", "must be > 0 (clear_faults removes the mode)")
        self.set_faults(
            replace(
                self._faults,
                resonance_hz=resonance_hz,
                resonance_damping=resonance_damping,
                resonance_mass_fraction=resonance_mass_fraction,
            )
        )

    def clear_faults(self) -> None:
        self.set_faults(_NO_FAULTS)

    # -- the plant drifting while it runs (wear, a load added; tests and the demo only) -------

    def set_params(self, params: RigParams) -> None:
        """Change the rig's physical parameters from the next step on, its state kept (a belt
        that loses stiffness, a load added, friction that rises). Call between steps from the
        stepping thread. Refused (ConfigError naming the field) where the state's layout would
        change: the command delay and the drive's speed window. The faults in effect are
        staged again on the new parameters; `set_friction`'s change is replaced by the
        params'."""
        if not isinstance(params, RigParams):
            raise ConfigError("params", f"must be RigParams, got {type(params).__name__}")
        old = self._p
        a, nwin = _param_array(params, float(old[_P_RATE]), int(old[_P_NSUB]))
        if params.command_delay_ticks != self._params.command_delay_ticks:
            raise ConfigError("command_delay_ticks", "cannot change while the rig runs")
        if nwin != int(old[_P_NWIN]):
            raise ConfigError("drive_speed_window_s", "cannot change while the rig runs")
        keep = set(_FAULT_SLOTS) | set(range(_P_NEW, _P_PENDING + 1))
        for i in range(_P_LEN):
            if i not in keep:
                old[i] = a[i]
        self._params = params
        self.set_faults(self._faults)

    def run_commands(self, command_deg_s: npt.NDArray[np.float64]
                     ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Step once per command (no load torque profile, this rig's encoder noise): the
        readings after each step, (position deg, rate deg/s), in one compiled call."""
        u = np.ascontiguousarray(command_deg_s, dtype=np.float64)
        if u.ndim != 1 or not np.all(np.isfinite(u)):
            raise ConfigError("command_deg_s", "one finite command per step")
        n = u.size
        noise = self.take_noise(n)
        pos = np.empty(n)
        rate = np.empty(n)
        _run_commands(self._x, self._p, u, noise, pos, rate)
        if n:
            self.advanced(n, float(pos[-1]), float(rate[-1]))
        return pos, rate

    # -- friction changes (a disturbance: wear, temperature, lubrication) ---------------------

    def set_friction(self, coulomb_torque_n_m: float, static_torque_n_m: float) -> None:
        """Change the load's Coulomb and static friction from the next step on (call between
        steps, from the stepping thread). Survives `reset()`; `params` keeps the original."""
        fc = in_range(coulomb_torque_n_m, "coulomb_torque_n_m", 0.0, 1e3)
        fs = in_range(static_torque_n_m, "static_torque_n_m", 0.0, 1e3)
        if fs < fc:
            raise ConfigError(
                "static_torque_n_m", f"must be >= coulomb_torque_n_m ({fc!r}), got {fs!r}"
            )
        self._p[_P_FC] = fc
        self._p[_P_FS] = fs

    @property
    def friction_n_m(self) -> tuple[float, float]:
        """(Coulomb, static) friction of the load in effect."""
        return float(self._p[_P_FC]), float(self._p[_P_FS])

    @property
    def faults(self) -> RigFaults:
        """The faults set last (the kernel takes them over at the next step)."""
        return self._faults

    @property
    def params(self) -> RigParams:
        return self._params

    @property
    def period_s(self) -> float:
        return self._period_s

    @property
    def time_s(self) -> float:
        """Simulated time since the last reset."""
        return self._tick * self._period_s

    @property
    def true_position_deg(self) -> float:
        """Load angle where the encoder reads it (the payload, with an extra mode), noise- and
        quantisation-free."""
        return float(self._x[_X_THL] + self._x[_X_Q]) / _DEG

    @property
    def true_speed_deg_s(self) -> float:
        """Load speed where the encoder reads it, noise-free."""
        return float(self._x[_X_WL] + self._x[_X_QD]) / _DEG

    @property
    def motor_speed_deg_s(self) -> float:
        """Motor shaft speed, MOTOR side (divide by the gear ratio for load side)."""
        return float(self._x[_X_WM]) / _DEG

    @property
    def drive_torque_n_m(self) -> float:
        """Drive output torque in the last sub-step, motor side."""
        return float(self._x[_X_TAU])

    def _refill_noise(self) -> None:
        std = self._params.position_noise_deg
        self._noise = (self._rng.standard_normal(_NOISE_BLOCK) * std).tolist()
        self._noise_i = 0

    def _next_noise(self) -> float:
        i = self._noise_i
        if i == _NOISE_BLOCK:
            self._refill_noise()
            i = 0
        self._noise_i = i + 1
        return self._noise[i]
