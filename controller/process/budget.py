"""Request budgets: token buckets per authenticated user and per session, checked before
anything is decoded.

A user may send `rate_per_s` requests a second on average and `burst` at once; a request
beyond that is refused at once with a reply naming the budget, never queued. The check is a
dictionary look-up and a few float operations under a lock: cheap enough for the Zenoh
callback of the edge process (`controller.process.edge`), before the payload is even read.

Per session, within the user's budget: one session of a user may use at most
`session_share` of the user's rate (and burst), so a runaway script leaves the rest to the
same user's other sessions (the dashboard, `dobtune ctl`). Zenoh does not prove which session
sent a query: the session is the one the query's `source_info` names (`dobtune`'s clients set
it; queries that name none share one "unnamed" session of their user). A claim can only
divide a user's own budget: the user's bucket, proven by the key scope, still bounds the sum,
so claiming other sessions buys nothing and can only starve the claimant's own user. Session
buckets are made only for requests the user's bucket allowed, and full ones are forgotten, so
their number stays bounded whatever a client claims.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

__all__ = ["RequestBudget"]


class RequestBudget:
    """Token buckets by user name and by (user, session) (thread-safe)."""

    #: Beyond this many session buckets, the full ones (refilled: the same as none) are dropped.
    SESSIONS_PRUNE_AT = 1024

    def __init__(
        self,
        rate_per_s: float,
        burst: float | None = None,
        session_share: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (math.isfinite(rate_per_s) and rate_per_s > 0):
            raise ValueError(f"rate_per_s: {rate_per_s!r} must be a positive number")
        self.rate_per_s = float(rate_per_s)
        self.burst = float(burst) if burst is not None else 2.0 * self.rate_per_s
        if not (math.isfinite(self.burst) and self.burst >= 1.0):
            raise ValueError(f"burst: {self.burst!r} must be at least 1")
        if not (math.isfinite(session_share) and 0.0 < session_share <= 1.0
                and self.burst * session_share >= 1.0):
            raise ValueError(f"session_share: {session_share!r} must be in (0, 1] and leave a "
                             f"session a burst of at least 1 (burst {self.burst:g})")
        self.session_share = float(session_share)
        self._session_rate = self.rate_per_s * self.session_share
        self._session_burst = self.burst * self.session_share
        self._clock = clock
        self._lock = threading.Lock()
        #: user -> (tokens, time of the last update)
        self._buckets: dict[str, tuple[float, float]] = {}
        #: (user, session) -> (tokens, time of the last update)
        self._sessions: dict[tuple[str, str], tuple[float, float]] = {}
        self._pruned_at = -math.inf
        #: user -> requests refused since the last `take_refusals`
        self._refused: dict[str, int] = {}

    @property
    def refusal(self) -> str:
        """The refusal's text (names the budget)."""
        return (f"request budget exceeded: {self.rate_per_s:g} requests/s per user "
                f"(bursts of {self.burst:g}), {self._session_rate:g}/s per session of the "
                f"user (bursts of {self._session_burst:g}); slow down")

    @property
    def session_buckets(self) -> int:
        return len(self._sessions)

    def allow(self, user: str, session: str | None = None) -> bool:
        """Take one token of `user`'s bucket (and of the session's, when `session` is given:
        both or neither); False (and counted) when either is empty."""
        now = self._clock()
        with self._lock:
            tokens, then = self._buckets.get(user, (self.burst, now))
            tokens = min(self.burst, tokens + (now - then) * self.rate_per_s)
            if tokens < 1.0:
                self._buckets[user] = (tokens, now)
                self._refused[user] = self._refused.get(user, 0) + 1
                return False
            if session is not None:
                sessions = self._sessions
                k = (user, session)
                s_tokens, s_then = sessions.get(k, (self._session_burst, now))
                s_tokens = min(self._session_burst,
                               s_tokens + (now - s_then) * self._session_rate)
                if s_tokens < 1.0:
                    sessions[k] = (s_tokens, now)
                    self._buckets[user] = (tokens, now)
                    self._refused[user] = self._refused.get(user, 0) + 1
                    return False
                sessions[k] = (s_tokens - 1.0, now)
                if len(sessions) > self.SESSIONS_PRUNE_AT and now - self._pruned_at >= 1.0:
                    self._prune(now)
            self._buckets[user] = (tokens - 1.0, now)
            return True

    def _prune(self, now: float) -> None:
        self._pruned_at = now
        rate, burst = self._session_rate, self._session_burst
        full = [k for k, (t, then) in self._sessions.items()
                if t + (now - then) * rate >= burst]
        for k in full:
            del self._sessions[k]

    def take_refusals(self) -> dict[str, int]:
        """Refusals by user since the previous call (for the audit and the status)."""
        with self._lock:
            out, self._refused = self._refused, {}
        return out
