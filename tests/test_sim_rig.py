"""The simulated rig against independent references: the article's M(s)P(s), a linearisation
built here with python-control, and static belt mechanics."""

from __future__ import annotations

import dataclasses
import math

import control as ct
import numpy as np
import pytest
from old_loop import OLD_LOOP

from controller.core.errors import ConfigError
from controller.core.trajectory import default_trajectory
from controller.sim.disturbance import (
    DISTURBANCES,
    NoDisturbance,
    SineTorque,
    StepTorque,
    disturbance_from_name,
)
from controller.sim.experiment import run_experiment
from controller.sim.sim_rig import RigFaults, RigParams, SimRig

# control.md eqs. (33) and (34): the article's identified models, speed command -> load rate.
M_ARTICLE = ct.tf([1.0], [1.013e-05, 0.004501, 1.0])
P_ARTICLE = ct.tf([1.013e-05, 0.004501, 1.0], [0.0005169, 0.03215, 1.0])


def _run(rig: SimRig, commands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed loop in the caller's pattern; the read before each step is what a controller sees."""
    pos = np.empty(len(commands))
    rate = np.empty(len(commands))
    for k, u in enumerate(commands):
        pos[k], rate[k] = rig.read()
        rig.step(float(u))
    return pos, rate


def _phasor(signal: np.ndarray, freq_hz: float, period_s: float) -> complex:
    t = np.arange(len(signal)) * period_s
    return complex(np.sum(signal * np.exp(-2j * math.pi * freq_hz * t)))


def _sine_response(freq_hz: float, offset_deg_s: float, amp_deg_s: float) -> complex:
    """u -> w of the full (noisy, quantised, nonlinear) rig around a one-way speed offset."""
    rig = SimRig()
    period = rig.period_s
    settle = round(2.0 / period)
    n_periods = max(1, math.ceil(10.0 * freq_hz))  # >= 10 s: averages tooth ripple and noise
    window = round(n_periods / freq_hz / period)
    k = np.arange(settle + window)
    u = offset_deg_s + amp_deg_s * np.sin(2 * math.pi * freq_hz * k * period)
    _, w = _run(rig, u)
    return _phasor(w[settle:], freq_hz, period) / _phasor(u[settle:], freq_hz, period)


def test_small_signal_response_matches_article_mp() -> None:
    # Full model: noise, both encoders' quantisation, backlash, friction and tooth ripple are ON.
    # 20 +- 2 deg/s keeps the load moving one way, so friction is a constant and the belt stays
    # on one side of the backlash. The measured phase includes ~1 tick of sampling delay
    # (held command + backward-difference rate): -1.8 deg at 5 Hz.
    print("\n  f Hz   |MP| dB  err dB  err deg")
    for f in (0.2, 0.5, 1.0, 2.0, 3.0, 5.0):
        g = _sine_response(f, offset_deg_s=20.0, amp_deg_s=2.0)
        ref = complex(np.squeeze((M_ARTICLE * P_ARTICLE)(2j * math.pi * f)))
        err_db = 20 * math.log10(abs(g) / abs(ref))
        err_deg = math.degrees(np.angle(g / ref))
        print(f"  {f:4.1f}  {20 * math.log10(abs(ref)):7.2f}  {err_db:6.3f}  {err_deg:7.2f}")
        assert abs(err_db) < 1.0, f"{f} Hz: {err_db:.2f} dB off M(s)P(s)"
        assert abs(err_deg) < 4.0, f"{f} Hz: {err_deg:.2f} deg off M(s)P(s)"


def test_mp_product_is_the_stated_second_order() -> None:
    # Guards the reference itself: M P = 1935 / (s^2 + 62.2 s + 1935) per control.md.
    mp = ct.minreal(M_ARTICLE * P_ARTICLE, verbose=False)
    wn, zeta, _ = ct.damp(mp, doprint=False)
    assert wn[0] ** 2 == pytest.approx(1935, rel=2e-3)
    assert zeta[0] == pytest.approx(0.707, abs=2e-3)


def test_same_seed_same_run_different_seed_differs() -> None:
    u = 5.0 * np.sin(np.arange(1500) * 1e-3 * 2 * math.pi)
    a = _run(SimRig(seed=3), u)
    b = _run(SimRig(seed=3), u)
    c = _run(SimRig(seed=4), u)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])
    rig = SimRig(seed=3)
    _run(rig, u)
    rig.reset()
    again = _run(rig, u)
    np.testing.assert_array_equal(a[1], again[1])


