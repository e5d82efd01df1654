"""Reference trajectories: closed-form values and validation."""

from __future__ import annotations

import math

import pytest

from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory, default_trajectory


def test_default_is_the_article_sine() -> None:
    tr = Trajectory()
    for t in (0.0, 1.0, 3.3, 12.0):
        p, v = tr.at(t)
        assert p == pytest.approx(5 * math.sin(0.5 * t), abs=1e-12)
        assert v == pytest.approx(2.5 * math.cos(0.5 * t), abs=1e-12)
    assert tr.period_s == pytest.approx(4 * math.pi)


def test_step_ramp_hold() -> None:
    step = default_trajectory("step")
    assert step.at(step.step_time_s - 1e-9)[0] == 0.0
    assert step.at(step.step_time_s)[0] == 5.0
    ramp = default_trajectory("ramp")
    assert ramp.at(7.0) == (7.0, 1.0)
    hold = default_trajectory("hold")
    assert hold.at(100.0) == (40.0, 0.0)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"kind": "zigzag"}, "kind"),
        ({"amplitude_deg": float("nan")}, "amplitude_deg"),
        ({"omega_rad_s": -0.1}, "omega_rad_s"),
        ({"slope_deg_s": "1"}, "slope_deg_s"),
        ({"step_time_s": float("inf")}, "step_time_s"),
    ],
)
def test_bad_values(kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(ConfigError) as info:
        Trajectory(**kwargs)  # type: ignore[arg-type]
    assert info.value.field == field
