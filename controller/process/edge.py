"""The controller's edge process: every request queryable, apart from the loop's process.

The loop's process (`controller.process.main`) keeps the 1 kHz tick, the streams and the
service. This child process
opens a Zenoh session of its own (a client of the loop process's session, or of the router
the controller logs in to) and declares the request queryables. Per query, in the Zenoh
callback, before anything is read: the sender's request budget (`controller.process.budget`,
with authentication: the user the key scope names), refused at once with a reply naming the
budget; then a bounded queue per request kind (beyond it a query is shed, as before).

A worker thread per kind then serves its queue:
- reads answered here, without the loop's process: history (read from the change log),
  configuration and plant knowledge (the loop process's latest snapshot of their replies:
  `EdgeSnapshot`, sent with every reply that may change them and whenever they change);
- everything else (applies, commands, adopting knowledge, the lease, identification) is
  forwarded over the kind's pipe to the loop process, one request at a time per kind, which
  handles it as before (`ZenohNode.handle_*`: lease, gate, audit) and sends the reply back.
  A payload over the size limit is not sent: only its size, for the refusal that names it.

E-stops are received by a second process of this body, the e-stop relay (`edge_main(...,
role="estops")`, `controller.process.estop_relay`: no request, so no other Python code wants
its interpreter lock): the public key and, with authentication, every user's scope. Its
Zenoh callback writes the arrival stamp, then raises the flag, in a small shared-memory
array (`ESTOP_FLAG`, `ESTOP_ARRIVAL`) that the loop's tick reads (a plain int; the tick
clears the flag, then reads the stamp: no e-stop is lost). No Python code of the loop's
process runs per e-stop: an e-stop flood costs it nothing but the tick's read. Their audit
lines are coalesced there: each sender's e-stops go to the loop process (the audit) at most
every ESTOP_REPORT_S, the first at once, with the count of the others (`repeats`). The loop
process's own e-stop subscriber raises one only when the relay did not
(`ZenohNode._estop_fallback`).

So whatever clients send, the loop process sees at most one request per kind at a time, each
within its sender's budget, and no read at all: the interpreter lock the loop needs is not
theirs to take. The request edge is niced once it serves (every thread of it: its flood's
work yields the CPU to the relay and the loop's process), the relay is not; both ignore
Ctrl-C and end with their parent (`controller.process.worker_start`).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from controller import protocol as proto
from controller.client.session import SessionOptions, connect
from controller.process.budget import RequestBudget
from controller.process.estop_keys import (
    ACTIVE_VERSION,
    ESTOP_ARRIVAL,
    ESTOP_FLAG,
    PUBLIC,
    SLOTS,
    estop_claims,
)
from controller.process.history import history_reply
from controller.process.persistence import StateStore
from controller.process.worker_start import lower_priority, worker_init

__all__ = [
    "CONNECT",
    "ESTOP_ARRIVAL",
    "ESTOP_FLAG",
    "FORWARDED",
    "FORWARD_TIMEOUT_S",
    "KINDS",
    "EdgeSnapshot",
    "EdgeSpec",
    "ForwardTimeout",
    "edge_main",
    "estop_flag",
]

log = logging.getLogger(__name__)

#: Request kinds (queryables) and the key each is served on.
KINDS: dict[str, Callable[[str], str]] = {
    "config": proto.key_config,
    "command": proto.key_command,
    "identify": proto.key_identify,
    "knowledge": proto.key_knowledge,
    "lease": proto.key_lease,
    "history": proto.key_history,
}
#: The kinds that can move the rig: an e-stop the loop's process received before one is
#: raised before it is served (`ZenohNode.estops_before`).
ORDERED = ("config", "command", "identify")
#: The kinds the loop process serves (each over a pipe of its own); history never reaches it.
FORWARDED = ("config", "command", "identify", "knowledge", "lease")
_REPLY_TYPES: dict[str, type[proto.Message]] = {
    "config": proto.ConfigReply,
    "command": proto.CommandReply,
    "identify": proto.IdentifyStatus,
    "knowledge": proto.KnowledgeReply,
    "lease": proto.LeaseReply,
    "history": proto.HistoryReply,
}
#: Sent by the loop process once its session is open: the edge connects from then on.
CONNECT = "connect"
#: How often the edge tries to connect until it succeeds.
CONNECT_RETRY_S = 0.1
#: How often the budget's refusals are reported to the loop process (audit, status).
REPORT_S = 1.0
INTERNAL_ERROR = b"internal error: the request was not served (see the controller's log)"
#: The shortest time between two e-stop reports (audit lines) to the loop process.
ESTOP_REPORT_S = 0.1
#: How long a forwarded request may take in the loop process before the client is told so.
FORWARD_TIMEOUT_S = 30.0


def claimed_session(query: Any) -> str:
    """The session a query claims to come from (its `source_info`'s Zenoh id, set by the
    sender: `controller.client` sets it), "" for one that names none: the key of the
    per-session budget (`controller.process.budget`: a claim only divides its user's budget)."""
    info = query.source_info
    if info is None:
        return ""
    return str(info.source_id.zid)


def estop_flag() -> Any:
    """The shared e-stop flag array (int64 [flag, arrival]), inherited by the edge process
    when forked and passed to it when spawned."""
    from multiprocessing.sharedctypes import RawArray

    return RawArray("q", SLOTS)


@dataclass(frozen=True)
class EdgeSpec:
    """What the edge process needs (pickled to it)."""

    rig: str
    session: SessionOptions
    auth_dir: Path | None
    state_dir: Path
    max_payload_bytes: int
    max_pending_queries: int
    budget_per_s: float | None
    """Requests a second per authenticated user (None: no budget, without authentication)."""
    parent_pid: int


@dataclass(frozen=True)
class EdgeSnapshot:
    """The loop process's replies to a configuration GET and a knowledge GET, numbered: the
    edge keeps the newest (`generation`), whichever pipe it came by."""

    generation: int
    config: bytes
    knowledge: bytes
    config_version: int
    """The version `config` shows (served only while the loop runs that version)."""


class ForwardTimeout(Exception):
    """The loop process did not answer a forwarded request within FORWARD_TIMEOUT_S."""


class _ChangeLogReader(StateStore):
    """The state directory's change log, read only (opening a `StateStore` would remove
    temporary files the loop process may be writing)."""

    def __init__(self, directory: Path) -> None:  # no super().__init__: nothing created
        self.directory = Path(directory)


class _Edge:
    def __init__(self, spec: EdgeSpec, conns: dict[str, Connection], control: Connection,
                 flag: Any = None) -> None:
        self.spec = spec
        self.flag = flag if flag is not None else [0] * SLOTS
        self._estop_lock = threading.Lock()
        #: E-stops not yet reported to the loop process, by key: [first sample, count,
        #: its arrival (monotonic ns)].
        self._estops: dict[str, list[Any]] = {}
        self._estop_event = threading.Event()
        self.conns = conns
        self.control = control
        self.queues: dict[str, queue.SimpleQueue[Any]] = {k: queue.SimpleQueue() for k in KINDS}
        self.budget = (RequestBudget(spec.budget_per_s)
                       if spec.budget_per_s is not None else None)
        self.refusal = self.budget.refusal.encode() if self.budget is not None else b""
        self.snapshot: EdgeSnapshot | None = None
        self._snap_lock = threading.Lock()
        self.changes = _ChangeLogReader(spec.state_dir)
        self.shed = 0
        self.stop = threading.Event()
        #: The loop process's session is open (CONNECT): connect.
        self.go = threading.Event()
        self._control_lock = threading.Lock()

    # -- Zenoh callbacks: budget, then hand over ---------------------------------------------

    def on_query(self, kind: str) -> Callable[[Any], None]:
        q = self.queues[kind]
        limit = self.spec.max_pending_queries
        budget = self.budget
        refusal = self.refusal
        user_of_key = proto.user_of_key
        clock = time.monotonic_ns

        def put(query: Any) -> None:
            arrival = clock()
            if budget is not None and not budget.allow(
                    user_of_key(query.key_expr) or "anonymous", claimed_session(query)):
                with contextlib.suppress(Exception):
                    query.reply_err(refusal)
                    query.drop()
                return
            if q.qsize() < limit:
                q.put((query, arrival))
            else:
                self.shed += 1  # released unanswered (the client times out)

        return put

    def on_estop(self, sample: Any) -> None:
        """An e-stop (Zenoh callback): the loop's flag first, then count it for the audit.

        As little as possible runs here, per sample: under a flood this callback's cost is
        the queue every other e-stop waits in. Who sent it and what it claims are read by
        `report_estops`, from the first sample of each key in a report period."""
        arrival = time.monotonic_ns()
        flag = self.flag
        key = str(sample.key_expr)
        with self._estop_lock:
            if arrival > flag[ESTOP_ARRIVAL]:
                flag[ESTOP_ARRIVAL] = arrival  # the stamp before the flag (the tick reads
            flag[ESTOP_FLAG] = 1               # the flag, clears it, then the stamp)
            entry = self._estops.get(key)
            if entry is not None:
                entry[1] += 1
                return
            self._estops[key] = [sample, 1, arrival]
        self._estop_event.set()

    def _estop_report(self, key: str, sample: Any, n: int, arrival_ns: int
                      ) -> tuple[str, str, dict[str, str], int, float]:
        """(who, key, claims, count, the first one's arrival as UNIX time)."""
        from controller.process.access import LOCAL

        who = proto.user_of_key(key) or (PUBLIC if self.spec.auth_dir is not None
                                         else LOCAL.user)
        arrived_s = time.time() - (time.monotonic_ns() - arrival_ns) / 1e9
        return who, key, estop_claims(sample), n, arrived_s

    def report_estops(self) -> None:
        """Each key's e-stops to the loop process (its audit): the first at once, then at
        most one report every ESTOP_REPORT_S, with the count (the claims are the first
        sample's of the period: one sender's key, its repeats counted)."""
        while not self.stop.is_set():
            self._estop_event.wait()
            self._estop_event.clear()
            with self._estop_lock:
                pending, self._estops = self._estops, {}
            if pending:
                with contextlib.suppress(OSError, ValueError):
                    self.send_control(("estop", [self._estop_report(key, *entry)
                                                 for key, entry in pending.items()]))
            self.stop.wait(ESTOP_REPORT_S)

    # -- workers -------------------------------------------------------------------------------

    def serve(self, kind: str) -> None:
        q = self.queues[kind]
        encoding = proto.encoding(_REPLY_TYPES[kind])
        while True:
            query, arrival = q.get()
            if query is None:
                return
            try:
                payload = query.payload
                data = b"" if payload is None else payload.to_bytes()
                reply = self.answer(kind, str(query.key_expr), arrival, data)
                if reply is None:
                    query.reply_err(INTERNAL_ERROR)
                else:
                    query.reply(query.key_expr, reply, encoding=encoding)
            except ForwardTimeout as exc:
                with contextlib.suppress(Exception):
                    query.reply_err(str(exc).encode())
            except Exception as exc:  # never let a query end the worker
                log.warning("edge: %s query: %s: %s", kind, type(exc).__name__, exc)
                with contextlib.suppress(Exception):
                    query.reply_err(INTERNAL_ERROR)
            finally:
                with contextlib.suppress(Exception):
                    query.drop()

    def answer(self, kind: str, key: str, arrival: int, data: bytes) -> bytes | None:
        """The reply's bytes (None: an internal error, told as such)."""
        too_large = len(data) > self.spec.max_payload_bytes
        if kind == "history":
            return self.history(data, too_large)
        if not too_large:
            local = self.read_locally(kind, data)
            if local is not None:
                return local
        conn = self.conns[kind]
        # Over the limit: only the size goes (the loop process names it in the refusal).
        conn.send((key, arrival, None if too_large else data, len(data)))
        if not conn.poll(FORWARD_TIMEOUT_S):
            # The loop process did not answer: this kind's pipe is out of step from now on
            # (a late reply would answer the next request), so this process ends and is
            # started again (`edge_link`).
            log.error("edge: %s: no reply from the loop process within %g s; edge restarts",
                      kind, FORWARD_TIMEOUT_S)
            self.stop.set()
            raise ForwardTimeout(
                f"edge forward timeout: the loop process did not answer this {kind} request "
                f"within {FORWARD_TIMEOUT_S:g} s (it may still take effect: read the state "
                f"before sending it again)")
        reply, snap = conn.recv()
        if snap is not None:
            self.take(snap)
        return reply  # type: ignore[no-any-return]

    def read_locally(self, kind: str, data: bytes) -> bytes | None:
        """A GET of the configuration or the plant knowledge, from the snapshot (None: not a
        GET, or malformed, or no snapshot yet: the loop process answers)."""
        snap = self.snapshot
        if snap is None or kind not in ("config", "knowledge"):
            return None
        try:
            if kind == "config":
                if data and proto.decode(data, proto.ConfigRequest).candidate is not None:
                    return None
                if snap.config_version != self.flag[ACTIVE_VERSION]:
                    return None  # not yet the loop's version: the loop process answers
                return snap.config
            if data:
                req = proto.decode(data, proto.KnowledgeRequest)
                if req.record is not None or req.adopt_run is not None:
                    return None
            return snap.knowledge
        except proto.ProtocolError:
            return None  # refused (and audited) by the loop process, naming the field

    def history(self, data: bytes, too_large: bool) -> bytes:
        if too_large:
            return proto.encode(proto.HistoryReply(
                ok=False, field="payload", message=f"payload: {len(data)} bytes is over the "
                f"limit of {self.spec.max_payload_bytes}"))
        try:
            req = proto.decode(data, proto.HistoryRequest) if data else proto.HistoryRequest()
        except proto.ProtocolError as exc:
            return proto.encode(proto.HistoryReply(ok=False, message=str(exc), field=exc.field))
        return proto.encode(history_reply(self.changes.read_changes, req.last))

    def take(self, snap: EdgeSnapshot) -> None:
        with self._snap_lock:
            if self.snapshot is None or snap.generation > self.snapshot.generation:
                self.snapshot = snap

    # -- the control pipe ------------------------------------------------------------------------

    def read_control(self) -> None:
        """Snapshots from the loop process; `None` (or its end) stops this process."""
        while True:
            try:
                msg = self.control.recv()
            except (EOFError, OSError):
                msg = None
            if msg is None:
                self.stop.set()
                return
            if isinstance(msg, EdgeSnapshot):
                self.take(msg)
            elif msg == CONNECT:
                self.go.set()

    def send_control(self, msg: Any) -> None:
        with self._control_lock:
            self.control.send(msg)

    def report(self) -> None:
        """The budget's refusals and the shed queries, every REPORT_S while there are any."""
        shed = 0
        while not self.stop.wait(REPORT_S):
            refused = self.budget.take_refusals() if self.budget is not None else {}
            new_shed, shed = self.shed - shed, self.shed
            if refused or new_shed:
                with contextlib.suppress(OSError, ValueError):
                    self.send_control(("refused", refused, new_shed))

    # -- the process -----------------------------------------------------------------------------

    def open_session(self) -> Any:
        """The edge's session, once the loop process says its own is open (CONNECT: the
        edge starts first), tried again every CONNECT_RETRY_S until it opens; None if told
        to stop meanwhile."""
        import zenoh

        while not (self.go.is_set() or self.stop.is_set()):
            self.stop.wait(CONNECT_RETRY_S)
        while not self.stop.is_set():
            try:
                return connect(self.spec.session)
            except zenoh.ZError as exc:
                log.debug("not connected yet: %s", exc)
                self.stop.wait(CONNECT_RETRY_S)
        return None

    def run(self, role: str = "requests") -> None:
        """Serve the request queryables (`role` "requests", the edge) or take the e-stops
        ("estops", the relay), until told to stop."""
        import zenoh

        rig = self.spec.rig
        scoped = proto.any_user_key if self.spec.auth_dir is not None else (lambda k: k)
        requests = role == "requests"
        threads = [threading.Thread(target=self.read_control, name="control", daemon=True)]
        if requests:
            threads.append(threading.Thread(target=self.report, name="report", daemon=True))
            threads += [threading.Thread(target=self.serve, args=(k,), name=f"{k}-worker",
                                         daemon=True) for k in KINDS]
        else:
            threads.append(threading.Thread(target=self.report_estops, name="estops",
                                            daemon=True))
        for t in threads:
            t.start()
        session = self.open_session()
        if session is None:
            return
        with session:
            entities: list[Any] = []
            if requests:
                entities += [
                    session.declare_queryable(
                        scoped(key(rig)),
                        zenoh.handlers.Callback(self.on_query(kind), indirect=False))
                    for kind, key in KINDS.items()
                ]
            else:
                estop_keys = [proto.key_estop(rig)]
                if self.spec.auth_dir is not None:
                    estop_keys.append(proto.any_user_key(proto.key_estop(rig)))
                entities += [session.declare_subscriber(
                    key, zenoh.handlers.Callback(self.on_estop, indirect=False))
                    for key in estop_keys]
            self.send_control(("ready",))
            if requests:
                # Loaded and serving: from now on the loop's process (and the e-stop relay)
                # win the CPU over this one (not before: the controller's start waits for it).
                lower_priority(every_thread=True)
            self.stop.wait()
            for e in entities:
                with contextlib.suppress(Exception):
                    e.undeclare()
            for q in self.queues.values():
                q.put((None, 0))


def edge_main(spec: EdgeSpec, conns: dict[str, Connection], control: Connection,
              flag: Any = None, role: str = "requests") -> None:
    """The edge process's body, or the e-stop relay's (`role` "estops") (multiprocessing
    target)."""
    # Forked from the controller: its SIGTERM handler (stop the loop) is not this process's.
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    worker_init(spec.parent_pid, True, nice=False)  # Ctrl-C ignored, ends with its parent
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s edge: %(message)s")
    _Edge(spec, conns, control, flag).run(role)
