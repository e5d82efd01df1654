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


def test_one_session_leaves_the_rest_of_its_users_budget_to_the_others() -> None:
    clock = Clock()
    b = RequestBudget(10.0, burst=20.0, session_share=0.5, clock=clock)
    # The runaway session gets half the burst, then half the rate.
    assert sum(b.allow("op1", "script") for _ in range(50)) == 10
    # The same user's dashboard session is still served: the other half.
    assert sum(b.allow("op1", "dashboard") for _ in range(50)) == 10
    # Then the user's own bucket is empty: a third session gets nothing.
    assert not b.allow("op1", "ctl")
    clock.t += 1.0  # 10 tokens back for the user, 5 for each session
    assert sum(b.allow("op1", "script") for _ in range(50)) == 5
    assert sum(b.allow("op1", "dashboard") for _ in range(50)) == 5
    assert b.take_refusals() == {"op1": 40 + 40 + 1 + 45 + 45}


def test_claiming_new_sessions_buys_nothing_beyond_the_users_budget() -> None:
    clock = Clock()
    b = RequestBudget(50.0, clock=clock)  # bursts of 100; sessions 25/s, bursts of 50
    allowed = 0
    for i in range(10_000):  # 1000 requests/s for 10 s, each claiming a new session
        clock.t += 0.001
        allowed += b.allow("view", f"s{i}")
    assert 100 + 50 * 10 - 2 <= allowed <= 100 + 50 * 10 + 1  # the user's rate, no more
    # Only the buckets of the last ~2 s (a session's refill time) are kept, not 10 000.
    assert b.session_buckets <= RequestBudget.SESSIONS_PRUNE_AT + 50 * 2 + 100


def test_the_refusal_names_the_session_budget_too() -> None:
    text = RequestBudget(50.0).refusal
    assert "25/s per session" in text and "bursts of 100" in text


@pytest.mark.parametrize("share", [0.0, -0.5, 1.5, float("nan"), 0.001])
def test_bad_session_shares_are_refused(share: float) -> None:
    with pytest.raises(ValueError, match="session_share"):
        RequestBudget(10.0, burst=20.0, session_share=share)
