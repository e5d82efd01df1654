"""The operator lease: grants, tokens bound to users, expiry, take-over, refusals with reasons,
and races modelled as interleavings on an injected clock (the lease reads no clock itself)."""

from __future__ import annotations

from pathlib import Path

import pytest

from controller.process.audit import ACTIONS, OUTCOMES, AuditLog, verify
from controller.process.lease import (
    ACQUIRE,
    EXPIRE,
    RELEASE,
    RENEW,
    TAKEOVER,
    Lease,
    LeaseEvent,
    LeaseResult,
    LeaseStatus,
    token_id,
)

OP = "operator"


def held(lease: Lease, user: str = "alice", now: float = 0.0, dur: float = 10.0) -> str:
    r = lease.acquire(user, OP, dur, now)
    assert r.ok, r.reason
    return r.token


# -- grants and tokens -----------------------------------------------------------------------


def test_acquire_grants_a_random_token_bound_to_the_user() -> None:
    lease = Lease()
    r = lease.acquire("alice", OP, 30.0, 100.0)
    assert r.ok and r.reason == "" and len(r.token) >= 40
    (ev,) = r.events
    assert (ev.action, ev.user, ev.granted, ev.holder, ev.at_s) == (ACQUIRE, "alice", True,
                                                                     "alice", 100.0)
    assert ev.expires_in_s == 30.0 and ev.token_id == token_id(r.token)
    assert lease.status(110.0) == LeaseStatus("alice", 20.0)
    assert lease.authorize("alice", r.token, 110.0).ok
    other = Lease().acquire("alice", OP, 30.0, 100.0).token
    assert other != r.token and not lease.authorize("alice", other, 110.0).ok


@pytest.mark.parametrize(
    ("user", "role", "words"),
    [("vic", "viewer", "viewer cannot hold"), ("x", "admin", "unknown role"),
     ("", OP, "no user name")],
)
def test_viewers_and_strangers_cannot_hold_the_lease(user: str, role: str, words: str) -> None:
    lease = Lease()
    for request in (lease.acquire, lease.take_over):
        r = request(user, role, 10.0, 0.0)
        assert not r.ok and words in r.reason and r.token == ""
        assert r.events[-1].outcome == "refused"
    held(lease, "alice", 1.0)
    r = lease.take_over("vic", "viewer", 10.0, 2.0)
    assert not r.ok and lease.status(2.0).holder == "alice"


@pytest.mark.parametrize("dur", [0.0, -1.0, float("nan"), float("inf"), 601.0])
def test_bad_durations_are_refused(dur: float) -> None:
    lease = Lease(max_duration_s=600.0)
    assert "duration_s" in lease.acquire("alice", OP, dur, 0.0).reason
    token = held(lease)
    r = lease.renew("alice", token, dur, 1.0)
    assert not r.ok and "duration_s" in r.reason
    assert lease.status(1.0).expires_in_s == 9.0


def test_only_the_holders_token_from_the_holder_authorises() -> None:
    lease = Lease()
    token = held(lease, "alice")
    assert lease.authorize("alice", token, 1.0).ok
    cases = {
        ("bob", token): "issued to another user",
        ("alice", "forged-token"): "unknown token",
        ("alice", None): "held by alice",
        ("bob", None): "held by alice",
    }
    for (user, tok), words in cases.items():
        a = lease.authorize(user, tok, 1.0, allow_unleased=True)
        assert not a.ok and words in a.reason and a.holder == "alice" and not a.unleased
    for attempt in (lease.renew("bob", token, 10.0, 1.0), lease.release("bob", token, 1.0)):
        assert not attempt.ok and "another user" in attempt.reason
    assert lease.status(1.0).holder == "alice"


# -- renew, release, expiry ------------------------------------------------------------------


def test_renew_moves_the_expiry_and_keeps_the_token() -> None:
    lease = Lease()
    token = held(lease, "alice", 0.0, 10.0)
    r = lease.renew("alice", token, 10.0, 8.0)
    assert r.ok and r.token == token and r.events[-1].action == RENEW
    assert r.events[-1].expires_in_s == 10.0
    assert lease.authorize("alice", token, 17.9).ok
    assert not lease.authorize("alice", token, 18.0).ok


