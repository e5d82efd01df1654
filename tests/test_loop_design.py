"""The cascade's linear design (controller.tune.loop_design) against python-control: the
margins it reads, and the loops it places meet its stated targets on the exact sampled loop."""

from __future__ import annotations

import math

import control as ct
import numpy as np
import pytest

from controller.gate.knowledge import (
    COMMISSIONING_BOUND,
    MeasuredResponse,
    PlantKnowledge,
)
from controller.gate.loop_model import nominal_continuous_response
from controller.tune.loop_design import (
    DesignTargets,
    design_position,
    design_speed,
    feedforward_gain,
    first_resonance_hz,
    loop_margins,
)

RATE = 1000.0
TS = 1.0 / RATE
MP = ct.tf([1.0], [1.013e-05, 0.004501, 1.0]) * ct.tf(
    [1.013e-05, 0.004501, 1.0], [0.0005169, 0.03215, 1.0])
Z = ct.tf([1.0, 0.0], [1.0], TS)


def _g_discrete(mp: ct.TransferFunction = MP) -> ct.TransferFunction:
    """u -> w of the sampled loop: ZOH of M P / s, then the backward difference."""
    return ct.c2d(mp * ct.tf([1.0], [1.0, 0.0]), TS, "zoh") * (Z - 1) / (Z * TS)


def _pi(kp: float, ki: float) -> ct.TransferFunction:
    return kp * (1 + ki * TS / 2 * (Z + 1) / (Z - 1))


W = 2 * np.pi * np.geomspace(0.05, 499.0, 6000)


def _resp(sys: ct.TransferFunction) -> np.ndarray:
    return np.asarray(ct.frequency_response(sys, W).complex).ravel()


def _all_margins(h: np.ndarray) -> tuple[list[float], list[float], list[float], list[float]]:
    """(GMs dB, their Hz, PMs deg, their Hz) of a loop given as its response on W (python-
    control's FRD margins: a product of factors evaluated one by one, so the near pole-zero
    cancellations at z = 1 of a multiplied-out sampled transfer function do not enter)."""
    gm, pm, _, wg, wp, _ = ct.stability_margins(ct.frd(h, W), returnall=True)
    return ([20 * math.log10(x) for x in np.atleast_1d(gm)], list(np.atleast_1d(wg) / 2 / np.pi),
            list(np.atleast_1d(pm)), list(np.atleast_1d(wp) / 2 / np.pi))


def _margins(h: np.ndarray) -> tuple[float, float, float]:
    """(upward GM dB, PM deg, highest crossover Hz): the gain margin at the phase crossovers
    above the lowest gain crossover (a loop with several integrators is conditionally stable:
    its gain-reduction margin lies below)."""
    gms, fgs, pms, fps = _all_margins(h)
    up = [g for g, f in zip(gms, fgs, strict=True) if f > min(fps)]
    return min(up) if up else math.inf, min(pms), max(fps)


def test_loop_margins_read_as_python_control_does() -> None:
    loop = ct.tf([2.0, 30.0], [1.0, 0.0]) * MP * ct.tf(*ct.pade(2e-3, 7))
    f = np.geomspace(0.01, 400, 4000)
    h = ct.frequency_response(loop, 2 * np.pi * f).complex
    m = loop_margins(np.asarray(h).ravel(), f)
    gm, pm, _, wc = ct.margin(loop)
    gm, fc = 20 * math.log10(gm), wc / (2 * math.pi)
    assert m.phase_margin_deg == pytest.approx(pm, abs=0.05)
    assert m.gain_margin_db == pytest.approx(gm, abs=0.05)
    assert m.crossover_hz == pytest.approx(fc, rel=1e-3)


