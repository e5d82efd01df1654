"""The gate judges on all the evidence: the plant model, measured responses, the bound beyond
the measured band. Checked against an independent truth (tests/fuzz_truth.py: the discrete
closed loop built with python-control from the true plant, nothing taken from the gate).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from fuzz_truth import Resonance, TruePlant, continuous_response, sampled_response, truth
from old_loop import OLD_LOOP

from controller.core.config import LoopConfig, NominalModel
from controller.gate.analysis import (
    UNRESOLVED_CHANGE,
    analyse,
    refined_winding_ok,
)
from controller.gate.knowledge import (
    COMMISSIONING_BOUND,
    BoundRecord,
    KnowledgeRecord,
    MeasuredResponse,
    PlantKnowledge,
    WeightBound,
)
from controller.gate.verdict import judge

ARTICLE = NominalModel()
RATE = 1000.0


def _k(*measured: MeasuredResponse) -> PlantKnowledge:
    return PlantKnowledge(measured, COMMISSIONING_BOUND, ARTICLE)


@pytest.mark.parametrize(
    "changes",
    [
        {"cv_ki_per_s": 0.0},
        {"pos_ki_per_s": 0.0},
        {"cv_ki_per_s": 0.0, "pos_ki_per_s": 0.0},
        {"cv_ki_per_s": 0.0, "pos_ki_per_s": 0.0, "dob_on": False},
    ],
)
def test_zero_integral_gains_have_no_spurious_pole(changes: dict[str, object]) -> None:
    cfg = LoopConfig(**changes)  # type: ignore[arg-type]
    t = truth(TruePlant(), cfg)
    a = analyse(cfg, PlantKnowledge(model=ARTICLE))
    assert t.stable
    # (Q31's triple pole near z = 1 makes the eigenvalues sensitive at ~1e-5: cube root.)
    assert a.max_pole_radius == pytest.approx(t.max_pole_radius, abs=1e-4)
    assert a.verdict != "reject", a.reasons


def test_the_candidates_nominal_is_never_evidence() -> None:
    """The same candidate judged on two plant models: the verdict follows the knowledge's
    model, whatever the candidate's nominal claims."""
    n = ARTICLE
    pn = n.pn_num
    big = NominalModel(mn_den=n.mn_den, pn_num=(8 * pn[0], 8 * pn[1], 8 * pn[2]), pn_den=n.pn_den)
    # The earlier default loop (its poles are well conditioned to 1e-6), claiming the plant
    # is 8x: F1 is sized for that.
    cfg = OLD_LOOP.with_(nominal=big)
    on_article = analyse(cfg, PlantKnowledge(model=ARTICLE))
    on_big = analyse(cfg, PlantKnowledge(model=big))
    assert on_article.max_pole_radius == pytest.approx(
        truth(TruePlant(), cfg).max_pole_radius, abs=1e-6
    )
    assert on_big.max_pole_radius == pytest.approx(
        truth(TruePlant(gain=8.0), cfg).max_pole_radius, abs=1e-6
    )
    assert on_article.max_pole_radius != pytest.approx(on_big.max_pole_radius, abs=1e-3)


def test_beyond_the_measured_band_the_gate_asks_to_measure_higher() -> None:
    """A response measured to 5 Hz only: a stiff speed loop (cv_kp 1.2, stable on the true
    plant) has gain where the bound grows; measured to 400 Hz, the same loop is not rejected."""
    cfg = OLD_LOOP.with_(cv_kp=1.2)  # the earlier default loop, stiffer
    assert truth(TruePlant(), cfg).stable
    low = np.geomspace(0.1, 5.0, 18)
    a = analyse(cfg, _k(MeasuredResponse("low", low, continuous_response(TruePlant(), RATE, low))))
    assert a.verdict == "reject"
    why = [r for r in a.rejections if "measure up to" in r]
    assert why, a.rejections
    top = float(why[0].split("measure up to ")[1].split(" Hz")[0])
    assert 5.0 < top <= 500.0
    full = np.geomspace(0.1, 400.0, 120)
    b = analyse(cfg, _k(MeasuredResponse("full", full,
                                         continuous_response(TruePlant(), RATE, full))))
    assert b.verdict != "reject", b.rejections


