"""The dashboard's worker threads: GUI callbacks only hand work to these and return.

- `LatestWins`: runs a function on the newest submitted item only (slider moves).
- `Periodic`: runs a function at a fixed rate (the live refresh).
- `Requests`: a small pool for blocking controller queries (apply, commands, uploads).
- `Refetch`: a query in that pool whenever a version the controller's status carries moves.
A failing run is logged with its traceback; the worker carries on.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Generic, TypeVar

__all__ = ["LatestWins", "Periodic", "Refetch", "Requests"]

log = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")


@dataclass
class LatestWins(Generic[T]):
    """A worker thread that runs `fn(item)` for the newest submitted item only."""

    fn: Callable[[T], None]
    name: str = "latest-wins"
    #: Wait this long for a newer item before running (keeps slow work off a moving slider).
    debounce_s: float = 0.0
    _item: T | None = None
    _has: bool = False
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _stop: bool = False
    _busy: bool = False
    _thread: threading.Thread | None = None

    def start(self) -> None:
        # Under the lock, so that a stop() from another thread (the dashboard closing while a
        # browser's panel is being built) never joins a thread that is not started yet.
        with self._cond:
            if self._stop:
                return
            self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
            self._thread.start()

    def submit(self, item: T) -> None:
        with self._cond:
            self._item = item
            self._has = True
            self._cond.notify()

    def idle(self) -> bool:
        with self._cond:
            return not self._has and not self._busy

    def wait_idle(self, timeout_s: float = 5.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.idle():
                return True
            time.sleep(0.002)
        return False

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
            thread = self._thread
        if thread is not None:
            thread.join(timeout=5.0)

    def _next(self) -> tuple[bool, T | None]:
        """Wait for the newest item (after the debounce); (False, None) when stopped."""
        with self._cond:
            while not self._has and not self._stop:
                self._cond.wait()
            if self._stop:
                return False, None
            self._busy = True
            if self.debounce_s > 0.0:
                while self._has and not self._stop:
                    self._has = False
                    self._cond.wait(self.debounce_s)
                if self._stop:
                    return False, None
            item, self._item, self._has = self._item, None, False
            return True, item

    def _run(self) -> None:
        while True:
            more, item = self._next()
            if not more:
                return
            try:
                run_logged(self.fn, item, what=self.name)
            finally:
                with self._cond:
                    self._busy = False


class Periodic:
    """A daemon thread that calls `fn(k)` (k = 0, 1, ...) every `period_s` until stopped.

    A late call is not made up for: after a stall the schedule restarts from now."""

    def __init__(self, fn: Callable[[int], None], period_s: float, name: str) -> None:
        self.fn = fn
        self.period_s = period_s
        self.name = name
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        # Under the lock, so that a stop() from another thread (the dashboard closing while a
        # browser's panel is being built) never joins a thread that is not started yet.
        with self._lock:
            if self._stop.is_set():
                return
            self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        with self._lock:
            thread = self._thread
        if thread is not None:
            thread.join(timeout=5.0)

    def _run(self) -> None:
        period = self.period_s
        next_t = time.monotonic()
        k = 0
        while not self._stop.is_set():
            run_logged(self.fn, k, what=self.name)
            k += 1
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:
                next_t = time.monotonic()
                delay = 0.0
            self._stop.wait(max(delay, 0.0))


class Requests:
    """A thread pool for blocking work; every failure is logged (a Future would keep it)."""

    def __init__(self, max_workers: int = 2, name: str = "ctl-request") -> None:
        self._pool = ThreadPoolExecutor(max_workers=max_workers, thread_name_prefix=name)

    def submit(self, fn: Callable[..., R], *args: object) -> Future[R | None]:
        return self._pool.submit(run_logged, fn, *args, what=getattr(fn, "__name__", "request"))

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)


class Refetch:
    """`fetch()` in `requests` whenever the version seen moves (`note`, from each status);
    `forget()` after a failed fetch makes the next status fetch again."""

    def __init__(self, requests: Requests, fetch: Callable[[], None]) -> None:
        self._requests = requests
        self._fetch = fetch
        self.version = -1
        """The version last fetched, or being fetched (-1: none)."""

    def note(self, version: int) -> None:
        if version != self.version:
            self.version = version
            self._requests.submit(self._fetch)

    def forget(self) -> None:
        self.version = -1


def run_logged(fn: Callable[..., R], *args: object, what: str) -> R | None:
    """`fn(*args)`; an exception is logged with its traceback instead of raised."""
    try:
        return fn(*args)
    except Exception:
        log.exception("%s failed", what)
        return None