def test_design_meets_its_targets_on_the_exact_sampled_loop() -> None:
    k = PlantKnowledge(bound=COMMISSIONING_BOUND)
    t = DesignTargets()
    sp = design_speed(k, RATE, t)
    po = design_position(k, RATE, sp, t)
    g = _resp(_g_discrete())
    cv = _resp(_pi(sp.kp, sp.ki_per_s))
    gm, pm, fc = _margins(cv * g)
    assert pm >= t.phase_margin_deg - 0.2 and gm >= t.gain_margin_db
    assert fc == pytest.approx(sp.crossover_hz, rel=0.01)
    assert sp.corner_hz == pytest.approx(fc / t.corner_ratio, rel=0.01)
    # the position loop around the closed speed loop, and the whole servo at the command
    integ = _resp(TS * Z / (Z - 1))
    cp = _resp(_pi(po.kp_per_s, po.ki_per_s))
    tv = cv * g / (1 + cv * g)
    gm_p, pm_p, fc_p = _margins(cp * tv * integ)
    assert fc_p == pytest.approx(po.crossover_hz, rel=0.01)
    assert sp.crossover_hz / fc_p == pytest.approx(t.position_ratio, rel=0.02)
    assert pm_p >= t.phase_margin_deg and gm_p >= t.gain_margin_db
    # The whole servo has three integrators (both PIs and theta = Ts/(1 - z^-1) w): it is
    # conditionally stable, with a gain-reduction margin below the crossover; the design's
    # target is the upward margin.
    whole = g * cv * (1 + cp * integ)
    gm_w, pm_w, fc_w = _margins(whole)
    assert pm_w >= t.phase_margin_deg - 0.2 and gm_w >= t.gain_margin_db
    gms, fgs, _, _ = _all_margins(whole)
    assert any(gdb < 0 and f < fc_w for gdb, f in zip(gms, fgs, strict=True))
    # the speed loop is limited by a target (not the grid's end): a bit more crossover misses
    assert "at " in sp.limit and ("margin" in sp.limit or "robust" in sp.limit)
    # velocity feedforward about 1 for a speed loop with integral action
    assert feedforward_gain(k, RATE, sp, 0.08) == pytest.approx(1.0, abs=0.01)


def test_a_measured_resonance_lowers_the_crossover_and_is_named() -> None:
    # measured densely across the mode (its half-power band is 4 % wide)
    f = np.unique(np.concatenate([np.geomspace(0.1, 200.0, 400), np.geomspace(24, 40, 300)]))
    wr = 2 * np.pi * 30.0
    s = 2j * np.pi * f
    mode = (wr**2) / (s * s + 2 * 0.02 * wr * s + wr**2)  # non-collocated, 30 Hz
    h = nominal_continuous_response(PlantKnowledge().model, f) * mode
    k = PlantKnowledge(measured=(MeasuredResponse("pos 0", f, h),), bound=COMMISSIONING_BOUND)
    plain = design_speed(PlantKnowledge(bound=COMMISSIONING_BOUND), RATE)
    sp = design_speed(k, RATE)
    assert sp.crossover_hz < plain.crossover_hz
    assert first_resonance_hz(k, RATE) == pytest.approx(30.0, rel=0.05)
    # independent check: margins of the sampled loop on the resonant plant
    res = ct.tf([wr**2], [1.0, 2 * 0.02 * wr, wr**2])
    gm, pm, _ = _margins(_resp(_pi(sp.kp, sp.ki_per_s)) * _resp(_g_discrete(MP * res)))
    assert gm >= 8.0 - 0.3 and pm >= 45.0 - 0.5


def test_a_poorly_known_low_interval_does_not_hold_the_speed_loop_down() -> None:
    """The demo's Measure at 3 positions (article-rig: friction at 3 deg/s makes the 0.1 Hz
    point 24 % uncertain, and the 0.1-0.3 Hz interval's allowance about 0.67): a speed loop
    crossing at about 0.4 Hz has |T| a little above 1 there and misses the 0.7 robust figure,
    while faster loops (|T| = 1 there) meet it. Searched from the bottom, the design stopped
    at 0.42 Hz and the whole-loop tune proposed a loop 13x worse than the starting one; now
    such a miss is passed over and the design finds about the crossover the model alone
    gives. The gate, judging independently, accepts the designed loop on that knowledge."""
    from demo_identification import DEMO_CONFIG, demo_identification

    from controller.gate.verdict import judge

    cfg = DEMO_CONFIG
    measured = demo_identification().measured_responses()
    assert max(float(m.spread[0]) for m in measured if m.spread is not None) > 0.1
    k = PlantKnowledge(measured=measured, bound=COMMISSIONING_BOUND)
    t = DesignTargets()
    sp = design_speed(k, RATE, t)
    model_only = design_speed(PlantKnowledge(bound=COMMISSIONING_BOUND), RATE, t)
    assert sp.crossover_hz > 0.5 * model_only.crossover_hz > 2.0, sp.limit
    assert "robust" not in sp.limit  # what limits it is a margin near the crossover
    po = design_position(k, RATE, sp, t)
    designed = cfg.with_(cv_kp=sp.kp, cv_ki_per_s=sp.ki_per_s, pos_kp_per_s=po.kp_per_s,
                         pos_ki_per_s=po.ki_per_s)
    v = judge(designed, k)
    assert v.verdict in ("accept", "caution"), v.rejections
