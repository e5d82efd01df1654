"""The start of a worker process (the gate's): a module of its own that imports nothing heavy.

A spawned worker imports its initializer's module before anything else runs in it; here that
takes milliseconds, so the worker ignores Ctrl-C (a terminal signals the whole process group:
the controller decides) before it loads the analysis for seconds (a SIGINT then would kill it
with a traceback).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal

from controller.process.parent_watch import watch_parent

__all__ = ["idle_priority", "lower_priority", "worker_init"]

PR_SET_PDEATHSIG = 1
#: How much lower a worker's priority is than the controller's (nice).
NICE = 10
#: This process's threads (Linux).
_TASKS = "/proc/self/task"


def _end_with_parent(parent_pid: int, death_signal: bool) -> None:
    """This worker ends when the controller does, even if it was SIGKILLed: a thread watches
    the parent's pid (`parent_watch`), and with `death_signal` the kernel also sends SIGKILL
    at once (Linux prctl PR_SET_PDEATHSIG; only for a worker started by the main thread: the
    signal follows the thread that started it)."""
    if death_signal:
        _set_death_signal()
    watch_parent(parent_pid, lambda: os._exit(1))


def _set_death_signal() -> None:
    """The kernel's SIGKILL when the parent dies; where it cannot be had (no Linux libc), the
    parent watch alone ends the worker, and the log says why."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        failed = libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0
        why = os.strerror(ctypes.get_errno()) if failed else ""
    except (OSError, AttributeError) as exc:  # no libc, or one without prctl
        failed, why = True, str(exc)
    if failed:
        logging.getLogger(__name__).warning(
            "analysis worker: no death signal (prctl PR_SET_PDEATHSIG: %s); it ends when "
            "its parent-pid watch sees the controller gone", why)


def worker_init(parent_pid: int, death_signal: bool, nice: bool = True) -> None:
    """Ignore Ctrl-C, end with the parent, and (`nice`) yield the CPU to it (`lower_priority`;
    the edge process does that itself once it serves, so the controller's start, which waits
    for it, is not slowed by its loading)."""
    # Ctrl-C in a terminal reaches the whole process group: the parent decides, not us.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _end_with_parent(parent_pid, death_signal)
    if nice:
        lower_priority()


def lower_priority(every_thread: bool = False) -> None:
    """Nice 10 more: the loop's process wins the CPU over this one.

    On Linux a nice value is a thread's, not the process's (os.nice changes the calling
    thread's, and threads started later inherit their starter's): called first thing (the
    analysis worker), every later thread is niced; `every_thread` renices each thread that
    runs already (the edge process: its workers and Zenoh's threads start before it serves)."""
    # The loop's process wins the CPU over an analysis on a busy machine (also over this
    # worker's loading: at normal priority it slowed the controller's own start by ~15 % at
    # load 20-25, bench_startup).
    try:
        if every_thread and os.path.isdir(_TASKS):
            for tid in os.listdir(_TASKS):
                with contextlib.suppress(ProcessLookupError):  # a thread that ended
                    nice = os.getpriority(os.PRIO_PROCESS, int(tid))
                    os.setpriority(os.PRIO_PROCESS, int(tid), min(19, nice + NICE))
        else:
            os.nice(NICE)
    except OSError as exc:
        logging.getLogger(__name__).warning(
            "worker process: runs at the controller's priority (os.nice: %s)", exc)


def idle_priority() -> str:
    """Every thread of this process, and each it starts later, to SCHED_IDLE (Linux): it runs
    only on a core nothing else wants, so it yields to the loop's process entirely (its
    publisher and Zenoh threads, which the loop's thread waits on for the interpreter lock,
    too). On a saturated machine it then gets almost no CPU (weight 3 against nice 0's 1024).
    Returns what happened; raises OSError when the policy cannot be set (the caller says so
    and lowers the priority the other way)."""
    if not hasattr(os, "SCHED_IDLE"):
        raise OSError("SCHED_IDLE: not on this platform")
    param = os.sched_param(0)
    os.sched_setscheduler(0, os.SCHED_IDLE, param)  # this thread: later threads inherit it
    tids = os.listdir(_TASKS) if os.path.isdir(_TASKS) else []
    for tid in tids:
        with contextlib.suppress(ProcessLookupError):  # a thread that ended
            os.sched_setscheduler(int(tid), os.SCHED_IDLE, param)
    return f"SCHED_IDLE ({len(tids) or 1} threads)"