@pytest.mark.parametrize("start_deg", [0.0, 1.5, -40.0])
def test_zero_command_from_rest_stays_put(start_deg: float) -> None:
    # Bias (0.10) + ripple (0.05) < stiction (0.35): the load must not creep or chatter.
    rig = SimRig(initial_position_deg=start_deg)
    pos, rate = _run(rig, np.zeros(2000))
    assert rig.true_position_deg == pytest.approx(start_deg, abs=1e-9)
    assert rig.true_speed_deg_s == 0.0
    lsb = 360.0 / 2**26
    assert np.all(np.abs(pos - start_deg) < 1e-5 * 6 + lsb)  # noise (std 1e-5) + quantum
    assert np.std(rate) < 0.03  # backward difference of that noise: ~0.014 deg/s


def test_stop_after_motion_sticks_without_chatter() -> None:
    rig = SimRig()
    u = np.concatenate([np.full(1000, 5.0), np.full(1000, -5.0), np.zeros(1500)])
    _run(rig, u)
    held = rig.true_position_deg
    speeds = []
    for _ in range(500):
        rig.step(0.0)
        speeds.append(rig.true_speed_deg_s)
    assert speeds == [0.0] * 500
    assert rig.true_position_deg == held


@pytest.mark.parametrize("command_deg_s", [20.0, -10.0, 1.0])
def test_dc_gain_is_one(command_deg_s: float) -> None:
    rig = SimRig()
    tooth_period_s = 360.0 / 30 / abs(command_deg_s)  # ripple and transmission error period
    settle = 2000
    window = round(math.ceil(6.0 / tooth_period_s) * tooth_period_s * 1000)  # whole periods
    _, w = _run(rig, np.full(settle + window, command_deg_s))
    assert np.mean(w[settle:]) == pytest.approx(command_deg_s, rel=5e-3)
    assert rig.motor_speed_deg_s / 132.0 == pytest.approx(command_deg_s, rel=0.05)


def test_step_torque_deflects_belt_by_its_compliance() -> None:
    # Moving at 10 deg/s, the drive holds the motor trajectory; a constant load torque only
    # re-stretches the belt: the load advances by T / k relative to an undisturbed run.
    p = RigParams()
    u = np.full(4000, 10.0)
    _run(quiet := SimRig(p), u)
    _run(pushed := SimRig(p, disturbance=StepTorque(amplitude_n_m=0.5, time_s=1.0)), u)
    shift_deg = pushed.true_position_deg - quiet.true_position_deg
    assert shift_deg == pytest.approx(math.degrees(0.5 / p.belt_stiffness_n_m_rad), rel=0.03)


def _linear_torque_to_load_angle(p: RigParams) -> ct.StateSpace:
    """Continuous linearisation (ideal drive measurement, no backlash): torque -> load angle."""
    n, jm, jl = p.gear_ratio, p.motor_inertia_kg_m2, p.load_inertia_kg_m2
    k, c = p.belt_stiffness_n_m_rad, p.belt_damping_n_m_s_rad
    kp, ki = p.drive_kp_n_m_s_rad, p.drive_ki_n_m_rad
    # States: motor angle, motor rate, load angle, load rate, drive integrator (speed ref = 0).
    a = np.zeros((5, 5))
    a[0, 1] = 1.0
    a[1, :] = [
        -k / n**2 / jm,
        (-kp - p.motor_viscous_n_m_s_rad - c / n**2) / jm,
        k / n / jm,
        c / n / jm,
        ki / jm,
    ]
    a[2, 3] = 1.0
    a[3, :] = [k / n / jl, c / n / jl, -k / jl, -(c + p.load_viscous_n_m_s_rad) / jl, 0.0]
    a[4, 1] = -1.0
    b = np.array([[0.0], [0.0], [0.0], [1.0 / jl], [0.0]])
    return ct.ss(a, b, np.array([[0.0, 0.0, 180.0 / math.pi, 0.0, 0.0]]), 0.0)


