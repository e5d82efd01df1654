"""The gate's nonlinear check on the simulated rig: the article's configuration passes, a fast
Q chatters at standstill and is flagged (a sustained oscillation rejects the candidate,
ringing that decays is a caution), deterministic."""

from __future__ import annotations

import pytest
from fuzz_truth import TruePlant, truth
from old_loop import OLD_LOOP

from controller.core.config import LoopConfig, NominalModel
from controller.gate.analysis import analyse
from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
from controller.gate.verdict import judge
from controller.sim.nonlinear_check import (
    HUNTING_P2P_DEG,
    OSCILLATION_RMS_DEG_S,
    SUSTAINED_RATIO,
    findings,
    nonlinear_check,
)


def test_the_article_configuration_has_no_finding() -> None:
    r = nonlinear_check(LoopConfig())
    assert r.reasons == ()
    assert r.hold_rms_deg_s < 0.5 * OSCILLATION_RMS_DEG_S
    assert r.hold_error_p2p_deg < 0.75 * HUNTING_P2P_DEG
    # Its run time is a benchmark figure (tests/bench/bench_nonlinear_check.py), not a test:
    # a wall-clock limit here failed at load 20.


@pytest.mark.parametrize("q_type", ["q31", "q20"])
def test_a_fast_q_chatters_at_standstill_and_is_flagged(q_type: str) -> None:
    # On the earlier default loop (Cv = 0.5 (1 + 55/s)), where the frequencies below were
    # measured.
    r = nonlinear_check(OLD_LOOP.with_(q_type=q_type, q_cutoff_hz=10.0))
    assert any(x.startswith("chatter at standstill") for x in r.reasons), r
    assert r.hold_rms_deg_s > OSCILLATION_RMS_DEG_S
    # The stick-slip chatter the loop watchdog measures for Q31 at 10 Hz at hold: 3-8 Hz
    # (tests/test_watchdog.py, its own band-pass and zero crossings on a separate run).
    assert r.hold_freq_hz is not None and 3.0 < r.hold_freq_hz < 8.0


def test_deterministic_and_the_plant_gain_follows_the_model() -> None:
    cfg = LoopConfig(q_cutoff_hz=2.0)
    a, b = nonlinear_check(cfg), nonlinear_check(cfg)
    assert (a.hold_rms_deg_s, a.reversal_rms_deg_s) == (b.hold_rms_deg_s, b.reversal_rms_deg_s)
    n = NominalModel()
    x4 = NominalModel(mn_den=n.mn_den, pn_num=(4 * n.pn_num[0], 4 * n.pn_num[1],
                                               4 * n.pn_num[2]), pn_den=n.pn_den)
    stiff = nonlinear_check(LoopConfig(), x4)
    assert stiff.hold_rms_deg_s != a.hold_rms_deg_s
    with pytest.raises(ValueError, match="cfg"):
        nonlinear_check("q31")  # type: ignore[arg-type]
    huge = NominalModel(mn_den=n.mn_den, pn_num=(1e3 * n.pn_num[0], 1e3 * n.pn_num[1],
                                                 1e3 * n.pn_num[2]), pn_den=n.pn_den)
    assert findings(LoopConfig(), n) == ()
    with pytest.raises(ValueError, match="model"):
        nonlinear_check(LoopConfig(), huge)  # 1000x the rig: beyond what it can simulate


#: The speed PI of the procedure's default loop, written out (the defaults may change).
PI_LOOP = LoopConfig(cv_kp=1.35, cv_ki_per_s=10.8, pos_kp_per_s=9.0, pos_ki_per_s=3.5,
                     ff_on=False, dob_on=True)


def test_sustained_chatter_is_a_rejection_of_the_verdict() -> None:
    """Chatter at standstill that does not decay (the earlier loop at Q31 4 Hz: a limit cycle
    the watchdog would roll back) rejects the candidate; the hunting beside it stays a
    caution; the article's configuration on that loop is accepted."""
    k = PlantKnowledge(bound=COMMISSIONING_BOUND)
    cfg = OLD_LOOP.with_(q_cutoff_hz=4.0)
    r = nonlinear_check(cfg)
    chatter = [f for f in r.findings if f.text.startswith("chatter at standstill")]
    assert chatter and chatter[0].sustained and r.hold_decay_ratio >= SUSTAINED_RATIO
    j = judge(cfg, k, nonlinear=findings)
    assert j.verdict == "reject" and not analyse(cfg, k).rejections  # linear analysis: stable
    assert any(x.startswith("nonlinear check: chatter at standstill") and "sustained" in x
               for x in j.rejections), j.rejections
    assert all(not x.startswith("nonlinear check: hunting") for x in j.rejections)
    assert judge(OLD_LOOP, k, nonlinear=findings).verdict == "accept"


def test_ringing_that_decays_stays_a_caution() -> None:
    """Q20 at 30 Hz on the PI loop rings after the reversal (a transient) and is calm at
    hold: a caution, not a rejection."""
    k = PlantKnowledge(bound=COMMISSIONING_BOUND)
    cfg = PI_LOOP.with_(q_type="q20", q_cutoff_hz=30.0)
    r = nonlinear_check(cfg)
    assert [f.sustained for f in r.findings] == [False], r.findings
    assert r.findings[0].text.startswith("ringing after a velocity reversal")
    j = judge(cfg, k, nonlinear=findings)
    assert j.verdict == "caution", j.reasons
    assert any(x.startswith("nonlinear check: ringing after") for x in j.cautions)


def test_a_conditionally_stable_loop_is_named_with_its_gain_reduction_margin() -> None:
    """Issue 22: Q31 at 15 Hz on the earlier loop has a gain margin of -10.8 dB (python-control
    on the independent loop says the same); its verdict (rejected: sustained chatter) names it
    conditionally stable with the 10.8 dB a gain reduction may take."""
    cfg = OLD_LOOP.with_(q_cutoff_hz=15.0)
    t = truth(TruePlant(), cfg)
    assert t.margins_speed is not None
    gm = t.margins_speed.gain_margin_db
    assert gm == pytest.approx(-10.8, abs=0.1)
    j = judge(cfg, PlantKnowledge(bound=COMMISSIONING_BOUND), nonlinear=findings)
    assert j.verdict == "reject"
    cond = [x for x in j.reasons if x.startswith("conditionally stable")]
    assert any(f"gain reduction of {-gm:.1f} dB destabilises the speed loop" in x
               for x in cond), j.reasons
    # An accepted loop carries no such note (the whole servo is conditionally stable by its
    # two integrators; that alone is no reason).
    assert not any("conditionally" in x
                   for x in judge(OLD_LOOP, PlantKnowledge(bound=COMMISSIONING_BOUND)).reasons)
