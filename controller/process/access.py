"""Who may change the rig, and the record of everything anyone did.

- Identity: with authentication (`--auth DIR`), a request's user is the one whose key scope it
  arrived on (`dobtune/<rig>/@user/<name>/...`; the access control lets only <name> reach it)
  and its role comes from the users file, never from anything the request says. Without
  authentication (loopback only) every request is `local`, an operator.
- Changes (apply, commands other than e-stop, identification, plant knowledge) need the
  operator lease (`controller.process.lease`): viewers never; an operator presenting the
  holder's token; without authentication, a request with no token while nobody holds it.
  The e-stop needs nothing: anyone who can reach the rig stops it.
- Audit: every action, accepted or refused, goes through a queue to a writer thread that
  appends it to the hash-chained `<state-dir>/audit.jsonl` (`controller.process.audit`), so a
  slow disk never delays a request or the e-stop; while the log cannot be written the records
  are held in order and retried (none dropped; Status.notes says so, and when they are
  written), and the controller runs on. The chain's head is published in Status (`audit_head`).
"""

from __future__ import annotations

import collections
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from controller import protocol as proto
from controller.process.audit import AuditError, AuditLog
from controller.process.lease import Lease, LeaseEvent, LeaseResult

__all__ = ["ANONYMOUS", "LOCAL", "Access", "Who"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Who:
    """The sender of a request as the controller knows it (never as the request claims)."""

    user: str
    role: str  # operator | viewer | controller
    authenticated: bool


LOCAL = Who("local", "operator", False)
"""Any request without authentication (the controller then listens on loopback only)."""
ANONYMOUS = Who("anonymous", "viewer", False)
"""A request on a key that names no known user (cannot pass the access control): refused."""

_STOP = object()
#: While the audit log cannot be written, the held records are retried this often.
RETRY_S = 1.0


class Access:
    """Roles, the lease and the audit trail of one controller (thread-safe)."""

    def __init__(
        self,
        users: Any | None,
        rig: str,
        audit: AuditLog | None,
        warn: Callable[..., None],
        *,
        clock: Callable[[], float] = time.monotonic,
        max_lease_s: float = 600.0,
    ) -> None:
        """`users`: `controller.auth.Users` with authentication, None without."""
        self.users = users
        self.rig = rig
        self.auth = users is not None
        self.audit = audit
        self.warn = warn
        self._clock = clock
        self._lease = Lease(max_duration_s=max_lease_s)
        self._lock = threading.Lock()
        self._q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._writer: threading.Thread | None = None
        self._audit_error = ""
        self._pending = 0
        self._pending_lock = threading.Lock()

    # -- identity ----------------------------------------------------------------------------

    def who(self, key_expr: object) -> Who:
        if not self.auth:
            return LOCAL
        from controller.auth import requester

        assert self.users is not None
        u = requester(self.users, key_expr)
        if u is None:
            return ANONYMOUS
        return Who(u.name, u.role, True)

    # -- the lease -----------------------------------------------------------------------------

    def may_change(self, who: Who, token: str) -> str:
        """ "" if `who` presenting `token` may change the rig now, else why not."""
        if who is ANONYMOUS:
            return "lease: the request names no known user"
        if who.role == "viewer":
            return f"lease: {who.user} is a viewer: viewers watch and may e-stop, not change"
        with self._lock:
            a = self._lease.authorize(
                who.user, token or None, self._clock(), allow_unleased=not self.auth
            )
        return "" if a.ok else f"lease: {a.reason}"

    @property
    def holder(self) -> str:
        with self._lock:
            return self._lease.status(self._clock()).holder

    def lease_request(self, who: Who, req: proto.LeaseRequest) -> proto.LeaseReply:
        now = self._clock()
        if req.action not in proto.LEASE_ACTIONS:
            return proto.LeaseReply(
                ok=False,
                field="action",
                message=f"action: {req.action!r} is not one of {', '.join(proto.LEASE_ACTIONS)}",
                holder=self.holder,
            )
        if not (math.isfinite(req.duration_s) and 0.0 < req.duration_s <= 3600.0):
            return proto.LeaseReply(
                ok=False,
                field="duration_s",
                holder=self.holder,
                message=f"duration_s: {req.duration_s!r} not in (0, 3600]",
            )
        if who is ANONYMOUS:
            return proto.LeaseReply(
                ok=False,
                field="user",
                holder=self.holder,
                message="the request names no known user",
            )
        with self._lock:
            lease = self._lease
            result: LeaseResult | None = None
            if req.action == "acquire":
                result = lease.acquire(who.user, who.role, req.duration_s, now)
            elif req.action == "takeover":
                result = lease.take_over(who.user, who.role, req.duration_s, now)
            elif req.action == "renew":
                result = lease.renew(who.user, req.token, req.duration_s, now)
            elif req.action == "release":
                result = lease.release(who.user, req.token, now)
            events = result.events if result is not None else lease.expire(now)
            st = lease.status(now)
        for e in events:
            self._record_lease(e)
        if result is None:
            return proto.LeaseReply(ok=True, holder=st.holder, expires_in_s=st.expires_in_s)
        return proto.LeaseReply(
            ok=result.ok,
            holder=st.holder,
            expires_in_s=st.expires_in_s,
            token=result.token,
            message=result.reason,
            field="" if result.ok else "lease",
        )

    def poll(self) -> None:
        """Record an expiry even when no request comes (the status thread calls this)."""
        with self._lock:
            events = self._lease.expire(self._clock())
        for e in events:
            self._record_lease(e)

    def _record_lease(self, e: LeaseEvent) -> None:
        self._enqueue(e.action, e.user, e.outcome, e.audit_fields())

    # -- audit ---------------------------------------------------------------------------------

    def record(self, action: str, who: Who | str, outcome: str, **fields: Any) -> None:
        """Queue one audit record (never blocks, never raises for the caller)."""
        user = who if isinstance(who, str) else who.user
        self._enqueue(action, user, outcome, fields)

    def _enqueue(self, action: str, user: str, outcome: str, fields: dict[str, Any]) -> None:
        if self.audit is not None:
            with self._pending_lock:
                self._pending += 1
            self._q.put((action, user, outcome, fields))

    def start(self) -> None:
        if self.audit is not None and self.audit.recovered:  # what opening the log found
            self.warn(f"audit: {self.audit.recovered}", key="audit-file")
        if self.audit is not None and self._writer is None:
            self._writer = threading.Thread(target=self._write, name="audit-writer", daemon=True)
            self._writer.start()

    def close(self) -> None:
        if self._writer is not None:
            self._q.put(_STOP)
            self._writer.join(timeout=5.0)
            self._writer = None
        if self.audit is not None:
            self.audit.close()

    def _write(self) -> None:
        """Writer thread: records in the order they were queued. While the file cannot be
        written they are held (in order, none dropped) and retried every RETRY_S."""
        backlog: collections.deque[tuple[str, str, str, dict[str, Any]]] = collections.deque()
        stopping = False
        while True:
            try:
                item = self._q.get(timeout=RETRY_S)
            except queue.Empty:
                item = None
                if not backlog:
                    self._check_file()
            if item is _STOP:
                stopping = True
            elif item is not None:
                backlog.append(item)
            self._drain(backlog)
            if stopping:
                if backlog:
                    self.warn(f"audit: {len(backlog)} record(s) not written at shutdown: "
                              f"{self._audit_error}")
                return

    def _check_file(self) -> None:
        """A log deleted or replaced while idle is noticed within RETRY_S (and reopened as a
        continuation: `AuditLog.check_file`); the Status notes say so."""
        assert self.audit is not None
        try:
            found = self.audit.check_file()
        except (AuditError, OSError) as exc:
            found = f"the audit log cannot be checked or reopened: {exc}"
        if found:
            self.warn(f"audit: {found}", key="audit-file")

    def _drain(self, backlog: collections.deque[tuple[str, str, str, dict[str, Any]]]) -> None:
        assert self.audit is not None
        while backlog:
            action, user, outcome, fields = backlog[0]
            fields = dict(fields)
            vb = fields.pop("version_before", None)
            va = fields.pop("version_after", None)
            found = self.audit.recovered
            try:
                self.audit.record(
                    action, user, outcome, version_before=vb, version_after=va, **fields
                )
                if self.audit.recovered is not found and self.audit.recovered:
                    self.warn(f"audit: {self.audit.recovered}", key="audit-file")
            except (AuditError, OSError) as exc:
                if not self._audit_error:
                    self.warn(f"audit: the log cannot be written ({exc}); records are held in "
                              f"order and retried every {RETRY_S:g} s", key="audit")
                self._audit_error = str(exc)
                return
            except ValueError as exc:  # a record that can never be written (a bug): say so
                self.warn(f"audit: a record was not written ({action} by {user}): {exc}")
            backlog.popleft()
            with self._pending_lock:
                self._pending -= 1
            if self._audit_error and not backlog:
                self._audit_error = ""
                self.warn("audit: the log is writable again; every held record is written, "
                          "in order", key="audit")

    @property
    def head(self) -> str:
        if self.audit is None:
            return ""
        seq, h = self.audit.head
        return f"{seq}:{h}"

    @property
    def pending(self) -> int:
        """Records queued or held, not written yet."""
        with self._pending_lock:
            return self._pending

    def flush(self, timeout_s: float = 5.0) -> bool:
        """Wait until every queued record is written (tests, shutdown)."""
        deadline = time.monotonic() + timeout_s
        while self.pending and time.monotonic() < deadline:
            time.sleep(0.005)
        return not self.pending
