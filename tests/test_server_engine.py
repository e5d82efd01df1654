"""The tuning engine (pure computation): verdicts and chart data of a candidate against the
active configuration, the recommended cut-off, the 12.6 s preview within 200 ms, measured
responses changing the verdict."""

from __future__ import annotations

import math
from typing import Any

import msgspec
import numpy as np
import pytest

from controller.core.config import LoopConfig, NominalModel
from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import MeasuredResponse
from controller.gate.loop_model import nominal_continuous_response
from server import charts
from server.engine import TuningEngine


def test_preview_of_one_sine_period() -> None:
    """The preview's time figure is a benchmark (tests/bench/bench_dashboard.py), not a limit
    here: a unit test on a loaded machine would measure the load."""
    eng = TuningEngine()
    cfg = LoopConfig()
    traj = Trajectory()
    eng.preview(cfg.with_(q_cutoff_hz=0.3), traj)  # warm-up (numba compile)
    res = eng.preview(cfg, traj)
    assert abs(res.t_s[-1] - 4 * math.pi) < 0.01
    assert res.elapsed_s > 0.0
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
    x, cand, act, off = p.chart_data
    assert len(x) == len(cand) == len(act) == len(off) <= 1500
    assert p.candidate.config.dob_on is False and p.active.config == active
    assert p.no_dob is not None and p.no_dob.config.dob_on is False


def test_preview_runs_the_rigs_disturbances_and_the_dob_off_beside() -> None:
    """With the demo's disturbances: the candidate's preview and its DOB-off run are the runs
    the autotune makes (same numbers, command noise included); the DOB-off run is one cached
    run whatever the candidate's cut-off; the rig's disturbances change the numbers."""
    from controller.sim.rig_disturbances import rig_setup
    from controller.tune.autotune import command_noise_deg_s, run_point

    traj = Trajectory()
    eng = TuningEngine(sim_disturbances=("drive-offset",))
    base = LoopConfig().with_(cv_kp=1.0, cv_ki_per_s=10.0)
    cand = base.with_(q_type="q20", q_cutoff_hz=6.0)
    p = eng.compare_preview(cand, base, traj)
    assert p.no_dob is not None and p.candidate.disturbances == "drive-offset"
    setup = rig_setup(["drive-offset"])
    for shown, cfg in ((p.candidate, cand), (p.no_dob, base.with_(dob_on=False))):
        r = run_point(cfg, traj, eng.preview_run_s(traj), setup=setup)
        assert shown.rmse_deg == r.rmse_deg and shown.peak_error_deg == r.peak_error_deg
        assert shown.command_noise_deg_s == command_noise_deg_s(r.command_deg_s, 1000.0)
    assert p.candidate.command_noise_deg_s > p.no_dob.command_noise_deg_s  # the DOB's price
    again = eng.compare_preview(cand.with_(q_cutoff_hz=2.0), base, traj)
    assert again.no_dob is p.no_dob
    plain = TuningEngine().preview(base.with_(dob_on=False), traj)
    assert plain.rmse_deg != p.no_dob.rmse_deg and plain.disturbances == "none"
    with pytest.raises(ConfigError, match="disturbance"):
        TuningEngine(sim_disturbances=("no-such",))


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
    assert np.isfinite(ev.verdict.margins.small_gain_peak)
    assert len(eng.measured) == 1
    assert "1 measured response(s) 0.1-20 Hz" in ev.verdict.knowledge


@pytest.mark.slow
def test_the_dashboard_verdict_is_the_controllers() -> None:
    """The dashboard's verdict equals the controller's gate (`analysis_worker.gate`, what the
    controller runs before applying) on the same plant knowledge, for random candidates."""
    from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord, PlantKnowledge
    from controller.process.analysis_worker import gate

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
        mine = eng.evaluate(cfg).verdict
        theirs = gate(cfg, record)
        assert mine.verdict == theirs.verdict, cfg
        assert mine.reasons == theirs.reasons, cfg
        # The whole verdict, margins included, bit for bit (NaN == NaN).
        np.testing.assert_equal(msgspec.to_builtins(mine), msgspec.to_builtins(theirs))
        seen[mine.verdict] += 1
    assert min(seen.values()) > 0, seen  # all three verdicts were exercised


