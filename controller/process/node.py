"""The Zenoh edge of the controller process: queryables, subscribers, publishers, their threads.

Threads (the loop's own thread is the main thread, see `controller.process.main`):
- state publisher: encodes finished sample blocks as StateBatch and puts them.
- status: Status every `status_period_s`, and the log records of what the loop did.
- config, command, identify workers: decode a query, convert the wire message to the
  runtime's domain request (`controller.process.requests`), let the service
  (`controller.process.service`) do it, encode and send its reply. By default the queryables
  are the edge process's (`controller.process.edge`): its forwarded requests reach the same
  `handle_*` methods from `controller.process.edge_link`'s threads, and these workers are not
  started; this process keeps the publishers and the e-stop subscribers.
- latch: writes the e-stop/fault latch to the state directory whenever the mode enters or
  leaves estop/fault (`StateStore.save_latch`), so a restart comes back latched.
Zenoh callbacks only hand the query to a worker's queue (or, for the e-stop key, set the
loop's flag); they never decode, block or call Zenoh.

Order: the callbacks run on Zenoh's own receiving thread (`Callback(f, indirect=False)`: by
default zenoh-python runs each callback on a thread of its own, and an e-stop sent after a
reset overtook it in 43 of 200 pairs), and each stamps its query or e-stop with the runtime's
arrival counter. The runtime refuses a reset stamped before the latest e-stop, so a reset sent
before an e-stop never clears it, while the e-stop itself needs no queue: it takes effect at
the next tick, whatever a worker is busy with.

An operator lease (`dobtune/<rig>/lease`) is not implemented yet: any peer that can reach
the endpoints may apply configurations and commands (Status.operator stays "").
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple, TypeVar

import msgspec

from controller import protocol as proto
from controller.core.errors import ConfigError
from controller.process import requests as rq
from controller.process.access import LOCAL, Who
from controller.process.blackbox import BlackBox
from controller.process.estop_keys import ESTOP_ARRIVAL, PUBLIC, estop_claims
from controller.process.persistence import Latch, PersistenceError
from controller.process.replay import ReplayServer
from controller.process.runtime import ESTOP, FAULT
from controller.process.service import ControllerService, RuntimeEvents

__all__ = ["PUBLIC", "SHUTDOWN", "ZenohNode", "estop_claims", "to_request"]

log = logging.getLogger(__name__)
R = TypeVar("R", bound=proto.Message)


class Unreadable(NamedTuple):
    """Why a request's payload cannot be read, for the refusal that names the field."""

    message: str
    field: str

def _claimed_command(data: bytes) -> tuple[str, int | None]:
    """The body type and `estop_seq` a command's payload claims, for the audit line, read
    without trusting it (a refused or malformed command is audited with what it claimed;
    the caller has refused a payload over the size limit before)."""
    try:
        message = msgspec.msgpack.decode(data)
    except (msgspec.DecodeError, RecursionError, UnicodeDecodeError):
        return "", None  # unreadable: the refusal audited beside it says why
    body = message.get("body") if isinstance(message, dict) else None
    if not isinstance(body, dict):
        return "", None
    body_type, seen = body.get("type"), body.get("estop_seq")
    return (body_type if isinstance(body_type, str) else ""), (seen if type(seen) is int else None)


#: How often the e-stop fallback reads its rings (with the edge process).
ESTOP_POLL_S = 0.01
#: How long an e-stop this process received may wait for the edge's relay before the
#: fallback raises it here.
ESTOP_GRACE_S = 0.5

#: The shortest time between two passes of the latch writer.
LATCH_MIN_S = 0.01

SHUTDOWN = object()
"""Put on a worker queue: the worker ends."""

_PLAIN_COMMANDS: dict[type, Callable[[], rq.RequestBody]] = {
    proto.Start: rq.Start,
    proto.Stop: rq.Stop,
    proto.EStop: rq.EStop,
}


