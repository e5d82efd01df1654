"""The operator lease: one operator at a time may change a rig.

Pure logic: no I/O, no threads, no clock. Every call takes `now_s` (monotonic seconds, read by
the caller); the caller serialises calls (one lock, or one thread) and records the returned
events in the audit log.

- `acquire` grants the lease to an operator when nobody holds it; `take_over` grants it even
  when someone does (the event names who was displaced); viewers can do neither.
- A lease is a random token (`secrets.token_urlsafe`) bound to the user name, valid on
  [granted, expires_at_s): `renew` moves the expiry, `release` ends it, and it expires on its
  own. The token stays the same across renewals.
- `authorize` accepts only the holder's token presented by the holder's user name. Refusals
  name the reason: another user's token, an expired, released or taken-over token (a replayed
  old one), an unknown token. With `allow_unleased` (the caller's policy, e.g. on
  loopback without authentication) a request without a token is served while nobody holds the
  lease.
- Calls may arrive with a `now_s` slightly older than one already seen (threads read the clock
  before taking the lock): time never runs backwards here, the latest `now_s` wins.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import secrets
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Any

__all__ = [
    "ACQUIRE",
    "EXPIRE",
    "RELEASE",
    "RENEW",
    "ROLES",
    "TAKEOVER",
    "Authorization",
    "Lease",
    "LeaseEvent",
    "LeaseResult",
    "LeaseStatus",
    "token_id",
]

ACQUIRE, RENEW, RELEASE, TAKEOVER, EXPIRE = (
    "lease.acquire", "lease.renew", "lease.release", "lease.takeover", "lease.expire",
)
#: Roles known to the lease; only operators may hold it.
ROLES = ("viewer", "operator")
HOLDER_ROLES = ("operator",)


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def token_id(token: str) -> str:
    """A short fingerprint of a token, to correlate audit records without writing the token."""
    return _digest(token)[:12]


@dataclass(frozen=True)
class LeaseEvent:
    """One lease change or refusal, for the audit log (it never holds a token)."""

    action: str  #: ACQUIRE, RENEW, RELEASE, TAKEOVER or EXPIRE
    user: str  #: who asked (EXPIRE: whose lease ended)
    granted: bool  #: False: refused (EXPIRE: always True, it happened)
    reason: str  #: why refused ("" when granted)
    at_s: float  #: when (EXPIRE: the instant the lease ran out)
    holder: str  #: who holds the lease after the event ("" nobody)
    displaced: str = ""  #: TAKEOVER: who lost the lease
    expires_in_s: float = 0.0  #: the holder's remaining time after the event
    token_id: str = ""  #: fingerprint of the lease concerned ("" none)

    @property
    def outcome(self) -> str:
        """The audit outcome: accepted / refused, noted for an expiry."""
        if self.action == EXPIRE:
            return "noted"
        return "accepted" if self.granted else "refused"

    def audit_fields(self) -> dict[str, Any]:
        """The fields to record besides action, user and outcome."""
        fields: dict[str, Any] = {"holder": self.holder, "lease_expires_in_s": self.expires_in_s}
        if self.reason:
            fields["reason"] = self.reason
        if self.displaced:
            fields["displaced"] = self.displaced
        if self.token_id:
            fields["token_id"] = self.token_id
        return fields


@dataclass(frozen=True)
class LeaseResult:
    """The answer to a lease request: its events (an expiry noticed first, then the request's
    own event, always last) and the token when the lease was granted or renewed."""

    events: tuple[LeaseEvent, ...]
    token: str = ""

    @property
    def ok(self) -> bool:
        return self.events[-1].granted

    @property
    def reason(self) -> str:
        return self.events[-1].reason


@dataclass(frozen=True)
class Authorization:
    """Whether a request may change the rig."""

    ok: bool
    reason: str  #: why not ("" when ok)
    holder: str  #: the lease holder ("" nobody)
    #: served without a lease because nobody holds it and the caller allows that
    unleased: bool = False


@dataclass(frozen=True)
class LeaseStatus:
    """For the Status message."""

    holder: str  #: "" nobody
    expires_in_s: float  #: 0 when nobody holds the lease


@dataclass(frozen=True)
class _Held:
    user: str
    token: str
    token_id: str
    expires_at_s: float


class Lease:
    """The lease of one rig. Not thread-safe: the caller serialises calls."""

    def __init__(self, *, max_duration_s: float = 600.0, remember_tokens: int = 256) -> None:
        """`max_duration_s`: the longest grant or renewal; `remember_tokens`: how many ended
        leases are remembered to explain why their token is refused."""
        self.max_duration_s = max_duration_s
        self._remember = remember_tokens
        self._held: _Held | None = None
        self._ended: OrderedDict[str, tuple[str, str]] = OrderedDict()  # digest -> user, why
        self._now_s = -math.inf

    # -- requests ----------------------------------------------------------------------------

    def acquire(self, user: str, role: str, duration_s: float, now_s: float) -> LeaseResult:
        """Take the lease if nobody holds it."""
        now, events = self._advance(now_s)
        why = self._may_hold(user, role) or self._duration_error(duration_s)
        h = self._held
        if not why and h is not None:
            why = (
                "you already hold the lease: renew it, or take over for a new token"
                if h.user == user
                else f"held by {h.user} for {h.expires_at_s - now:.1f} s more"
            )
        if why:
            return LeaseResult((*events, self._event(ACQUIRE, user, False, why, now)))
        return self._grant(ACQUIRE, user, duration_s, now, events, displaced="")

    def take_over(self, user: str, role: str, duration_s: float, now_s: float) -> LeaseResult:
        """Take the lease from whoever holds it (an explicit, recorded displacement)."""
        now, events = self._advance(now_s)
        why = self._may_hold(user, role) or self._duration_error(duration_s)
        if why:
            return LeaseResult((*events, self._event(TAKEOVER, user, False, why, now)))
        h = self._held
        displaced = ""
        if h is not None:
            displaced = h.user
            self._end(f"taken over by {user}")
        return self._grant(TAKEOVER, user, duration_s, now, events, displaced=displaced)

    def renew(self, user: str, token: str, duration_s: float, now_s: float) -> LeaseResult:
        """Move the expiry of the holder's lease to `now_s + duration_s`."""
        now, events = self._advance(now_s)
        why = self._token_error(user, token, now) or self._duration_error(duration_s)
        if why:
            return LeaseResult((*events, self._event(RENEW, user, False, why, now)))
        assert self._held is not None
        self._held = replace(self._held, expires_at_s=now + duration_s)
        return LeaseResult((*events, self._event(RENEW, user, True, "", now)), token)

    def release(self, user: str, token: str, now_s: float) -> LeaseResult:
        """End the holder's lease."""
        now, events = self._advance(now_s)
        why = self._token_error(user, token, now)
        if why:
            return LeaseResult((*events, self._event(RELEASE, user, False, why, now)))
        tid = self._end("released")
        return LeaseResult((*events, self._event(RELEASE, user, True, "", now, tid=tid)))

    def expire(self, now_s: float) -> tuple[LeaseEvent, ...]:
        """The expiry event if the lease ran out by `now_s` (call it periodically, so that an
        expiry is recorded even when no request comes)."""
        return self._advance(now_s)[1]

    # -- queries (no change of state) --------------------------------------------------------

    def authorize(
        self, user: str, token: str | None, now_s: float, *, allow_unleased: bool = False
    ) -> Authorization:
        """May `user` presenting `token` change the rig now?"""
        now = max(now_s, self._now_s)
        holder = self._holder(now)
        if not token:
            if holder:
                return Authorization(False, f"the lease is held by {holder}", holder)
            if allow_unleased:
                return Authorization(True, "", "", unleased=True)
            return Authorization(False, "nobody holds the lease: acquire it first", "")
        why = self._token_error(user, token, now)
        return Authorization(not why, why, holder)

    def status(self, now_s: float) -> LeaseStatus:
        now = max(now_s, self._now_s)
        holder = self._holder(now)
        if not holder:
            return LeaseStatus("", 0.0)
        assert self._held is not None
        return LeaseStatus(holder, self._held.expires_at_s - now)

    # -- internals ---------------------------------------------------------------------------

    def _holder(self, now: float) -> str:
        h = self._held
        return h.user if h is not None and now < h.expires_at_s else ""

    def _advance(self, now_s: float) -> tuple[float, tuple[LeaseEvent, ...]]:
        """Move time to `now_s` (never back); end the lease if it ran out."""
        self._now_s = now = max(now_s, self._now_s)
        h = self._held
        if h is None or now < h.expires_at_s:
            return now, ()
        self._end("expired")
        return now, (
            LeaseEvent(EXPIRE, h.user, True, "", h.expires_at_s, "", token_id=h.token_id),
        )

    def _grant(
        self,
        action: str,
        user: str,
        duration_s: float,
        now: float,
        events: tuple[LeaseEvent, ...],
        displaced: str,
    ) -> LeaseResult:
        token = secrets.token_urlsafe(32)
        self._held = _Held(user, token, token_id(token), now + duration_s)
        event = self._event(action, user, True, "", now, displaced=displaced)
        return LeaseResult((*events, event), token)

    def _end(self, why: str) -> str:
        h = self._held
        assert h is not None
        self._held = None
        self._ended[_digest(h.token)] = (h.user, why)
        while len(self._ended) > self._remember:
            self._ended.popitem(last=False)
        return h.token_id

    def _event(
        self,
        action: str,
        user: str,
        granted: bool,
        reason: str,
        now: float,
        *,
        displaced: str = "",
        tid: str = "",
    ) -> LeaseEvent:
        h = self._held
        holder, left = ("", 0.0) if h is None else (h.user, h.expires_at_s - now)
        if not tid and granted and h is not None:
            tid = h.token_id
        return LeaseEvent(action, user, granted, reason, now, holder, displaced, left, tid)

    def _may_hold(self, user: str, role: str) -> str:
        if not user:
            return "no user name"
        if role not in ROLES:
            return f"unknown role {role!r}"
        if role not in HOLDER_ROLES:
            return f"a {role} cannot hold the lease"
        return ""

    def _duration_error(self, duration_s: float) -> str:
        if not (math.isfinite(duration_s) and 0.0 < duration_s <= self.max_duration_s):
            return f"duration_s must be in (0, {self.max_duration_s:g}], got {duration_s!r}"
        return ""

    def _token_error(self, user: str, token: str, now: float) -> str:
        h = self._held
        if h is not None and hmac.compare_digest(token.encode(), h.token.encode()):
            if user != h.user:
                return "the token was issued to another user"
            if now >= h.expires_at_s:
                return "the lease expired"
            return ""
        ended = self._ended.get(_digest(token))
        if ended is not None:
            owner, why = ended
            if owner != user:
                return "the token was issued to another user"
            return f"the token's lease ended ({why})"
        return "unknown token"
