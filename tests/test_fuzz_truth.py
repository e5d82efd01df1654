"""The independent truth of tests/fuzz_truth.py, against the tick itself and python-control.

The closed loop built from python-control blocks must reproduce, sample for sample, a time
simulation of `controller.core.loop.ServoLoop` on the same discrete plant; its margins must be
the ones `control.stability_margins` finds, and on the article's configuration the ones
control.md states (GM ~22 dB, PM ~57.5 deg at ~4.5 Hz).
"""

from __future__ import annotations

import math

import control as ct
import numpy as np
import pytest
from fuzz_truth import (
    Resonance,
    TruePlant,
    continuous_response,
    discrete_plant,
    disturbance_loop,
    loop_margins,
    open_loops,
    sampled_response,
    truth,
)
from old_loop import OLD_LOOP

from controller.core.config import LoopConfig, NominalModel
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.gate.analysis import analyse

ARTICLE = LoopConfig()
#: Plants and configurations the loop checks run on (name, plant, config changes).
CASES = [
    ("article", TruePlant(), {}),
    ("no_dob", TruePlant(gain=1.7), {"dob_on": False}),
    ("q20_fast", TruePlant(wn_scale=0.7, damping_scale=0.5), {"q_type": "q20", "q_cutoff_hz": 5}),
    (
        "resonance_delay",
        TruePlant(gain=0.6, resonance=Resonance(25.0, 0.03, 0.8), delay_ticks=2),
        {"q_cutoff_hz": 2.0, "cv_kp": 0.3},
    ),
    ("zero_integrals", TruePlant(gain=1.3), {"cv_ki_per_s": 0.0, "pos_ki_per_s": 0.0}),
    (
        "lying_nominal",
        TruePlant(),
        {"nominal": NominalModel(pn_num=(3 * 1.013e-05, 3 * 0.004501, 3.0)), "q_cutoff_hz": 3.0},
    ),
]


def _simulate(plant: TruePlant, cfg: LoopConfig, position: bool, d: np.ndarray) -> np.ndarray:
    """ServoLoop on the discrete plant, disturbance d added to the command at the plant input;
    returns w (and theta) per tick, measured before the tick computes its command."""
    g = discrete_plant(plant, cfg.rate_hz)
    sys = g.full if position else g.speed
    a, b, c = (np.asarray(m, dtype=float) for m in (sys.A, sys.B, sys.C))
    loop = ServoLoop(LoopCoefficients.build(cfg))
    x = np.zeros(a.shape[0])
    out = np.zeros((c.shape[0], d.size))
    for k in range(d.size):
        y = c @ x
        out[:, k] = y
        if position:
            u = loop.tick(0.0, 0.0, float(y[1]), float(y[0]))
        else:
            u = loop.tick_speed(0.0, float(y[0]))
        assert abs(u) < cfg.command_limit_deg_s  # stays linear
        x = a @ x + b[:, 0] * (u + d[k])
    return out


@pytest.mark.parametrize("position", [True, False], ids=["full", "speed"])
@pytest.mark.parametrize(("name", "plant", "changes"), CASES, ids=[c[0] for c in CASES])
def test_loop_matches_servo_loop_time_simulation(
    name: str, plant: TruePlant, changes: dict[str, object], position: bool
) -> None:
    cfg = ARTICLE.with_(command_limit_deg_s=1e4, **changes)
    n = 3000
    d = np.zeros(n)
    d[0] = 1.0  # impulse
    d[1500:] = 0.5  # and a step
    sim = _simulate(plant, cfg, position, d)
    cl = disturbance_loop(plant, cfg, position=position)
    resp = ct.forced_response(cl, T=np.arange(n) * cfg.period_s, U=d)
    ref = np.atleast_2d(resp.outputs)
    scale = np.max(np.abs(ref), axis=1, keepdims=True)
    assert np.max(np.abs(sim - ref) / scale) < 1e-9, name


def test_unstable_loop_grows_like_the_largest_pole() -> None:
    plant = TruePlant(gain=3.0, delay_ticks=3)
    cfg = ARTICLE.with_(cv_kp=2.0, command_limit_deg_s=1e4)
    t = truth(plant, cfg)
    assert not t.stable and t.radius_full > 1.0
    n = 3000
    d = np.zeros(n)
    d[0] = 1e-25
    mag = np.abs(_simulate(plant, cfg, True, d)[1])
    # Growth per tick from the peaks of the last 1000 ticks (the unstable pair dominates).
    k = np.nonzero((mag[1:-1] > mag[:-2]) & (mag[1:-1] >= mag[2:]))[0] + 1
    k = k[k >= 2000]
    growth = math.exp(np.polyfit(k, np.log(mag[k]), 1)[0])
    assert growth == pytest.approx(t.radius_full, abs=2e-5)