def test_sensitivity_chart_matches_the_gates_margins() -> None:
    """The S and T curves drawn: their peaks are the gate's peak sensitivities (speed loop and
    whole servo, refined by the gate between grid points: the grid peak is at most 0.3 dB
    below), and |S| <= 1 + |T| everywhere (S + T = 1: the triangle inequality)."""
    import pytest

    from controller.gate.analysis import analyse
    from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge

    eng = TuningEngine()
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

    def racing(cfg: LoopConfig, gen: int, plant: Any) -> Any:
        eng.set_knowledge(record)  # the fetch lands while this evaluation runs
        return original(cfg, gen, plant)

    eng._evaluate = racing  # type: ignore[method-assign]
    first = eng.evaluate(LoopConfig())
    assert "not yet fetched" in first.verdict.knowledge  # judged on what it started with
    eng._evaluate = original  # type: ignore[method-assign]
    second = eng.evaluate(LoopConfig())
    assert "not yet fetched" not in second.verdict.knowledge
    assert "1 measured response(s)" in second.verdict.knowledge


# -- the Nyquist view's loops -------------------------------------------------------------------


def _reference_loop(cfg: LoopConfig, dob: bool) -> Any:
    """The speed loop at the plant input as python-control builds it from the tick's
    equations (tests/fuzz_truth.py: nothing taken from the gate), the plant = the model."""
    import fuzz_truth

    l_speed, _ = fuzz_truth.open_loops(fuzz_truth.TruePlant(), cfg.with_(dob_on=dob))
    return l_speed


NODOB_CASES = [
    LoopConfig(),
    LoopConfig(cv_kp=1.2, pos_kp_per_s=20.0, q_cutoff_hz=3.0, dob_on=False),
    LoopConfig(cv_kp=0.3, cv_ki_per_s=20.0, q_type="q20", q_cutoff_hz=0.3),
]


@pytest.mark.parametrize("cfg", NODOB_CASES, ids=["default", "stiff-dob-off", "soft-q20"])
def test_speed_loop_without_dob_is_python_controls_discrete_loop(cfg: LoopConfig) -> None:
    """The without-DOB L (G Cv, the implemented discrete loop: ZOH plant with the
    backward-difference rate, Tustin PI) equals python-control's state-space loop to a
    relative 1e-9 on the chart grid, whatever the candidate's DOB switch; its margins equal
    control.stability_margins on that loop (PM 1e-4 deg, GM 1e-4 dB, crossovers 1e-6
    relative); and it is the loop behind the analysis' eq. 18 (T = L / (1 + L))."""
    import control

    from controller.gate.analysis import analyse

    eng = TuningEngine()
    c = eng.evaluate(cfg).curves
    nl = c.nyquist_nodob
    assert nl is not None
    ref = _reference_loop(cfg, dob=False)
    import fuzz_truth

    np.testing.assert_allclose(nl.response, fuzz_truth.frequency_response(ref, c.freq_hz),
                               rtol=1e-9)
    # "frd": python-control's exact response on its own grid, crossings refined there
    # ("best" says its polynomial method may be inaccurate here, and falls back to this).
    gm, pm, _sm, wpc, wgc, _wms = control.stability_margins(ref, method="frd")
    assert nl.phase_margin_deg == pytest.approx(pm, abs=1e-4)
    assert nl.gain_margin_db == pytest.approx(20 * np.log10(gm), abs=1e-4)
    w = 2 * np.pi
    assert float(nl.gain_crossover_hz[np.argmin(np.abs(nl.gain_crossover_hz - wgc / w))]) == (
        pytest.approx(wgc / w, rel=1e-6))
    assert float(nl.phase_crossover_hz[np.argmin(np.abs(nl.phase_crossover_hz - wpc / w))]) == (
        pytest.approx(wpc / w, rel=1e-6))
    np.testing.assert_allclose(np.abs(nl.gain_crossings), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.angle(-nl.phase_crossings), 0.0, atol=1e-6)
    a = analyse(cfg, eng.plant, freq_hz=c.freq_hz)
    np.testing.assert_allclose(nl.response / (1 + nl.response), a.closed_loop_no_dob, rtol=1e-9)


