"""A process that ends with the one that started it, even when that one is killed outright
(SIGKILL: no chance to stop its children): the analysis worker with its controller, and a
controller or router with the launcher that started it (`dobtune demo`, `--parent-pid`).

A thread watches the parent's pid: when the process is re-parented (its parent is gone), the
`on_gone` callback runs. Imports nothing heavy (the worker's start imports this first).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable

__all__ = ["stop_self", "watch_parent"]


def watch_parent(parent_pid: int, on_gone: Callable[[], None], poll_s: float = 0.5) -> None:
    """Call `on_gone` (in a daemon thread, once) as soon as `parent_pid` is no longer this
    process's parent: at once if it is not its parent now (the parent may have died before
    the child got here), else within `poll_s` of the parent's death."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
        on_gone()

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def stop_self() -> None:
    """SIGTERM to this process: its own handler stops it as a launcher's SIGTERM would (the
    controller: command 0, close, exit 0); without a handler yet, the default ends it."""
    os.kill(os.getpid(), signal.SIGTERM)
