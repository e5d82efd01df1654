"""The e-stop relay: a process of its own whose Python does nothing but take e-stops.

Its Zenoh callback (`controller.process.edge._Edge.on_estop`) raises the loop's shared flag
(`edge.estop_flag`, read by the tick) and counts the e-stop for the audit; its reporter
sends each sender's e-stops to the loop process at most every `edge.ESTOP_REPORT_S` (the
audit lines, written here by `_estops`). It serves no request.

Why not in the edge process that serves the requests: a Zenoh callback needs its process's
interpreter lock, and under a request flood the edge's threads (the query callbacks, which
check the budget, and the workers, which answer reads) hold that lock nearly all the time,
each up to the switch interval (5 ms) before it passes; the e-stop's callback waited behind
them, and on the same link behind every query that came before it (bench_flood: e-stop put
-> tick p99 52-88 ms, max 78-118 ms under a viewer's flood at load 4-14). Here nothing else
wants the lock. The relay runs at the controller's priority (the edge is niced: a flood's
work yields the CPU to the e-stop, not the other way).

`RelayLink` (in the loop's process) starts it (forked at the controller's start with the
edge, spawned again if it dies, `RESTART_S` apart) and reads its control pipe: ("ready",)
once it relays, ("estop", reports) for the audit. While it is not relaying, the loop
process's own e-stop rings are the fallback (`ZenohNode._estop_fallback`, `relaying`).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

from controller.process.child_link import CLOSE_S, ChildLink
from controller.process.edge import CONNECT, EdgeSpec, edge_main

__all__ = ["RelayLink"]

log = logging.getLogger(__name__)

class RelayLink(ChildLink):
    """Runs the e-stop relay process: `launch()` (the process) then `watch()` (the thread
    that reads it), so that a first start forks before any thread of the caller's exists."""

    child_name = "e-stop relay process"
    ready_text = "relaying e-stops"
    warn_key = "estop-relay"

    def __init__(self, spec: EdgeSpec, flag: Any) -> None:
        super().__init__()
        self.spec = spec
        self.flag = flag
        self.relaying = threading.Event()
        """Set while the relay process takes e-stops (the node's fallback waits for it)."""
        self._proc: Any = None
        self._control: Connection | None = None
        self._control_lock = threading.Lock()
        self._connect = False

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def launch(self) -> None:
        """Start the process (forked the first time, as the edge is; spawned again after)."""
        if self._closing.is_set():
            return
        first = self._proc is None and "fork" in multiprocessing.get_all_start_methods()
        ctx: Any = multiprocessing.get_context("fork" if first else "spawn")
        control, theirs = ctx.Pipe(duplex=True)
        proc = ctx.Process(target=edge_main, args=(self.spec, {}, theirs, self.flag, "estops"),
                           name="dobtune-estop-relay", daemon=True)
        self._started_at = time.monotonic()
        proc.start()
        theirs.close()
        with self._control_lock:
            self._control = control
        self._proc = proc
        if self._connect:  # started again: the session is open
            self._send(CONNECT)

    def watch(self) -> None:
        """Read the process's control pipe from a thread (started again when it dies)."""
        control, proc = self._control, self._proc
        if control is None or proc is None:
            return
        threading.Thread(target=self._read_control, args=(control, proc),
                         name="estop-relay-control", daemon=True).start()

    def connect_now(self) -> None:
        self._connect = True
        self._send(CONNECT)

    def _send(self, msg: Any) -> None:
        with self._control_lock:
            control = self._control
            if control is not None:
                with contextlib.suppress(OSError, ValueError, TypeError):
                    control.send(msg)

    def close(self) -> None:
        self._closing.set()
        proc = self._proc
        if proc is not None:
            proc.terminate()
            proc.join(CLOSE_S)
            if proc.is_alive():
                proc.kill()
                proc.join(CLOSE_S)
        with self._control_lock:
            control, self._control = self._control, None
        if control is not None:
            with contextlib.suppress(OSError):
                control.close()

    @property
    def ready_event(self) -> threading.Event:
        return self.relaying

    def on_message(self, msg: tuple[Any, ...]) -> None:
        if msg[0] == "estop":
            self._estops(msg[1])

    def restart(self) -> None:
        self.launch()
        self.watch()

    def _estops(self, estops: list[tuple[str, str, dict[str, str], int, float]]) -> None:
        """The audit lines of the e-stops the relay received: one per sender and report, the
        others it coalesced counted (`repeats`); `arrived_s`: when the first one reached the
        relay (UNIX time; the line itself is written up to ESTOP_REPORT_S later)."""
        access = self.service.access
        for who, key, claims, n, arrived_s in estops:
            access.record("estop", who, "accepted", source="estop key", key=key,
                          relayed="edge", arrived_s=round(arrived_s, 6), **claims,
                          **({"repeats": n - 1} if n > 1 else {}))
