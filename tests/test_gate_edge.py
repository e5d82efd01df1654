"""Loops at the edge of instability: the gate keeps a margin on every loop and every piece of
evidence. Each loop here is built with the independent truth (tests/fuzz_truth.py: the plant's
gain scaled until the largest closed-loop pole radius of the python-control loop is just past
1) and must be rejected. What the margin costs on comfortably stable loops is measured by the
fuzz (`tests/bench/fuzz_gate.py`: comfortable accepted).

The cases are the ones the hostile fuzz (`tests/bench/fuzz_gate.py --edge`) found accepted: a
sharp resonance between two points of densely measured data (the robust test sampled each
interval's allowance only at the measured points, where it is the points' own 5 %, and stepped
over the interval's peak), and on identification-grid data.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from fuzz_truth import Resonance, TruePlant, edge_plant, sampled_response, truth

from controller.core.config import LoopConfig, NominalModel
from controller.gate.analysis import GateLimits, analyse
from controller.gate.knowledge import COMMISSIONING_BOUND, MeasuredResponse, PlantKnowledge
from controller.gate.verdict import judge

RATE = 1000.0
DENSE_HZ = np.geomspace(0.01, 0.4999 * RATE, 500)
IDENT_HZ = np.logspace(-1.0, math.log10(20.0), 24)
ARTICLE = NominalModel()


def _cfg(**kw: object) -> LoopConfig:
    """Every loop value explicit (the defaults may change)."""
    base: dict[str, object] = dict(
        rate_hz=RATE, nominal=ARTICLE, cv_kp=0.5, cv_ki_per_s=55.0, pos_kp_per_s=9.0,
        pos_ki_per_s=3.5, ff_on=False, dob_on=True, q_type="q31", q_cutoff_hz=0.5,
    )
    return LoopConfig(**(base | kw))  # type: ignore[arg-type]


def _dense(plant: TruePlant) -> PlantKnowledge:
    h = sampled_response(plant, RATE, DENSE_HZ)
    m = MeasuredResponse("dense", DENSE_HZ, h, sampled=True)
    return PlantKnowledge((m,), COMMISSIONING_BOUND, ARTICLE)


def _ident(plant: TruePlant, seed: int = 0) -> PlantKnowledge:
    """As identification hands it over: 3 positions, 2 % complex noise, the sampling factor
    (ZOH + backward difference) divided out."""
    x = np.pi * IDENT_HZ / RATE
    h = sampled_response(plant, RATE, IDENT_HZ) / (np.exp(-2j * x) * np.sinc(x / np.pi) ** 2)
    rng = np.random.default_rng(seed)
    out = []
    for i in range(3):
        noise = rng.normal(0.0, 0.02, (2, IDENT_HZ.size)) / math.sqrt(2.0)
        out.append(MeasuredResponse(f"pos{i}", IDENT_HZ, h * (1.0 + noise[0] + 1j * noise[1])))
    return PlantKnowledge(tuple(out), COMMISSIONING_BOUND, ARTICLE)


#: (name, plant before scaling, candidate, evidence, radius - 1)
EDGE_CASES = [
    ("dense_101Hz_pi", TruePlant(resonance=Resonance(101.5, 0.015, 0.8)),
     _cfg(cv_kp=1.0, cv_ki_per_s=10.0), _dense, 2e-6),
    ("dense_102Hz_pi", TruePlant(resonance=Resonance(102.3, 0.015, 0.8)),
     _cfg(cv_kp=1.0, cv_ki_per_s=10.0), _dense, 2e-6),
    ("dense_101Hz_q20", TruePlant(resonance=Resonance(101.5, 0.015, 0.8)),
     _cfg(q_type="q20", q_cutoff_hz=5.0), _dense, 2e-6),
    ("dense_61Hz_fuzz28",
     TruePlant(wn_scale=0.6184, damping_scale=1.2095, delay_ticks=2,
               resonance=Resonance(60.565, 0.024734, 0.82292)),
     _cfg(cv_kp=0.21643, cv_ki_per_s=164.84, pos_kp_per_s=5.6154, pos_ki_per_s=8.9265,
          q_cutoff_hz=16.054), _dense, 5.26e-5),
    ("ident_4Hz_fuzz115",
     TruePlant(wn_scale=1.6801, damping_scale=0.78731, delay_ticks=1,
               resonance=Resonance(4.3171, 0.013648, 1.0527)),
     _cfg(nominal=NominalModel(pn_num=(1.6184e-06, 0.00071908, 0.15976),
                               pn_den=(0.00018312, 0.015066, 1.0)),
          cv_kp=0.77888, cv_ki_per_s=0.0, pos_kp_per_s=1.0774, pos_ki_per_s=1.2686,
          ff_on=True, q_type="q20", q_cutoff_hz=8.8977), _ident, 5.55e-5),
]


@pytest.mark.parametrize(("name", "plant", "cfg", "evidence", "eps"), EDGE_CASES,
                         ids=[c[0] for c in EDGE_CASES])
def test_a_loop_just_past_the_boundary_is_rejected(
    name: str, plant: TruePlant, cfg: LoopConfig, evidence: object, eps: float
) -> None:
    res = plant.resonance
    assert res is not None
    found = edge_plant(plant, cfg, 1.0 + eps, near_hz=res.freq_hz)
    assert found is not None, name
    edge, radius = found
    assert 1.0 < radius <= (1.0 + eps) * (1.0 + 1e-9)
    assert not truth(edge, cfg, margins="never").stable
    knowledge = evidence(edge)  # type: ignore[operator]
    j = judge(cfg, knowledge)
    assert j.verdict == "reject", (name, radius, j.reasons)


def test_between_dense_points_the_reason_asks_for_a_denser_measurement() -> None:
    _name, plant, cfg, _evidence, eps = EDGE_CASES[0]
    found = edge_plant(plant, cfg, 1.0 + eps, near_hz=101.5)
    assert found is not None
    j = judge(cfg, _dense(found[0]))
    denser = [r for r in j.rejections if "measure denser between" in r]
    assert denser, j.rejections
    # The interval named holds the resonance's peak (the truth's critical pole at ~103.6 Hz).
    lo = float(denser[0].split("measure denser between ")[1].split(" Hz")[0])
    hi = float(denser[0].split(" and ")[-1].split(" Hz")[0])
    assert lo < 103.6 < hi and hi / lo < 1.05


def test_model_poles_keep_a_margin_from_the_unit_circle() -> None:
    """Plant model only, no bound (the model taken as exact): a loop whose slowest pole sits
    at radius 1 - 2e-6 (the truth: stable, a 500 s time constant) is rejected as having no
    margin; the same loop at the model's own gain is accepted."""
    cfg = _cfg(dob_on=False, cv_kp=1.0, cv_ki_per_s=10.0)
    found = edge_plant(TruePlant(), cfg, 1.0 - 2e-6)
    assert found is not None
    g = found[0].gain
    assert truth(found[0], cfg, margins="never").stable
    n = ARTICLE
    model = NominalModel(mn_den=n.mn_den, pn_num=tuple(g * c for c in n.pn_num),  # type: ignore[arg-type]
                         pn_den=n.pn_den)
    a = analyse(cfg, PlantKnowledge(model=model))
    assert a.max_pole_radius == pytest.approx(found[1], abs=1e-7)
    assert a.verdict == "reject", a.reasons
    assert any("no margin from instability" in r for r in a.rejections), a.rejections
    assert analyse(cfg, PlantKnowledge(model=ARTICLE)).verdict != "reject"
    # The margin is a stated limit: without it the same loop is only cautioned.
    loose = GateLimits(pole_time_constant_max_s=1e6, stability_margin_min=0.0)
    assert analyse(cfg, PlantKnowledge(model=model), loose).verdict != "reject"