def test_speed_loop_with_dob_is_the_gates_loop_and_margins() -> None:
    """The with-DOB L equals the gate's L of a DOB-on candidate (the analysis on the gate's
    grid, thinned for the charts; python-control's loop, 1e-6: the DOB's poles near z = 1 cost
    digits) and carries the gate's margins; a DOB-off candidate still gets the with-DOB loop
    its DOB would give, with the same margins (computed apart: `speed_loop`)."""
    import fuzz_truth

    from controller.gate.analysis import analyse
    from server.engine import chart_index

    eng = TuningEngine()
    cfg = LoopConfig(q_cutoff_hz=2.0)
    c = eng.evaluate(cfg).curves
    a = analyse(cfg, eng.plant)
    idx = chart_index(a.freq_hz.size)
    np.testing.assert_array_equal(c.freq_hz, a.freq_hz[idx])
    assert c.nyquist_dob is not None
    np.testing.assert_allclose(c.nyquist_dob.response, a.open_loop[idx], rtol=1e-12)
    ref = fuzz_truth.frequency_response(_reference_loop(cfg, dob=True), c.freq_hz)
    np.testing.assert_allclose(c.nyquist_dob.response, ref, rtol=1e-6)
    assert c.nyquist_dob.phase_margin_deg == pytest.approx(a.phase_margin_deg, abs=1e-9)
    assert c.nyquist_dob.gain_margin_db == pytest.approx(a.gain_margin_db, abs=1e-9)
    off = eng.evaluate(cfg.with_(dob_on=False)).curves
    assert off.nyquist_dob is not None and off.nyquist_nodob is not None
    np.testing.assert_allclose(off.nyquist_dob.response, c.nyquist_dob.response, rtol=1e-12)
    assert off.nyquist_dob.phase_margin_deg == pytest.approx(a.phase_margin_deg, abs=1e-9)
    assert off.nyquist_dob.gain_margin_db == pytest.approx(a.gain_margin_db, abs=1e-9)
    np.testing.assert_allclose(off.nyquist_dob.gain_crossover_hz,
                               c.nyquist_dob.gain_crossover_hz, rtol=1e-12)
    a_off = analyse(cfg.with_(dob_on=False), eng.plant)
    np.testing.assert_allclose(off.nyquist_nodob.response, a_off.open_loop[idx], rtol=1e-12)
    assert off.nyquist_nodob.phase_margin_deg == pytest.approx(a_off.phase_margin_deg, abs=1e-9)
    # The DOB-on candidate's loop without the DOB (cached across cut-offs) is the same.
    assert c.nyquist_nodob is not None
    np.testing.assert_allclose(c.nyquist_nodob.response, a_off.open_loop[idx], rtol=1e-12)
    assert c.nyquist_nodob.phase_margin_deg == pytest.approx(a_off.phase_margin_deg, abs=1e-9)


# -- one analysis per candidate ------------------------------------------------------------------

ONE_PASS_CASES = [
    LoopConfig(q_cutoff_hz=0.5),
    LoopConfig(q_cutoff_hz=4.0),
    LoopConfig(cv_kp=0.3, cv_ki_per_s=20.0, q_type="q20", q_cutoff_hz=0.3),
]


@pytest.mark.parametrize("cfg", ONE_PASS_CASES, ids=["q31-0.5", "q31-4", "soft-q20-0.3"])
def test_the_one_analysis_gives_python_controls_margins(cfg: LoopConfig) -> None:
    """The dashboard's single pass (one analysis: verdict box, charts, Nyquist view) against
    an independent reference: python-control's state-space loop built from the tick's
    equations, its margins with control.stability_margins' selection rules bisected on its
    exact response (tests/fuzz_truth.py `loop_margins`, checked against stability_margins in
    tests/test_fuzz_truth.py). PM 1e-3 deg, GM 1e-3 dB, peak sensitivity 1e-3 dB (the DOB's
    poles near z = 1 cost digits: 1e-6 relative on the loop); the verdict box, the Nyquist
    view and the open-loop chart say the same."""
    import fuzz_truth

    eng = TuningEngine()
    ev = eng.evaluate(cfg)
    ref = _reference_loop(cfg, dob=True)
    r = fuzz_truth.loop_margins(ref)
    m = ev.verdict.margins
    assert m.phase_margin_deg == pytest.approx(r.phase_margin_deg, abs=1e-3)
    assert m.gain_margin_db == pytest.approx(r.gain_margin_db, abs=1e-3)
    assert m.peak_sensitivity_db == pytest.approx(-20 * np.log10(r.stability_margin), abs=1e-3)
    nq = ev.curves.nyquist_dob
    assert nq is not None
    assert (nq.phase_margin_deg, nq.gain_margin_db) == (m.phase_margin_deg, m.gain_margin_db)

    np.testing.assert_allclose(
        ev.curves.open_loop_db,
        20 * np.log10(np.abs(fuzz_truth.frequency_response(ref, ev.curves.freq_hz))),
        atol=1e-4)


