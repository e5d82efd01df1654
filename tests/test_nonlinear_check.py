"""The gate's nonlinear check on the simulated rig: the article's configuration passes, a fast
Q chatters at standstill and is flagged (a caution of the verdict), deterministic."""

from __future__ import annotations

import pytest
from old_loop import OLD_LOOP

from controller.core.config import LoopConfig, NominalModel
from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
from controller.gate.verdict import judge
from controller.sim.nonlinear_check import (
    HUNTING_P2P_DEG,
    OSCILLATION_RMS_DEG_S,
    findings,
    nonlinear_check,
)


def test_the_article_configuration_has_no_finding() -> None:
    r = nonlinear_check(LoopConfig())
    assert r.reasons == ()
    assert r.hold_rms_deg_s < 0.5 * OSCILLATION_RMS_DEG_S
    assert r.hold_error_p2p_deg < 0.75 * HUNTING_P2P_DEG
    assert r.run_time_s < 1.0  # generous: the budget is measured in tests/bench


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


def test_a_finding_is_a_caution_of_the_verdict() -> None:
    k = PlantKnowledge(bound=COMMISSIONING_BOUND)
    j = judge(OLD_LOOP.with_(q_cutoff_hz=4.0), k, nonlinear=findings)  # the earlier loop
    assert j.verdict == "caution"
    assert any(r.startswith("nonlinear check: chatter at standstill") for r in j.cautions)
    assert judge(LoopConfig(), k, nonlinear=findings).verdict == "accept"
