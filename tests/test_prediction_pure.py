"""The pure part of predicted-then-measured (controller/tune/prediction.py) against closed
forms and independent computations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.sim.experiment import run_experiment
from controller.sim.rig_disturbances import rig_setup
from controller.tune.autotune import command_noise_deg_s
from controller.tune.plant import SimPlant
from controller.tune.prediction import (
    BANDS_HZ,
    TOLERANCE_REL,
    Figures,
    band_rms_deg,
    check_window_s,
    figures_of,
    judge,
    meaning,
    predict,
)

RATE = 1000.0


def test_the_window_holds_whole_periods_of_a_sine() -> None:
    slow = Trajectory(kind="sine", omega_rad_s=0.5)  # 12.57 s period
    assert check_window_s(slow) == pytest.approx(2 * math.pi / 0.5)
    fast = Trajectory(kind="sine", omega_rad_s=2.0)  # 3.14 s: four periods reach 10 s
    assert check_window_s(fast) == pytest.approx(4 * math.pi)
    assert check_window_s(Trajectory(kind="ramp")) == 10.0
    assert check_window_s(Trajectory(kind="hold"), 4.0) == 4.0
    with pytest.raises(ValueError, match="min_window_s"):
        check_window_s(slow, 0.0)


def test_band_rms_of_sines_is_their_amplitude_over_root_two() -> None:
    t = np.arange(20_000) / RATE
    e = 0.3 * np.sin(2 * math.pi * 0.5 * t) + 0.04 * np.sin(2 * math.pi * 5.0 * t) \
        + 0.002 * np.sin(2 * math.pi * 50.0 * t)
    bands = band_rms_deg(e, RATE)
    assert len(bands) == len(BANDS_HZ)
    assert bands[0] == pytest.approx(0.3 / math.sqrt(2), rel=1e-6)
    assert bands[1] == pytest.approx(0.04 / math.sqrt(2), rel=1e-6)
    assert bands[2] == pytest.approx(0.002 / math.sqrt(2), rel=1e-6)
    assert bands[3] == pytest.approx(0.0, abs=1e-12)


def test_the_bands_add_up_to_the_variance() -> None:
    rng = np.random.default_rng(7)
    for n in (1000, 1001):  # even and odd lengths (the Nyquist bin)
        e = rng.normal(0.1, 0.5, n)
        assert sum(b * b for b in band_rms_deg(e, RATE)) == pytest.approx(np.var(e), rel=1e-9)


def test_figures_of_a_window() -> None:
    t = np.arange(10_000) / RATE
    e = 0.05 * np.sin(2 * math.pi * 0.2 * t)
    cmd = np.random.default_rng(1).normal(0.0, 1.0, t.size)
    f = figures_of(e, cmd, RATE)
    assert f.rmse_deg == pytest.approx(0.05 / math.sqrt(2), rel=1e-6)
    assert f.peak_error_deg == pytest.approx(0.05, rel=1e-4)
    assert f.command_noise_deg_s == command_noise_deg_s(cmd, RATE)
    with pytest.raises(ValueError, match="empty"):
        figures_of(np.zeros(0), np.zeros(0), RATE)


def _fig(rmse: float, peak: float, noise: float) -> Figures:
    return Figures(peak_error_deg=peak, rmse_deg=rmse, command_noise_deg_s=noise,
                   band_rms_deg=(0.0, 0.0, 0.0, 0.0))


def test_judge_held_failed_and_failed_badly() -> None:
    p = _fig(0.03, 0.08, 0.07)
    t = TOLERANCE_REL
    held = judge(p, _fig(0.03 * (1 + 0.9 * t["rmse_deg"]), 0.08, 0.07))
    assert held.state == "held" and held.outside == ()
    assert held.off_rel["rmse_deg"] == pytest.approx(0.9 * t["rmse_deg"])
    failed = judge(p, _fig(0.03 * (1 + 1.5 * t["rmse_deg"]), 0.08, 0.07))
    assert failed.state == "failed" and failed.outside == ("rmse_deg",)
    badly = judge(p, _fig(0.03, 0.08 * (1 - 2.5 * t["peak_error_deg"]), 0.07))
    assert badly.state == "failed badly" and badly.outside == ("peak_error_deg",)
    with pytest.raises(ValueError, match="rmse_deg"):
        judge(p, _fig(math.nan, 0.08, 0.07))
    assert "can be trusted" in meaning(held, "")
    assert "model is wrong" in meaning(failed, "stiffness alarm")
    assert "a disturbance the twin lacks" in meaning(failed, "")


def test_the_prediction_is_the_plant_run_over_the_last_window() -> None:
    """`predict` against run_experiment on the same plant's rig, sliced by hand."""
    setup = rig_setup(("article-rig",))
    plant = SimPlant.of_setup(setup)
    cfg = LoopConfig()
    traj = Trajectory(kind="sine", omega_rad_s=2.0)
    window = check_window_s(traj, 5.0)
    p = predict(cfg, traj, plant, window, settle_s=3.0)
    lead = check_window_s(traj, 3.0)
    res = run_experiment(cfg, traj, lead + window, rig=plant.rig_on(traj, cfg.rate_hz))
    n = round(window * RATE)
    err = np.asarray(res.error_deg)[-n:]
    assert p.rmse_deg == pytest.approx(float(np.sqrt(np.mean(err**2))), rel=1e-9)
    assert p.peak_error_deg == pytest.approx(float(np.max(np.abs(err))), rel=1e-9)


def _check(version: int, state: str) -> object:
    from controller import protocol as proto

    return proto.PredictionCheck(rig="r", config_version=version, epoch_s=0.0,
                                 trajectory=Trajectory(), model="m", window_s=10.0,
                                 settle_s=3.0, state=state)


def test_the_rollback_is_offered_only_when_failed_badly_on_an_unmoved_plant() -> None:
    from controller.process.prediction_check import rollback_offer

    checks = {1: _check(1, "held"), 2: _check(2, "held"), 3: _check(3, "failed"),
              4: _check(4, "failed badly")}
    assert rollback_offer("failed badly", "", checks, 4)[0] == 2  # the newest that held
    assert rollback_offer("failed", "", checks, 4) == (None, "")
    assert rollback_offer("held", "", checks, 4) == (None, "")
    v, text = rollback_offer("failed badly", "stiffness alarm", checks, 4)
    assert v is None and "measure it again first" in text  # judged on the old plant
    v, text = rollback_offer("failed badly", "", {4: _check(4, "failed badly")}, 4)
    assert v is None and "no earlier version" in text
