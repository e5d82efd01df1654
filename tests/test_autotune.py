"""Autotune: its best point is the best of an explicit sweep of the same grid (each point run
independently here), only accepted candidates count, rejected ones are never run."""

from __future__ import annotations

import io
import json
import math

import numpy as np
import pytest

from controller.core.config import LoopConfig
from controller.core.trajectory import default_trajectory
from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
from controller.gate.verdict import judge
from controller.sim.disturbance import disturbance_from_name
from controller.sim.experiment import run_experiment
from controller.tune.autotune import autotune, run_point

K = PlantKnowledge(bound=COMMISSIONING_BOUND)


def test_best_is_the_best_of_an_explicit_sweep() -> None:
    traj = default_trajectory("hold")
    dist = disturbance_from_name("sine-0.05hz")
    res = autotune(LoopConfig(), K, traj, duration_s=8.0, disturbance=dist, points=4,
                   refine=0, q_types=("q31",), lowest_hz=0.2, highest_hz=5.0, noise_weight=0.0)
    assert res.baseline.config.dob_on is False
    scores = {}
    for fc in np.geomspace(0.2, 5.0, 4):
        cfg = LoopConfig(q_cutoff_hz=float(fc))
        if judge(cfg, K).verdict != "accept":
            continue
        scores[float(fc)] = run_experiment(cfg, traj, 8.0, disturbance=dist).rmse_deg
    assert res.best is not None
    assert res.best.q_cutoff_hz == pytest.approx(min(scores, key=scores.__getitem__))
    assert res.best.rmse_deg == pytest.approx(min(scores.values()), rel=1e-12)
    assert res.best.verdict == "accept"


def test_rejected_candidates_are_not_run_and_bad_input_is_named() -> None:
    stiff = LoopConfig(cv_kp=30.0)  # unstable whatever the Q (pole radius 1.007): all rejected
    res = autotune(stiff, K, default_trajectory("sine"), duration_s=2.0, points=2, refine=0,
                   q_types=("q31",))
    assert res.best is None and all(p.verdict == "reject" for p in res.curve)
    assert all(math.isnan(p.rmse_deg) for p in res.curve)
    assert "keep the DOB off" in res.summary()
    with pytest.raises(ValueError, match="objective"):
        autotune(LoopConfig(), K, default_trajectory("sine"), objective="mse")
    with pytest.raises(ValueError, match="cut-off range"):
        autotune(LoopConfig(), K, default_trajectory("sine"), lowest_hz=5.0, highest_hz=1.0)


@pytest.mark.slow
def test_cli_json_has_best_baseline_and_curve() -> None:
    import argparse

    from controller.cli.autotune import autotune_main

    args = argparse.Namespace(config=None, knowledge=None, trajectory="sine", disturbance="none",
                              objective="rmse", noise_weight=0.001, duration=4.0, points=3,
                              lowest_hz=0.2, highest_hz=5.0, allow_caution=False, json=True)
    out = io.StringIO()
    assert autotune_main(args, out, io.StringIO()) == 0
    data = json.loads(out.getvalue())
    assert set(data) >= {"best", "baseline", "curve", "dob_helps", "summary"}
    assert {"q_type", "q_cutoff_hz", "rmse_deg", "peak_error_deg", "verdict"} <= set(
        data["curve"][0])
    assert data["baseline"]["config"]["dob_on"] is False


@pytest.mark.slow
def test_cli_runs_with_the_named_belt_disturbances_and_names_a_bad_one() -> None:
    import argparse

    from controller.cli.autotune import autotune_main

    def run(disturbance: list[str] | None) -> tuple[int, str]:
        args = argparse.Namespace(
            config=None, knowledge=None, trajectory="sine", disturbance=disturbance,
            objective="rmse", noise_weight=0.001, duration=3.0, points=2, lowest_hz=0.2,
            highest_hz=2.0, allow_caution=False, json=True)
        out = io.StringIO()
        return autotune_main(args, out, io.StringIO()), out.getvalue()

    code, plain = run(None)
    assert code == 0
    code, belt = run(["tooth-meshing", "load-steps"])
    assert code == 0
    quiet, loud = json.loads(plain)["baseline"], json.loads(belt)["baseline"]
    # A 0.5 N m tooth ripple and 1 N m load steps make the same loop track worse.
    assert loud["rmse_deg"] > quiet["rmse_deg"]
    code, bad = run(["belt-snap"])
    assert code == 2 and "disturbance" in bad and "belt-snap" in bad


def test_command_noise_is_the_rms_above_20_hz() -> None:
    """A 1 Hz command with a 50 Hz component of amplitude 2 deg/s: the noise figure is that
    component's RMS through a 2nd-order Butterworth high-pass at 20 Hz, closed form
    2 / sqrt(2) / sqrt(1 + (20/50)^4); the 1 Hz part (100x larger) passes at (1/20)^2."""
    from controller.tune.autotune import command_noise_deg_s

    t = np.arange(20000) / 1000.0
    u = 100.0 * np.sin(2 * np.pi * 1.0 * t) + 2.0 * np.sin(2 * np.pi * 50.0 * t)
    want = math.hypot(2.0 / math.sqrt(1 + (20 / 50) ** 4), 100.0 / math.sqrt(1 + 20.0**4))
    assert command_noise_deg_s(u, 1000.0) == pytest.approx(want / math.sqrt(2), rel=0.01)


def test_autotune_runs_on_the_twin_when_something_was_measured() -> None:
    """Issue 35 item 2: with measured responses the runs are the twin's (here a rig with twice
    the drive gain), not the built-in model's; with nothing measured the result says so."""
    from controller.sim.rig_disturbances import rig_setup
    from controller.sim.sim_rig import RigFaults, RigParams
    from controller.tune.family import true_knowledge
    from controller.tune.plant import BUILT_IN, plant_for

    cfg = LoopConfig()
    traj = default_trajectory("sine")
    measured = true_knowledge(RigParams(), RigFaults(plant_gain=2.0))
    kw = dict(duration_s=6.0, points=2, refine=0, q_types=("q31",), lowest_hz=0.3,
              highest_hz=1.0, setup=rig_setup(()))
    on_twin = autotune(cfg, measured, traj, **kw)  # type: ignore[arg-type]
    on_model = autotune(cfg, PlantKnowledge(bound=COMMISSIONING_BOUND), traj, **kw)  # type: ignore[arg-type]
    assert on_model.plant_source == BUILT_IN and BUILT_IN in on_model.summary()
    assert on_twin.plant_source.startswith("rig's twin") and BUILT_IN not in on_twin.summary()
    twin = plant_for(measured, rig_setup(()))
    again = run_point(cfg.with_(dob_on=False), traj, 6.0, plant=twin)
    assert on_twin.baseline.rmse_deg == pytest.approx(again.rmse_deg, rel=1e-12)
    assert on_twin.baseline.rmse_deg != pytest.approx(on_model.baseline.rmse_deg, rel=0.01)