def test_article_configuration_margins_as_control_md_states() -> None:
    t = truth(TruePlant(), OLD_LOOP)  # control.md's margins are those of Cv = 0.5 (1 + 55/s)
    assert t.stable and t.comfortable()
    m = t.margins_speed
    assert m is not None
    assert m.gain_margin_db == pytest.approx(22.0, abs=0.3)
    assert m.phase_margin_deg == pytest.approx(57.5, abs=0.5)
    assert m.gain_crossover_hz == pytest.approx(4.5, abs=0.1)
    assert t.max_pole_radius < 0.999


def test_article_configuration_agrees_with_the_gate_nominal_analysis() -> None:
    """Same plant (the nominal model) and the same loop: same margins, same pole radius
    (the radius to 1e-4: six closed-loop poles cluster at Q31's triple pole near 0.998 and
    their computed spread depends on the realisation)."""
    t = truth(TruePlant(), ARTICLE)
    a = analyse(ARTICLE)
    assert t.margins_speed is not None
    assert t.margins_speed.gain_margin_db == pytest.approx(a.margins.gain_margin_db, abs=1e-3)
    assert t.margins_speed.phase_margin_deg == pytest.approx(a.margins.phase_margin_deg, abs=1e-3)
    assert t.radius_full == pytest.approx(a.max_pole_radius, abs=1e-4)


@pytest.mark.parametrize(("name", "plant", "changes"), CASES[:4], ids=[c[0] for c in CASES[:4]])
def test_exact_margins_equal_control_stability_margins(
    name: str, plant: TruePlant, changes: dict[str, object]
) -> None:
    for loop in open_loops(plant, ARTICLE.with_(**changes)):
        fast = loop_margins(loop)
        ref = loop_margins(loop, method="control")
        assert fast.gain_margin_db == pytest.approx(ref.gain_margin_db, abs=0.02), name
        assert fast.phase_margin_deg == pytest.approx(ref.phase_margin_deg, abs=0.05), name
        assert fast.gain_crossover_hz == pytest.approx(ref.gain_crossover_hz, rel=1e-3), name
        assert fast.stability_margin == pytest.approx(ref.stability_margin, abs=1e-3), name


def test_delay_costs_exactly_its_phase_at_crossover() -> None:
    base = truth(TruePlant(), ARTICLE).margins_speed
    late = truth(TruePlant(delay_ticks=3), ARTICLE).margins_speed
    assert base is not None and late is not None
    assert late.gain_crossover_hz == pytest.approx(base.gain_crossover_hz, rel=1e-9)
    lag = 360.0 * base.gain_crossover_hz * 3 * ARTICLE.period_s
    assert base.phase_margin_deg - late.phase_margin_deg == pytest.approx(lag, abs=1e-6)


def test_zero_integral_gains_add_no_pole_at_one() -> None:
    t = truth(TruePlant(), ARTICLE.with_(cv_ki_per_s=0.0, pos_ki_per_s=0.0, dob_on=False))
    assert t.stable and t.max_pole_radius < 0.999


def test_plant_errors_and_sampled_response() -> None:
    p = TruePlant(gain=2.0, wn_scale=1.5, damping_scale=0.5, resonance=Resonance(30.0, 0.05, 0.9))
    tf = p.transfer_function()
    assert float(np.real(tf(0))) == pytest.approx(2.0)
    poles = np.sort(np.abs(tf.poles()))
    wn = math.sqrt(1.0 / ARTICLE.nominal.pn_den[0]) * 1.5
    assert poles[0] == pytest.approx(wn, rel=1e-9)  # the belt mode moved by wn_scale
    assert poles[-1] == pytest.approx(2 * math.pi * 30.0, rel=1e-9)
    # Sampled u[k] -> w[k] = ZOH + backward difference: G_c e^{-j w Ts} sinc^2 below Nyquist.
    f = np.geomspace(0.01, 20.0, 30)
    x = np.pi * f * ARTICLE.period_s
    approx = continuous_response(p, 1000.0, f) * np.exp(-2j * x) * np.sinc(x / np.pi) ** 2
    assert np.allclose(sampled_response(p, 1000.0, f), approx, rtol=2e-3)
    # Delay in ticks is a pure z^-d.
    late = TruePlant(gain=2.0, delay_ticks=2)
    z = np.exp(-2j * np.pi * f / 1000.0)
    ratio = sampled_response(late, 1000.0, f) / sampled_response(TruePlant(gain=2.0), 1000.0, f)
    assert np.allclose(ratio, z**2, rtol=1e-9)


def test_sampled_rate_source_is_the_sampled_output() -> None:
    p = TruePlant()
    f = np.geomspace(0.01, 100.0, 20)
    sampled = sampled_response(p, 1000.0, f, rate_source="sampled")
    zoh = ct.c2d(ct.ss(p.transfer_function()), 1e-3, "zoh")
    assert np.allclose(sampled, zoh(np.exp(2j * np.pi * f * 1e-3)), rtol=1e-7)
    t = truth(p, ARTICLE, rate_source="sampled")
    assert t.stable and t.margins_speed is not None