@pytest.mark.parametrize("freq_hz", [0.05, 0.5, 2.0])
def test_sine_torque_moves_load_as_linear_model_predicts(freq_hz: float) -> None:
    p = RigParams()
    amp = 1.0
    settle = 2000
    window = round(max(1, math.ceil(10 * freq_hz)) / freq_hz * 1000)
    u = np.full(settle + window, 20.0)
    pos0, _ = _run(SimRig(p), u)
    pos1, _ = _run(SimRig(p, disturbance=SineTorque(amplitude_n_m=amp, freq_hz=freq_hz)), u)
    dpos = (pos1 - pos0)[settle:]
    torque = amp * np.sin(2 * math.pi * freq_hz * np.arange(settle + window) * 1e-3)[settle:]
    g = _phasor(dpos, freq_hz, 1e-3) / _phasor(torque, freq_hz, 1e-3)
    ref = complex(np.squeeze(_linear_torque_to_load_angle(p)(2j * math.pi * freq_hz)))
    print(f"\n  {freq_hz} Hz: |dpos/T| {abs(g):.4f} deg/N m, linear {abs(ref):.4f}")
    assert abs(g) == pytest.approx(abs(ref), rel=0.05)
    assert math.degrees(abs(np.angle(g / ref))) < 5.0


def test_disturbance_registry_and_validation() -> None:
    assert set(DISTURBANCES) >= {"none", "sine-0.05hz", "step"}
    assert isinstance(disturbance_from_name("none"), NoDisturbance)
    sine = disturbance_from_name("sine-0.05hz")
    assert isinstance(sine, SineTorque) and sine.freq_hz == 0.05
    assert sine.torque_n_m(5.0) == pytest.approx(sine.amplitude_n_m)  # quarter period
    with pytest.raises(ValueError, match=r"disturbance.*'bogus'.*none.*sine-0\.05hz.*step"):
        disturbance_from_name("bogus")
    with pytest.raises(ValueError, match="freq_hz"):
        SineTorque(amplitude_n_m=1.0, freq_hz=0.0)
    with pytest.raises(ValueError, match="amplitude_n_m"):
        SineTorque(amplitude_n_m=math.nan, freq_hz=1.0)
    with pytest.raises(ValueError, match="time_s"):
        StepTorque(amplitude_n_m=1.0, time_s=-1.0)
    with pytest.raises(ValueError, match="amplitude_n_m"):
        StepTorque(amplitude_n_m=math.inf, time_s=1.0)
    with pytest.raises(ValueError, match="disturbance"):
        SimRig(disturbance="step")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("gear_ratio", 0.0),
        ("motor_inertia_kg_m2", -1e-5),
        ("load_inertia_kg_m2", math.nan),
        ("belt_stiffness_n_m_rad", math.inf),
        ("backlash_deg", -0.01),
        ("coulomb_torque_n_m", -0.1),
        ("static_torque_n_m", 0.1),  # below Coulomb
        ("pulley_teeth", 2.5),
        ("load_encoder_bits", 0),
        ("position_noise_deg", -1e-6),
        ("drive_speed_window_s", 0.0),
    ],
)
def test_param_validation_names_the_field(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        RigParams(**{field: value})  # type: ignore[arg-type]


def test_every_param_is_checked() -> None:
    """Each field declares its check (a new one without would take NaN silently)."""
    for f in dataclasses.fields(RigParams):
        with pytest.raises(ConfigError, match=rf"^{f.name}: must be finite, got nan$"):
            RigParams(**{f.name: math.nan})  # type: ignore[arg-type]


def test_rig_argument_validation() -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        SimRig(rate_hz=0.0)
    with pytest.raises(ValueError, match="substeps"):
        SimRig(substeps=0)
    with pytest.raises(ValueError, match="seed"):
        SimRig(seed=-1)
    with pytest.raises(ValueError, match="initial_position_deg"):
        SimRig(initial_position_deg=math.nan)
    rig = SimRig()
    with pytest.raises(ValueError, match="position_deg"):
        rig.reset(math.inf)
    with pytest.raises(ValueError, match="command_deg_s"):
        rig.step(math.nan)


def test_interface_bookkeeping() -> None:
    rig = SimRig(RigParams(position_noise_deg=0.0), initial_position_deg=12.0)
    assert rig.read() == (pytest.approx(12.0, abs=1e-5), 0.0)
    for _ in range(250):
        rig.step(4.0)
    assert rig.time_s == pytest.approx(0.25)
    assert rig.true_speed_deg_s == pytest.approx(4.0, rel=0.2)
    assert rig.motor_speed_deg_s == pytest.approx(4.0 * 132, rel=0.2)
    rig.set_disturbance(SineTorque(amplitude_n_m=1.0, freq_hz=1.0))
    rig.reset(-3.0)
    assert rig.time_s == 0.0
    assert rig.true_position_deg == pytest.approx(-3.0)
    assert rig.true_speed_deg_s == 0.0


def test_substeps_converged_and_rate_configurable() -> None:
    # Halving the integration step must not change the 2 Hz response: 10 kHz is converged.
    def response(**kwargs: int | float) -> complex:
        rig = SimRig(RigParams(position_noise_deg=0.0), **kwargs)  # type: ignore[arg-type]
        period = rig.period_s
        n = round(4.0 / period)
        u = 20.0 + 2.0 * np.sin(2 * math.pi * 2.0 * np.arange(n) * period)
        _, w = _run(rig, u)
        half = n // 2
        return _phasor(w[half:], 2.0, period) / _phasor(u[half:], 2.0, period)

    base = response()
    fine = response(substeps=20)
    assert abs(fine / base - 1) < 0.01
    slow_loop = response(rate_hz=500.0)  # 2 ms ticks: only the sampling delay changes
    assert abs(abs(slow_loop) / abs(base) - 1) < 0.01
    extra_delay_deg = -math.degrees(np.angle(slow_loop / base))
    assert extra_delay_deg == pytest.approx(360 * 2.0 * 1e-3, abs=0.5)  # one more ms of delay


def test_position_is_quantised_to_26_bits() -> None:
    rig = SimRig(RigParams(position_noise_deg=0.0))
    pos, _ = _run(rig, np.full(300, 7.0))
    lsb = 360.0 / 2**26
    counts = pos / lsb
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-6)
    assert abs(rig.read()[0] - rig.true_position_deg) <= lsb / 2 + 1e-12


