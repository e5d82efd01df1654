"""The tuning engine (pure computation): verdicts and chart data of a candidate against the
active configuration, the recommended cut-off, the 12.6 s preview within 200 ms, measured
responses changing the verdict."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from controller.core.config import LoopConfig, NominalModel
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import MeasuredResponse
from controller.gate.loop_model import nominal_continuous_response
from server import charts
from server.engine import TuningEngine


def test_preview_of_one_sine_period_within_200_ms() -> None:
    eng = TuningEngine()
    cfg = LoopConfig()
    traj = Trajectory()
    eng.preview(cfg.with_(q_cutoff_hz=0.3), traj)  # warm-up (numba compile)
    res = eng.preview(cfg, traj)
    print(f"preview 12.6 s sine: {res.elapsed_s * 1e3:.0f} ms, peak {res.peak_error_deg:.4f}")
    assert abs(res.t_s[-1] - 4 * math.pi) < 0.01
    assert res.elapsed_s <= 0.2
    assert 0.0 < res.rmse_deg < res.peak_error_deg


def test_compare_gives_every_bode_chart_its_data() -> None:
    eng = TuningEngine()
    active = LoopConfig()
    cmp = eng.compare(active.with_(q_cutoff_hz=2.0), active)
    assert cmp.candidate.config.q_cutoff_hz == 2.0 and cmp.active.config == active
    assert set(cmp.chart_data) == {spec.key for spec in charts.BODE_CHARTS}
    for spec in charts.BODE_CHARTS:
        assert len(cmp.chart_data[spec.key]) == len(spec.series)
    # The candidate's |Q| and the active one's differ; the evaluation is cached.
    _, q_cand, q_act, _, _ = cmp.chart_data["small_gain"]
    assert not np.allclose(q_cand, q_act)
    assert eng.evaluate(active) is cmp.active


def test_compare_preview_draws_both_runs() -> None:
    eng = TuningEngine()
    active = LoopConfig()
    p = eng.compare_preview(active.with_(dob_on=False), active, Trajectory())
    x, cand, act = p.chart_data
    assert len(x) == len(cand) == len(act) <= 1500
    assert p.candidate.config.dob_on is False and p.active.config == active


def test_recommendation_is_cached_per_gains() -> None:
    eng = TuningEngine()
    cfg = LoopConfig()
    assert eng.cached_recommendation(cfg) == (False, None)
    rec = eng.recommended_max_cutoff_hz(cfg)
    assert rec is not None and rec > 0.0
    # The cut-off and the DOB switch do not change the recommendation's key.
    assert eng.cached_recommendation(cfg.with_(q_cutoff_hz=3.0, dob_on=False)) == (True, rec)


def test_measured_response_enters_the_verdict() -> None:
    eng = TuningEngine()
    cfg = LoopConfig()
    assert eng.evaluate(cfg).curves.inv_delta_measured_db is None
    f = np.geomspace(0.1, 20, 40)
    response = 1.1 * nominal_continuous_response(NominalModel(), f)
    eng.set_knowledge(eng.with_measured(MeasuredResponse(name="m", freq_hz=f, response=response)))
    ev = eng.evaluate(cfg)
    assert ev.curves.inv_delta_measured_db is not None
    assert np.isfinite(ev.gate.margins["small_gain_peak"])
    assert len(eng.measured) == 1
    assert "1 measured response(s) 0.1-20 Hz" in ev.gate.knowledge


def test_the_dashboard_verdict_is_the_controllers() -> None:
    """The dashboard's verdict equals the controller's gate (`gate_worker.gate`, what the
    controller runs before applying) on the same plant knowledge, for random candidates."""
    from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord, PlantKnowledge
    from controller.process.gate_worker import gate

    f = np.geomspace(0.1, 20, 31)
    h = 1.3 * nominal_continuous_response(NominalModel(), f) * np.exp(-2j * np.pi * f * 0.002)
    record = KnowledgeRecord.of(PlantKnowledge(
        (MeasuredResponse("pos0", f, h),), COMMISSIONING_BOUND, version=4, source="test"))
    eng = TuningEngine()
    eng.set_knowledge(record)
    rng = np.random.default_rng(7)
    bases = [LoopConfig(cv_kp=kp, pos_kp_per_s=pk) for kp, pk in
             ((0.3, 5.0), (0.5, 9.0), (0.8, 15.0), (1.2, 20.0), (0.45, 0.0 + 3.0))]
    seen = {"accept": 0, "caution": 0, "reject": 0}
    for _ in range(200):
        base = bases[int(rng.integers(len(bases)))]
        cfg = base.with_(
            q_type=str(rng.choice(["q20", "q31"])),
            q_cutoff_hz=float(np.exp(rng.uniform(np.log(0.05), np.log(50.0)))),
            dob_on=bool(rng.uniform() < 0.85),
        )
        mine = eng.evaluate(cfg).gate
        theirs = gate(cfg, record)
        assert mine.verdict == theirs.verdict, cfg
        assert mine.reasons == theirs.reasons or mine.verdict == "accept"
        seen[mine.verdict] += 1
    assert min(seen.values()) > 0, seen  # all three verdicts were exercised


def test_sensitivity_chart_matches_the_gates_margins() -> None:
    """The S and T curves drawn: their peaks are the gate's peak sensitivities (speed loop and
    whole servo, refined by the gate between grid points: the grid peak is at most 0.3 dB
    below), and |S| <= 1 + |T| everywhere (S + T = 1: the triangle inequality)."""
    import pytest

    from controller.gate.analysis import analyse
    from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge

    eng = TuningEngine(n_freq=2000)
    cfg = LoopConfig(q_cutoff_hz=2.0)
    c = eng.evaluate(cfg).curves
    a = analyse(cfg, PlantKnowledge(bound=COMMISSIONING_BOUND))
    assert c.s_db is not None and c.s_full_db is not None and c.t_db is not None
    assert np.max(c.s_db) == pytest.approx(a.margins.peak_sensitivity_db, abs=0.3)
    assert a.margins_full is not None
    assert np.max(c.s_full_db) == pytest.approx(a.margins_full.peak_sensitivity_db, abs=0.3)
    lin = 10 ** (np.asarray(c.s_db) / 20)
    assert np.all(lin <= 1.0 + 10 ** (np.asarray(c.t_db) / 20) + 1e-9)


def test_a_verdict_computed_while_new_knowledge_arrives_is_not_served_for_it() -> None:
    """The knowledge fetch can land while the slider's evaluation runs on the old plant: that
    result must not be cached for the new plant (it was: the dashboard then showed
    "judged on plant knowledge v0 (not yet fetched)" for good)."""
    from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord, PlantKnowledge

    f = np.geomspace(0.1, 20, 31)
    h = nominal_continuous_response(NominalModel(), f)
    record = KnowledgeRecord.of(PlantKnowledge(
        (MeasuredResponse("pos0", f, h),), COMMISSIONING_BOUND, version=3, source="fetched"))
    eng = TuningEngine()
    original = eng._evaluate

    def racing(cfg: LoopConfig, plant: Any) -> Any:
        eng.set_knowledge(record)  # the fetch lands while this evaluation runs
        return original(cfg, plant)

    eng._evaluate = racing  # type: ignore[method-assign]
    first = eng.evaluate(LoopConfig())
    assert "not yet fetched" in first.gate.knowledge  # judged on what it started with
    eng._evaluate = original  # type: ignore[method-assign]
    second = eng.evaluate(LoopConfig())
    assert "not yet fetched" not in second.gate.knowledge
    assert "1 measured response(s)" in second.gate.knowledge
