"""Helpers every test folder shares: free loopback ports, waiting on conditions, whether a
controller answers.

Tests wait on a condition with a generous deadline, never a fixed sleep standing in for
synchronisation (the machine may be at load 15).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import Any

__all__ = ["answers", "free_port", "port_is_free", "wait_for", "wait_until"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def port_is_free(port: int) -> bool:
    """True if nothing listens on 127.0.0.1:port: we can bind it ourselves (SO_REUSEADDR, so
    connections of the old process lingering in TIME_WAIT do not count)."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def wait_until(condition: Callable[[], object], timeout_s: float, poll_s: float = 0.01) -> bool:
    """True as soon as `condition()` is true; False when `timeout_s` passed first."""
    deadline = time.monotonic() + timeout_s
    while True:
        if condition():
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)


def wait_for(condition: Callable[[], object], timeout_s: float = 20.0,
             what: str = "timed out", poll_s: float = 0.05) -> None:
    """Until `condition()` is true; fails the test with `what` after `timeout_s`."""
    assert wait_until(condition, timeout_s, poll_s), what


def answers(client: Any) -> bool:
    """True if the controller answers `client` (a `ControllerClient`) a configuration query
    now; False if it is unavailable (not up yet, or gone)."""
    from controller.client import ControllerUnavailable

    try:
        client.get_config()
        return True
    except ControllerUnavailable:
        return False
