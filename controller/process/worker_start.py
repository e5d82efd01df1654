"""The start of a worker process (the gate's): a module of its own that imports nothing heavy.

A spawned worker imports its initializer's module before anything else runs in it; here that
takes milliseconds, so the worker ignores Ctrl-C (a terminal signals the whole process group:
the controller decides) before it loads the analysis for seconds (a SIGINT then would kill it
with a traceback). Once loaded it lowers its priority (`lower_priority`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time

__all__ = ["lower_priority", "worker_init"]

PR_SET_PDEATHSIG = 1
#: The worker's niceness once it has loaded (`lower_priority`).
WORKER_NICE = 10
_niced = False


def _end_with_parent(parent_pid: int, death_signal: bool, poll_s: float = 0.5) -> None:
    """This worker ends when the controller does, even if it was SIGKILLed: a thread watches
    the parent's pid (the worker is re-parented when the parent dies), and with
    `death_signal` the kernel also sends SIGKILL at once (Linux prctl PR_SET_PDEATHSIG; only
    for a worker started by the main thread: the signal follows the thread that started it)."""
    if death_signal:
        _set_death_signal()

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(1)
            time.sleep(poll_s)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _set_death_signal() -> None:
    with contextlib.suppress(Exception):
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def worker_init(parent_pid: int, death_signal: bool) -> None:
    # Ctrl-C in a terminal reaches the whole process group: the parent decides, not us.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _end_with_parent(parent_pid, death_signal)


def lower_priority() -> None:
    """From now on the loop's process wins the CPU over this worker's analyses on a busy
    machine (niceness +`WORKER_NICE`, once). A worker loads (and judges the running
    configuration) at normal priority first, like the controller's own start-up: niced, it
    needed many times longer behind a busy machine, and the first apply waited for it."""
    global _niced
    if not _niced:
        _niced = True
        with contextlib.suppress(OSError):
            os.nice(WORKER_NICE)
