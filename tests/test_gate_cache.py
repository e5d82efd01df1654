"""What the gate caches, and that it answers as if it cached nothing: the recommended
cut-off's search (`RecommendationSearch`: only as far as the verdict needs, the same answers
as the whole search), the nonlinear check per (configuration, model), and the analysis worker's
verdicts per (configuration, plant knowledge). Adversarial: a changed input (the gains at the
same cut-off, the evidence under the same knowledge version) must miss."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import msgspec
import numpy as np
import pytest
from plant_evidence import three_positions

from controller.core.config import LoopConfig, NominalModel
from controller.gate import search
from controller.gate.analysis import analyse
from controller.gate.knowledge import (
    KnowledgeRecord,
    PlantKnowledge,
)
from controller.gate.search import TopSearch, recommendation_search
from controller.gate.verdict import judge
from controller.process.analysis_worker import AnalysisWorker, clear_caches, gate
from controller.sim.nonlinear_check import findings, nonlinear_check

GRID = np.geomspace(0.02, 100.0, 16)


def reference_top(ok: Callable[[float], bool], grid: np.ndarray, rel_tol: float) -> float | None:
    """The recommended cut-off's search written out plainly (the coarse scan from below, the
    first transition bisected in log): what `TopSearch` must answer."""
    if not ok(float(grid[0])):
        return None
    lo, hi = float(grid[0]), None
    for fc in grid[1:]:
        if ok(float(fc)):
            lo = float(fc)
        else:
            hi = float(fc)
            break
    if hi is None:
        return lo
    while hi / lo > 1.0 + rel_tol:
        mid = math.sqrt(lo * hi)
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return lo


def islands(seed: int) -> Callable[[float], bool]:
    """ok() with up to three accepted islands on a log axis: not monotone, so the answer
    depends on the scan order, not only on where ok holds."""
    rng = np.random.default_rng(seed)
    edges = np.sort(rng.uniform(math.log(0.01), math.log(200.0), 2 * rng.integers(1, 4)))
    if rng.random() < 0.7:
        edges[0] = math.log(0.001)  # most often accepted from the lowest cut-off

    def ok(fc: float) -> bool:
        return bool(np.searchsorted(edges, math.log(fc)) % 2 == 1)

    return ok


def test_the_search_answers_as_the_whole_search_evaluating_no_more() -> None:
    for seed in range(300):
        ok = islands(seed)
        calls: list[float] = []

        def counted(fc: float, ok: Callable[[float], bool] = ok,
                    calls: list[float] = calls) -> bool:
            calls.append(fc)
            return ok(fc)

        expected = reference_top(counted, GRID, 0.01)
        whole = list(calls)
        for q in np.geomspace(0.005, 300.0, 25):
            calls.clear()
            s = TopSearch(counted, GRID, 0.01)
            holds = lambda r, q=q: not q > r * 1.0001  # noqa: E731  (the verdict's question)
            got = s.decide(holds)
            assert got == (None if expected is None else holds(expected)), (seed, q)
            # Only what the whole search evaluates, in its order, each point once.
            assert calls == whole[: len(calls)] and len(set(calls)) == len(calls)
            assert s.value() == expected and calls == whole
        assert TopSearch(ok, GRID, 0.01).none() == (expected is None)


def test_coarse_points_judged_together_give_the_same_answers() -> None:
    """`prefetch` (the coarse points a question needs, judged at once by `ok_many`): the
    answers are the whole search's; what is judged together is only coarse points up to the
    first at which the question holds, each once."""
    batched_any = False
    for seed in range(300):
        ok = islands(seed)
        expected = reference_top(ok, GRID, 0.01)
        for q in np.geomspace(0.005, 300.0, 25):
            batches: list[list[float]] = []
            singles: list[float] = []

            def many(fcs: list[float], ok: Callable[[float], bool] = ok,
                     batches: list[list[float]] = batches) -> list[bool]:
                batches.append(list(fcs))
                return [ok(fc) for fc in fcs]

            def one(fc: float, ok: Callable[[float], bool] = ok,
                    singles: list[float] = singles) -> bool:
                singles.append(fc)
                return ok(fc)

            s = TopSearch(one, GRID, 0.01, many)
            holds = lambda r, q=q: not q > r * 1.0001  # noqa: E731
            if s.none():
                assert expected is None
                continue
            s.prefetch(holds)
            got = s.decide(holds)
            assert got == holds(expected), (seed, q)
            assert len(batches) <= 1
            for batch in batches:
                batched_any = True
                needed = [float(g) for g in GRID if not holds(float(g))]
                top = GRID[min(len(needed), GRID.size - 1)]
                assert all(fc in GRID and fc <= top for fc in batch)
                assert not set(batch) & set(singles) and len(set(batch)) == len(batch)
            assert s.value() == expected
    assert batched_any


def test_a_search_shared_by_threads_gives_the_one_answer() -> None:
    for seed in range(40):
        ok = islands(seed)

        def slow(fc: float, ok: Callable[[float], bool] = ok) -> bool:
            time.sleep(0.0002)  # work that lets the other threads step meanwhile
            return ok(fc)

        expected = reference_top(ok, GRID, 0.01)
        s = TopSearch(slow, GRID, 0.01)
        got: list[tuple[object, object]] = []

        def ask(q: float, s: TopSearch = s, got: list[tuple[object, object]] = got) -> None:
            got.append((q, s.decide(lambda r: not q > r * 1.0001)))
            got.append(("value", s.value()))

        qs = [float(q) for q in np.geomspace(0.01, 100.0, 8)]
        threads = [threading.Thread(target=ask, args=(q,)) for q in qs]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for q, answer in got:
            if q == "value":
                assert answer == expected
            else:
                assert isinstance(q, float)
                assert answer == (None if expected is None else not q > expected * 1.0001)


def _reference_recommendation(cfg: LoopConfig, plant: PlantKnowledge) -> float | None:
    """The gate's top cut-off by the plain search (no spread: the test responses agree)."""
    base = cfg.with_(dob_on=True)

    def ok(fc: float) -> bool:
        return analyse(base.with_(q_cutoff_hz=fc), plant).accepted

    return reference_top(ok, np.geomspace(0.02, 0.1 * cfg.rate_hz, 16), 0.01)