def test_moving_the_cutoff_reuses_only_what_does_not_depend_on_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Incremental work: with the DOB on, a new cut-off computes the loop without the DOB and
    the plant chart no more (cached); what is reused equals a fresh computation for the new
    cut-off (nothing stale), and new gains compute it again (they change it)."""
    import server.engine as engine_module
    from server.engine import plant_curves, speed_loop

    moved = LoopConfig(q_cutoff_hz=3.0)
    f = TuningEngine().evaluate(moved).curves  # fresh: computed for this cut-off alone
    eng = TuningEngine()
    calls: list[bool] = []
    real = engine_module.speed_loop

    def counted(cfg: LoopConfig, *a: Any, dob: bool) -> Any:
        calls.append(dob)
        return real(cfg, *a, dob=dob)

    monkeypatch.setattr(engine_module, "speed_loop", counted)
    first = eng.evaluate(LoopConfig(q_cutoff_hz=0.5)).curves
    assert calls == [False]
    c = eng.evaluate(moved).curves
    assert calls == [False]  # nothing recomputed for the cut-off
    assert c.nyquist_nodob is not None and first.nyquist_nodob is not None
    assert f.nyquist_nodob is not None and f.plant is not None and c.plant is not None
    np.testing.assert_array_equal(c.nyquist_nodob.response, f.nyquist_nodob.response)
    assert c.nyquist_nodob.phase_margin_deg == f.nyquist_nodob.phase_margin_deg
    np.testing.assert_array_equal(c.plant.model_db,
                                  plant_curves(eng.plant, c.freq_hz, 1000.0).model_db)
    np.testing.assert_array_equal(c.plant.model_db, f.plant.model_db)
    # The with-DOB loop does follow the cut-off.
    assert c.nyquist_dob is not None and first.nyquist_dob is not None
    assert not np.allclose(c.nyquist_dob.response, first.nyquist_dob.response)
    stiff = eng.evaluate(moved.with_(cv_kp=0.9)).curves
    assert calls == [False, False]
    assert stiff.nyquist_nodob is not None
    expect = speed_loop(moved.with_(cv_kp=0.9), eng.plant.model, eng.evaluate(moved).curves
                        .freq_hz, dob=False)
    np.testing.assert_allclose(stiff.nyquist_nodob.response, expect.response, rtol=1e-12)


# -- the plant chart ----------------------------------------------------------------------------


def _model_db(f: np.ndarray) -> np.ndarray:
    """20 log10 |M P| by scipy (independent of the gate's polyval)."""
    from scipy import signal

    nm = NominalModel()
    _, h = signal.freqs(nm.pn_num, np.polymul(nm.mn_den, nm.pn_den), worN=2 * np.pi * f)
    return np.asarray(20 * np.log10(np.abs(h)))


def _plant_chart(eng: TuningEngine) -> dict[str, np.ndarray]:
    spec = {s.key: s for s in charts.BODE_CHARTS}["plant"]
    data = eng.compare(LoopConfig(q_cutoff_hz=2.0), LoopConfig()).chart_data["plant"]
    assert len(data) == len(spec.series) == 7 + charts.PLANT_POSITIONS + 2
    assert all(d.shape == data[0].shape for d in data)
    return {"f": data[0], **{c.split(".")[1]: d for c, d in zip(spec.columns, data[1:],
                                                                 strict=True)}}


def test_plant_chart_draws_measured_spread_over_the_model() -> None:
    """With a measured response: the model |M P| (scipy), the measured points at their
    frequencies (20 log10 |H|, nothing between), the band 20 log10(|H| (1 +- spread))
    computed here (the lower edge at most 20 dB below |H|), the phase near the model's;
    a column of something not measured (a second position, the spread between positions) is
    NaN throughout, no stand-in value; the band's edges are the series after the measured
    points."""
    f_m = np.geomspace(0.2, 30.0, 25)
    h = 1.2 * nominal_continuous_response(NominalModel(), f_m) * np.exp(-2j * np.pi * f_m * 2e-3)
    spread = np.linspace(0.0, 1.5, f_m.size)  # up to beyond 1: the lower edge is clipped
    eng = TuningEngine()
    eng.set_knowledge(eng.with_measured(MeasuredResponse("pos0", f_m, h, spread=spread)))
    d = _plant_chart(eng)
    f = d["f"]
    assert f[0] == f_m[0]
    drawn = ("model_db", "measured_db", "upper_db", "lower_db", "model_phase_deg",
             "measured_phase_deg", "pos1_db")
    assert all(np.isfinite(d[k][0]) for k in drawn)
    assert all(np.isnan(d[k]).all() for k in ("pos2_db", "pos3_db", "pos4_db", "spread_db"))
    np.testing.assert_allclose(d["model_db"], _model_db(f), atol=1e-9)
    at = np.isin(f, f_m)
    assert at.sum() == f_m.size
    assert np.isnan(d["measured_db"][~at]).all() and np.isnan(d["upper_db"][~at]).all()
    mag = np.abs(h)
    np.testing.assert_allclose(d["measured_db"][at], 20 * np.log10(mag), rtol=1e-12)
    np.testing.assert_allclose(d["upper_db"][at], 20 * np.log10(mag * (1 + spread)), rtol=1e-12)
    exact = spread < 0.9
    np.testing.assert_allclose(d["lower_db"][at][exact],
                               20 * np.log10(mag[exact] * (1 - spread[exact])), rtol=1e-12)
    np.testing.assert_allclose(d["lower_db"][at][~exact], 20 * np.log10(mag[~exact]) - 20.0,
                               rtol=1e-12)
    phase_ref = np.degrees(np.angle(h / nominal_continuous_response(NominalModel(), f_m)))
    np.testing.assert_allclose(d["measured_phase_deg"][at] - d["model_phase_deg"][at],
                               phase_ref, atol=1e-9)
    spec = {s.key: s for s in charts.BODE_CHARTS}["plant"]
    labels = [s["label"] for s in spec.series[2:5]]
    assert labels == ["|H| measured", "|H| (1 + spread)", "|H| (1 - spread)"]
    assert np.all(d["lower_db"][at] <= d["measured_db"][at])
    assert np.all(d["measured_db"][at] <= d["upper_db"][at])


def test_plant_chart_with_several_responses_shows_their_envelope() -> None:
    """Two responses at the same frequencies: the points are their mean in dB, the band the
    envelope of both bands."""
    f_m = np.geomspace(0.5, 10.0, 8)
    g = nominal_continuous_response(NominalModel(), f_m)
    eng = TuningEngine()
    eng.set_knowledge(eng.with_measured(MeasuredResponse("a", f_m, 0.9 * g,
                                                         spread=np.full(8, 0.1))))
    eng.set_knowledge(eng.with_measured(MeasuredResponse("b", f_m, 1.3 * g)))
    d = _plant_chart(eng)
    at = np.isin(d["f"], f_m)
    m = 20 * np.log10(np.abs(g))
    np.testing.assert_allclose(d["measured_db"][at], m + 10 * np.log10(0.9 * 1.3), atol=1e-9)
    np.testing.assert_allclose(d["upper_db"][at], m + 20 * np.log10(1.3), atol=1e-9)
    np.testing.assert_allclose(d["lower_db"][at], m + 20 * np.log10(0.9 * 0.9), atol=1e-9)


def test_plant_chart_without_measured_responses_still_draws() -> None:
    """No measured response: the model over the whole chart grid, the measured columns
    empty (NaN throughout: no stand-in first value; the chart's y scales are fixed from the
    finite values, so the model is drawn on a finite scale)."""
    eng = TuningEngine()
    d = _plant_chart(eng)
    np.testing.assert_array_equal(d["f"], eng.freq_hz)
    np.testing.assert_allclose(d["model_db"], _model_db(d["f"]), atol=1e-9)
    for name in ("measured_db", "upper_db", "lower_db", "measured_phase_deg", "pos1_db",
                 "spread_db", "divergence_marks"):
        assert np.isnan(d[name]).all(), name
    spec = {s.key: s for s in charts.BODE_CHARTS}["plant"]
    data = (d["f"], *(d[c.split(".")[1]] for c in spec.columns))
    scales = charts.ranged_scales(spec, data, charts.Y_STEPS)
    lo, hi = scales["y"]["range"]
    assert lo <= d["model_db"].min() and d["model_db"].max() <= hi
    assert np.isfinite(scales["deg"]["range"]).all()


def test_plant_chart_draws_a_sampled_response_in_the_continuous_basis() -> None:
    """A sampled response (u[k] -> w[k]: the exact sampled model here, from the gate's ZOH
    discretisation) is drawn in the model's continuous basis: the ZOH + backward-difference
    factor divided out, it lies on M P within 0.01 dB and 0.01 deg up to 100 Hz (raw it is
    0.28 dB and 36 deg off there)."""
    from controller.gate.knowledge import PlantKnowledge
    from controller.gate.loop_model import discrete_plant, plant_response
    from server.engine import freq_grid_hz, plant_curves

    f = np.geomspace(0.1, 100.0, 30)
    h = plant_response(discrete_plant(NominalModel(), 1000.0), np.exp(-2j * np.pi * f / 1000.0))
    pc = plant_curves(PlantKnowledge((MeasuredResponse("s", f, h, sampled=True),)),
                      freq_grid_hz(), 1000.0)
    at = np.isin(pc.freq_hz, f)
    assert at.sum() == f.size
    np.testing.assert_allclose(pc.measured_db[at], _model_db(f), atol=0.01)
    np.testing.assert_allclose(pc.measured_phase_deg[at], pc.model_phase_deg[at], atol=0.01)
    assert np.max(np.abs(20 * np.log10(np.abs(h)) - _model_db(f))) > 0.2  # the test can fail


def test_plant_chart_shows_each_position_their_spread_and_where_they_diverge() -> None:
    """Three responses (a belt mode at 4.9, 7 and 9.1 Hz): each drawn at its points as
    20 log10 |H| (computed here), the spread between them (max - min dB, here) and a vertical
    mark at the frequency where they part by more than 1 dB, the position spread's own."""
    from controller.gate.knowledge import position_spread

    f_m = np.geomspace(0.1, 20.0, 30)

    def mode(fn: float) -> np.ndarray:
        wn, s = 2 * np.pi * fn, 2j * np.pi * f_m
        return wn * wn / (s * s + 1.414 * wn * s + wn * wn)

    hs = [mode(7.0 * k) for k in (0.7, 1.0, 1.3)]
    eng = TuningEngine()
    for i, h in enumerate(hs, start=1):
        eng.set_knowledge(eng.with_measured(MeasuredResponse(f"pos{i}", f_m, h)))
    d = _plant_chart(eng)
    at = np.isin(d["f"], f_m)
    mags = np.array([20 * np.log10(np.abs(h)) for h in hs])
    for i in range(3):
        np.testing.assert_allclose(d[f"pos{i + 1}_db"][at], mags[i], rtol=1e-12)
        assert np.isnan(d[f"pos{i + 1}_db"][~at]).all()
    assert np.isnan(d["pos4_db"][1:]).all()
    np.testing.assert_allclose(d["spread_db"][at], mags.max(0) - mags.min(0), atol=1e-9)
    sp = position_spread(tuple(eng.plant.measured))
    assert sp is not None and sp.divergence_hz is not None and 1.0 < sp.divergence_hz < 3.0
    marks = np.flatnonzero(np.isfinite(d["divergence_marks"]))
    assert marks.size == 2 and d["f"][marks[0]] <= sp.divergence_hz <= d["f"][marks[1]]


def test_the_preview_runs_on_the_twin_of_what_was_measured() -> None:
    """Issue 35 item 2: with measured responses (here of a rig with twice the drive gain) the
    preview and its DOB-off run are the twin's (`plant_for`, as Suggest's), not the built-in
    model's; with nothing measured the preview says it ran on the built-in model."""
    from controller.gate.knowledge import KnowledgeRecord
    from controller.sim.rig_disturbances import rig_setup
    from controller.sim.sim_rig import RigFaults, RigParams
    from controller.tune.autotune import run_point
    from controller.tune.family import true_knowledge
    from controller.tune.plant import BUILT_IN, plant_for

    cfg = LoopConfig()
    traj = Trajectory(kind="sine", omega_rad_s=2.0)
    e = TuningEngine(sim_disturbances=("article-rig",))
    before = e.compare_preview(cfg, cfg, traj)
    assert before.candidate.plant_source == BUILT_IN
    measured = true_knowledge(RigParams(), RigFaults(plant_gain=2.0))
    e.set_knowledge(KnowledgeRecord.of(measured))
    after = e.compare_preview(cfg, cfg, traj)
    assert after.candidate.plant_source.startswith("rig's twin")
    twin = plant_for(measured, rig_setup(("article-rig",)))
    run = run_point(cfg, traj, e.preview_run_s(traj), plant=twin)
    assert after.candidate.rmse_deg == pytest.approx(run.rmse_deg, rel=1e-12)
    off = run_point(cfg.with_(dob_on=False), traj, e.preview_run_s(traj), plant=twin)
    assert after.no_dob is not None
    assert after.no_dob.rmse_deg == pytest.approx(off.rmse_deg, rel=1e-12)
    assert after.candidate.rmse_deg != pytest.approx(before.candidate.rmse_deg, rel=0.01)
