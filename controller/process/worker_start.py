"""The start of a worker process (the gate's): a module of its own that imports nothing heavy.

A spawned worker imports its initializer's module before anything else runs in it; here that
takes milliseconds, so the worker ignores Ctrl-C (a terminal signals the whole process group:
the controller decides) before it loads the analysis for seconds (a SIGINT then would kill it
with a traceback).
"""

from __future__ import annotations

import contextlib
import os
import signal

from controller.process.parent_watch import watch_parent

__all__ = ["worker_init"]

PR_SET_PDEATHSIG = 1


def _end_with_parent(parent_pid: int, death_signal: bool) -> None:
    """This worker ends when the controller does, even if it was SIGKILLed: a thread watches
    the parent's pid (`parent_watch`), and with `death_signal` the kernel also sends SIGKILL
    at once (Linux prctl PR_SET_PDEATHSIG; only for a worker started by the main thread: the
    signal follows the thread that started it)."""
    if death_signal:
        _set_death_signal()
    watch_parent(parent_pid, lambda: os._exit(1))


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
    # The loop's process wins the CPU over an analysis on a busy machine (also over this
    # worker's loading: at normal priority it slowed the controller's own start by ~15 % at
    # load 20-25, bench_startup).
    with contextlib.suppress(OSError):
        os.nice(10)