def test_the_verdict_searches_only_as_far_as_it_needs_and_is_the_whole_searchs() -> None:
    plant = three_positions()
    base = LoopConfig(cv_kp=0.6, pos_kp_per_s=6.0)
    rec = _reference_recommendation(base, plant)
    assert rec is not None and 0.1 < rec < 2.0
    for fc, caution in ((0.5 * rec, False), (1.5 * rec, True)):
        search._SEARCHES.clear()
        cfg = base.with_(q_cutoff_hz=fc)
        j = judge(cfg, plant, recommendation=False)
        above = [c for c in j.cautions if "above the recommended maximum" in c]
        assert bool(above) == caution, j.cautions
        if caution:
            assert f"{rec:.3g} Hz" in above[0]
        s = recommendation_search(cfg, plant)
        lazy = s.gate.evaluations
        assert s.value() == rec
        if not caution:  # the coarse scan up to the cut-off, not the whole search
            assert lazy < s.gate.evaluations
        assert judge(cfg, plant).recommended_max_cutoff_hz == rec


def test_the_same_cutoff_with_other_gains_searches_again() -> None:
    """Adversarial: the recommendation of one set of gains must not serve another at the
    same cut-off (here the verdict changes: within the first gains' recommendation, above
    the second's)."""
    plant = three_positions()
    a = LoopConfig(cv_kp=0.6, pos_kp_per_s=6.0)
    b = a.with_(cv_kp=0.45)
    rec_a, rec_b = _reference_recommendation(a, plant), _reference_recommendation(b, plant)
    assert rec_a is not None and rec_b is not None and rec_b < 0.5 * rec_a
    fc = 0.8 * rec_a
    ja = judge(a.with_(q_cutoff_hz=fc), plant, recommendation=False)
    jb = judge(b.with_(q_cutoff_hz=fc), plant)
    assert not any("recommended maximum" in c for c in ja.cautions)
    assert any(f"recommended maximum {rec_b:.3g} Hz" in c for c in jb.cautions)
    assert jb.recommended_max_cutoff_hz == rec_b


