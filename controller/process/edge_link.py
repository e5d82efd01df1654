"""The loop process's side of the edge process (`controller.process.edge`): start it, serve
what it forwards, keep it informed, start it again if it dies.

- One thread per forwarded kind reads the kind's pipe and calls the node's handler
  (`ZenohNode.handle_*`: lease, gate, audit), with the arrival stamp the edge gave the query
  (`time.monotonic_ns`, the same clock as the loop's e-stop stamps, across processes); the
  reply goes back with the newest `EdgeSnapshot` when the request may have changed it, so a
  read that follows an apply's reply sees the applied configuration.
- The status thread calls `push()`: a snapshot that changed (a watchdog rollback, new plant
  knowledge) goes over the control pipe.
- The control pipe brings the edge's refusals (request budget, shed queries): one audit record
  per user and report, and a Status.notes line; and the e-stops it received (each sender's,
  coalesced): their audit lines. The e-stops themselves reach the tick through the shared
  flag (`edge.estop_flag`), not through this process's Python code.
- The e-stops are not the edge's: a process of their own relays them (`estop_relay`,
  `RelayLink`, started and stopped with the edge: the edge's interpreter lock is the
  requests'). The node's own e-stop subscribers are the fallback
  (`ZenohNode._estop_fallback`): rings of one sample, read every 10 ms; an e-stop the relay
  did not relay (dead, not yet relaying, or not within 0.5 s) is raised from there.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import queue
import socket
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from controller import protocol as proto
from controller.process.child_link import CLOSE_S, ChildLink
from controller.process.edge import (
    CONNECT,
    FORWARDED,
    ORDERED,
    EdgeSnapshot,
    EdgeSpec,
    edge_main,
    estop_flag,
)
from controller.process.estop_relay import RelayLink

__all__ = ["EdgeLink", "Oversized", "free_loopback_port"]

log = logging.getLogger(__name__)

#: How long `push` waits for its snapshot to be sent.
PUSH_WAIT_S = 0.05


def free_loopback_port() -> int:
    """A TCP port free on 127.0.0.1 now (for the loop session's private endpoint)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Oversized(bytes):
    """An empty payload standing for one of `size` bytes that the edge did not send (over
    the size limit): `len()` is the size, so the handler's size check refuses it, naming it."""

    size: int

    def __new__(cls, size: int) -> Oversized:
        obj = super().__new__(cls, b"")
        obj.size = size
        return obj

    def __len__(self) -> int:
        return self.size


class EdgeLink(ChildLink):
    """Runs the edge process: `start()` early (it loads and connects beside the controller's
    start-up), `attach(node)` once the node exists (the forwarded requests wait until then)."""

    child_name = "edge process"
    ready_text = "serving requests"
    warn_key = "edge"

    def __init__(self, spec: EdgeSpec) -> None:
        super().__init__()
        self.spec = spec
        self.node: Any = None
        self.rt: Any = None
        self._handlers: dict[str, Callable[[bytes, Any], bytes]] = {}
        self._snap_lock = threading.Lock()
        self._snap_key: tuple[Any, ...] = ()
        self._snap: EdgeSnapshot | None = None
        self._pushed = -1
        self._control: Connection | None = None
        self._outq: queue.SimpleQueue[tuple[Any, threading.Event]] = queue.SimpleQueue()
        self._connect = False
        self._pushing: threading.Thread | None = None
        self._proc: Any = None
        self._conns: dict[str, Connection] = {}
        self.ready = threading.Event()
        self.refused: dict[str, int] = {}
        """Requests refused by the budget since the start, by user."""
        self.shed = 0
        #: The e-stop flag the relay raises and the tick reads (`controller.process.edge`).
        self.estop_flag = estop_flag()
        #: The e-stop relay process (`controller.process.estop_relay`).
        self.relay = RelayLink(spec, self.estop_flag)

    @property
    def relaying(self) -> threading.Event:
        """Set while the e-stop relay process takes the e-stops."""
        return self.relay.relaying

    # -- snapshots -----------------------------------------------------------------------------

    def snapshot(self) -> EdgeSnapshot:
        """The replies to a configuration GET and a knowledge GET now (encoded again only when
        what they show changed: the active coefficients, the verdict, the knowledge, its
        twin once built)."""
        svc = self.service
        key = (svc.rt.loop.active, svc.running_verdict, svc.knowledge, svc.twin_built)
        with self._snap_lock:
            snap = self._snap
            if snap is None or any(a is not b for a, b in zip(key, self._snap_key, strict=True)):
                gen = 0 if snap is None else snap.generation + 1
                snap = self._snap = EdgeSnapshot(
                    gen, proto.encode(svc.active_config()),
                    proto.encode(svc.knowledge_reply(True)), key[0].version)
                self._snap_key = key
            return snap

    def push(self, *, always: bool = False) -> None:
        """Hand the snapshot to the pusher thread if it changed since the last push (never
        blocks long: an edge process that does not read its pipe holds up no caller)."""
        snap = self.snapshot()
        if always or snap.generation != self._pushed:
            self._pushed = snap.generation
            sent = self._send(snap)
            # Normally sent at once, before the status that shows the change (a client that
            # reads the configuration on seeing it gets the new one); never waited on long.
            sent.wait(PUSH_WAIT_S)

    def connect_now(self) -> None:
        """The loop process's session is open: the edge process may connect (before, each
        of its attempts would have cost the start CPU)."""
        self._connect = True
        self._send(CONNECT)
        self.relay.connect_now()

    def _send(self, msg: Any) -> threading.Event:
        """Queue `msg` for the edge's control pipe; the event is set once it is sent."""
        sent = threading.Event()
        self._outq.put((msg, sent))
        return sent

    def _pusher(self) -> None:
        """Sends what is queued for the control pipe, in order."""
        while True:
            msg, sent = self._outq.get()
            if msg is None:
                return
            control = self._control
            if control is not None:
                # TypeError: the Connection closed by another thread meanwhile (see `close`).
                with contextlib.suppress(OSError, ValueError, TypeError):
                    control.send(msg)
            sent.set()

    # -- the process ---------------------------------------------------------------------------

    def start(self) -> None:
        """Start the edge process (and, once attached, the threads that serve it)."""
        if self._closing.is_set():
            return
        # The first start forks (the controller's start, before any Zenoh session or thread
        # of its own: the child has every module loaded and costs the start nothing); a
        # start again spawns a fresh interpreter (a fork now would copy a running Zenoh).
        first = self._proc is None and "fork" in multiprocessing.get_all_start_methods()
        ctx: Any = multiprocessing.get_context("fork" if first else "spawn")
        if self._proc is None:
            self.relay.launch()  # forked too, before any thread of ours
        ours: dict[str, Connection] = {}
        theirs: dict[str, Connection] = {}
        for kind in FORWARDED:
            ours[kind], theirs[kind] = ctx.Pipe(duplex=True)
        control, their_control = ctx.Pipe(duplex=True)
        proc = ctx.Process(target=edge_main,
                           args=(self.spec, theirs, their_control, self.estop_flag),
                           name="dobtune-edge", daemon=True)
        self._started_at = time.monotonic()
        proc.start()
        for c in (*theirs.values(), their_control):
            c.close()  # the child's ends: ours see EOF when it dies
        self._control = control
        self._proc = proc
        self._conns = ours
        threading.Thread(target=self._read_control, args=(control, proc), name="edge-control",
                         daemon=True).start()
        if self._pushing is None:  # after the fork: no thread of ours in it
            self.relay.watch()
            self._pushing = threading.Thread(target=self._pusher, name="edge-push", daemon=True)
            self._pushing.start()
        if self._connect:  # started again: the session is open
            self._send(CONNECT)
        if self.node is not None:
            self._serve_threads()

    def attach(self, node: Any) -> None:
        """Serve the edge's forwarded requests with `node`'s handlers from now on."""
        self.node = node
        self.service = node.service
        self.relay.service = node.service
        self.rt = node.rt
        node.rt.estop_flag = self.estop_flag
        self._handlers = {
            "config": node.handle_config,
            "command": node.handle_command,
            "identify": node.handle_identify,
            "knowledge": node.handle_knowledge,
            "lease": node.handle_lease,
        }
        self._serve_threads()

    def _serve_threads(self) -> None:
        self.push(always=True)  # a new process has none
        for kind, conn in self._conns.items():
            threading.Thread(target=self._serve, args=(kind, conn), name=f"edge-{kind}",
                             daemon=True).start()

    def close(self) -> None:
        """End the edge process (SIGTERM: nothing of it needs saving; SIGKILL if it lingers)
        and the e-stop relay's."""
        self._closing.set()
        self.relay.close()
        self._outq.put((None, threading.Event()))
        proc = self._proc
        if proc is not None:
            proc.terminate()
            proc.join(CLOSE_S)
            if proc.is_alive():
                proc.kill()
                proc.join(CLOSE_S)
        # The pusher ends (its stop is queued above) before the pipe closes: a send running
        # while another thread closes the Connection fails inside multiprocessing with a
        # TypeError (its handle None), the likely "Exception in thread edge-push" once seen.
        pusher = self._pushing
        if pusher is not None:
            pusher.join(CLOSE_S)
        control, self._control = self._control, None
        if control is not None:
            with contextlib.suppress(OSError):
                control.close()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    # -- threads -------------------------------------------------------------------------------

    def _serve(self, kind: str, conn: Connection) -> None:
        handle = self._handlers[kind]
        access = self.service.access
        rt = self.rt
        node = self.node
        ordered = kind in ORDERED
        with conn:
            while True:
                try:
                    key, arrival, data, size = conn.recv()
                except (EOFError, OSError):
                    return  # the edge process ended
                snap: EdgeSnapshot | None = None
                try:
                    if ordered:
                        node.estops_before(arrival)
                    who = access.who(key)
                    with rt.arrival_scope(arrival):
                        reply: bytes | None = handle(
                            Oversized(size) if data is None else data, who)
                    if kind != "identify" and kind != "lease":
                        snap = self.snapshot()
                except Exception as exc:  # never end the thread: the client is told
                    self.service.warn(f"query handler error: {type(exc).__name__}: {exc}")
                    reply = None
                try:
                    conn.send((reply, snap))
                except (OSError, ValueError):
                    return

    @property
    def ready_event(self) -> threading.Event:
        return self.ready

    def on_message(self, msg: tuple[Any, ...]) -> None:
        if msg[0] == "refused":
            self._refused(msg[1], msg[2])

    def restart(self) -> None:
        self.start()

    def _refused(self, refused: dict[str, int], shed: int) -> None:
        access = self.service.access
        budget = f"{self.spec.budget_per_s:g} requests/s per user"
        for user, n in refused.items():
            self.refused[user] = self.refused.get(user, 0) + n
            access.record("request.budget", user, "refused", count=n, budget=budget)
        self.shed += shed
        if refused:
            users = ", ".join(f"{u} {n}" for u, n in sorted(self.refused.items()))
            self.service.warn(f"request budget ({budget}): {sum(self.refused.values())} "
                              f"requests refused ({users})", key="budget")
