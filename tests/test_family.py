"""The family of rigs (controller.tune.family): the true rig's linear response is what the
simulated rig does, and on a fixed few drawn rigs the whole-loop tune (identify, twin, tune)
gives a loop the gate accepts on the true rig, that beats the default starting loop and comes
near a brute-force search (tests/bench/bench_family.py: a fresh seed, >= 20 rigs)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rig_linear import linear_params

from controller.core.config import LoopConfig, NominalModel
from controller.gate.loop_model import discrete_equivalent
from controller.sim.sim_rig import RigFaults, SimRig
from controller.tune.family import RANGES, BruteGrid, draw_family, identify, run_rig
from controller.tune.whole_loop import Objective
from controller.twin.fit import rig_response


def _measured(rig: SimRig, f_hz: float, periods: int = 6) -> tuple[complex, float]:
    """u -> w at f_hz from a sine on a speed offset (the belt stays loaded), one DFT bin."""
    ts = rig.period_s
    n_per = round(1.0 / (f_hz * ts))
    f = 1.0 / (n_per * ts)
    settle = 2 * n_per + 500
    n = settle + periods * n_per
    u = 20.0 + 2.0 * np.sin(2 * math.pi * f * ts * np.arange(n))
    w = np.empty(n)
    for k in range(n):
        w[k] = rig.read()[1]
        rig.step(float(u[k]))
    e = np.exp(-2j * math.pi * f * ts * np.arange(settle, n))
    return complex(np.sum(w[settle:] * e) / np.sum((u[settle:] - 20.0) * e)), f


@pytest.mark.parametrize("f_hz", [1.0, 5.0, 20.0])
def test_true_response_is_the_simulated_rigs(f_hz: float) -> None:
    params = linear_params(position_noise_deg=0.0, load_encoder_bits=48,
                           motor_encoder_counts_per_rev=2**30, command_delay_ticks=2,
                           drive_droop_rpm_per_n_m=300.0)
    faults = RigFaults(plant_gain=1.3, resonance_hz=40.0, resonance_damping=0.05)
    rig = SimRig(params)
    rig.set_faults(faults)
    h, f = _measured(rig, f_hz)
    # the sampled loop: the held command and the backward-difference rate
    ref = complex(discrete_equivalent(rig_response(params, faults, np.array([f])), [f],
                                      1000.0)[0])
    assert 20 * math.log10(abs(h / ref)) == pytest.approx(0.0, abs=0.3)
    assert math.degrees(np.angle(h / ref)) == pytest.approx(0.0, abs=3.0)


def test_the_family_is_drawn_from_its_seed_within_the_ranges() -> None:
    a, b = draw_family(11, 20), draw_family(11, 20)
    assert a == b and draw_family(12, 20) != a
    for r in a:
        for name, (lo, hi) in RANGES.items():
            assert lo <= getattr(r, name) <= hi
        assert 1 <= r.delay_ticks <= 3
        assert r.params.command_delay_ticks == r.delay_ticks
        assert r.faults.plant_gain == r.drive_gain


@pytest.mark.timeout(600)  # a hang's bound
def test_a_rig_whose_drive_gain_is_not_1_is_fitted_with_its_dc_gain() -> None:
    """Seed 271127335 rig 4 (drive gain x0.55, inertia x0.31, 3 ticks of delay): its speed
    response's DC gain is 0.55, which a unit-DC second order cannot follow (3.0 dB / 16 deg rms,
    not a usable model: the knowledge then held the built-in article model, and the gate judged
    the tuned loop's peak sensitivity 8.2 dB on it against 2.1 dB on the true rig). Identified
    now, the knowledge's model has the fitted DC gain, close to the rig's, and is not the
    built-in one."""
    rig = draw_family(271127335, 5)[4]
    assert rig.drive_gain == pytest.approx(0.55, abs=0.01)
    known = identify(rig.plant, LoopConfig())
    assert known.model != NominalModel()
    assert known.model.dc_gain == pytest.approx(rig.drive_gain, rel=0.04)


@pytest.mark.parametrize("index", [0, 1])
@pytest.mark.timeout(1200)  # a hang's bound: 290-300 s each at load 17-20 (four busy loops)
def test_tuned_loop_on_the_true_rig(index: int) -> None:
    rig = draw_family(1, 2)[index]
    grid = BruteGrid(speed_scales=tuple(float(x) for x in np.geomspace(0.1, 3.0, 6)),
                     position_scales=(0.5, 1.0, 2.0, 3.0), cutoffs_hz=(0.3, 1.0, 3.0), keep=2)
    out = run_rig(rig, Objective(), grid=grid)
    assert out.tuned is not None, "\n".join(out.explanation)
    assert out.accepted  # judged on the true rig's exact responses
    if out.default_stable:
        assert out.vs_default < 1.0
    assert out.brute is not None
    # within 10 % of the brute force, or (the brute force's best being a loop the tune's
    # stated margins exclude) within 25 %
    assert out.vs_brute <= 1.1 or (out.brute_misses is not None and out.vs_brute <= 1.25), (
        out.vs_brute, out.brute_misses)
    # within 10 % of the brute force's best among the PIs that meet the tune's own margins on
    # the true rig, where the grid has one (seed 1: rig 0's grid has none, rig 1's 0.81)
    if out.brute_in_targets is not None:
        assert out.vs_brute_in_targets <= 1.1, out.vs_brute_in_targets
    if out.brute_misses is None:  # the brute force's best meets them: it is that one
        assert out.brute_in_targets == out.brute
