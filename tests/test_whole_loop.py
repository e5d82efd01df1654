"""The whole-loop tune (controller.tune.whole_loop) on the default simulated rig: what it
proposes is accepted by the gate, tracks better than the starting loop when run again
independently, and its explanation's reference lag agrees with a linear simulation."""

from __future__ import annotations

import pytest
from rig_linear import linear_rig

from controller.core.config import LoopConfig
from controller.core.trajectory import default_trajectory
from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
from controller.gate.verdict import judge
from controller.sim.experiment import run_experiment
from controller.sim.rig_disturbances import rig_setup
from controller.tune.autotune import run_point
from controller.tune.plant import BUILT_IN, SimPlant
from controller.tune.whole_loop import Objective, reference_lag, tune_whole_loop

KNOWLEDGE = PlantKnowledge(bound=COMMISSIONING_BOUND)
SETUP = rig_setup(("article-rig",))


@pytest.fixture(scope="module")
def tuned_no_ff():  # type: ignore[no-untyped-def]
    return tune_whole_loop(LoopConfig(), KNOWLEDGE, SimPlant.of_setup(SETUP),
                           Objective(feedforward=False))


def test_the_candidate_is_accepted_and_beats_the_starting_loop(tuned_no_ff) -> None:  # type: ignore[no-untyped-def]
    res = tuned_no_ff
    assert res.best is not None
    cfg = res.best.config
    assert not cfg.ff_on
    assert judge(cfg, KNOWLEDGE).verdict == "accept"
    traj = default_trajectory("sine")
    again = run_point(cfg, traj, 15.0, setup=SETUP)  # the autotune's own run, not the tune's
    start = run_point(LoopConfig(), traj, 15.0, setup=SETUP)
    assert again.rmse_deg == pytest.approx(res.best.rmse_deg, rel=1e-9)
    assert again.rmse_deg < 0.8 * start.rmse_deg
    # the position loop crosses over higher than the starting loop's 1.27 Hz, 4x below the
    # speed loop, as the targets say
    assert res.position.crossover_hz > 1.5
    assert res.speed.crossover_hz / res.position.crossover_hz == pytest.approx(4.0, rel=0.05)
    text = "\n".join(res.explanation)
    assert BUILT_IN in text and "reference lag" in text and "limited by" in text
    # nothing measured, no resonance: the speed-command filter stays off, and it says so
    assert cfg.command_filter.kind == "off" and res.filter_design is None
    assert "speed-command filter: off (no measured resonance limits the speed loop)" in text
    # the starting loop's crossovers as the issue measured them (6.9 Hz, 1.27 Hz)
    assert "speed loop crossing at 6.88 Hz, position loop at 1.27 Hz" in text


def test_reference_lag_is_what_a_linear_rig_shows() -> None:
    cfg = LoopConfig(dob_on=False)
    traj = default_trajectory("sine")
    run = run_experiment(cfg, traj, 15.0, rig=linear_rig())
    lag = reference_lag(cfg, KNOWLEDGE, traj)
    assert lag == pytest.approx(run.rmse_deg, rel=0.05)
    # the starting loop's sine error on the article rig is mostly this lag (issue 35: 97 %)
    on_rig = run_point(cfg, traj, 15.0, setup=SETUP)
    assert (lag / on_rig.rmse_deg) ** 2 > 0.85
    # with feedforward the lag nearly vanishes
    assert reference_lag(cfg.with_(ff_on=True), KNOWLEDGE, traj) < 0.1 * lag


def test_bad_objectives_are_refused_naming_the_field() -> None:
    with pytest.raises(ValueError, match="objective"):
        Objective(metric="max")
    with pytest.raises(ValueError, match="noise_budget_deg_s"):
        Objective(noise_budget_deg_s=-1.0)
    with pytest.raises(ValueError, match="duration_s"):
        Objective(duration_s=1.0)


def test_the_tune_never_proposes_worse_than_where_it_started() -> None:
    """Targets no fast loop meets (gain margin 30 dB; no feedforward, a command-noise budget the
    DOB's faster settings exceed) make every designed loop slow: the
    accepted starting loop tracks better on the plant than anything the tune finds, so it is
    what the tune proposes, unchanged, and the explanation says so (on the demo's measured
    knowledge the tune once proposed a loop 13x worse than the running one)."""
    from controller.tune.loop_design import DesignTargets

    start_cfg = LoopConfig()
    res = tune_whole_loop(start_cfg, KNOWLEDGE, SimPlant.of_setup(SETUP),
                          Objective(noise_budget_deg_s=0.1, feedforward=False),
                          DesignTargets(gain_margin_db=30.0),
                          q_types=("q31",), cutoffs=2, refine_rounds=0, refine_position=False,
                          design_command_filter=False, robust=False)
    assert res.best is not None and res.best is res.start
    assert res.best.config == start_cfg
    assert res.beaten is not None and res.beaten.score > res.start.score
    # independently: the designed loop, run again, tracks worse than the starting loop
    traj = default_trajectory("sine")
    slow = run_point(res.designed.config, traj, 15.0, setup=SETUP)
    start = run_point(start_cfg, traj, 15.0, setup=SETUP)
    assert slow.rmse_deg > start.rmse_deg
    text = "\n".join(res.explanation)
    assert "the starting loop is proposed unchanged" in text
