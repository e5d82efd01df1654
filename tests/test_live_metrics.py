"""The live metrics' window (server/panels/live.py metrics_window): a whole number of the
running trajectory's periods (issue 33: the default 10 s window over the sine's 12.6 s period
made the RMSE of a steady loop wander with where the window cut the sine)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.panels.live import metrics_window, window_metrics

SINE_PERIOD_S = 2 * math.pi / 0.5  # the demo's 5 sin(0.5 t)


def test_the_window_is_a_whole_number_of_periods_at_least_one() -> None:
    assert metrics_window(10.0, SINE_PERIOD_S) == (pytest.approx(SINE_PERIOD_S),
                                                   "last 1 period (12.6 s)")
    assert metrics_window(30.0, SINE_PERIOD_S) == (pytest.approx(2 * SINE_PERIOD_S),
                                                   "last 2 periods (25.1 s)")
    assert metrics_window(10.0, None) == (10.0, "last 10 s")  # a step, a hold: no period
    assert metrics_window(10.0, math.inf) == (10.0, "last 10 s")


def test_a_steady_error_reads_the_same_wherever_the_window_ends() -> None:
    """A steady periodic error e = 0.03 sqrt(2) sin(0.5 t) + 0.01 sin(1.5 t): over a whole
    period its RMSE is sqrt(0.03^2 + 0.01^2 / 2) (closed form) wherever the window ends; over
    10 s it wandered by several per cent."""
    dt = 1e-3
    t = np.arange(0.0, 60.0, dt)
    e = 0.03 * math.sqrt(2) * np.sin(0.5 * t) + 0.01 * np.sin(1.5 * t)
    exact = math.sqrt(0.03**2 + 0.01**2 / 2)
    span, _ = metrics_window(10.0, SINE_PERIOD_S)
    whole, ten = [], []
    for end in np.linspace(30.0, 45.0, 31):
        for width, out in ((span, whole), (10.0, ten)):
            sel = (t > end - width) & (t <= end)
            out.append(window_metrics(e[sel])[1])
    assert max(abs(r / exact - 1) for r in whole) < 2e-3
    assert max(ten) / min(ten) - 1 > 0.05  # what the 10 s window did