def to_request(body: proto.CommandBody, client: str) -> rq.RequestBody:
    """A wire command body as the runtime's request (not IdentifyStart: its spec, already
    validated on decode, goes to `ControllerService.start_identify`)."""
    plain = _PLAIN_COMMANDS.get(type(body))
    if plain is not None:
        return plain()
    if isinstance(body, proto.ResetFault):
        if body.estop_seq is None:
            raise ConfigError(
                "estop_seq", "required: the latest e-stop the sender saw (Status.estop_seq, -1 "
                "if none); a reset clears only that e-stop (update the client)"
            )
        return rq.ResetFault(body.estop_seq)
    if isinstance(body, proto.SetTrajectory):
        return rq.SetTrajectory(body.trajectory)
    if isinstance(body, proto.IdentifyAbort):
        return rq.AbortProgram(f"aborted by {client or 'a client'}")
    if isinstance(body, proto.SimFault):
        from controller.sim.sim_rig import RigFaults

        # Raises ConfigError naming the field (the caller names it body.<field>).
        return rq.InjectFault(RigFaults(**msgspec.structs.asdict(body)))
    if isinstance(body, proto.SimDrift):
        for name, value in msgspec.structs.asdict(body).items():
            if not (math.isfinite(value) and 0.05 <= value <= 20.0):
                raise ConfigError(name, f"must be a factor in [0.05, 20], got {value!r}")
        return rq.DriftRig(**msgspec.structs.asdict(body))
    raise TypeError(f"no runtime request for {type(body).__name__}")