def test_the_nonlinear_check_cache_misses_on_other_gains_and_another_model() -> None:
    """Q31 at 8 Hz chatters at standstill; half the gain, or a plant of half the gain, does
    not, or otherwise: each is simulated, not served the first one's findings."""
    cfg = LoopConfig(q_cutoff_hz=8.0)
    model = NominalModel()
    p = model.pn_num
    first = findings(cfg, model)
    assert first == nonlinear_check(cfg, model).findings and first
    half_gains = cfg.with_(cv_kp=0.5 * cfg.cv_kp)
    half_plant = msgspec.structs.replace(model, pn_num=(0.5 * p[0], 0.5 * p[1], 0.5 * p[2]))
    for c, m in ((half_gains, model), (cfg, half_plant)):
        got = findings(c, m)
        assert got == nonlinear_check(c, m).findings and got != first
    assert findings(cfg, model) is first  # the same inputs: served from the cache


def test_the_analysis_workers_verdicts_follow_every_input() -> None:
    """The worker's caches (converted knowledge, verdicts) are keyed on the whole record and
    the whole configuration: a record with the same version and source but other evidence,
    other gains at the same cut-off, or the rig's limit must each give the fresh verdict."""
    clear_caches()
    k1 = KnowledgeRecord.of(three_positions())
    # The same version and source, another plant model (half the gain).
    p = k1.model.pn_num
    half = msgspec.structs.replace(k1.model, pn_num=(0.5 * p[0], 0.5 * p[1], 0.5 * p[2]))
    k2 = msgspec.structs.replace(k1, model=half)
    assert (k1.version, k1.source) == (k2.version, k2.source) and k1 != k2
    cfg = LoopConfig(cv_kp=0.6, pos_kp_per_s=6.0, q_cutoff_hz=0.3)
    v1 = gate(cfg, k1)
    v2 = gate(cfg, k2)
    v3 = gate(cfg.with_(cv_kp=0.45), k1)
    clear_caches()
    fresh = [gate(cfg, k1)]
    clear_caches()
    fresh.append(gate(cfg, k2))
    clear_caches()
    fresh.append(gate(cfg.with_(cv_kp=0.45), k1))
    assert [v1, v2, v3] == fresh
    assert v1.margins != v2.margins and v1.reasons != v3.reasons
    # The rig's limit is checked before any cached verdict.
    runner = AnalysisWorker(subprocess=False, command_limit_max_deg_s=0.5 * cfg.command_limit_deg_s)
    assert not runner.check(cfg, k1).applicable


def test_a_repeated_candidate_is_not_judged_again(monkeypatch: pytest.MonkeyPatch) -> None:
    import controller.gate.verdict as verdict_module

    clear_caches()
    k = KnowledgeRecord.of(three_positions())
    cfg = LoopConfig(cv_kp=0.6, pos_kp_per_s=6.0, q_cutoff_hz=0.25)
    calls: list[object] = []
    real = verdict_module.analyse

    def counted(c: LoopConfig, *a: object, **kw: object) -> object:
        calls.append(c)
        return real(c, *a, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(verdict_module, "analyse", counted)
    first = gate(cfg, k)
    assert calls == [cfg]
    assert gate(cfg, KnowledgeRecord.of(three_positions())) == first  # an equal record
    assert calls == [cfg]