def test_expiry_is_exact_and_recorded_once_at_its_instant() -> None:
    lease = Lease()
    token = held(lease, "alice", 0.0, 10.0)
    assert lease.authorize("alice", token, 9.999).ok
    a = lease.authorize("alice", token, 10.0)
    assert not a.ok and "expired" in a.reason and a.holder == ""
    assert lease.status(10.0) == LeaseStatus("", 0.0)
    (ev,) = lease.expire(12.5)  # noticed late, recorded at the instant it happened
    assert (ev.action, ev.user, ev.at_s, ev.holder, ev.outcome) == (EXPIRE, "alice", 10.0, "",
                                                                    "noted")
    assert ev.token_id == token_id(token)
    assert lease.expire(13.0) == ()
    for r in (lease.renew("alice", token, 5.0, 13.0), lease.release("alice", token, 13.0)):
        assert not r.ok and "ended (expired)" in r.reason and r.events == r.events[-1:]


def test_release_ends_the_lease_and_its_token() -> None:
    lease = Lease()
    token = held(lease)
    r = lease.release("alice", token, 2.0)
    assert r.ok and r.events[-1].action == RELEASE and r.events[-1].holder == ""
    assert r.events[-1].token_id == token_id(token)
    assert lease.status(2.0).holder == ""
    a = lease.authorize("alice", token, 2.0)
    assert not a.ok and "ended (released)" in a.reason
    assert not lease.release("alice", token, 3.0).ok


def test_a_replayed_old_token_is_refused_after_a_new_grant() -> None:
    lease = Lease()
    old = held(lease, "alice", 0.0)
    lease.release("alice", old, 1.0)
    new = held(lease, "alice", 2.0)
    assert lease.authorize("alice", new, 3.0).ok
    for r in (lease.authorize("alice", old, 3.0), lease.renew("alice", old, 5.0, 3.0)):
        assert not r.ok and "ended (released)" in r.reason
    a = lease.authorize("bob", old, 3.0)
    assert not a.ok and "another user" in a.reason
    assert lease.authorize("alice", new, 3.0).ok  # the refused replay changed nothing


def test_forgotten_tokens_are_unknown() -> None:
    lease = Lease(remember_tokens=2)
    first = held(lease, "alice", 0.0)
    lease.release("alice", first, 0.5)
    for t in (1.0, 2.0):
        lease.release("alice", held(lease, "alice", t), t + 0.5)
    assert lease.authorize("alice", first, 3.0).reason == "unknown token"


# -- take-over -------------------------------------------------------------------------------


def test_take_over_records_who_was_displaced() -> None:
    lease = Lease()
    alice = held(lease, "alice", 0.0)
    r = lease.take_over("bob", OP, 20.0, 3.0)
    assert r.ok
    ev = r.events[-1]
    assert (ev.action, ev.user, ev.displaced, ev.holder) == (TAKEOVER, "bob", "alice", "bob")
    assert ev.audit_fields()["displaced"] == "alice"
    assert lease.authorize("bob", r.token, 4.0).ok
    a = lease.authorize("alice", alice, 4.0)
    assert not a.ok and "taken over by bob" in a.reason


def test_take_over_when_nobody_holds_it_displaces_nobody() -> None:
    r = Lease().take_over("bob", OP, 20.0, 3.0)
    assert r.ok and r.events[-1].displaced == "" and "displaced" not in r.events[-1].audit_fields()


def test_a_second_acquire_by_the_holder_is_refused_take_over_gives_a_new_token() -> None:
    lease = Lease()
    first = held(lease, "alice", 0.0)
    r = lease.acquire("alice", OP, 10.0, 1.0)  # a second tab, or a reload that lost the token
    assert not r.ok and "already hold" in r.reason
    r = lease.take_over("alice", OP, 10.0, 2.0)
    assert r.ok and r.events[-1].displaced == "alice"
    assert lease.authorize("alice", r.token, 3.0).ok
    assert "taken over by alice" in lease.authorize("alice", first, 3.0).reason


# -- the loopback policy and the status view -------------------------------------------------


