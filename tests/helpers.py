"""Helpers every test folder shares: free loopback ports, waiting on conditions, whether a
controller answers, starting a child process that dies with the test process.

Tests wait on a condition with a generous deadline, never a fixed sleep standing in for
synchronisation (the machine may be at load 15).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

__all__ = ["answers", "children", "free_port", "gone", "no_new_files", "port_is_free", "spawn",
           "wait_for", "wait_until"]

_PR_SET_PDEATHSIG = 1
#: libc's prctl, looked up now: the child calls it between fork and exec, where it should do
#: as little as possible (no import, no library loading).
_prctl = ctypes.CDLL(None, use_errno=True).prctl


def spawn(args: Sequence[str], **popen_kwargs: Any) -> subprocess.Popen[Any]:
    """`subprocess.Popen(args, **popen_kwargs)` for a test's child (a controller, a router, a
    demo): the kernel SIGKILLs it when this test process dies, however it dies (a suite run
    killed at its timeout leaves no controller or router running). Linux's
    PR_SET_PDEATHSIG, which follows the thread that started the child: only from the main
    thread (a child of another thread would die when that thread ends)."""
    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError("spawn: start test processes from the main thread (PR_SET_PDEATHSIG "
                           "would kill the child when this thread ends)")
    parent = os.getpid()

    def die_with_parent() -> None:
        if _prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
        if os.getppid() != parent:  # the test process died before prctl: nobody to signal
            os.kill(os.getpid(), signal.SIGKILL)

    return subprocess.Popen(args, preexec_fn=die_with_parent, **popen_kwargs)


class Output:
    """A child's merged stdout/stderr, read into `lines` by a thread (the pipe never fills)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None, "start the child with stdout=subprocess.PIPE, text=True"
        self.proc = proc
        self.lines: list[str] = []
        self.reader = threading.Thread(target=lambda: self.lines.extend(proc.stdout or ()),
                                       daemon=True)
        self.reader.start()

    def text(self) -> str:
        return "".join(self.lines)

    def wait_url(self, timeout_s: float) -> str:
        """The dashboard's URL with its token, once printed (fails at once if it exits)."""
        wait_for(lambda: any("?token=" in ln for ln in self.lines)
                 or self.proc.poll() is not None, timeout_s, "the dashboard printed no URL")
        assert self.proc.poll() is None, self.text()
        return next(ln for ln in self.lines if "?token=" in ln).split()[2]


def _stat(pid: int | str) -> list[str] | None:
    """/proc/PID/stat's fields after the command name (state, ppid, ...); None: no such pid."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return None


def gone(pid: int) -> bool:
    """True once process `pid` has ended (no such process, or a zombie nobody reaped yet)."""
    fields = _stat(pid)
    return fields is None or fields[0] in ("Z", "X")


def children(pid: int) -> list[int]:
    """The live child processes of `pid` (from /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            fields = _stat(entry)
            if fields is not None and fields[1] == str(pid) and fields[0] not in ("Z", "X"):
                out.append(int(entry))
    return out


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


@contextlib.contextmanager
def no_new_files(directory: Path) -> Iterator[None]:
    """While inside: no file can be created, renamed or removed in `directory` (its files can
    still be written and appended to), for any process, root included: what a directory
    whose permissions were taken away does. Root ignores permissions: it gets the immutable
    attribute (chattr +i; ext4 and most Linux file systems) instead of chmod 555."""
    if os.geteuid() != 0:
        mode = directory.stat().st_mode
        directory.chmod(0o555)
        try:
            yield
        finally:
            directory.chmod(mode)
        return
    done = subprocess.run(["chattr", "+i", str(directory)], capture_output=True, text=True)
    if done.returncode != 0:
        raise AssertionError(
            f"chattr +i {directory}: {done.stderr.strip()}: as root, this test needs a file "
            "system with the immutable attribute (ext4, xfs, btrfs; not tmpfs), or run it as "
            "another user (then chmod 555 is used)")
    try:
        probe = directory / ".no_new_files_probe"
        try:
            probe.touch()
        except PermissionError:
            pass
        else:
            probe.unlink()
            raise AssertionError(f"chattr +i did not stop new files in {directory}")
        yield
    finally:
        subprocess.run(["chattr", "-i", str(directory)], check=True, capture_output=True)


class FakeClock:
    """Time advances only through sleep(), rig work, and 1 us per clock read (so spins end)."""

    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        self.now += 1e-6
        return self.now

    def sleep(self, s: float) -> None:
        assert s >= 0.0
        self.sleeps.append(s)
        self.now += s
