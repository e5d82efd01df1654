"""Request budgets: a token bucket per authenticated user, checked before anything is decoded.

A user may send `rate_per_s` requests a second on average and `burst` at once; a request
beyond that is refused at once with a reply naming the budget, never queued. The check is a
dictionary look-up and a few float operations under a lock: cheap enough for the Zenoh
callback of the edge process (`controller.process.edge`), before the payload is even read.

Per session: Zenoh does not tell a queryable which session sent a query (no source info on a
query unless the sender sets it, which would be its claim), so the budget is per user, the
identity the access control proves (the key scope); every session of a user shares it.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

__all__ = ["RequestBudget"]


class RequestBudget:
    """Token buckets by user name (thread-safe)."""

    def __init__(
        self,
        rate_per_s: float,
        burst: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (math.isfinite(rate_per_s) and rate_per_s > 0):
            raise ValueError(f"rate_per_s: {rate_per_s!r} must be a positive number")
        self.rate_per_s = float(rate_per_s)
        self.burst = float(burst) if burst is not None else 2.0 * self.rate_per_s
        if not (math.isfinite(self.burst) and self.burst >= 1.0):
            raise ValueError(f"burst: {self.burst!r} must be at least 1")
        self._clock = clock
        self._lock = threading.Lock()
        #: user -> (tokens, time of the last update)
        self._buckets: dict[str, tuple[float, float]] = {}
        #: user -> requests refused since the last `take_refusals`
        self._refused: dict[str, int] = {}

    @property
    def refusal(self) -> str:
        """The refusal's text (names the budget)."""
        return (f"request budget exceeded: {self.rate_per_s:g} requests/s per user "
                f"(bursts of {self.burst:g}); slow down")

    def allow(self, user: str) -> bool:
        """Take one token of `user`'s bucket; False (and counted) when it is empty."""
        now = self._clock()
        with self._lock:
            tokens, then = self._buckets.get(user, (self.burst, now))
            tokens = min(self.burst, tokens + (now - then) * self.rate_per_s)
            if tokens >= 1.0:
                self._buckets[user] = (tokens - 1.0, now)
                return True
            self._buckets[user] = (tokens, now)
            self._refused[user] = self._refused.get(user, 0) + 1
            return False

    def take_refusals(self) -> dict[str, int]:
        """Refusals by user since the previous call (for the audit and the status)."""
        with self._lock:
            out, self._refused = self._refused, {}
        return out
