"""The article's experiments (controller/sim/paper*.py and their parts), each piece checked
against an independent computation: python-control, scipy, closed forms."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import control as ct
import numpy as np
import pytest
from old_loop import OLD_LOOP
from scipy import optimize, signal

from controller.cli.experiment import experiment_main
from controller.core.config import LoopConfig, config_to_builtins
from controller.core.discrete import sos_response
from controller.core.errors import ConfigError
from controller.core.qfilter import design_q
from controller.core.trajectory import Trajectory
from controller.sim import rig_disturbances
from controller.sim.disturbance import StepsTorque, SumTorque
from controller.sim.experiment import run_experiment
from controller.sim.linear_rig import LinearRig, PlantVariant
from controller.sim.paper import ARTICLE, VARIANTS_40, speed_step_run
from controller.sim.paper_freq import (
    disturbance_responses,
    sensitivity_curves,
    suppression_curve,
)
from controller.sim.position_dob import PositionDobLoop, q41_tau_s
from controller.sim.rig_disturbances import (
    RIG_DISTURBANCES,
    RigDisturbance,
    ScheduledRig,
    build_rig,
    rig_setup,
)
from controller.sim.sim_rig import RigParams, SimRig

# -- named disturbances on the simulated rig ---------------------------------------------------


def test_named_disturbances_compose() -> None:
    s = rig_setup(["tooth-meshing", "stick-slip", "load-steps", "sine-0.05hz", "none"])
    assert s.names == ("tooth-meshing", "stick-slip", "load-steps", "sine-0.05hz")
    assert s.params.ripple_torque_n_m == 0.5 and s.params.transmission_error_deg == 0.03
    assert s.params.static_torque_n_m == 0.8 and s.params.stribeck_speed_deg_s == 1.0
    assert s.params.coulomb_torque_n_m == RigParams().coulomb_torque_n_m
    assert isinstance(s.torque, SumTorque)
    # 1 N m from the steps plus the 0.05 Hz sine (1 N m) at a quarter period (5 s).
    assert s.torque.torque_n_m(5.0) == pytest.approx(1.0 + 1.0)
    assert rig_setup([]).label == "none" and rig_setup(["none"]).torque is None


def test_unknown_or_conflicting_disturbance_names_the_field(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    with pytest.raises(ConfigError, match=r"disturbance.*earthquake"):
        rig_setup(["earthquake"])
    monkeypatch.setitem(
        rig_disturbances.RIG_DISTURBANCES, "sticky",
        RigDisturbance("sticky", "test", params=(("static_torque_n_m", 0.5),)),
    )
    with pytest.raises(ConfigError, match="static_torque_n_m"):
        rig_setup(["stick-slip", "sticky"])


def test_steps_torque_levels_and_validation() -> None:
    d = StepsTorque(times_s=(1.0, 11.0, 21.0), levels_n_m=(1.0, -1.0, 0.0))
    assert [d.torque_n_m(t) for t in (0.0, 0.999, 1.0, 10.0, 11.0, 25.0)] == [
        0.0, 0.0, 1.0, 1.0, -1.0, 0.0]
    with pytest.raises(ConfigError, match=r"times_s\[1\]"):
        StepsTorque(times_s=(2.0, 1.0), levels_n_m=(1.0, 2.0))


def test_friction_change_happens_at_its_time() -> None:
    s = rig_setup(["friction-change"])
    rig = build_rig(s, rate_hz=1000.0, seed=0, initial_position_deg=0.0)
    assert isinstance(rig, ScheduledRig)
    fc, fs = RigParams().coulomb_torque_n_m, RigParams().static_torque_n_m
    for _ in range(5000):  # ticks 0 .. 4999: t < 5 s
        rig.step(0.0)
    assert rig.rig.friction_n_m == (fc, fs)
    rig.step(0.0)  # the tick at t = 5 s runs with the new friction
    assert rig.rig.friction_n_m == pytest.approx((1.6 * fc, 1.6 * fs))


def test_set_friction_validates() -> None:
    rig = SimRig()
    with pytest.raises(ConfigError, match="static_torque_n_m"):
        rig.set_friction(0.5, 0.4)
    with pytest.raises(ConfigError, match="coulomb_torque_n_m"):
        rig.set_friction(float("nan"), 0.4)


def _motor_speed_amplitude(params: RigParams, freq_hz: float) -> float:
    rig = SimRig(params, seed=0)
    n = 4000
    v = np.empty(n)
    for k in range(n + 2000):
        rig.step(10.0)
        if k >= 2000:
            v[k - 2000] = rig.motor_speed_deg_s
    t = np.arange(n) / 1000.0
    return float(2 * abs(np.mean((v - v.mean()) * np.exp(-2j * np.pi * freq_hz * t))))


def test_cogging_shakes_the_motor_at_its_order() -> None:
    """10 deg/s at the load is 1320 deg/s at the motor: 3.667 rev/s, so 12 cogging periods per
    motor revolution come at 44 Hz. With cogging the motor speed carries that line; without,
    it does not (the kernel skips the term: tests/test_sim_rig.py checks the plain rig)."""
    f = 10.0 * 132.0 / 360.0 * 12.0
    on = _motor_speed_amplitude(RigParams(cogging_torque_n_m=0.005), f)
    off = _motor_speed_amplitude(RigParams(), f)
    print(f"motor speed at {f:.1f} Hz: cogging {on:.3g}, none {off:.3g} deg/s")
    assert on > 20.0 * off
    assert on > 1.0  # deg/s at the motor: clearly there


def test_cogging_params_validate() -> None:
    with pytest.raises(ConfigError, match="cogging_torque_n_m"):
        RigParams(cogging_torque_n_m=-1.0)
    with pytest.raises(ConfigError, match="cogging_periods_per_rev"):
        RigParams(cogging_periods_per_rev=0)
    assert set(RIG_DISTURBANCES) >= {"tooth-meshing", "cogging", "load-steps",
                                      "friction-change", "stick-slip", "big-step"}


# -- the linear rig against python-control -------------------------------------------------------


def test_linear_rig_rate_loop_matches_python_control() -> None:
    """The runtime's rate loop (tick_speed, DOB off) on the linear nominal plant, against the
    discrete closed loop built by python-control: ZOH plant u -> theta, backward-difference
    rate, Tustin PI."""
    cfg = LoopConfig(dob_on=False)
    ts = cfg.period_s
    run = speed_step_run(cfg, PlantVariant("nominal"), 0.4, disturbance_deg_s=0.0)
    nom = cfg.nominal
    g = ct.tf(list(nom.pn_num), list(np.polymul(np.polymul(nom.mn_den, nom.pn_den), [1, 0])))
    g_theta = ct.c2d(ct.minreal(g, verbose=False), ts, "zoh")
    z = ct.tf([1.0, 0.0], [1.0], ts)
    g_w = g_theta * (1 - 1 / z) / ts
    cv = cfg.cv_kp * (1 + cfg.cv_ki_per_s * ts / 2 * (z + 1) / (z - 1))
    closed = ct.feedback(cv * g_w, 1)
    t = np.arange(len(run.t_s)) * ts
    resp = ct.forced_response(closed, T=t, U=np.full(len(t), 10.0))
    err = np.max(np.abs(np.asarray(resp.outputs).ravel() - run.speed_deg_s))
    print(f"max |w_sim - w_python-control| = {err:.2e} deg/s (step 10 deg/s)")
    assert err < 1e-6


def test_perturbed_plant_has_its_gain_and_mode() -> None:
    v = VARIANTS_40[1]
    nom = LoopConfig().nominal
    f = np.array([1e-4, 5.0, 100.0])
    ratio = v.response(nom, f) / PlantVariant("n").response(nom, f)
    # DC: the 40 %; at the mode (closed form): |R(j wp)| = |1 - (wp/wz)^2 + j 2 zz wp/wz| /
    # (2 zp), times 1.4; far above: (wp/wz)^2 * 1.4.
    assert abs(ratio[0]) == pytest.approx(1.4, rel=1e-6)
    at_mode = abs(complex(1 - 1.25**2, 2 * 0.05 * 1.25)) / (2 * 0.05)
    assert abs(ratio[1]) == pytest.approx(1.4 * at_mode, rel=1e-6)
    assert abs(ratio[2]) == pytest.approx(1.4 * 1.5625, rel=2e-3)


def test_figs_8_9_loops_are_stable_and_the_dob_removes_the_offset() -> None:
    cfg = LoopConfig()
    for v in VARIANTS_40:
        # 5 s after the disturbance: Cv's integral corner (1.7 Hz) and Q31 at 0.5 Hz settle.
        off = speed_step_run(cfg.with_(dob_on=False), v, 6.0)
        on = speed_step_run(cfg, v, 6.0)
        assert off.stable and on.stable
        # PI alone: the rate error integrates to -d / (kp ki) (closed form); the DOB's
        # 1/(1 - Q) adds integral action that drives it back toward zero.
        assert off.offset_deg() == pytest.approx(-5.0 / (cfg.cv_kp * cfg.cv_ki_per_s), rel=0.02)
        assert abs(on.offset_deg()) < 0.3 * abs(off.offset_deg())


# -- the position-loop DOB ---------------------------------------------------------------------


def test_q41_cutoff_is_minus_3_db() -> None:
    fc = 0.5
    tau = q41_tau_s(fc)
    _, h = signal.freqs([4 * tau, 1.0], np.poly([-1 / tau] * 4) * tau**4, [2 * np.pi * fc])
    assert abs(h[0]) == pytest.approx(1 / math.sqrt(2), rel=1e-9)


def test_position_dob_inverts_the_nominal_closed_rate_loop() -> None:
    """F1 ~ Q41 Tn^-1 and Tn ~ 1/s at low frequency, so F1(z) ~ j w there (1 %), and on the
    nominal linear plant without disturbance its estimate stays small next to r."""
    cfg = LoopConfig(dob_on=False)
    loop = PositionDobLoop(cfg)
    f = np.array([0.005])
    h = sos_response(_f1_sos(cfg), f, 1000.0)
    assert h[0] / (2j * np.pi * f[0]) == pytest.approx(1.0, rel=0.01)
    traj = Trajectory(kind="sine", amplitude_deg=5.0, omega_rad_s=0.75)
    res = run_experiment(cfg, traj, 12.0, rig=LinearRig(PlantVariant("n")), loop=loop)
    ratio = np.max(np.abs(res.d_hat_deg_s[2000:])) / np.max(np.abs(res.speed_ref_deg_s))
    print(f"position DOB on the nominal plant: max |d_hat| / max |r| = {ratio:.3g}")
    assert ratio < 0.02


def _f1_sos(cfg: LoopConfig) -> np.ndarray:
    from controller.core.discrete import tustin_zpk, zpk_to_sos
    from controller.sim.position_dob import position_dob_zpk

    z, p, k = position_dob_zpk(cfg)
    return zpk_to_sos(*tustin_zpk(z, p, k, cfg.rate_hz, cfg.q_cutoff_hz))


# -- frequency-domain results ---------------------------------------------------------------------


def test_eq23_with_the_nominal_plant_is_one_over_one_minus_q31_closed_form() -> None:
    # Eq. 23 with the article's names: E1/E2 = Gdw without / with the DOB = 1/(1 - Q), P = Pn.
    cfg = LoopConfig()
    c = suppression_curve(cfg, "q31", 0.5)
    x = 2 * np.pi * c.freq_hz * design_q("q31", cutoff_hz=0.5).tau_s
    closed = -10 * np.log10(x**4 * (x**2 + 9) / (1 + x**2) ** 3)
    assert np.max(np.abs(c.gain_db - closed)) < 1e-9
    # The waterbed: 1/|1 - Q31| dips to -2.27 dB (control.md).
    dip = optimize.minimize_scalar(
        lambda y: -10 * np.log10(y**4 * (y**2 + 9) / (1 + y**2) ** 3), bounds=(0.5, 10),
        method="bounded").fun
    assert c.waterbed_db == pytest.approx(dip, abs=0.01) and dip == pytest.approx(-2.27, abs=0.01)
    assert c.at(0.1) > 10.0 and 0.2 < c.crossover_hz < 0.35  # helps below ~0.26 Hz


@pytest.mark.parametrize("q_type", ["q20", "q31"])
def test_eq23_on_a_perturbed_plant_matches_python_control(q_type: str) -> None:
    cfg = LoopConfig()
    v = VARIANTS_40[1]
    f = np.geomspace(0.01, 50.0, 200)
    nom = cfg.nominal
    s = ct.tf("s")
    q = ct.tf(*design_q(q_type, cutoff_hz=0.5).tf())  # type: ignore[arg-type]
    p = ct.tf(*v.p_polys(nom))
    pn = ct.tf(list(nom.pn_num), list(nom.pn_den))
    loop = cfg.cv_kp * (1 + cfg.cv_ki_per_s / s) * ct.tf([1.0], list(nom.mn_den)) * p
    # Gdw with and without the DOB (eqs. 16, 18), as python-control computes them.
    g_dob = p * (1 - q) / (1 + loop + (p / pn - 1) * q)
    g_plain = p / (1 + loop)
    jw = 2j * np.pi * f
    ref = 20 * np.log10(np.abs(np.asarray((g_plain / g_dob)(jw)).ravel()))
    ours = suppression_curve(cfg, q_type, 0.5, v, f).gain_db
    assert np.max(np.abs(ours - ref)) < 1e-6
    r = disturbance_responses(cfg, q_type, 0.5, v, f)
    assert np.max(np.abs(r.e1_db - 20 * np.log10(np.abs(np.asarray(g_plain(jw)).ravel())))) < 1e-6
    assert np.max(np.abs(r.e2_db - 20 * np.log10(np.abs(np.asarray(g_dob(jw)).ravel())))) < 1e-6


def test_the_disturbance_response_peak_is_the_speed_loops() -> None:
    """Eq. 16's peak lies where eq. 18's does (the speed loop's sensitivity peak times P, the
    same with and without the DOB), and moves with Cv: 6.3 Hz for the earlier 0.5 (1 + 55/s)
    (python-control's frequency response on a fine grid)."""
    f = np.geomspace(1.0, 30.0, 3000)
    for cfg in (LoopConfig(), OLD_LOOP):
        r = disturbance_responses(cfg, "q31", 0.5, freq_hz=f)
        s = ct.tf("s")
        loop = cfg.cv_kp * (1 + cfg.cv_ki_per_s / s) * ct.tf(
            [1.0], list(cfg.nominal.mn_den)) * ct.tf(list(cfg.nominal.pn_num),
                                                     list(cfg.nominal.pn_den))
        e1 = ct.tf(list(cfg.nominal.pn_num), list(cfg.nominal.pn_den)) / (1 + loop)
        ref_hz = f[int(np.argmax(np.abs(np.asarray(e1(2j * np.pi * f)).ravel())))]
        assert r.peak("e1")[1] == pytest.approx(ref_hz, rel=2e-3)
        assert r.peak("e2")[1] == pytest.approx(ref_hz, rel=0.03)
    assert disturbance_responses(OLD_LOOP, "q31", 0.5, freq_hz=f).peak("e2")[1] == pytest.approx(
        6.3, abs=0.1)


def test_sensitivities_match_a_finite_difference_in_p() -> None:
    cfg = LoopConfig()
    f = np.geomspace(0.01, 50.0, 300)
    s = 2j * np.pi * f
    nom = cfg.nominal
    cv = cfg.cv_kp * (1 + cfg.cv_ki_per_s / s)
    m = 1 / np.polyval(nom.mn_den, s)
    pn = np.polyval(nom.pn_num, s) / np.polyval(nom.pn_den, s)
    qn, qd = design_q("q31", cutoff_hz=0.5).tf()
    q = np.polyval(qn, s) / np.polyval(qd, s)
    for v in (VARIANTS_40[1], VARIANTS_40[2]):
        p = v.response(nom, f)
        curves = sensitivity_curves(cfg, v, f)
        for w, ours in (
            (lambda p_: cv * m * p_ / (1 + cv * m * p_), curves.s1_db),
            (lambda p_: cv * m * p_ / (1 + cv * m * p_ + (p_ / pn - 1) * q), curves.s2_db),
        ):
            h = 1e-7
            sens = (w(p * (1 + h)) - w(p * (1 - h))) / (2 * h) / w(p)
            # central difference in float64: ~1e-5 relative where |S| is ~1e-6 (-105 dB)
            assert np.max(np.abs(20 * np.log10(np.abs(sens)) - ours)) < 1e-3


def test_article_table_names_figures_and_says_not_reported() -> None:
    figs = {a.figure for a in ARTICLE}
    assert figs >= {"Fig. 8", "Fig. 9", "Fig. 10", "Fig. 11", "Fig. 14", "Fig. 15",
                    "Fig. 16", "Fig. 17", "Eqs. 28-29"}
    by = {(a.figure, a.quantity.split(",")[0], a.run): a.value for a in ARTICLE}
    assert by[("Fig. 14", "RMSE", "no DOB")] == 0.0231
    assert by[("Fig. 14", "RMSE", "DOB + FF")] == 0.0052
    assert all(a.text.startswith("not reported") for a in ARTICLE if a.value is None)


# -- the command line ------------------------------------------------------------------------------


def _run(**kw: object) -> tuple[int, str, str]:
    args: dict[str, object] = dict(test="sine", dob_on=None, ff_on=None, q_type=None,
                                   cutoff_hz=None, duration_s=None, seed=0, disturbance=None,
                                   as_json=True)
    args.update(kw)
    out, err = io.StringIO(), io.StringIO()
    code = experiment_main(**args, out=out, err=err)  # type: ignore[arg-type]
    return code, out.getvalue(), err.getvalue()


def test_figure_experiment_json_carries_the_article_values() -> None:
    code, out, err = _run(test="fig11")
    assert code == 0, err
    data = json.loads(out)
    (fig,) = data["figures"]
    assert fig["figure"] == "Fig. 11" and fig["agreement"] in ("agrees", "disagrees")
    assert any(a["value"] == 8.0 for a in fig["article"])
    assert fig["numbers"]["q31_waterbed_db"] == pytest.approx(-2.27, abs=0.01)


def test_config_file_and_flags(tmp_path: Path) -> None:
    path = tmp_path / "cfg.json"
    path.write_text(json.dumps(config_to_builtins(LoopConfig(q_type="q20", q_cutoff_hz=1.0))))
    code, out, err = _run(test="step", duration_s=1.0, config_path=path)
    assert code == 0, err
    cfg = json.loads(out)["config"]
    assert cfg["q_type"] == "q20" and cfg["q_cutoff_hz"] == 1.0
    code, out, err = _run(test="step", duration_s=1.0, config_path=path, cutoff_hz=2.0,
                          disturbance=["load-steps", "stick-slip"])
    assert code == 0, err
    data = json.loads(out)
    assert data["config"]["q_cutoff_hz"] == 2.0 and data["config"]["q_type"] == "q20"
    assert data["disturbance"] == "load-steps+stick-slip"


@pytest.mark.parametrize(
    ("kw", "needle"),
    [
        ({"test": "fig10", "duration_s": 3.0}, "duration_s"),
        ({"test": "fig10", "disturbance": ["earthquake"]}, "disturbance"),
        ({"test": "hold", "disturbance": ["none", "bogus"]}, "disturbance"),
        ({"test": "fig99"}, "test"),
    ],
)
def test_bad_experiment_inputs_exit_2(kw: dict[str, object], needle: str) -> None:
    code, _, err = _run(**kw)
    assert code == 2 and needle in err


def test_bad_config_file_names_the_field(tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text('{\n  "q_cutoff_hz": -1\n}\n')
    code, _, err = _run(test="sine", duration_s=3.0, config_path=path)
    assert code == 2 and "q_cutoff_hz" in err and "bad.json:2" in err


def test_command_noise_is_the_rms_above_the_band() -> None:
    """Parseval: a 50 Hz sine of amplitude 0.3 on top of a slow one -> 0.3 / sqrt(2)."""
    from types import SimpleNamespace

    from controller.sim.paper import command_noise_deg_s

    t = np.arange(10000) * 1e-3
    u = 5.0 * np.sin(2 * np.pi * 0.5 * t) + 0.3 * np.sin(2 * np.pi * 50.0 * t)
    r = SimpleNamespace(t_s=t, command_deg_s=u, metrics=SimpleNamespace(window_s=(0.0, 10.0)))
    assert command_noise_deg_s(r) == pytest.approx(0.3 / np.sqrt(2), rel=1e-3)  # type: ignore[arg-type]
    r2 = SimpleNamespace(t_s=t, command_deg_s=u, metrics=SimpleNamespace(window_s=(2.0, 10.0)))
    assert command_noise_deg_s(r2) == pytest.approx(0.3 / np.sqrt(2), rel=1e-3)  # type: ignore[arg-type]


def test_backlash_rig_without_play_is_the_linear_rig_and_the_play_shows_at_reversals() -> None:
    from controller.sim.linear_rig import BacklashRig, LinearRig

    v = PlantVariant("nominal")
    u = 10.0 * np.sin(2 * np.pi * 0.4 * np.arange(3000) * 1e-3)
    exact, plain, loose = LinearRig(v), BacklashRig(v, backlash_deg=0.0), BacklashRig(
        v, backlash_deg=0.2)
    a, b, c = (np.empty(len(u)) for _ in range(3))
    for k, x in enumerate(u):
        for rig, out in ((exact, a), (plain, b), (loose, c)):
            rig.step(float(x))
            out[k] = rig.read()[0]
    # Sub-stepped ZOH against the exact discretisation: within 0.02 % of the travel.
    assert np.max(np.abs(a - b)) < 2e-4 * np.max(np.abs(a))
    # Moving one way, the input sits at one edge of the play: the load lags by half of it.
    assert (b - c)[1200] == pytest.approx(0.1, abs=2e-3)  # moving forward (0.4 Hz sine)
    assert (b - c)[2400] == pytest.approx(-0.1, abs=2e-3)  # moving back after the reversal
    with pytest.raises(ConfigError, match="backlash_deg"):
        BacklashRig(v, backlash_deg=-1.0)
