"""What the loop process's links to its two children share (`EdgeLink`: the edge process that
serves requests; `RelayLink`: the e-stop relay): read the child's control pipe until it ends,
then say so and start it again, at most every `RESTART_S`."""

from __future__ import annotations

import logging
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

__all__ = ["CLOSE_S", "RESTART_S", "ChildLink"]

log = logging.getLogger(__name__)

#: How long `close` and the control reader wait for a child process to end.
CLOSE_S = 5.0
#: The shortest time between two starts of a child process.
RESTART_S = 1.0


class ChildLink:
    """A child process's control pipe: ("ready",) sets `ready_event` (logged with
    `ready_text`); any other tuple goes to `on_message` once the node's service is attached.
    When the pipe ends the event is cleared and, unless the link is closing, the child is
    started again (`restart`) and the service warns under `warn_key`."""

    child_name = "child process"
    ready_text = "ready"
    warn_key = "child"

    def __init__(self) -> None:
        self.service: Any = None
        self.restarts = 0
        self._closing = threading.Event()
        self._started_at = 0.0

    @property
    def ready_event(self) -> threading.Event:
        raise NotImplementedError

    def on_message(self, msg: tuple[Any, ...]) -> None:
        raise NotImplementedError

    def restart(self) -> None:
        raise NotImplementedError

    def _read_control(self, control: Connection, proc: Any) -> None:
        ready = self.ready_event
        while True:
            try:
                msg = control.recv()
            except (EOFError, OSError):
                break
            if msg == ("ready",):
                ready.set()
                log.info("%s %d %s", self.child_name, proc.pid, self.ready_text)
            elif isinstance(msg, tuple) and msg and self.service is not None:
                self.on_message(msg)
        proc.join(CLOSE_S)
        ready.clear()  # (the e-stops: the node's fallback takes them meanwhile)
        if self._closing.is_set():
            return
        self.restarts += 1
        text = f"{self.child_name} ended (exit code {proc.exitcode}); started again"
        if self.service is not None:
            self.service.warn(text, key=self.warn_key)
        else:
            log.warning("%s", text)
        wait = RESTART_S - (time.monotonic() - self._started_at)
        if wait > 0 and self._closing.wait(wait):
            return
        self.restart()
