"""The position spread as evidence (issue 20 item 4): the spread between responses measured at
several turntable positions, where they diverge, and the recommended Q cut-off with and without
that evidence, each against an independent computation (closed forms, scipy's root finder).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from controller.core.config import LoopConfig
from controller.gate.analysis import analyse
from controller.gate.knowledge import (
    COMMISSIONING_BOUND,
    DIVERGENCE_FRACTION,
    MeasuredResponse,
    PlantKnowledge,
    position_spread,
)
from controller.gate.loop_model import discrete_equivalent
from controller.gate.search import (
    SPREAD_MARGIN,
    knowledge_spread,
    recommend,
    recommended_max_cutoff_hz,
    spread_limited_cutoff_hz,
)
from controller.gate.verdict import judge

#: A conventional speed PI (corner at a third of the crossover or below), as issue 20 asks.
CFG = LoopConfig().with_(cv_kp=1.0, cv_ki_per_s=10.0)
#: The belt mode's frequency at three positions (stiffness changing with the belt span).
SCALES = (0.7, 1.0, 1.3)
F_NAT_HZ, ZETA = 7.0, 0.707


def second_order(f: np.ndarray, fn: float, zeta: float = ZETA) -> np.ndarray:
    wn = 2.0 * math.pi * fn
    s = 1j * 2.0 * math.pi * np.asarray(f, dtype=np.float64)
    return wn * wn / (s * s + 2.0 * zeta * wn * s + wn * wn)


def responses(f: np.ndarray, scales: tuple[float, ...] = SCALES) -> tuple[MeasuredResponse, ...]:
    return tuple(
        MeasuredResponse(f"pos{i}", f, second_order(f, F_NAT_HZ * k))
        for i, k in enumerate(scales, start=1)
    )


def closed_form_spread(f: np.ndarray, scales: tuple[float, ...] = SCALES) -> np.ndarray:
    """max_i |H_i / H_ref - 1|, H_ref the geometric mean: |H|'s in dB averaged, phases (all
    within (-180, 0] deg for these responses) averaged."""
    h = np.array([second_order(f, F_NAT_HZ * k) for k in scales])
    ref = np.exp(np.mean(np.log(np.abs(h)), axis=0)) * np.exp(1j * np.mean(np.angle(h), axis=0))
    return np.max(np.abs(h / ref - 1.0), axis=0)


def q31_mag(f: np.ndarray, cutoff_hz: float) -> np.ndarray:
    """|Q31| by eq. (32) with control.md's -3 dB constant f_c tau = 0.261407."""
    tau = 0.261407 / cutoff_hz
    ts = 1j * 2.0 * math.pi * np.asarray(f) * tau
    return np.abs((3.0 * ts + 1.0) / (ts**3 + 3.0 * ts**2 + 3.0 * ts + 1.0))


def test_spread_and_divergence_match_the_closed_form() -> None:
    f = np.geomspace(0.1, 20.0, 200)
    sp = position_spread(responses(f))
    assert sp is not None and sp.names == ("pos1", "pos2", "pos3")
    truth = closed_form_spread(f)
    np.testing.assert_allclose(sp.relative, truth, rtol=1e-9, atol=1e-12)
    mags = 20 * np.log10(np.abs([second_order(f, F_NAT_HZ * k) for k in SCALES]))
    np.testing.assert_allclose(sp.mag_db, mags.max(0) - mags.min(0), atol=1e-9)
    # Agree at low frequency, diverge above: the divergence frequency where the closed form
    # crosses 1 dB's fraction.
    assert sp.relative[0] < 0.01 and sp.relative[-1] > 0.5
    want = brentq(lambda x: closed_form_spread(np.array([x]))[0] - DIVERGENCE_FRACTION, 0.1, 20)
    assert sp.divergence_hz == pytest.approx(want, rel=0.005)
    assert 1.0 < want < 3.0  # the article's "agree below about 1 Hz", roughly


def test_spread_across_grids_and_forms() -> None:
    """Responses on different grids are compared on the band they share; a sampled response is
    brought to the continuous form first (`knowledge_spread`), and mixing forms without a
    converter is refused rather than compared wrongly."""
    f1, f2 = np.geomspace(0.1, 20.0, 80), np.geomspace(0.2, 30.0, 57)
    a = MeasuredResponse("a", f1, second_order(f1, 5.0))
    b = MeasuredResponse("b", f2, second_order(f2, 7.0))
    sp = position_spread((a, b))
    assert sp is not None
    assert sp.freq_hz[0] == pytest.approx(0.2) and sp.freq_hz[-1] == pytest.approx(20.0)
    exact = np.abs(second_order(sp.freq_hz, 5.0) / second_order(sp.freq_hz, 7.0))
    # Two responses: H_ref is their geometric mean, so the larger |H_i/H_ref - 1| is one side
    # of the square root of their ratio; the interpolation errs a little between points.
    ratio = second_order(sp.freq_hz, 5.0) / second_order(sp.freq_hz, 7.0)
    truth = np.maximum(np.abs(np.sqrt(ratio) - 1), np.abs(1 / np.sqrt(ratio) - 1))
    np.testing.assert_allclose(sp.relative, truth, rtol=0.02, atol=2e-3)
    np.testing.assert_allclose(sp.mag_db, np.abs(20 * np.log10(exact)), atol=0.05)
    sampled = MeasuredResponse("b", f2, discrete_equivalent(b.response, f2, 1000.0), sampled=True)
    with pytest.raises(ValueError, match="mix sampled and continuous"):
        position_spread((a, sampled))
    mixed = knowledge_spread(PlantKnowledge((a, sampled)), 1000.0)
    assert mixed is not None
    np.testing.assert_allclose(mixed.relative, sp.relative, rtol=1e-9, atol=1e-12)
    assert position_spread((a,)) is None
    # No band in common: the spread is not measured (no evidence either way).
    far = MeasuredResponse("c", np.array([25.0, 30.0]), np.full(2, 1.0 + 0j))
    assert position_spread((a, far)) is None