# -- runtime fault injection ------------------------------------------------------------------


def _faulted_sine_response(
    freq_hz: float, faults: RigFaults, offset_deg_s: float = 20.0
) -> complex:
    """u -> w of the rig with `faults` set before the run, as `_sine_response` measures it."""
    rig = SimRig()
    rig.set_faults(faults)
    period = rig.period_s
    settle = round(2.0 / period)
    window = round(max(1, math.ceil(5.0 * freq_hz)) / freq_hz / period)
    k = np.arange(settle + window)
    u = offset_deg_s + 2.0 * np.sin(2 * math.pi * freq_hz * k * period)
    _, w = _run(rig, u)
    return _phasor(w[settle:], freq_hz, period) / _phasor(u[settle:], freq_hz, period)


@pytest.mark.parametrize("gain", [2.0, 0.5])
def test_plant_gain_fault_scales_the_low_frequency_response(gain: float) -> None:
    nominal = _faulted_sine_response(0.2, RigFaults(), offset_deg_s=10.0)
    faulted = _faulted_sine_response(0.2, RigFaults(plant_gain=gain), offset_deg_s=10.0)
    assert abs(faulted / nominal) == pytest.approx(gain, rel=0.02)
    assert abs(math.degrees(np.angle(faulted / nominal))) < 2.0


def test_plant_gain_fault_while_running_and_cleared() -> None:
    rig = SimRig()
    _run(rig, np.full(1500, 10.0))
    rig.set_plant_gain(2.0)
    assert rig.faults == RigFaults(plant_gain=2.0)
    _run(rig, np.full(1500, 10.0))
    assert rig.true_speed_deg_s == pytest.approx(20.0, rel=0.05)
    rig.clear_faults()
    assert not rig.faults.active
    _run(rig, np.full(1500, 10.0))
    assert rig.true_speed_deg_s == pytest.approx(10.0, rel=0.05)


