"""The analysis refines every piece of evidence's crossings and peaks together (one `solve`
for the plant model and every measured response): each task must come out as refining it
alone does. Checked against the refinement written out plainly, one task at a time, on
random candidates and plant knowledge: every field of the analysis, bit for bit. (Against the
code this replaced: tests/bench/gate_answers_ab.py --before REV.)"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from gate_cases import canon, knowledge_set, random_configs

from controller.core.config import LoopConfig
from controller.gate import analysis, margins, measured_evidence, search
from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
from controller.gate.margins import Evaluator, GroupEvaluator, RefineTask
from controller.gate.search import RecommendationSearch


def plain_solve(tasks: list[RefineTask], ev: Evaluator, n: int = 9, rounds: int = 2) -> None:
    """`margins.solve` for one task at a time, as it was written before the analysis refined
    its tasks together: n points per bracket per round, the bracket shrunk around the sign
    change (roots) or the best point (extrema), then a secant or parabola step."""
    for t in tasks:
        for _ in range(rounds):
            p = np.linspace(t.lo, t.hi, n)
            v = t.fn(ev(np.exp(p))[t.key])
            if t.kind == 0:
                s = np.sign(v)
                k = np.nonzero(s[:-1] != s[1:])[0]
                if k.size:
                    i = int(k[0])
                    t.lo, t.hi = float(p[i]), float(p[i + 1])
                    a, b = float(v[i]), float(v[i + 1])
                    t.x = t.lo if a == b else (t.lo * b - t.hi * a) / (b - a)
                else:
                    t.x = float(p[int(np.argmin(np.abs(v)))])
                continue
            sv = np.where(np.isfinite(v), -t.kind * v, np.inf)
            i = int(np.argmin(sv))
            if not sv[i] >= -t.kind * t.best_v:
                t.best_x, t.best_v = float(p[i]), float(v[i])
            i0, i1 = max(i - 1, 0), min(i + 1, n - 1)
            t.lo, t.hi = float(p[i0]), float(p[i1])
            t.x = float(p[i])
            if 0 < i < n - 1:
                den = sv[i - 1] - 2.0 * sv[i] + sv[i + 1]
                if den > 0:
                    t.x = float(p[i] + 0.5 * (p[1] - p[0]) * (sv[i - 1] - sv[i + 1]) / den)
        # (Two points: numpy multiplies a one-element complex array in place with other
        # rounding than a longer one, and the blocks' filter responses are built that way.)
        final = ev(np.exp(np.array([t.x, t.x])))[t.key][:1]
        t.out = complex(final[0])
        t.value = float(t.fn(final)[0])
        if t.kind != 0 and not (-t.kind * t.value <= -t.kind * t.best_v):
            t.x, t.value = t.best_x, t.best_v


def test_refining_every_evidence_together_equals_each_task_alone(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    plants = knowledge_set()
    cases = random_configs(120, seed=11)
    together = [canon(analysis.analyse(cfg, plants[k])) for cfg, k in cases]
    tasks: list[int] = []
    real = analysis.solve

    def counted(ts: list[RefineTask], ev: Evaluator) -> None:
        tasks.append(len(ts))
        plain_solve(ts, ev)

    monkeypatch.setattr(analysis, "solve", counted)
    alone = [canon(analysis.analyse(cfg, plants[k])) for cfg, k in cases]
    assert real is not counted
    verdicts = [a["verdict"] for a in together]  # type: ignore[index]
    # The cases are varied: every verdict, measured responses (several tasks per evidence).
    assert {"accept", "caution", "reject"} <= set(verdicts)
    assert max(tasks) >= 30 and not math.isnan(float(np.mean(tasks)))
    for i, (a, b) in enumerate(zip(together, alone, strict=True)):
        assert a == b, (i, cases[i])


def test_the_searchs_verdict_only_path_answers_as_the_whole_analysis() -> None:
    """`accepted` (what the recommended cut-off's search asks of each cut-off: only what can
    give a reason, stopping at the first) against `analyse(...).accepted`: random candidates
    on every kind of knowledge, and the cut-offs a search of random gains evaluates."""
    plants = knowledge_set()
    cases = random_configs(300, seed=12)
    rng = np.random.default_rng(13)
    for k in (0, 1, 3):  # the coarse scan's cut-offs for new gains, as the gate asks them
        for _ in range(4):
            base = LoopConfig(cv_kp=float(rng.uniform(0.2, 1.2)),
                              pos_kp_per_s=float(rng.uniform(2.0, 14.0)))
            cases += [(base.with_(q_cutoff_hz=float(fc)), k)
                      for fc in np.geomspace(0.02, 100.0, 16)]
    answers = []
    for cfg, k in cases:
        whole = analysis.analyse(cfg, plants[k]).accepted
        assert analysis.accepted(cfg, plants[k]) == whole, (cfg, k)
        answers.append(whole)
    assert 0.2 < np.mean(answers) < 0.8  # both answers, often
    # The search on it, bisection included: the top of the accepted region as the whole
    # analysis finds it.
    for cv_kp in (0.6, 0.8):
        base = LoopConfig(cv_kp=cv_kp)
        s = RecommendationSearch(base, plants[0])
        top = search._top_of(
            lambda fc, base=base: analysis.analyse(base.with_(q_cutoff_hz=fc), plants[0]).accepted,
            np.geomspace(0.02, 100.0, 16), 0.01)
        assert top is not None and s.gate.value() == top and s.gate.evaluations > 8


def test_cutoffs_judged_together_answer_as_each_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    """`accepted_cutoffs` (the coarse scan's cut-offs judged with one refinement) against
    `accepted` of each cut-off alone and the whole analysis: the same answers, and every
    refined crossing and peak bit for bit."""
    plants = knowledge_set()
    rng = np.random.default_rng(14)
    refined: list[list[tuple[str, float, float, complex]]] = []
    real = analysis.solve_groups

    def spied(groups: list[list[RefineTask]], ev: GroupEvaluator) -> None:
        real(groups, ev)
        refined.extend([(t.key, t.x, t.value, t.out) for t in g] for g in groups)

    monkeypatch.setattr(analysis, "solve_groups", spied)
    answers, widest = [], 0
    for k in range(5):
        for _ in range(3):
            base = LoopConfig(cv_kp=float(rng.uniform(0.2, 1.2)),
                              pos_kp_per_s=float(rng.uniform(2.0, 14.0)),
                              q_type=str(rng.choice(["q31", "q20"])))
            fcs = [float(fc) for fc in np.geomspace(0.02, 100.0, 16)]
            refined.clear()
            together = analysis.accepted_cutoffs(base, fcs, plants[k])
            widest = max(widest, len(refined))
            batch = canon(refined)
            refined.clear()
            alone = [analysis.accepted(base.with_(q_cutoff_hz=fc), plants[k]) for fc in fcs]
            assert together == alone, (k, base)
            assert batch == canon(refined), (k, base)
            whole = [analysis.analyse(base.with_(q_cutoff_hz=fc), plants[k]).accepted
                     for fc in fcs]
            assert together == whole, (k, base)
            answers += together
    assert 0.2 < np.mean(answers) < 0.8 and widest >= 5  # both answers; several refined at once


def test_the_refinement_of_every_task_at_once_equals_each_alone_on_odd_values() -> None:
    """`solve` (every task refined together, each round's brackets made for all at once)
    against `plain_solve` on outputs with NaN, inf, zeros, ties and -1 (the loop through -1):
    every task's state bit for bit."""
    rng = np.random.default_rng(15)
    fns = [margins.log_mag, margins.neg_arg, margins.dist_of, margins.abs_of,
           margins.bandwidth_of]

    def ev(ff: np.ndarray) -> dict[str, np.ndarray]:
        # A fixed function of each point (so both refinements see the same values).
        u = (np.sin(ff * 7919.0) + 1.0) / 2.0
        out = {}
        for j, key in enumerate(("a", "b", "c")):
            h = np.cos(3.0 * ff + j) * (1.0 + j / ff) + 1j * np.sin(ff * (j + 1.5))
            h = np.where(u < 0.04, np.nan, h)
            h = np.where((u > 0.96), np.inf, h)
            h = np.where((u > 0.5) & (u < 0.53), 0.0, h)
            h = np.where((u > 0.7) & (u < 0.75), -1.0, h)
            out[key] = h if j < 2 else np.ones_like(h)  # ("c": ties everywhere)
        return out

    odd = 0
    for _ in range(300):
        made = []
        for _ in range(int(rng.integers(1, 14))):
            lo = float(rng.uniform(-3.0, 2.0))
            t = RefineTask(str(rng.choice(["a", "b", "c"])), int(rng.choice([0, -1, 1])),
                           fns[int(rng.integers(0, len(fns)))], lo,
                           lo + float(rng.choice([0.0, rng.exponential(0.5)])))
            if t.kind and rng.random() < 0.5:
                t.best_x, t.best_v = lo, float(rng.standard_normal())
            made.append(t)
        together = [RefineTask(**vars(t)) for t in made]
        alone = [RefineTask(**vars(t)) for t in made]
        with np.errstate(all="ignore"):  # (log of 0, inf - inf: the odd values)
            margins.solve(together, ev)
            plain_solve(alone, ev)
        a, b = canon([vars(t) for t in together]), canon([vars(t) for t in alone])
        assert a == b
        odd += sum(not math.isfinite(t.value) for t in together)
    assert odd > 20  # the odd values were met


def test_each_measured_response_judged_beside_others_as_alone(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The measured responses' first pass (their loops as rows of one array where they share
    a grid) against each response judged alone: every figure of its evidence bit for bit, on
    knowledge that mixes responses sharing a grid, one on a grid of its own, and loops that
    turn fast enough to be refined."""
    plants = knowledge_set()
    mixed = [dataclasses.replace(m, name=f"{k}/{m.name}")
             for k in (0, 3, 4) for m in plants[k].measured]
    both = PlantKnowledge(tuple(mixed), COMMISSIONING_BOUND, plants[0].model)
    alone = [PlantKnowledge((m,), COMMISSIONING_BOUND, plants[0].model) for m in mixed]
    rows: list[int] = []
    refined = 0
    real_windings, real_refine = margins.windings_ok, measured_evidence.refine_by_phase

    def windings(d: np.ndarray, m: list[int]) -> list[bool]:
        rows.append(d.shape[0])
        return real_windings(d, m)

    def refine(*args: object) -> object:
        nonlocal refined
        refined += 1
        return real_refine(*args)  # type: ignore[arg-type]

    # (The measured responses' first pass lives in measured_evidence.)
    monkeypatch.setattr(measured_evidence, "windings_ok", windings)
    monkeypatch.setattr(measured_evidence, "refine_by_phase", refine)
    stable = set()
    for cfg, _ in random_configs(40, 23):
        a = analysis.analyse(cfg, both)
        stable |= {s.base_loop_stable for s in a.sources[1:]}
        for i, k in enumerate(alone):
            assert canon(a.sources[1 + i]) == canon(analysis.analyse(cfg, k).sources[1]), (cfg, i)
    # Judged together (both loops of several responses in one array), refined alone, and
    # responses that prove the loop stable and others that do not.
    assert max(rows) >= 6 and refined > 0 and stable == {True, False}