def test_a_mode_between_measured_points_is_not_interpolated_over() -> None:
    """A sharp resonance at 12 Hz sampled at 10 points per decade: the response changes by
    more than the interpolation can be trusted with between two points; the gate asks for a
    denser measurement where the loop has gain, and the truth shows why."""
    plant = TruePlant(resonance=Resonance(freq_hz=12.0, damping=0.01, zero_ratio=0.7))
    f = np.logspace(-1, math.log10(40.0), 27)
    h = continuous_response(plant, RATE, f)
    change = np.abs(np.diff(np.log(h / continuous_response(TruePlant(), RATE, f))))
    assert np.max(change) > UNRESOLVED_CHANGE  # the points do not resolve the mode
    cfg = LoopConfig(cv_kp=0.9)
    a = analyse(cfg, _k(MeasuredResponse("sparse", f, h)))
    assert a.verdict == "reject"
    assert any("measure denser" in r for r in a.rejections), a.rejections


def test_refined_winding_resolves_a_curve_that_passes_close_to_zero() -> None:
    """D(f) = f - f0 + j eps (a circle-like pass by 0): on a coarse grid the phase steps by
    ~180 deg; the refinement follows it and gets the winding right both ways."""

    def pass_by(eps: float):
        def d(f: np.ndarray) -> np.ndarray:
            x = np.log(f / 3.0)
            # a loop 1 + L that starts with phase -90 (one integrator) and ends at 1
            return (1.0 + 10.0 / (1j * f)) * (x + 1j * eps) / (x + 1j) * (1 + 0j)
        return d

    f = np.geomspace(0.01, 499.0, 50)
    ok_pos = refined_winding_ok(pass_by(+1e-4), f, 1)
    ok_neg = refined_winding_ok(pass_by(-1e-4), f, 1)
    assert ok_pos != ok_neg  # passing above or below 0 is the difference: resolved


def test_dense_measured_responses_match_the_truth_near_the_boundary() -> None:
    """Candidates across the true stability boundary (speed gain swept), judged on the exact
    sampled response: no unstable candidate is accepted, and the comfortably stable ones are."""
    plant = TruePlant(gain=1.2, delay_ticks=1)
    f = np.geomspace(0.01, 0.4999 * RATE, 500)
    m = MeasuredResponse("dense", f, sampled_response(plant, RATE, f), sampled=True)
    k = _k(m)
    seen_unstable = seen_comfy = 0
    for kp in np.geomspace(0.1, 4.0, 24):
        cfg = OLD_LOOP.with_(cv_kp=float(kp))  # Cv's integral 55/s: unstable from kp ~ 2
        t = truth(plant, cfg, margins="if_stable")
        v = analyse(cfg, k).verdict
        if not t.stable:
            seen_unstable += 1
            assert v == "reject", (kp, v)
        elif t.comfortable():
            seen_comfy += 1
            assert v != "reject", (kp, analyse(cfg, k).rejections)
    assert seen_unstable >= 3 and seen_comfy >= 3


def test_knowledge_record_round_trip_and_validation() -> None:
    f = np.geomspace(0.1, 20.0, 10)
    m = MeasuredResponse("p", f, continuous_response(TruePlant(), RATE, f),
                         spread=np.full(10, 0.03))
    k = PlantKnowledge((m,), COMMISSIONING_BOUND, ARTICLE, 5, "test")
    back = KnowledgeRecord.of(k).to_knowledge()
    assert back.version == 5 and back.source == "test"
    assert isinstance(back.bound, WeightBound) and back.bound.unity_freq_hz == 40.0
    np.testing.assert_array_equal(back.measured[0].response, m.response)
    np.testing.assert_array_equal(back.measured[0].spread, m.spread)
    assert analyse(LoopConfig(), back).verdict == analyse(LoopConfig(), k).verdict
    with pytest.raises(ValueError, match="spread"):
        MeasuredResponse("p", f, m.response, spread=np.full(10, -1.0))
    with pytest.raises(ValueError, match="unity_freq_hz"):
        KnowledgeRecord(bound=BoundRecord(low_freq_fraction=0.2)).to_knowledge()
    with pytest.raises(ValueError, match="measured\\[0\\]"):
        KnowledgeRecord(measured=[KnowledgeRecord.of(k).measured[0].__class__(
            name="x", freq_hz=[2.0, 1.0], re=[1.0, 1.0], im=[0.0, 0.0])]).to_knowledge()


def test_verdict_adds_the_recommended_cutoff_caution() -> None:
    k = PlantKnowledge(bound=COMMISSIONING_BOUND)
    j = judge(LoopConfig(), k)
    rec = j.recommended_max_cutoff_hz
    assert j.verdict == "accept" and rec is not None
    above = judge(LoopConfig(q_cutoff_hz=1.2 * rec), k)
    assert above.verdict != "accept"
    assert any("above the recommended maximum" in r for r in above.cautions)
    assert analyse(LoopConfig(q_cutoff_hz=rec), k).verdict == "accept"
