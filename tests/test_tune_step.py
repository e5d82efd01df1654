"""The guided path's "Tune the whole loop" step (server/panels/tune_step.py; issue 35 item 3):
its objective from the controls (bad values named), a viewer's press refused before anything
runs, and a real tune for the peak objective put into the candidate, nothing else changed.

The tune itself is `controller.tune.whole_loop.tune_whole_loop` (tests/test_whole_loop.py);
the page's path on the demo is in tests/browser/test_guide_browser.py."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import pytest

from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from server.engine import TuningEngine
from server.gui import Browser
from server.http_access import Refused
from server.panels.tune_step import METRICS, TuneStep, objective_of, objective_text, tune_html


@dataclass
class Target:
    """A candidate panel as the step sees it (`TuneTarget`): what was loaded is recorded."""

    engine: TuningEngine = field(default_factory=TuningEngine)
    trajectory: Trajectory = field(default_factory=Trajectory)
    base_version: int | None = 3
    config: LoopConfig = field(default_factory=LoopConfig)
    loads: list[tuple[LoopConfig, int | None, str]] = field(default_factory=list)

    def candidate(self) -> LoopConfig:
        return self.config

    def load(self, a: LoopConfig, version: int | None, say_text: str = "") -> None:
        self.loads.append((a, version, say_text))
        self.config = a


def test_the_objective_comes_from_the_controls_and_bad_values_are_named() -> None:
    traj = Trajectory()
    o = objective_of(traj, "peak |error|", 0.0, 12.6)
    assert (o.metric, o.noise_budget_deg_s, o.duration_s) == ("peak", None, 12.6)
    assert "peak |error|" in objective_text(o) and "twice the designed loop" in objective_text(o)
    o = objective_of(traj, "tracking RMSE", 2.5, 3.0)
    assert (o.metric, o.noise_budget_deg_s) == ("rmse", 2.5)
    assert o.duration_s == 8.0  # at least MIN_RUN_S: the objective needs more than 2.5 s
    assert "2.5 deg/s" in objective_text(o)
    with pytest.raises(ValueError, match="objective"):
        objective_of(traj, "bogus", 0.0, 12.6)
    for bad in (-1.0, math.nan, math.inf, 1e6):
        with pytest.raises(ValueError, match="noise_budget_deg_s"):
            objective_of(traj, "tracking RMSE", bad, 12.6)
    assert set(METRICS.values()) == {"rmse", "peak"}


def test_a_viewers_press_is_refused_before_anything_runs() -> None:
    asked: list[tuple[Browser, str]] = []

    def viewer(browser: Browser, action: str) -> None:
        asked.append((browser, action))
        raise Refused(f"{action}: view is a viewer")

    target = Target()
    step = TuneStep(target, authorize=viewer, may_change=False)
    assert "operators only" in step.state.text
    step.start()
    try:
        assert step.request(None) is False
        assert step.wait_idle(5.0)
    finally:
        step.stop()
    assert asked == [(None, "tune the whole loop")]
    assert step.state.state == "todo" and step.last is None and target.loads == []


def test_the_peak_objective_is_tuned_and_put_into_the_candidate_only() -> None:
    target = Target()
    start = target.config
    step = TuneStep(target, authorize=lambda _b, _a: None)
    step.start()
    try:
        # The controls' values (no GUI here: what the dropdown and the field would hold).
        step.metric = SimpleNamespace(value="peak |error|")  # type: ignore[assignment]
        step.budget = SimpleNamespace(value=0.0)  # type: ignore[assignment]
        assert step.request(None) is True
        assert step.wait_idle(600.0)
    finally:
        step.stop()
    res = step.last
    assert step.state.state == "done", step.state.text
    assert res is not None and res.best is not None
    assert res.objective.metric == "peak" and res.objective.noise_budget_deg_s is None
    assert res.best.peak_error_deg < res.start.peak_error_deg
    assert len(target.loads) == 1
    cfg, version, said = target.loads[0]
    assert cfg == res.best.config and version == 3 and "not applied" in said
    assert (cfg.cv_kp, cfg.pos_kp_per_s) != (start.cv_kp, start.pos_kp_per_s)
    html = tune_html(res, 1.0)
    assert f"speed PI Kp {cfg.cv_kp:.3g}" in html and "peak |error|" in html
    assert "built-in model" in html  # nothing measured: said
