"""The whole-loop tune refines the position loop below the design's 45 deg, down to a stated
floor (issue 35 item 4; `DesignTargets.position_floor_*`, `tune_whole_loop` step 5b): the
gate-checked brute force's best loops on the family sit at 30-36 deg of position-loop phase
margin, and the design alone came 1.13-1.45x behind them."""

from __future__ import annotations

import math

import pytest

from controller.core.config import LoopConfig
from controller.gate.verdict import judge
from controller.tune.autotune import SIGNIFICANT_REL
from controller.tune.family import draw_family, true_knowledge
from controller.tune.loop_design import DesignTargets
from controller.tune.whole_loop import (
    Objective,
    evaluate,
    meets_targets,
    position_figures,
    tune_limits,
    tune_whole_loop,
)


@pytest.mark.parametrize(("field", "value"), [
    ("position_floor_pm_deg", 29.0), ("position_floor_pm_deg", 50.0),
    ("position_floor_gm_db", 5.5), ("position_floor_gm_db", 9.0),
    ("position_corner_floor", 1.0), ("position_corner_floor", 5.0),
    ("sensitivity_inside_db", -0.1), ("sensitivity_inside_db", 3.5),
])
def test_floors_outside_the_gate_and_the_design_are_refused(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        DesignTargets(**{field: value})


@pytest.mark.slow
@pytest.mark.timeout(900)  # a hang's bound; a few tunes' worth of runs
def test_the_position_loop_is_refined_within_the_floor_on_family_rig_2() -> None:
    """Family rig 2 of seed 2632146472, tuned on its exact responses with the true rig as
    the plant (no identification: the twin's error out of it). The design's loop sits at the
    whole servo's 8 dB gain margin; the refinement raises the position gain past it, within
    the floors: the result misses the design's targets but meets the floors, the gate accepts
    it, it scores better than the unrefined loop on the rig (run again here), and the
    explanation says from which margin to which and why. Without the refinement the result
    is the unrefined loop. Tuned with the gate's own peak-sensitivity limit (no allowance for
    the twin's uncertainty: the plant here is the true rig): with the 0.5 dB allowance the
    design itself steps down and no refinement fits (the test below)."""
    rig = draw_family(2632146472, 3)[2]
    base = LoopConfig()
    truth = true_knowledge(rig.params, rig.faults, base.rate_hz, base.nominal)
    obj = Objective()
    t = DesignTargets(sensitivity_inside_db=0.0)
    res = tune_whole_loop(base, truth, rig.plant, obj, t)
    assert res.best is not None and res.unrefined is not None
    b, u = res.best.config, res.unrefined.config
    assert b != u, "\n".join(res.explanation)
    assert meets_targets(u, truth, t) is None
    assert meets_targets(b, truth, t, floor=True) is None
    assert meets_targets(b, truth, t) is not None  # below the design's own targets
    assert judge(b, truth).verdict == "accept"
    again_b, again_u = evaluate(b, rig.plant, obj, None), evaluate(u, rig.plant, obj, None)
    assert again_b.score < again_u.score
    assert again_b.score == pytest.approx(res.best.score, rel=1e-9)
    pm, _, ratio = position_figures(b, truth)
    assert pm >= t.position_floor_pm_deg and ratio >= t.position_corner_floor
    line = next(x for x in res.explanation if x.startswith("position loop of the candidate"))
    assert f"PM {pm:.1f} deg" in line and "refined on the twin from the design's PM" in line
    assert "not fragile on its variants" in line, line
    plain = tune_whole_loop(base, truth, rig.plant, obj, t, refine_position=False)
    # (the unrefined loop, or the same with the DOB off where it scored within 1 % of it)
    got = plain.dob_dropped or plain.best
    assert got is not None and got.config == u
    assert plain.best is not None and (plain.best.config == u or plain.best.config == u.with_(
        dob_on=False))
    assert math.isfinite(plain.best.score) and plain.best.score > res.best.score


@pytest.mark.slow
@pytest.mark.timeout(900)  # a hang's bound
def test_every_candidate_keeps_the_allowance_inside_the_gates_peak_sensitivity() -> None:
    """`DesignTargets.sensitivity_inside_db` (0.5 dB by default): the tune holds what it runs
    and proposes to a peak sensitivity that far inside the gate's 6 dB, for the twin's
    uncertainty. On family rig 2 (true responses) the loop tuned at the gate's own limit sits
    between the two (accepted by the gate, not within the allowance); the default tune's loop
    is within it, and says so."""
    rig = draw_family(2632146472, 3)[2]
    base = LoopConfig()
    truth = true_knowledge(rig.params, rig.faults, base.rate_hz, base.nominal)
    obj = Objective()
    edge = tune_whole_loop(base, truth, rig.plant, obj, DesignTargets(sensitivity_inside_db=0.0))
    kept = tune_whole_loop(base, truth, rig.plant, obj)
    assert edge.best is not None and kept.best is not None
    inside = tune_limits(DesignTargets())
    assert inside.peak_sensitivity_max_db == pytest.approx(5.5, abs=1e-12)
    assert judge(edge.best.config, truth).verdict == "accept"
    assert judge(edge.best.config, truth, inside).verdict != "accept"
    assert judge(kept.best.config, truth, inside).verdict == "accept"
    assert any("peak sensitivity <= 5.5 dB (the gate's 6 dB - 0.5 dB" in x
               for x in kept.explanation)


@pytest.mark.slow
@pytest.mark.timeout(900)  # a hang's bound
def test_a_dob_within_the_predictions_accuracy_of_the_dob_off_is_dropped() -> None:
    """Step 6a: family rig 2 (true responses), tuned without the position refinement at the
    gate's own limit: the twin's best has a DOB that scores within 1 % of the same loop without
    it (here it scores worse: the search had not run the loop without it); the tune proposes
    the loop without it, keeps the other for the words, and both scores are what the plant
    gives when run again here."""
    rig = draw_family(2632146472, 3)[2]
    base = LoopConfig()
    truth = true_knowledge(rig.params, rig.faults, base.rate_hz, base.nominal)
    obj = Objective()
    res = tune_whole_loop(base, truth, rig.plant, obj, DesignTargets(sensitivity_inside_db=0.0),
                          refine_position=False)
    b, d = res.best, res.dob_dropped
    assert b is not None and d is not None, "\n".join(res.explanation)
    assert d.config.dob_on and not b.config.dob_on and d.config.with_(dob_on=False) == b.config
    assert d.score >= b.score * (1 - SIGNIFICANT_REL)  # not better by more than 1 %
    assert evaluate(d.config, rig.plant, obj, None).score == pytest.approx(d.score, rel=1e-9)
    assert evaluate(b.config, rig.plant, obj, None).score == pytest.approx(b.score, rel=1e-9)
    assert judge(b.config, truth).verdict == "accept"
    line = next(x for x in res.explanation if x.startswith("DOB off: with it"))
    assert f"{d.config.q_type} at {d.config.q_cutoff_hz:.3g} Hz" in line and "within 1 %" in line
