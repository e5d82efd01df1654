"""The speed-command filter designed with the speed PI (controller.tune.filter_design) and the
whole-loop tune that keeps it (controller.tune.whole_loop): a notch where a measured mode
limits the speed loop, margins checked against python-control's loop with the filter
(tests/fuzz_truth.py), every position's mode covered, no filter where no mode limits, and on
a simulated rig with a lightly damped mode the tuned loop with the filter beats the tuned loop
without it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from fuzz_truth import Resonance, TruePlant, continuous_response, truth

from controller.core.command_filter import command_filter_response
from controller.core.config import LoopConfig
from controller.core.trajectory import default_trajectory
from controller.gate.knowledge import COMMISSIONING_BOUND, MeasuredResponse, PlantKnowledge
from controller.gate.verdict import judge
from controller.sim.experiment import run_experiment
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import RigFaults, RigParams
from controller.tune.family import true_knowledge
from controller.tune.filter_design import MIN_RAISE, design_filter
from controller.tune.loop_design import (
    DesignTargets,
    NoSpeedDesign,
    design_position,
    design_speed,
)
from controller.tune.plant import SimPlant
from controller.tune.whole_loop import Objective, WholeLoopResult, tune_whole_loop

RATE = 1000.0
F = np.unique(np.concatenate([np.geomspace(0.1, 400.0, 300), np.geomspace(15.0, 60.0, 200)]))


def _plant(mode_hz: float) -> TruePlant:
    """The article's model with a lightly damped non-collocated mode (zeros far above) and a
    tick of delay."""
    return TruePlant(resonance=Resonance(mode_hz, 0.02, zero_ratio=10.0), delay_ticks=1)


def _knowledge(plants: list[TruePlant]) -> PlantKnowledge:
    return PlantKnowledge(
        measured=tuple(MeasuredResponse(f"pos {i}", F, continuous_response(p, RATE, F))
                       for i, p in enumerate(plants)),
        bound=COMMISSIONING_BOUND)


def _config(knowledge: PlantKnowledge, targets: DesignTargets, fd_speed=None):  # type: ignore[no-untyped-def]
    sp = fd_speed or design_speed(knowledge, RATE, targets)
    po = design_position(knowledge, RATE, sp, targets)
    return LoopConfig(cv_kp=sp.kp, cv_ki_per_s=sp.ki_per_s, pos_kp_per_s=po.kp_per_s,
                      pos_ki_per_s=po.ki_per_s, dob_on=False, command_filter=sp.command_filter)


def test_a_notch_at_the_limiting_mode_raises_the_crossover_as_python_control_finds() -> None:
    p = _plant(30.0)
    k = _knowledge([p])
    t = DesignTargets()
    plain = design_speed(k, RATE, t)
    fd = design_filter(k, RATE, plain, t)
    assert fd is not None and fd.command_filter.kind == "notch"
    cf = fd.command_filter
    assert cf.notch_hz == pytest.approx(30.0, rel=0.01)
    assert fd.speed.crossover_hz >= MIN_RAISE * plain.crossover_hz
    # python-control's loop with the filter (its own Tustin discretisation of the prototype):
    # the design's margins and crossover, and the targets met
    with_f = truth(p, _config(k, t, fd.speed))
    without = truth(p, _config(k, t))
    assert with_f.stable and without.stable
    ms = with_f.margins_speed
    assert ms is not None and without.margins_speed is not None
    mine = fd.speed.figures[0].margins
    assert ms.gain_margin_db == pytest.approx(mine.gain_margin_db, abs=0.05)
    assert ms.phase_margin_deg == pytest.approx(mine.phase_margin_deg, abs=0.2)
    assert ms.gain_crossover_hz == pytest.approx(mine.crossover_hz, rel=1e-3)
    assert ms.gain_margin_db >= t.gain_margin_db - 0.05
    assert ms.phase_margin_deg >= t.phase_margin_deg - 0.2
    assert ms.gain_crossover_hz > 1.4 * without.margins_speed.gain_crossover_hz
    assert with_f.margins_full is not None
    assert with_f.margins_full.phase_margin_deg >= t.phase_margin_deg - 0.2
    # the gate judges the loop with the filter, and accepts it
    assert judge(_config(k, t, fd.speed), k).verdict == "accept"


def test_the_filter_covers_every_positions_mode() -> None:
    modes = (26.0, 30.0, 35.0)
    plants = [_plant(m) for m in modes]
    k = _knowledge(plants)
    t = DesignTargets()
    fd = design_filter(k, RATE, design_speed(k, RATE, t), t)
    assert fd is not None
    assert sorted(fd.modes_hz) == pytest.approx(modes, rel=0.01)
    cf = fd.command_filter
    cut_db = 20 * np.log10(np.abs(command_filter_response(cf, np.array(fd.modes_hz), RATE)))
    if cf.kind == "notch":
        assert np.all(cut_db <= -cf.notch_depth_db / 2), cut_db
    else:
        assert cf.kind == "lowpass" and cf.lowpass_hz < min(modes)
    cfg = _config(k, t, fd.speed)
    for p in plants:
        ms = truth(p, cfg).margins_speed
        assert ms is not None
        assert ms.gain_margin_db >= t.gain_margin_db - 0.1
        assert ms.phase_margin_deg >= t.phase_margin_deg - 0.2
    assert judge(cfg, k).verdict != "reject"


def test_where_no_pi_alone_meets_the_targets_a_filter_may() -> None:
    """Measured at 10 points a decade (a mode's frequency known to half a step): no speed PI
    alone meets the targets (the mode's peak crosses 0 dB); the notch designed instead covers
    the true mode and python-control's loop on the true plant meets the targets."""
    p = _plant(30.0)
    f = np.geomspace(0.3, 60.0, 24)
    k = PlantKnowledge(measured=(MeasuredResponse("pos 0", f, continuous_response(p, RATE, f)),),
                       bound=COMMISSIONING_BOUND)
    t = DesignTargets()
    with pytest.raises(NoSpeedDesign) as exc:
        design_speed(k, RATE, t)
    fd = design_filter(k, RATE, exc.value, t)
    assert fd is not None and fd.command_filter.kind == "notch"
    cf = fd.command_filter
    cut = 20 * np.log10(abs(command_filter_response(cf, np.array([30.0]), RATE)[0]))
    assert cut <= -cf.notch_depth_db / 2
    ms = truth(p, _config(k, t, fd.speed)).margins_speed
    assert ms is not None
    assert ms.gain_margin_db >= t.gain_margin_db and ms.phase_margin_deg >= t.phase_margin_deg


def test_no_filter_where_no_measured_mode_limits_the_speed_loop() -> None:
    t = DesignTargets()
    for k in (PlantKnowledge(bound=COMMISSIONING_BOUND),        # nothing measured
              true_knowledge(RigParams(), RigFaults()),         # the default rig, measured
              true_knowledge(RigParams(), RigFaults(resonance_hz=140.0,
                                                    resonance_damping=0.015))):  # far above
        assert design_filter(k, RATE, design_speed(k, RATE, t), t) is None


#: A rig of the issue's family (seed 1950567981, rig 11: the one the gate did not accept in
#: the family table) with its 31 Hz mode: J x0.41, k x0.65, drive gain x0.89, z 0.015, 1 tick.
BASE = RigParams()
RIG = replace(BASE, load_inertia_kg_m2=BASE.load_inertia_kg_m2 * 0.41,
              belt_stiffness_n_m_rad=BASE.belt_stiffness_n_m_rad * 0.65, command_delay_ticks=1)
#: A mode at 20 Hz: the speed loop without a filter crosses at about 1/8 of it, and the tuned
#: loop with the notch tracks 2.5x better than the tuned loop without it (at 31 Hz, below,
#: the position loop's refinement (step 5b) lifts the loop without a filter past it).
FAULTS = RigFaults(plant_gain=0.89, resonance_hz=20.0, resonance_damping=0.015)


def _tuned_both_ways(faults: RigFaults) -> tuple[PlantKnowledge, SimPlant, WholeLoopResult,
                                               WholeLoopResult]:
    """The true rig's knowledge and twin, and the whole-loop tune on it (no feedforward) with
    and without the speed-command filter's design."""
    k = true_knowledge(RIG, faults, RATE)
    plant = SimPlant.of_setup(rig_setup(("article-rig",), base=RIG), source="true rig",
                              faults=faults)
    obj = Objective(feedforward=False)
    with_f = tune_whole_loop(LoopConfig(), k, plant, obj)
    without = tune_whole_loop(LoopConfig(), k, plant, obj, design_command_filter=False)
    assert with_f.best is not None and without.best is not None
    return k, plant, with_f, without


@pytest.mark.slow
def test_on_a_rig_with_a_mode_the_tune_keeps_a_filter_that_beats_the_loop_without() -> None:
    k, plant, with_f, without = _tuned_both_ways(FAULTS)
    cf = with_f.best.config.command_filter
    assert cf.kind != "off" and without.best.config.command_filter.kind == "off"
    assert with_f.filter_design is not None and with_f.filter_design.kept
    assert judge(with_f.best.config, k).verdict == "accept"
    text = "\n".join(with_f.explanation)
    assert "speed-command filter: the mode at" in text and "lets the speed loop cross at" in text
    assert f"{with_f.speed.crossover_hz:.3g} Hz instead of " in text
    assert with_f.speed.crossover_hz > 1.5 * without.speed.crossover_hz
    # run again on the true rig with another noise seed (the tune's runs used seed 0)
    traj = default_trajectory("sine")
    rmse = [run_experiment(r.best.config, traj, 15.0,
                           rig=plant.rig_on(traj, RATE, seed=7)).rmse_deg
            for r in (with_f, without)]
    assert rmse[0] < 0.6 * rmse[1], rmse


@pytest.mark.slow
def test_a_filter_the_tuned_loop_does_not_need_is_not_kept() -> None:
    """With the mode at 31 Hz the notch lets the speed loop cross 2x higher and the designed
    loop (DOB off) with it tracks 3.6x better, but the gate then holds the whole servo at its
    sensitivity limit, while the loop without it takes the position loop's refinement (step
    5b) further: tuned, the loop without the filter tracks better. The tune compares the tuned
    loops, so it keeps no filter and proposes what the tune without one proposes (the seventh
    session's tune kept the filter on the designed loops' comparison: 0.0184 deg against 0.0104
    on the true rig)."""
    _, _, with_f, without = _tuned_both_ways(replace(FAULTS, resonance_hz=31.0))
    fd = with_f.filter_design
    assert fd is not None and not fd.kept  # designed, tried, not kept
    assert with_f.best.config.command_filter.kind == "off"
    assert with_f.best.config == without.best.config
    # the designed loops alone point the other way: the comparison has to be on the tuned ones
    other = with_f.designed_other
    assert other is not None and other.config.command_filter.kind == "notch"
    assert other.score < with_f.designed.score
    tuned = with_f.other_best
    assert tuned is not None and tuned.config.command_filter.kind == "notch"
    assert with_f.best.score < tuned.score
    text = "\n".join(with_f.explanation)
    assert "the loop tuned with it did not do better" in text
    assert (f"{tuned.error_deg('rmse'):.4g} deg against "
            f"{with_f.best.error_deg('rmse'):.4g} without it") in text