def _reversal_play_deg(rig: SimRig) -> float:
    """The motor reaches the same angle twice, moving down then moving up (5 deg/s legs of 1 s):
    the load ends apart by the backlash plus the belt's friction deflection, both ways."""
    leg = np.full(1000, 5.0)
    rest = np.zeros(500)
    _run(rig, np.concatenate([leg, -leg, rest]))
    down = rig.true_position_deg
    _run(rig, np.concatenate([-leg, leg, rest]))
    return down - rig.true_position_deg


def test_loosened_belt_adds_its_backlash_to_the_play_at_reversal() -> None:
    nominal = _reversal_play_deg(SimRig())
    loose = SimRig()
    loose.loosen_belt(0.3)
    assert loose.faults.extra_backlash_deg == 0.3
    assert _reversal_play_deg(loose) - nominal == pytest.approx(0.3, rel=0.03)


def test_loosened_belt_raises_the_closed_loop_reversal_error() -> None:
    # The article's sine: its error peaks at the reversals; 0.3 deg more play makes them worse
    # (the 2x was measured on the earlier default loop, Cv = 0.5 (1 + 55/s)).
    cfg = OLD_LOOP
    traj = default_trajectory("sine")
    nominal = run_experiment(cfg, traj, 12.0)
    rig = SimRig()
    rig.loosen_belt(0.3)
    loose = run_experiment(cfg, traj, 12.0, rig=rig)
    assert loose.peak_error_deg > 2.0 * nominal.peak_error_deg
    t_peak = loose.t_s[np.argmax(np.abs(loose.error_deg) * (loose.t_s >= 2.0))]
    print(
        f"\n  peak |e| {nominal.peak_error_deg:.3f} -> {loose.peak_error_deg:.3f} deg, {t_peak} s"
    )
    # 5 sin(0.5 t): reversals at t = pi, 3 pi; the error peaks while the play is taken up.
    since = t_peak - np.array([math.pi, 3 * math.pi])
    assert np.any((since > 0.0) & (since < 1.0))


def _linear_with_mode(p: RigParams, f: RigFaults) -> ct.StateSpace:
    """`_linear_torque_to_load_angle` with a payload on a spring: torque on the hub -> angle of
    the payload (where the encoder reads)."""
    base = _linear_torque_to_load_angle(p)
    jp = f.resonance_mass_fraction * p.load_inertia_kg_m2
    jh = p.load_inertia_kg_m2 - jp
    wr = 2 * math.pi * f.resonance_hz
    kr, cr = jp * wr**2, 2 * f.resonance_damping * wr * jp
    a = np.zeros((7, 7))
    a[:5, :5] = base.A
    a[3, :] *= p.load_inertia_kg_m2 / jh  # the hub alone takes the belt's torque
    a[3, 5:] = [kr / jh, cr / jh]  # the spring pulls the hub
    a[5, 6] = 1.0
    a[6, :] = -a[3, :]  # relative deflection: minus the hub's acceleration...
    a[6, 5:] -= [kr / jp, cr / jp]  # ...minus the spring's pull on the payload
    b = np.zeros((7, 1))
    b[3, 0] = 1.0 / jh
    b[6, 0] = -1.0 / jh
    c = np.zeros((1, 7))
    c[0, 2] = c[0, 5] = 180.0 / math.pi
    return ct.ss(a, b, c, 0.0)


