"""The rig's rate disturbances at P's input, its position-dependent belt and its encoder
errors, each against a closed form or a linear model built here (not the rig's own code)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.core.errors import ConfigError
from controller.sim.disturbance import StepTorque
from controller.sim.rig_disturbances import RIG_DISTURBANCES, rig_setup
from controller.sim.sim_rig import RigParams, SimRig

RPM_TO_LOAD_DEG_S = 360.0 / 60.0 / 132.0


def _run(rig: SimRig, commands: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pos = np.empty(len(commands))
    rate = np.empty(len(commands))
    torque = np.empty(len(commands))
    for k, u in enumerate(commands):
        pos[k], rate[k] = rig.read()
        rig.step(float(u))
        torque[k] = rig.drive_torque_n_m
    return pos, rate, torque


def _whole_tooth_window(speed_deg_s: float, seconds: float) -> int:
    """Samples in a whole number of tooth periods (30/rev) of at least `seconds`."""
    period_s = 360.0 / 30 / abs(speed_deg_s)
    return round(math.ceil(seconds / period_s) * period_s * 1000)


def test_drive_offset_turns_the_load_when_commanded_zero() -> None:
    # The drive integrates its speed error: at zero command the motor settles at the offset.
    rig = SimRig(RigParams(drive_offset_rpm=20.0))
    settle, window = 3000, _whole_tooth_window(20.0 * RPM_TO_LOAD_DEG_S, 4.0)
    _, w, _ = _run(rig, np.zeros(settle + window))
    assert np.mean(w[settle:]) == pytest.approx(20.0 * RPM_TO_LOAD_DEG_S, rel=0.01)


@pytest.mark.parametrize("command_deg_s", [10.0, -10.0])
def test_drive_droop_lowers_the_speed_by_droop_times_torque(command_deg_s: float) -> None:
    droop = 2000.0  # rpm per N m
    settle, window = 2000, _whole_tooth_window(command_deg_s, 6.0)
    u = np.full(settle + window, command_deg_s)
    _, w, tau = _run(SimRig(RigParams(drive_droop_rpm_per_n_m=droop)), u)
    expected = command_deg_s - droop * np.mean(tau[settle:]) * RPM_TO_LOAD_DEG_S
    assert abs(np.mean(tau[settle:])) > 1e-3  # the load's friction needs torque
    assert np.mean(w[settle:]) == pytest.approx(expected, rel=2e-3)
    assert abs(np.mean(w[settle:]) - command_deg_s) > 0.05  # the droop is visible


def test_motor_and_gearbox_friction_add_their_torque_to_the_drive() -> None:
    # At constant speed the drive's integral supplies every torque; the belt carries the load's
    # viscous + Coulomb friction minus the bias torque. Motor side: tau = tb/N (1 + f) + Fm.
    p0 = RigParams()
    p1 = RigParams(motor_coulomb_n_m=0.004, gearbox_friction_fraction=0.25)
    speed = 10.0
    settle, window = 2000, _whole_tooth_window(speed, 6.0)
    u = np.full(settle + window, speed)
    _, _, tau0 = _run(SimRig(p0), u)
    _, w1, tau1 = _run(SimRig(p1), u)
    tb = p0.load_viscous_n_m_s_rad * math.radians(speed) + p0.coulomb_torque_n_m
    tb -= p0.bias_torque_n_m
    extra = 0.004 + 0.25 * tb / 132.0
    assert np.mean(tau1[settle:]) - np.mean(tau0[settle:]) == pytest.approx(extra, rel=0.02)
    assert np.mean(w1[settle:]) == pytest.approx(speed, rel=5e-3)  # the drive still holds it


def test_motor_friction_makes_the_motor_stick_at_a_reversal() -> None:
    # The drive must build up the friction torque before the motor turns back: a dead time.
    u = np.concatenate([np.full(500, 2.0), np.full(500, -2.0)])
    stuck = []
    for p in (RigParams(), RigParams(motor_coulomb_n_m=0.02)):
        rig = SimRig(p)
        n = 0
        for v in u:
            rig.step(float(v))
            n += rig.motor_speed_deg_s == 0.0
        stuck.append(n)
    assert stuck[0] == 0 and stuck[1] >= 1


def test_gearbox_backlash_is_in_series_with_the_belt() -> None:
    u = np.concatenate([np.full(800, 3.0), np.full(800, -3.0), np.zeros(400)])
    a, _, _ = _run(SimRig(RigParams(gearbox_backlash_deg=0.3, position_noise_deg=0.0)), u)
    b, _, _ = _run(SimRig(RigParams(backlash_deg=0.32, position_noise_deg=0.0)), u)
    assert np.max(np.abs(a - b)) < 1e-6
    c, _, _ = _run(SimRig(RigParams(position_noise_deg=0.0)), u)
    assert np.max(np.abs(a - c)) > 0.1  # 0.3 deg more play is seen


def test_ratio_ripple_moves_the_load_by_the_kinematic_error() -> None:
    # The pulley angle seen by the belt is theta + (a/n) sin(n theta); the load follows it
    # through the belt, P(s) = (c s + k) / (J s^2 + (c + b) s + k) at the ripple frequency.
    a, n, speed = 0.01, 7, 20.0
    base = RigParams(position_noise_deg=0.0, transmission_error_deg=0.0, ripple_torque_n_m=0.0)
    rip = RigParams(**{**{f: getattr(base, f) for f in base.__dataclass_fields__},
                       "ratio_ripple_fraction": a, "ratio_ripple_periods_per_rev": n})
    f_hz = n * speed / 360.0
    settle = 3000
    window = round(math.ceil(6 * f_hz) / f_hz * 1000)
    u = np.full(settle + window, speed)
    p0, _, _ = _run(SimRig(base), u)
    p1, _, _ = _run(SimRig(rip), u)
    d = (p1 - p0)[settle:]
    t = np.arange(len(u))[settle:] * 1e-3
    motor_angle = np.radians(speed) * t  # the pulley angle (the drive holds the speed)
    drive = math.degrees(a / n) * np.sin(n * motor_angle)
    g = np.sum(d * np.exp(-1j * n * motor_angle)) / np.sum(drive * np.exp(-1j * n * motor_angle))
    s = 2j * math.pi * f_hz
    k, c, j, b = base.belt_stiffness_n_m_rad, base.belt_damping_n_m_s_rad, 0.08, 5.54
    ref = (c * s + k) / (j * s * s + (c + b) * s + k)
    assert abs(g) == pytest.approx(abs(ref), rel=0.03)
    assert math.degrees(abs(np.angle(g / ref))) < 3.0


@pytest.mark.parametrize("angle_deg", [0.0, 90.0, 180.0])
def test_belt_stiffness_varies_with_the_turntable_angle(angle_deg: float) -> None:
    # A load torque re-stretches the belt; near an angle, the varying belt must do what a
    # fixed belt of stiffness k (1 + v cos theta), damping c (1 + w cos theta) does there.
    v, w = 0.2, 0.3
    varying = RigParams(belt_stiffness_variation=v, belt_damping_variation=w)
    speed = 2.0
    start = angle_deg - 5.0  # the torque comes at 1 s, measured at 4 s: theta moves +-3 deg
    u = np.full(4000, speed)
    shifts = []
    for p in (varying, _fixed_belt_at(angle_deg, v, w), RigParams()):
        quiet = SimRig(p, initial_position_deg=start)
        pushed = SimRig(p, initial_position_deg=start,
                        disturbance=StepTorque(amplitude_n_m=0.5, time_s=1.0))
        _run(quiet, u)
        _run(pushed, u)
        shifts.append(pushed.true_position_deg - quiet.true_position_deg)
    assert shifts[0] == pytest.approx(shifts[1], rel=0.02)
    if angle_deg != 90.0:  # there the belt is the nominal one
        assert abs(shifts[0] / shifts[2] - 1.0) > 0.1


def _fixed_belt_at(angle_deg: float, v: float, w: float) -> RigParams:
    p = RigParams()
    cos_a = math.cos(math.radians(angle_deg))
    return RigParams(belt_stiffness_n_m_rad=p.belt_stiffness_n_m_rad * (1.0 + v * cos_a),
                     belt_damping_n_m_s_rad=p.belt_damping_n_m_s_rad * (1.0 + w * cos_a))


def test_encoder_interpolation_error_is_in_the_reading() -> None:
    a, periods = 5e-4, 16384
    lsb = 360.0 / 2**26
    for start in (0.0, 0.003, 12.3456, -7.0001):
        rig = SimRig(RigParams(position_noise_deg=0.0, encoder_cyclic_error_deg=a,
                               encoder_cyclic_periods_per_rev=periods),
                     initial_position_deg=start)
        pos, _ = rig.read()
        expected = start + a * math.sin(periods * math.radians(start))
        assert abs(pos - expected) <= lsb / 2 + 1e-12


def test_named_disturbances_set_what_they_say() -> None:
    parts = ("motor-friction", "gearbox", "drive-offset", "drive-droop", "ratio-ripple",
             "belt-tension", "encoder")
    every: dict[str, float] = {}
    for name in parts:
        setup = rig_setup([name])
        for field, value in RIG_DISTURBANCES[name].params:
            assert getattr(setup.params, field) == value
            every[field] = value
    article = rig_setup(["article-rig"]).params
    for field, value in every.items():
        assert getattr(article, field) == value
    with pytest.raises(ConfigError, match="both set"):
        rig_setup(["article-rig", "gearbox"])


@pytest.mark.parametrize(
    ("field", "value"),
    [("motor_coulomb_n_m", -1.0), ("belt_stiffness_variation", 0.95),
     ("ratio_ripple_periods_per_rev", 0), ("encoder_cyclic_periods_per_rev", 2.5),
     ("drive_offset_rpm", math.nan)],
)
def test_new_params_are_validated(field: str, value: float) -> None:
    with pytest.raises(ConfigError) as exc:
        RigParams(**{field: value})  # type: ignore[arg-type]
    assert exc.value.field == field
