"""The approach onto a trajectory: bounded speed and acceleration, no jump, then hand-over."""

from __future__ import annotations

import itertools
import math

import pytest

from controller.core.ramp import Ramp


def _follow(ramp: Ramp, target: object, max_ticks: int = 200_000) -> list[float]:
    refs = []
    for k in range(max_ticks):
        t = k * ramp.period_s
        pos, speed = target(t)  # type: ignore[operator]
        refs.append(ramp.step(pos, speed))
        if not ramp.active:
            break
    return refs


def sine(t: float) -> tuple[float, float]:
    return 5.0 * math.sin(0.5 * t), 2.5 * math.cos(0.5 * t)


@pytest.mark.parametrize(
    ("start", "speed"), [(150.0, 0.0), (-3.0, 5.0), (0.0, 0.0), (-400.0, -50.0)]
)
def test_speed_and_acceleration_stay_bounded_and_it_hands_over(start: float, speed: float) -> None:
    ramp = Ramp(0.001, speed_max_deg_s=20.0, accel_max_deg_s2=40.0)
    ramp.begin(start, speed)
    refs = [start, *_follow(ramp, sine)]
    assert not ramp.active  # caught the trajectory
    speeds = [(b - a) / 0.001 for a, b in itertools.pairwise(refs)]
    accels = [(b - a) / 0.001 for a, b in itertools.pairwise(speeds)]
    assert max(abs(v) for v in speeds) <= 20.0 + 1e-6
    assert max(abs(a) for a in accels[1:]) <= 40.0 + 1e-3
    assert abs(refs[-1] - sine(len(refs) * 0.001 - 0.002)[0]) < 0.01


def test_a_target_faster_than_the_bound_is_followed_at_the_bound() -> None:
    ramp = Ramp(0.001, speed_max_deg_s=10.0, accel_max_deg_s2=100.0)
    ramp.begin(0.0)
    refs = _follow(ramp, lambda t: (50.0 * t, 50.0), max_ticks=5000)
    assert ramp.active and abs(ramp.speed_deg_s) <= 10.0
    assert refs[-1] == pytest.approx(10.0 * 5.0 - 0.5 * 10.0**2 / 100.0, abs=0.05)


def test_parameters_are_validated() -> None:
    with pytest.raises(ValueError, match="period_s"):
        Ramp(0.0)
    with pytest.raises(ValueError, match="speed_max"):
        Ramp(0.001, speed_max_deg_s=math.inf)
    with pytest.raises(ValueError, match="accel_max"):
        Ramp(0.001, accel_max_deg_s2=-1.0)