@pytest.mark.parametrize("freq_hz", [5.0, 15.0, 17.0])
def test_added_resonance_moves_load_as_linear_model_predicts(freq_hz: float) -> None:
    p = RigParams()
    faults = RigFaults(resonance_hz=15.0, resonance_damping=0.05, resonance_mass_fraction=0.2)
    settle = 2000
    window = round(max(1, math.ceil(5 * freq_hz)) / freq_hz * 1000)
    u = np.full(settle + window, 20.0)
    runs = []
    for d in (None, SineTorque(amplitude_n_m=0.2, freq_hz=freq_hz)):
        rig = SimRig(p, disturbance=d)
        rig.set_faults(faults)
        runs.append(_run(rig, u)[0])
    dpos = (runs[1] - runs[0])[settle:]
    torque = 0.2 * np.sin(2 * math.pi * freq_hz * np.arange(settle + window) * 1e-3)[settle:]
    g = _phasor(dpos, freq_hz, 1e-3) / _phasor(torque, freq_hz, 1e-3)
    ref = complex(np.squeeze(_linear_with_mode(p, faults)(2j * math.pi * freq_hz)))
    plain = complex(np.squeeze(_linear_torque_to_load_angle(p)(2j * math.pi * freq_hz)))
    print(f"\n  {freq_hz} Hz: |dpos/T| {abs(g):.5f} linear {abs(ref):.5f} no mode {abs(plain):.5f}")
    assert abs(g) == pytest.approx(abs(ref), rel=0.05)
    assert math.degrees(abs(np.angle(g / ref))) < 5.0


def test_added_resonance_shows_in_the_speed_response() -> None:
    # Payload of 20 % at 15 Hz against a clamped hub: with the hub free the pair resonates near
    # 15 / sqrt(0.8) = 16.8 Hz; the encoder reads the payload, so the phase falls through it.
    faults = RigFaults(resonance_hz=15.0, resonance_damping=0.05, resonance_mass_fraction=0.2)
    low = _faulted_sine_response(0.5, faults) / _faulted_sine_response(0.5, RigFaults())
    assert abs(low) == pytest.approx(1.0, abs=0.02)
    peak = _faulted_sine_response(16.0, faults) / _faulted_sine_response(16.0, RigFaults())
    assert abs(peak) > 3.0
    assert -110.0 < math.degrees(np.angle(peak)) < -50.0


def test_adding_and_removing_the_mode_keeps_the_motion() -> None:
    rig = SimRig(RigParams(position_noise_deg=0.0))
    _run(rig, np.full(1000, 10.0))
    before = rig.true_speed_deg_s
    rig.add_resonance(20.0, resonance_damping=0.1)
    rig.step(10.0)
    assert rig.true_speed_deg_s == pytest.approx(before, rel=0.02)
    _run(rig, np.full(500, 10.0))
    pos, speed = rig.true_position_deg, rig.true_speed_deg_s
    rig.clear_faults()
    rig.step(10.0)
    assert rig.true_position_deg == pytest.approx(pos + 1e-3 * speed, abs=2e-3)
    assert rig.true_speed_deg_s == pytest.approx(speed, rel=0.05)
    assert rig.faults == RigFaults()


def test_faults_survive_reset() -> None:
    rig = SimRig()
    rig.set_faults(RigFaults(plant_gain=2.0, extra_backlash_deg=0.1, resonance_hz=30.0))
    rig.reset(5.0)
    assert rig.faults.plant_gain == 2.0
    _run(rig, np.full(2000, 5.0))
    assert rig.true_speed_deg_s == pytest.approx(10.0, rel=0.1)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("plant_gain", -0.1),
        ("plant_gain", math.nan),
        ("plant_gain", 1e3),
        ("extra_backlash_deg", -0.01),
        ("extra_backlash_deg", math.inf),
        ("resonance_hz", -1.0),
        ("resonance_damping", 0.0),
        ("resonance_mass_fraction", 0.95),
        ("resonance_mass_fraction", "0.1"),
    ],
)
def test_fault_validation_names_the_field(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        RigFaults(**{field: value})  # type: ignore[arg-type]


def test_fault_methods_validate() -> None:
    rig = SimRig()
    with pytest.raises(ValueError, match=r"resonance_hz.*600"):
        rig.add_resonance(600.0)  # 10 kHz integration: modes up to 500 Hz
    with pytest.raises(ValueError, match="resonance_hz"):
        rig.add_resonance(0.0)
    with pytest.raises(ValueError, match="plant_gain"):
        rig.set_plant_gain(-1.0)
    with pytest.raises(ValueError, match="extra_backlash_deg"):
        rig.loosen_belt(-0.5)
    with pytest.raises(ValueError, match="faults"):
        rig.set_faults({"plant_gain": 2.0})  # type: ignore[arg-type]
    assert rig.faults == RigFaults()  # nothing half-applied
