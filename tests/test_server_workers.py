"""The dashboard's worker threads: only the newest item runs, a failure is logged (with its
traceback) and the worker goes on."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from server.workers import LatestWins, Periodic, Requests


def _boom(_item: object) -> None:
    raise RuntimeError("boom")


def test_latest_wins_runs_only_the_newest_item() -> None:
    seen: list[int] = []
    gate = threading.Event()
    running = threading.Event()

    def slow(item: int) -> None:
        running.set()
        gate.wait(5.0)
        seen.append(item)

    w = LatestWins(slow, name="test-latest")
    w.start()
    try:
        w.submit(0)
        assert running.wait(10.0)  # 0 is running and blocked
        for k in range(1, 10):
            w.submit(k)
        gate.set()
        assert w.wait_idle(5.0)
    finally:
        w.stop()
    assert seen == [0, 9]


def test_latest_wins_logs_a_failure_and_goes_on(caplog: pytest.LogCaptureFixture) -> None:
    seen: list[int] = []
    w = LatestWins(lambda item: _boom(item) if item == 1 else seen.append(item), name="t-fail")
    w.start()
    try:
        with caplog.at_level(logging.ERROR, logger="server.workers"):
            w.submit(1)
            assert w.wait_idle(5.0)
            w.submit(2)
            assert w.wait_idle(5.0)
    finally:
        w.stop()
    assert seen == [2]
    assert any("t-fail failed" in r.getMessage() and r.exc_info for r in caplog.records)


def test_periodic_keeps_running_after_a_failure(caplog: pytest.LogCaptureFixture) -> None:
    calls: list[int] = []

    def fn(k: int) -> None:
        calls.append(k)
        if k == 0:
            raise RuntimeError("first call fails")

    p = Periodic(fn, 0.01, name="t-periodic")
    with caplog.at_level(logging.ERROR, logger="server.workers"):
        p.start()
        end = time.monotonic() + 5.0
        while len(calls) < 3 and time.monotonic() < end:
            time.sleep(0.01)
        p.stop()
    assert calls[:3] == [0, 1, 2]
    assert any("t-periodic failed" in r.getMessage() for r in caplog.records)


def test_requests_log_what_a_future_would_keep(caplog: pytest.LogCaptureFixture) -> None:
    r = Requests(max_workers=1, name="t-req")
    with caplog.at_level(logging.ERROR, logger="server.workers"):
        r.submit(_boom, None).result(5.0)
    r.shutdown()
    assert any("_boom failed" in rec.getMessage() and rec.exc_info for rec in caplog.records)


def test_a_stop_racing_the_start_never_joins_an_unstarted_thread() -> None:
    """The dashboard closing while a browser's panel is being built (seen in a test teardown:
    "RuntimeError: cannot join thread before it is started" from LatestWins.stop)."""
    errors: list[BaseException] = []
    for _ in range(200):
        w: LatestWins[int] = LatestWins(fn=lambda _i: None, name="race")
        go = threading.Barrier(2)

        def stopper(worker: LatestWins[int] = w, barrier: threading.Barrier = go) -> None:
            barrier.wait()
            try:
                worker.stop()
            except BaseException as exc:  # collected and asserted below
                errors.append(exc)

        t = threading.Thread(target=stopper)
        t.start()
        go.wait()
        w.start()
        t.join()
        w.stop()
        assert w._thread is None or not w._thread.is_alive()
    assert errors == []


def test_a_worker_stopped_before_it_starts_starts_no_thread() -> None:
    w: LatestWins[int] = LatestWins(fn=lambda _i: None)
    w.stop()
    w.start()
    assert w._thread is None


def test_a_periodic_stopped_before_it_starts_starts_no_thread() -> None:
    p = Periodic(lambda _k: None, 0.01, name="t-never")
    p.stop()
    p.start()
    assert p._thread is None