class ZenohNode:
    """The Zenoh side of one controller: handlers, publishers and their threads."""

    def __init__(self, service: ControllerService) -> None:
        self.service = service
        self.opts = opts = service.opts
        self.rt = service.rt
        self.stop_event = service.stop_event
        self.events = RuntimeEvents(service.rt, opts.loop_summary_period_s)
        self.config_q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.command_q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.identify_q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.knowledge_q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.lease_q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.history_q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.access = service.access
        self._reply_encoding = {
            id(self.config_q): proto.encoding(proto.ConfigReply),
            id(self.command_q): proto.encoding(proto.CommandReply),
            id(self.identify_q): proto.encoding(proto.IdentifyStatus),
            id(self.knowledge_q): proto.encoding(proto.KnowledgeReply),
            id(self.lease_q): proto.encoding(proto.LeaseReply),
            id(self.history_q): proto.encoding(proto.HistoryReply),
        }
        self.blackbox = BlackBox(
            service.store.directory / "blackbox", opts.rig_name, service.warn
        )
        service.recent_state = self.blackbox.held  # the twin's window of normal running
        self._bb_mode = service.rt.mode
        self._bb_rollbacks = 0
        self._threads: list[threading.Thread] = []
        self._entities: list[Any] = []
        self.state_pub: Any = None
        self.status_pub: Any = None
        self.shed_queries = 0
        #: The edge process's link (`controller.process.edge_link`), when it serves requests.
        self.edge: Any = None
        self._estop_callback: Callable[[Any, int | None], None] | None = None
        self._estop_rings: list[Any] = []
        #: The rings' bookkeeping (`_look_rings`), shared by the fallback's thread and the
        #: forwarded requests' (`estops_before`): when they were last looked at, and an e-stop
        #: taken from them that the relay has not (yet) raised, with the look before it.
        self._ring_lock = threading.Lock()
        self._ring_seen_ns = time.monotonic_ns()
        self._ring_pending: tuple[Any, int] | None = None
        #: The latch as last written (the store's view at start).
        self._latch_written: Latch | None = service.store.load_latch_or_none()

    # -- lifecycle ---------------------------------------------------------------------------

    def declare(self, session: Any, *, queryables: bool = True) -> None:
        """Publishers, liveliness, the e-stop subscribers and (`queryables`) the request
        queryables on `session`."""
        import zenoh

        rig = self.opts.rig_name
        self.state_pub = session.declare_publisher(
            proto.key_state(rig),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self.status_pub = session.declare_publisher(
            proto.key_status(rig), congestion_control=zenoh.CongestionControl.DROP
        )
        self._entities += [self.state_pub, self.status_pub]
        # The state stream again, from the black box's batches (a recorder's lost samples).
        replay = ReplayServer(rig, self.blackbox.held, self.service.warn)
        replay.declare(session, auth=self.access.auth)
        self._entities.append(replay)
        # Announce the rig (routers carry it to every site): it leaves the list when this
        # session ends or is lost.
        self._entities.append(session.liveliness().declare_token(proto.key_alive(rig)))
        # Callbacks: hand over and return (no decoding, no Zenoh calls, no blocking). With
        # authentication the requests arrive on per-user scopes only (the key names the user).
        # With the edge process (`controller.process.edge`) it declares them, not this one.
        scoped = proto.any_user_key if self.access.auth else (lambda k: k)
        for key, q in () if not queryables else (
            (proto.key_config(rig), self.config_q),
            (proto.key_command(rig), self.command_q),
            (proto.key_identify(rig), self.identify_q),
            (proto.key_knowledge(rig), self.knowledge_q),
            (proto.key_lease(rig), self.lease_q),
            (proto.key_history(rig), self.history_q),
        ):
            handler = zenoh.handlers.Callback(self._enqueue(q), indirect=False)
            self._entities.append(session.declare_queryable(scoped(key), handler))
        rt = self.rt
        access = self.access

        def estop(sample: Any, arrival: int | None = None) -> None:
            rt.estop("estop key", rt.next_arrival() if arrival is None else arrival)
            key = str(sample.key_expr)
            who = proto.user_of_key(key) or (PUBLIC if access.auth else LOCAL.user)
            access.record("estop", who, "accepted", source="estop key", key=key,
                          **estop_claims(sample))

        self._estop_callback = estop
        # Anyone who reaches the rig stops it: the public key, and (with authentication) every
        # user's own scope. Without the edge process, a callback. With it, the edge takes the
        # e-stops (`controller.process.edge`: a shared flag the tick reads) and these are the
        # fallback: samples kept in a ring of one, in Zenoh (no Python code runs per sample),
        # read every ESTOP_POLL_S (`_estop_fallback`).
        estop_keys = [proto.key_estop(rig)]
        if self.access.auth:
            estop_keys.append(proto.any_user_key(proto.key_estop(rig)))
        for key in estop_keys:
            if queryables:
                self._entities.append(session.declare_subscriber(
                    key, zenoh.handlers.Callback(estop, indirect=False)))
            else:
                ring = session.declare_subscriber(key, zenoh.handlers.RingChannel(1))
                self._entities.append(ring)
                self._estop_rings.append(ring)

    def _estop_fallback(self) -> None:
        """The relay's e-stops checked, every ESTOP_POLL_S: an e-stop sample this process
        received that the relay did not raise (its flag's stamp not past the look before:
        the relay dead, not yet relaying, or not within ESTOP_GRACE_S) stops the loop from
        here. At most one sample per ring and look: a flood costs nothing."""
        stop = self.stop_event
        while not stop.wait(ESTOP_POLL_S):
            with self._ring_lock:
                self._look_rings()
                pending = self._ring_pending
            if pending is not None:
                self._settle(pending, self._relayed(pending[1]), None)

    def _look_rings(self) -> None:
        """Take the rings' samples (under `_ring_lock`): one the relay has not raised since
        the last look becomes pending (an earlier pending one stays: raising it covers both)."""
        now = time.monotonic_ns()
        got = None
        for ring in self._estop_rings:
            sample = ring.try_recv()
            if sample is not None:
                got = sample
        seen, self._ring_seen_ns = self._ring_seen_ns, now
        if (got is not None and self._ring_pending is None
                and not self.rt.estop_flag[ESTOP_ARRIVAL] > seen):
            self._ring_pending = (got, seen)

    def _settle(self, pending: tuple[Any, int], relayed: bool, arrival: int | None) -> None:
        """`pending` settled by one thread only (the fallback's or a request's): dropped if
        the relay raised it, else the loop stopped for it from here."""
        with self._ring_lock:
            if self._ring_pending is not pending:
                return  # another thread settled it
            self._ring_pending = None
        if not relayed:
            callback = self._estop_callback
            assert callback is not None  # declared with the rings
            callback(pending[0], arrival)

    def estops_before(self, arrival: int) -> None:
        """Before a forwarded request that can move the rig (config, command, identify;
        `arrival`: the edge's stamp): an e-stop this process received before it and the relay
        has not raised yet is raised now, stamped just before the request. Zenoh delivers one
        link's messages in order, so an e-stop a client sent before the request is in this
        process's ring before the request even reaches the edge; the relay is another process
        and under load raised it after the request was served (a Start accepted 1-21 ticks
        before the e-stop in 2 of 3000 reset / e-stop / Start triples, sixth session). A reset
        that came before the e-stop is refused by the stamp (the safe side)."""
        if not self._estop_rings:
            return
        with self._ring_lock:
            self._look_rings()
            pending = self._ring_pending
        if pending is not None:
            self._settle(pending, self.rt.estop_flag[ESTOP_ARRIVAL] > pending[1], arrival - 1)

    def _relayed(self, since: int) -> bool:
        """Whether the edge process relayed an e-stop that arrived after `since` (waits up to
        ESTOP_GRACE_S while it serves)."""
        edge = self.edge
        flag = self.rt.estop_flag
        deadline = time.monotonic() + ESTOP_GRACE_S
        while True:
            if flag[ESTOP_ARRIVAL] > since:
                return True
            if (edge is None or not edge.relaying.is_set() or time.monotonic() > deadline
                    or self.stop_event.wait(0.002)):
                return False

    def _enqueue(self, q: queue.SimpleQueue[Any]) -> Callable[[Any], None]:
        limit = self.opts.max_pending_queries
        arrival = self.rt.next_arrival

        def put(query: Any) -> None:
            # A flood beyond the bound is shed: the query is released unanswered (the client
            # times out) instead of growing memory without limit.
            if q.qsize() < limit:
                q.put((query, arrival()))
            else:
                self.shed_queries += 1

        return put

    def start_threads(self, *, workers: bool = True) -> None:
        """The publishers' and the latch's threads, and (`workers`) the request workers."""
        threads: tuple[tuple[str, Callable[[], None]], ...] = (
            ("state-publisher", self._publish_state),
            ("status", self._publish_status),
            ("latch", self._persist_latch),
            ("config-worker", lambda: self.serve_queue(self.config_q, self.handle_config)),
            ("command-worker", lambda: self.serve_queue(self.command_q, self.handle_command)),
            ("identify-worker", lambda: self.serve_queue(self.identify_q, self.handle_identify)),
            (
                "knowledge-worker",
                lambda: self.serve_queue(self.knowledge_q, self.handle_knowledge),
            ),
            ("lease-worker", lambda: self.serve_queue(self.lease_q, self.handle_lease)),
            ("history-worker", lambda: self.serve_queue(self.history_q, self.handle_history)),
        )
        if self._estop_rings:
            threads = (*threads, ("estop-fallback", self._estop_fallback))
        for name, target in threads if workers else (*threads[:3], *threads[9:]):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    def close(self) -> None:
        """Stop the threads (after the loop has finished), then undeclare everything."""
        self.stop_event.set()
        queues = (self.config_q, self.command_q, self.identify_q, self.knowledge_q, self.lease_q,
                  self.history_q)
        for q in queues:
            q.put(SHUTDOWN)
        for t in self._threads:
            t.join(timeout=5.0)
        for e in reversed(self._entities):
            with contextlib.suppress(Exception):
                e.undeclare()
        self._entities.clear()
        # Queries that arrived after the workers ended are dropped (the client times out).
        for q in queues:
            with contextlib.suppress(queue.Empty):
                while True:
                    item = q.get_nowait()
                    if item is not SHUTDOWN:
                        with contextlib.suppress(Exception):
                            item[0].drop()
        self.write_latch()  # the mode the loop ended in
        self.events.poll()
        self.events.summary()
        if self.shed_queries:
            log.warning("%d queries shed (flood)", self.shed_queries)

    # -- state and status --------------------------------------------------------------------

    def _publish_state(self) -> None:
        rt = self.rt
        rig = self.opts.rig_name
        rate = rt.options.rate_hz
        encode = proto.encode
        put = self.state_pub.put
        state_encoding = proto.encoding(proto.StateBatch)

        def sink(seq0: int, version: int, mode: str, cols: Sequence[list[float]]) -> None:
            msg = proto.state_batch(
                rig=rig,
                seq0=seq0,
                rate_hz=rate,
                config_version=version,
                columns=cols,
                epoch_s=rt.epoch_s,
                mode=mode,
            )
            self.blackbox.add(msg)
            try:
                put(encode(msg), encoding=state_encoding)
            except Exception as exc:
                self.service.warn(f"state put failed: {exc}")

        rt.publisher(sink, self.stop_event)

    def _black_box(self) -> None:
        """Write the black box on entering estop or fault, and on a watchdog rollback."""
        rt = self.rt
        # The rollbacks the service has reported, each with its text (the loop's count moves
        # first: its black box was written with no text or the previous rollback's).
        mode, rollbacks = rt.mode, self.service.rollbacks_reported
        if mode != self._bb_mode and mode in (ESTOP, FAULT):
            why = rt.estop_source if mode == ESTOP else (rt.fault or "fault")
            self.blackbox.trigger(mode, f"{mode}: {why} (seq {rt.seq})")
        if rollbacks != self._bb_rollbacks:
            self.blackbox.trigger("rollback", self.service.watchdog_text or "watchdog rollback")
        self._bb_mode, self._bb_rollbacks = mode, rollbacks

    def status(self) -> proto.Status:
        shed = self.shed_queries + (self.edge.shed if self.edge is not None else 0)
        return self.service.status((f"{shed} queries shed (flood)",) if shed else ())

    def _publish_status(self) -> None:
        period = self.opts.status_period_s
        while not self.stop_event.wait(period):
            try:
                self.events.poll()
                self.service.poll_rollback()
                self.service.poll_faults()
                self.access.poll()
                self._black_box()
                if self.edge is not None:
                    self.edge.push()  # what a rollback or new knowledge changed
                self.status_pub.put(
                    proto.encode(self.status()), encoding=proto.encoding(proto.Status)
                )
            except Exception as exc:
                self.service.warn(f"status put failed: {exc}")

    # -- the e-stop / fault latch -------------------------------------------------------------

    def write_latch(self) -> None:
        """Persist the latch if it differs from what was written last (any thread but the
        loop's). A state directory that cannot be written is reported; the loop runs on."""
        rt = self.rt
        mode = rt.mode
        if mode == ESTOP:
            latch: Latch | None = Latch(mode, rt.estop_source or "e-stop", rt.fault or "")
        elif mode == FAULT:
            latch = Latch(mode, rt.fault or "fault", "")
        else:
            latch = None
        if latch == self._latch_written:
            return
        try:
            self.service.store.save_latch(latch)
        except PersistenceError as exc:
            # Retried every second: one Status.notes line, counted (never pushing others out).
            self.service.warn(f"state_dir: the e-stop/fault latch was not saved: {exc}",
                              key="latch")
            return
        self._latch_written = latch
        self.service.clear_warning("latch")

    def _persist_latch(self) -> None:
        changed = self.rt.latch_changed
        while not self.stop_event.is_set():
            # A failed write is retried every second until it succeeds.
            changed.wait(1.0)
            changed.clear()
            try:
                self.write_latch()  # first: a rollback's save may wait for an apply's lock
                self.service.poll_rollback()  # a rollback is saved at once, not at the status
            except Exception as exc:  # never end this thread
                self.service.warn(f"latch writer: {type(exc).__name__}: {exc}")
            # At most one pass per LATCH_MIN_S: an e-stop flood moves the latch (estop_seq)
            # every tick; this process does not wake for each (issue 31).
            self.stop_event.wait(LATCH_MIN_S)

    # -- queries -----------------------------------------------------------------------------

    def serve_queue(
        self, q: queue.SimpleQueue[Any], handle: Callable[[bytes, Who], bytes]
    ) -> None:
        """Worker body: serve (query, arrival) items from `q` until SHUTDOWN. The sender is
        who the key it arrived on names (with authentication), never what it claims."""
        rt = self.rt
        while True:
            item = q.get()
            if item is SHUTDOWN:
                return
            query, arrival = item
            try:
                payload = query.payload
                data = b"" if payload is None else payload.to_bytes()
                who = self.access.who(query.key_expr)
                with rt.arrival_scope(arrival):
                    reply = handle(data, who)
                query.reply(query.key_expr, reply, encoding=self._reply_encoding.get(id(q)))
            except Exception as exc:  # never let a query end the worker
                # The details go to the log; the client gets no internal text.
                self.service.warn(f"query handler error: {type(exc).__name__}: {exc}")
                with contextlib.suppress(Exception):
                    query.reply_err(b"internal error: the request was not served (see the log)")
            finally:
                with contextlib.suppress(Exception):
                    query.drop()

    def _too_large(self, data: bytes) -> str | None:
        if len(data) > self.opts.max_payload_bytes:
            return f"payload: {len(data)} bytes is over the limit of {self.opts.max_payload_bytes}"
        return None

    def _read(self, data: bytes, kind: type[R], empty: R | None = None) -> R | Unreadable:
        """The request in `data` (`empty`, when given, for no payload), or why it cannot be
        read: over the size limit (field `payload`) or malformed (the offending field)."""
        big = self._too_large(data)
        if big is not None:
            return Unreadable(big, "payload")
        if not data and empty is not None:
            return empty
        try:
            return proto.decode(data, kind)
        except proto.ProtocolError as exc:
            log.debug("malformed %s: %s", kind.__name__, exc)
            return Unreadable(str(exc), exc.field)

    def handle_config(self, data: bytes, who: Who = LOCAL) -> bytes:
        """ConfigRequest -> ConfigReply (always a ConfigReply, also for a malformed request).
        A GET is for anyone; a candidate needs the lease (`controller.process.access`)."""
        svc = self.service
        req = self._read(data, proto.ConfigRequest, proto.ConfigRequest())
        if isinstance(req, Unreadable):
            self.access.record("apply", who, "refused", field=req.field, reason=req.message[:300])
            return proto.encode(
                svc.config_reply(accepted=False, reasons=[req.message], field=req.field)
            )
        if req.candidate is None:
            return proto.encode(svc.active_config())
        before = svc.rt.loop.active.version
        why = self.access.may_change(who, req.lease)
        if why:
            reply = svc.config_reply(accepted=False, reasons=[why], field="lease")
        else:
            reply = svc.apply(
                req.candidate, who.user, confirm=req.confirm, expect_version=req.expect_version
            )
        # The audit keeps its flat record (verdict kind, margins, knowledge version), as in
        # the audit logs written before the verdict was one nested field on the wire.
        v = reply.verdict
        self.access.record(
            "apply", who, "accepted" if reply.accepted else "refused",
            version_before=before, version_after=reply.version,
            verdict=v.verdict if v is not None else "",
            margins=msgspec.to_builtins(v.margins) if v is not None else None,
            knowledge_version=v.knowledge_version if v is not None else None,
            reasons=list(reply.reasons), field=reply.field, confirm=req.confirm,
            expect_version=req.expect_version, client=req.client[:100],
        )
        return proto.encode(reply)

    def handle_command(self, data: bytes, who: Who = LOCAL) -> bytes:
        """Command -> CommandReply. An EStop engages before the payload is even validated
        further than its type, from anyone; every other command needs the lease."""
        reply = self._command(data, who)
        body_type, seen = ("", None) if self._too_large(data) else _claimed_command(data)
        extra: dict[str, Any] = {}
        if body_type == "reset" and seen is not None:
            extra["estop_seq"] = seen  # the e-stop the reset acknowledged
        action = {"estop": "estop", "reset": "reset", "identify_start": "identify",
                  "identify_abort": "identify"}.get(body_type, "command")
        self.access.record(
            action, who, "accepted" if reply.ok else "refused", command=body_type[:40],
            message=reply.message, field=reply.field, mode=reply.mode, loop_seq=reply.seq,
            **extra,
        )
        return proto.encode(reply)

    def _command(self, data: bytes, who: Who) -> proto.CommandReply:
        svc = self.service
        cmd = self._read(data, proto.Command)
        if isinstance(cmd, Unreadable):
            return svc.refused(cmd.message, field=cmd.field)
        body = cmd.body
        if not isinstance(body, proto.EStop):
            why = self.access.may_change(who, cmd.lease)
            if why:
                return svc.refused(why, field="lease")
        if not isinstance(body, proto.IdentifyStart):
            try:
                request = to_request(body, cmd.client)
            except ConfigError as exc:
                name = f"body.{exc.field}"
                return svc.refused(f"{name}: {exc}", field=name)
            return svc.command(request, who.user)
        try:
            return svc.start_identify(body.spec, who.user)
        except ConfigError as exc:
            name = f"body.spec.{exc.field}"
            return svc.refused(f"{name}: {exc}", field=name)

    def handle_knowledge(self, data: bytes, who: Who = LOCAL) -> bytes:
        """KnowledgeRequest (or nothing) -> KnowledgeReply. Adopting needs the lease."""
        svc = self.service
        req = self._read(data, proto.KnowledgeRequest, proto.KnowledgeRequest())
        if isinstance(req, Unreadable):
            self.access.record("knowledge", who, "refused", field=req.field,
                               reason=req.message[:300])
            return proto.encode(svc.knowledge_reply(False, req.message, field=req.field))
        if req.record is None and req.adopt_run is None:
            return proto.encode(svc.knowledge_reply(True))
        before = svc.knowledge.version
        why = self.access.may_change(who, req.lease)
        reply = svc.knowledge_reply(False, why, field="lease") if why else svc.handle_knowledge(
            msgspec.structs.replace(req, client=who.user)
        )
        self.access.record(
            "knowledge", who, "accepted" if reply.ok else "refused",
            knowledge_before=before, knowledge_after=reply.record.version,
            message=reply.message, field=reply.field, adopt_run=req.adopt_run,
        )
        return proto.encode(reply)

    def handle_history(self, data: bytes, who: Who = LOCAL) -> bytes:
        """HistoryRequest (or nothing) -> HistoryReply: the applied configurations."""
        req = self._read(data, proto.HistoryRequest, proto.HistoryRequest())
        if isinstance(req, Unreadable):
            return proto.encode(proto.HistoryReply(ok=False, message=req.message,
                                                   field=req.field))
        return proto.encode(self.service.history(req.last))

    def handle_lease(self, data: bytes, who: Who = LOCAL) -> bytes:
        """LeaseRequest (or nothing: status) -> LeaseReply (recorded in the audit trail)."""
        req = self._read(data, proto.LeaseRequest, proto.LeaseRequest())
        if isinstance(req, Unreadable):
            return proto.encode(proto.LeaseReply(ok=False, message=req.message, field=req.field))
        return proto.encode(self.access.lease_request(who, req))

    def handle_identify(self, data: bytes, who: Who = LOCAL) -> bytes:
        """Any payload -> IdentifyStatus of the latest run."""
        return proto.encode(self.service.identify.status())
