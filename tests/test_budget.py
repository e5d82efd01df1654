"""The per-user request budget (controller/process/budget.py), on a clock the test moves."""

from __future__ import annotations

import pytest

from controller.process.budget import RequestBudget


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_a_burst_then_the_rate_and_users_apart() -> None:
    clock = Clock()
    b = RequestBudget(10.0, burst=5.0, clock=clock)
    assert [b.allow("view") for _ in range(7)] == [True] * 5 + [False] * 2
    assert b.allow("op1")  # another user's bucket is full
    clock.t += 0.15  # one token and a half back at 10/s
    assert b.allow("view") and not b.allow("view")
    clock.t += 10.0  # refilled to the burst, never beyond
    assert sum(b.allow("view") for _ in range(20)) == 5
    assert b.take_refusals() == {"view": 2 + 1 + 15}
    assert b.take_refusals() == {}


def test_a_steady_sender_gets_the_rate() -> None:
    clock = Clock()
    b = RequestBudget(50.0, clock=clock)  # bursts of 100
    allowed = 0
    for _ in range(10_000):  # 1000 requests/s for 10 s
        clock.t += 0.001
        allowed += b.allow("view")
    assert 100 + 50 * 10 - 2 <= allowed <= 100 + 50 * 10 + 1


def test_the_refusal_names_the_budget() -> None:
    assert RequestBudget(50.0).refusal.startswith(
        "request budget exceeded: 50 requests/s per user")


@pytest.mark.parametrize("rate, burst", [(0.0, None), (-1.0, None), (float("nan"), None),
                                         (10.0, 0.5), (10.0, float("inf"))])
def test_bad_budgets_are_refused(rate: float, burst: float | None) -> None:
    with pytest.raises(ValueError):
        RequestBudget(rate, burst)
