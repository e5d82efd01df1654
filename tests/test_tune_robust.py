"""The whole-loop tune's robustness check (controller.tune.whole_loop, step 6): a twin is an
estimate, so the best candidates are also run on its variants (`twin_variants`), and one whose
score on a variant is worse than `FRAGILE_RATIO` x its score on the twin is passed over."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from controller.core.config import LoopConfig
from controller.sim.rig_disturbances import rig_setup
from controller.tune.family import draw_family, identify, true_knowledge
from controller.tune.loop_design import DesignTargets
from controller.tune.plant import SimPlant, plant_for
from controller.tune.whole_loop import (
    FRAGILE_RATIO,
    VARIANT_INERTIA,
    Objective,
    evaluate,
    tune_whole_loop,
    twin_variants,
)

SETUP = rig_setup(("article-rig",))


def test_the_built_in_model_has_no_variants() -> None:
    assert twin_variants(SimPlant.of_setup(SETUP)) == []


@pytest.mark.parametrize("delay", [0, 3])
def test_a_twins_variants_are_its_delay_a_tick_either_way_and_its_inertia(delay: int) -> None:
    base = SimPlant.of_setup(SETUP, source="a twin")
    twin = replace(base, params=replace(base.params, command_delay_ticks=delay))
    got = dict(twin_variants(twin))
    delays = [delay - 1, delay + 1] if delay else [1]
    assert len(got) == len(delays) + 2
    for d in delays:
        v = got[f"delay {d} ticks"]
        assert v.params == replace(twin.params, command_delay_ticks=d)
        assert (v.faults, v.torque, v.source) == (twin.faults, twin.torque, twin.source)
    j = twin.params.load_inertia_kg_m2
    inertias = sorted(v.params.load_inertia_kg_m2 for k, v in got.items() if "inertia" in k)
    assert inertias == pytest.approx([j / VARIANT_INERTIA, j * VARIANT_INERTIA], rel=1e-12)


def test_a_robust_loop_is_not_fragile_on_the_variants() -> None:
    """The starting loop on the article rig taken as a twin: its score moves well within the
    fragility ratio on every variant (the check does not pass over an ordinary loop)."""
    twin = SimPlant.of_setup(SETUP, source="a twin")
    obj = Objective()
    cfg = LoopConfig()
    own = evaluate(cfg, twin, obj, None).score
    assert math.isfinite(own)
    for name, v in twin_variants(twin):
        s = evaluate(cfg, v, obj, None).score
        assert s < FRAGILE_RATIO * own, name


@pytest.mark.slow
@pytest.mark.timeout(1800)  # a hang's bound: 280 s at load 12-14 with two busy loops (35 s
# CPU); over 900 s at load 17-20 (four busy loops and benches beside it)
def test_a_knife_edge_the_twin_ranks_first_is_passed_over() -> None:
    """Family rig 17 of seed 2632146472 (J x0.46, k x0.52, gain x0.65, delay 3): on its twin
    the best candidate was q31 at 3.42 Hz on a 9 Hz speed loop (0.0047 on the twin, 0.0150 on
    the true rig, 4x the brute force). The tune passes such candidates over as fragile, and what
    it proposes instead does better on the TRUE rig than the first one it passed over. Tuned
    at the gate's own peak-sensitivity limit: the default 0.5 dB inside it (for the twin's
    uncertainty) keeps that knife edge from being run at all, as it should."""
    rig = draw_family(2632146472, 18)[17]
    known = identify(rig.plant, LoopConfig())
    twin = plant_for(known, SETUP)
    obj = Objective()
    res = tune_whole_loop(LoopConfig(), known, twin, obj,
                          DesignTargets(sensitivity_inside_db=0.0))
    assert res.best is not None and res.passed_over, "\n".join(res.explanation)
    assert res.best not in res.passed_over
    first = res.passed_over[0]
    assert first.score < res.best.score  # the twin ranked it higher
    # fragile, checked here on the variants independently of the tune's early stop
    worst = max(evaluate(first.config, v, obj, None).score for _, v in twin_variants(twin))
    assert worst > FRAGILE_RATIO * first.score
    text = "\n".join(res.explanation)
    assert "fragile: passed over" in text and "robustness: the twin is an estimate" in text
    # and the true rig agrees: what was proposed instead tracks better there
    truth = true_knowledge(rig.params, rig.faults)
    proposed = evaluate(res.best.config, rig.plant, obj, truth)
    passed = evaluate(first.config, rig.plant, obj, truth)
    assert proposed.verdict == "accept"
    assert proposed.score < passed.score, (proposed.score, passed.score)