def test_spread_limited_cutoff_matches_an_independent_search() -> None:
    """The largest Q31 cut-off with max |Delta Q| <= 1 / SPREAD_MARGIN: scipy's root of the
    closed forms (spread eq. above, Q31 eq. 32) on a dense grid, against the search."""
    f = np.geomspace(0.05, 100.0, 400)  # wide enough that holding the edges plays no part
    sp = position_spread(responses(f))
    assert sp is not None
    dense = np.geomspace(0.05, 100.0, 6000)
    a = closed_form_spread(dense)

    def excess(fc: float) -> float:
        return float(np.max(a * q31_mag(dense, fc))) - 1.0 / SPREAD_MARGIN

    want = brentq(excess, 0.05, 20.0, xtol=1e-6)
    got = spread_limited_cutoff_hz("q31", sp)
    assert got is not None and got == pytest.approx(want, rel=0.005)
    # Q rolls off where the responses part: the limit sits near the divergence frequency.
    assert sp.divergence_hz is not None and 0.5 * sp.divergence_hz < got < 2 * sp.divergence_hz
    # Responses that agree everywhere leave the cut-off free up to the search's top.
    same = position_spread(responses(f, (1.0, 1.001, 0.999)))
    assert same is not None and same.divergence_hz is None
    assert spread_limited_cutoff_hz("q31", same) == pytest.approx(100.0)
    with pytest.raises(ValueError, match="margin"):
        spread_limited_cutoff_hz("q31", sp, margin=0.5)


def test_recommended_cutoff_with_and_without_the_spread() -> None:
    """Without spread evidence (one position, or the spread not used) the recommendation is the
    gate's accepted region; with three positions it is held below where they diverge, and the
    verdict cautions for a cut-off between the two."""
    f = np.geomspace(0.1, 20.0, 40)
    three = PlantKnowledge(responses(f), COMMISSIONING_BOUND)
    r = recommend(CFG, three, q_type="q31")
    assert r.spread is not None and r.gate_hz is not None and r.spread_hz is not None
    assert r.spread_hz == pytest.approx(spread_limited_cutoff_hz("q31", r.spread), rel=1e-9)
    assert r.recommended_hz == min(r.gate_hz, r.spread_hz)
    assert r.limited_by_spread and r.recommended_hz < 0.8 * r.gate_hz
    gate_only = recommended_max_cutoff_hz(CFG, three, q_type="q31", spread_margin=None)
    assert gate_only == pytest.approx(r.gate_hz, rel=1e-12)
    one = PlantKnowledge(responses(f)[1:2], COMMISSIONING_BOUND)
    r1 = recommend(CFG, one, q_type="q31")
    assert r1.spread is None and r1.recommended_hz == r1.gate_hz
    assert "diverge above" in r.describe()
    mid = math.sqrt(r.recommended_hz * r.gate_hz)
    j = judge(CFG.with_(q_type="q31", q_cutoff_hz=mid), three)
    cand = CFG.with_(q_type="q31", q_cutoff_hz=mid)
    assert analyse(cand, three).verdict == "accept"  # the analysis alone takes it ...
    assert j.verdict == "caution"  # ... the recommendation does not
    assert any("spread between the measured responses" in c for c in j.cautions)


def test_check_reports_the_spread_from_frd_files(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """`dobtune check --frd` with three positions: the recommendation with the spread, the
    gate's alone and where the responses diverge, in the table and the JSON."""
    import io
    import json

    from controller.cli.check import check_main
    from controller.cli.frd_files import write_frd_csv
    from controller.core.config import config_to_builtins

    f = np.geomspace(0.1, 20.0, 40)
    paths = []
    for m in responses(f):
        p = tmp_path / f"{m.name}.csv"
        write_frd_csv(p, m.freq_hz, m.response, np.ones(f.size))
        paths.append(p)
    cfg_path = tmp_path / "cfg.json"
    cfg_path.write_text(json.dumps(config_to_builtins(CFG)))
    out = io.StringIO()
    check_main(cfg_path, "q31", 0.5, paths, True, out)
    got = json.loads(out.getvalue())
    r = recommend(CFG, PlantKnowledge(responses(f), COMMISSIONING_BOUND), q_type="q31")
    assert got["recommended_max_cutoff_hz"] == pytest.approx(r.recommended_hz, rel=0.01)
    assert got["recommended_gate_only_hz"] == pytest.approx(r.gate_hz, rel=0.01)
    assert got["spread_limited_cutoff_hz"] < got["recommended_gate_only_hz"]
    assert got["position_spread"]["divergence_hz"] == pytest.approx(
        r.spread.divergence_hz, rel=0.01)  # type: ignore[union-attr]
    out = io.StringIO()
    check_main(cfg_path, "q31", 0.5, paths, False, out)
    assert "responses diverge above" in out.getvalue()
    assert f"gate alone {got['recommended_gate_only_hz']:.3g} Hz" in out.getvalue()