def test_no_token_is_served_only_while_nobody_holds_it_and_the_caller_allows_it() -> None:
    lease = Lease()
    a = lease.authorize("anyone", None, 0.0)
    assert not a.ok and "nobody holds the lease" in a.reason and a.holder == ""
    a = lease.authorize("anyone", None, 0.0, allow_unleased=True)
    assert a.ok and a.unleased
    token = held(lease, "alice", 1.0)
    assert not lease.authorize("anyone", None, 2.0, allow_unleased=True).ok
    assert not lease.authorize("anyone", "", 2.0, allow_unleased=True).ok
    lease.release("alice", token, 3.0)
    assert lease.authorize("anyone", None, 4.0, allow_unleased=True).unleased
    # A stale token is refused even where a request without one would be served.
    assert not lease.authorize("alice", token, 4.0, allow_unleased=True).ok


def test_status_counts_down() -> None:
    lease = Lease()
    assert lease.status(0.0) == LeaseStatus("", 0.0)
    held(lease, "alice", 0.0, 30.0)
    assert lease.status(12.5) == LeaseStatus("alice", 17.5)


# -- races as interleavings ------------------------------------------------------------------


@pytest.mark.parametrize("first", ["alice", "bob"])
def test_two_acquires_at_the_same_instant_first_wins(first: str) -> None:
    lease = Lease()
    second = "bob" if first == "alice" else "alice"
    r1, r2 = (lease.acquire(u, OP, 10.0, 5.0) for u in (first, second))
    assert r1.ok and not r2.ok and f"held by {first}" in r2.reason
    assert lease.authorize(first, r1.token, 5.0).ok
    assert lease.status(5.0).holder == first


def test_acquire_at_the_instant_of_expiry_is_granted_after_the_expiry() -> None:
    lease = Lease()
    alice = held(lease, "alice", 0.0, 10.0)
    r = lease.acquire("bob", OP, 10.0, 10.0)
    assert r.ok
    assert [(e.action, e.user, e.at_s) for e in r.events] == [(EXPIRE, "alice", 10.0),
                                                              (ACQUIRE, "bob", 10.0)]
    assert not lease.renew("alice", alice, 10.0, 10.0).ok


def test_renew_at_the_instant_of_expiry_is_too_late_whatever_the_order() -> None:
    for bob_first in (False, True):
        lease = Lease()
        alice = held(lease, "alice", 0.0, 10.0)
        if bob_first:
            assert lease.acquire("bob", OP, 10.0, 10.0).ok
        r = lease.renew("alice", alice, 10.0, 10.0)
        assert not r.ok and "expired" in r.reason
        if not bob_first:
            assert r.events[0].action == EXPIRE and lease.acquire("bob", OP, 10.0, 10.0).ok
        assert lease.status(10.0).holder == "bob"


def test_take_over_during_renew_both_orders() -> None:
    # renew first: granted, then the take-over displaces the renewed lease
    lease = Lease()
    alice = held(lease, "alice", 0.0)
    assert lease.renew("alice", alice, 10.0, 5.0).ok
    r = lease.take_over("bob", OP, 10.0, 5.0)
    assert r.ok and r.events[-1].displaced == "alice"
    assert not lease.authorize("alice", alice, 5.0).ok
    # take-over first: the renewal is refused and names why
    lease = Lease()
    alice = held(lease, "alice", 0.0)
    assert lease.take_over("bob", OP, 10.0, 5.0).ok
    r = lease.renew("alice", alice, 10.0, 5.0)
    assert not r.ok and "taken over by bob" in r.reason
    assert lease.status(5.0).holder == "bob"


def test_a_late_clock_read_does_not_run_time_backwards() -> None:
    # Two threads read the clock, the later reader takes the lock first.
    lease = Lease()
    alice = held(lease, "alice", 0.0, 10.0)
    assert lease.acquire("bob", OP, 10.0, 10.002).ok  # expiry processed at 10.002
    r = lease.renew("alice", alice, 10.0, 9.999)  # read before the expiry, served after
    assert not r.ok and "expired" in r.reason
    assert lease.status(9.0).holder == "bob"  # a stale read does not resurrect alice
    assert lease.status(9.0).expires_in_s == pytest.approx(10.0)


