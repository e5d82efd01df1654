"""The starting speed PI: the procedure's result against python-control, and the default
configuration is that result (rounded), not a fitted number."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import control as ct
import numpy as np
import pytest

from controller.cli.inputs import load_config
from controller.core.config import LoopConfig
from controller.gate.analysis import analyse
from controller.gate.knowledge import PlantKnowledge
from controller.tune.starting_loop import ARTICLE_BOUND, starting_loop, starting_speed_pi

MP = ct.tf([1.0], [1.013e-05, 0.004501, 1.0]) * ct.tf(
    [1.013e-05, 0.004501, 1.0], [0.0005169, 0.03215, 1.0]
)
DELAY = ct.tf(*ct.pade(1e-3, 7))  # one tick


def _margins(kp: float, ki: float) -> tuple[float, float, float]:
    """(gain margin dB, phase margin deg, crossover Hz) of Cv M P e^{-sT}, python-control."""
    loop = ct.tf([kp, kp * ki], [1.0, 0.0]) * MP * DELAY
    gm, pm, _, wc = ct.margin(loop)
    return 20 * math.log10(gm), pm, wc / (2 * math.pi)


def test_procedure_places_the_crossover_for_the_stated_phase_margin() -> None:
    pi = starting_speed_pi()
    gm_db, pm, fc = _margins(pi.kp, pi.ki_per_s)
    assert pm == pytest.approx(60.0, abs=0.1)
    assert fc == pytest.approx(pi.crossover_hz, rel=1e-3)
    assert pi.ki_per_s == pytest.approx(2 * math.pi * fc / 4.0, rel=1e-3)
    assert gm_db > 20.0
    # Another margin gives another crossover: the procedure, not a constant.
    assert starting_speed_pi(phase_margin_deg=45.0).crossover_hz > pi.crossover_hz


def test_default_config_is_the_procedures_result() -> None:
    cfg = LoopConfig()
    chosen, pi, peak = starting_loop(cfg)
    assert chosen == cfg  # the default is exactly what the procedure gives (rounded)
    assert cfg.cv_kp == float(f"{pi.kp:.3g}") and cfg.cv_ki_per_s == float(f"{pi.ki_per_s:.3g}")
    gm_db, pm, fc = _margins(cfg.cv_kp, cfg.cv_ki_per_s)
    corner_hz = cfg.cv_ki_per_s / (2 * math.pi)
    assert corner_hz <= fc / 3.0  # a conventional PI: corner at or below a third of crossover
    assert pm == pytest.approx(pi.phase_margin_deg, abs=1.0) and gm_db > 20.0
    # Step 4: the margin was raised only as far as robustness to the article's bound needs.
    assert peak <= 0.7
    lower = starting_speed_pi(cfg.nominal, cfg.rate_hz, pi.phase_margin_deg - 5.0)
    softer = cfg.with_(cv_kp=float(f"{lower.kp:.3g}"), cv_ki_per_s=float(f"{lower.ki_per_s:.3g}"))
    assert analyse(softer, PlantKnowledge(bound=ARTICLE_BOUND)).small_gain_peak > 0.7


def _robust_peak_python_control(kp: float, ki: float) -> float:
    """||W T|| of the speed loop alone (continuous, python-control) for control.md's bound."""
    loop = ct.tf([kp, kp * ki], [1.0, 0.0]) * MP * DELAY
    t = ct.feedback(loop, 1)
    num, den = ARTICLE_BOUND.transfer_function()
    w = ct.tf(list(num), list(den))
    f = np.geomspace(0.1, 200.0, 4000)
    return float(np.max(np.abs(np.asarray((w * t)(2j * np.pi * f)).ravel())))


def test_robustness_rises_with_the_phase_margin_by_python_control() -> None:
    # The trend step 4 relies on, computed independently of the gate (speed loop only).
    peaks = []
    for pm in (60.0, 65.0, 70.0, 75.0):
        pi = starting_speed_pi(phase_margin_deg=pm)
        peaks.append(_robust_peak_python_control(pi.kp, pi.ki_per_s))
    assert all(a > b for a, b in itertools.pairwise(peaks))


def test_position_loop_keeps_margins_around_the_closed_speed_loop() -> None:
    cfg = LoopConfig()
    speed = ct.feedback(
        ct.tf([cfg.cv_kp, cfg.cv_kp * cfg.cv_ki_per_s], [1.0, 0.0]) * MP * DELAY, 1
    )
    cp = ct.tf([cfg.pos_kp_per_s, cfg.pos_kp_per_s * cfg.pos_ki_per_s], [1.0, 0.0])
    gm, pm, _, wc = ct.margin(cp * speed * ct.tf([1.0], [1.0, 0.0]))
    assert pm > 45.0 and 20 * math.log10(gm) > 10.0
    assert wc / (2 * math.pi) < starting_loop()[1].crossover_hz / 4.0  # cascade separation


def test_old_loop_example_is_the_earlier_guess() -> None:
    old = load_config(Path(__file__).resolve().parents[1] / "examples" / "loop_cv_0.5_55.json")
    assert (old.cv_kp, old.cv_ki_per_s) == (0.5, 55.0)
    assert old.with_(cv_kp=LoopConfig().cv_kp, cv_ki_per_s=LoopConfig().cv_ki_per_s) == LoopConfig()
    _, _, fc = _margins(old.cv_kp, old.cv_ki_per_s)
    assert old.cv_ki_per_s / (2 * math.pi) > fc  # its corner sits above its crossover
    assert np.isfinite(fc)