def _interleavings(programs: list[list[str]]) -> list[list[tuple[int, str]]]:
    """Every merge of the programs that keeps each one's own order."""
    if all(not p for p in programs):
        return [[]]
    out = []
    for i, p in enumerate(programs):
        if p:
            rest = [q[1:] if j == i else q for j, q in enumerate(programs)]
            out += [[(i, p[0]), *tail] for tail in _interleavings(rest)]
    return out


def _request(lease: Lease, op: str, user: str, role: str, token: str, now: float) -> LeaseResult:
    if op == "acquire":
        return lease.acquire(user, role, 6.0, now)
    if op == "take_over":
        return lease.take_over(user, role, 6.0, now)
    if op == "renew":
        return lease.renew(user, token, 6.0, now)
    return lease.release(user, token, now)


def test_every_interleaving_keeps_one_holder_and_only_its_token_valid() -> None:
    users = [("alice", OP), ("bob", OP), ("vic", "viewer")]
    programs = [["acquire", "renew", "release"], ["acquire", "take_over", "renew"], ["acquire"]]
    schedules = _interleavings(programs)
    assert len(schedules) == 140
    for schedule in schedules:
        lease = Lease()
        tokens: dict[str, str] = {}
        issued: list[tuple[str, str]] = []  # (user, token) of every grant
        grants = 0
        for step, (who, op) in enumerate(schedule):
            user, role = users[who]
            now = 4.0 * step  # leases of 6 s: some expire between steps
            result = _request(lease, op, user, role, tokens.get(user, ""), now)
            last = result.events[-1]
            assert last.user == user and last.granted == result.ok
            assert bool(last.reason) != result.ok
            for ev in result.events[:-1]:
                assert ev.action == EXPIRE and ev.at_s <= now
            if result.ok and op in ("acquire", "take_over"):
                grants += 1
                tokens[user] = result.token
                issued.append((user, result.token))
            holder = lease.status(now).holder
            assert holder in ("", "alice", "bob"), schedule
            assert last.holder == holder
            for u, _ in users:
                for owner, t in issued:
                    ok = lease.authorize(u, t, now).ok
                    assert ok == (u == owner == holder and t == issued[-1][1]), (schedule, step)
        assert len({t for _, t in issued}) == grants


# -- into the audit log ----------------------------------------------------------------------


def test_events_go_into_the_audit_log_without_tokens(tmp_path: Path) -> None:
    lease = Lease()
    results = [lease.acquire("alice", OP, 10.0, 0.0), lease.acquire("bob", OP, 10.0, 1.0)]
    results.append(lease.take_over("bob", OP, 10.0, 2.0))
    results.append(lease.renew("alice", results[0].token, 10.0, 3.0))
    results.append(lease.release("bob", results[2].token, 4.0))
    results.append(lease.acquire("vic", "viewer", 10.0, 5.0))
    results.append(lease.acquire("alice", OP, 1.0, 6.0))
    events: list[LeaseEvent] = [e for r in results for e in r.events]
    events += lease.expire(8.0)
    tokens = [r.token for r in results if r.token]
    path = tmp_path / "audit.jsonl"
    with AuditLog(path, rig="demo") as log:
        for ev in events:
            assert ev.action in ACTIONS and ev.outcome in OUTCOMES
            log.record(ev.action, ev.user, ev.outcome, **ev.audit_fields())
    text = path.read_text()
    assert all(t not in text for t in tokens)
    assert verify(path).ok
    assert [e.action for e in events] == [ACQUIRE, ACQUIRE, TAKEOVER, RENEW, RELEASE, ACQUIRE,
                                          ACQUIRE, EXPIRE]
    assert [e.outcome for e in events] == ["accepted", "refused", "accepted", "refused",
                                           "accepted", "refused", "accepted", "noted"]


def test_lease_module_is_pure() -> None:
    import ast

    import controller.process.lease as mod

    tree = ast.parse(Path(mod.__file__).read_text())
    names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import)
             for a in n.names}
    names |= {n.module.split(".")[0] for n in ast.walk(tree)
              if isinstance(n, ast.ImportFrom) and n.module}
    assert names <= {"__future__", "hashlib", "hmac", "math", "secrets", "collections",
                     "dataclasses", "typing"}, names
