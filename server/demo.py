"""`dobtune demo`: a simulated-plant controller subprocess plus the dashboard, in one go.

The controller runs as its own process (as on a real rig), listening on loopback; the dashboard
connects to it. Ctrl-C / SIGTERM stops the dashboard, then the controller (SIGINT, then SIGTERM,
then SIGKILL if it does not exit), and removes the temporary state directory.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from server.app import Dashboard, DashboardOptions

__all__ = ["DemoOptions", "controller_process", "run_demo"]


@dataclass(frozen=True)
class DemoOptions:
    host: str = "127.0.0.1"
    port: int = 8080
    zenoh_port: int = 7447
    rig_name: str = "demo"
    #: Where the controller keeps its active config; a temporary directory when None.
    state_dir: Path | None = None
    #: How long to wait for the controller's first status before giving up.
    startup_timeout_s: float = 30.0
    verbose: bool = True


def controller_command(endpoint: str, rig_name: str, state_dir: Path) -> list[str]:
    return [
        sys.executable, "-m", "controller",
        "--plant", "sim",
        "--listen", endpoint,
        "--rig-name", rig_name,
        "--state-dir", str(state_dir),
    ]


def stop_process(proc: subprocess.Popen[Any], timeout_s: float = 5.0) -> int:
    """SIGINT, then SIGTERM, then SIGKILL; returns the exit code."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        if proc.poll() is not None:
            break
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=timeout_s)
    if proc.poll() is None:
        proc.kill()
        proc.wait(timeout=timeout_s)
    return int(proc.returncode)


@contextlib.contextmanager
def controller_process(
    endpoint: str, rig_name: str, state_dir: Path | None = None
) -> Iterator[subprocess.Popen[Any]]:
    """The simulated controller as a child process, stopped on exit."""
    with contextlib.ExitStack() as stack:
        if state_dir is None:
            state_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="dobtune-")))
        proc = subprocess.Popen(controller_command(endpoint, rig_name, state_dir))
        try:
            yield proc
        finally:
            stop_process(proc)


def run_demo(opts: DemoOptions) -> int:
    """Start both, print the URL, run until Ctrl-C / SIGTERM; returns the exit code."""
    stop = threading.Event()

    def _handler(signum: int, _frame: Any) -> None:
        stop.set()

    old = {s: signal.signal(s, _handler) for s in (signal.SIGINT, signal.SIGTERM)}
    endpoint = f"tcp/127.0.0.1:{opts.zenoh_port}"
    code = 0
    try:
        with controller_process(endpoint, opts.rig_name, opts.state_dir) as proc, Dashboard(
            DashboardOptions(
                connect=(endpoint,), rig_name=opts.rig_name, host=opts.host, port=opts.port,
                verbose=opts.verbose,
            )
        ) as dash:
            deadline = time.monotonic() + opts.startup_timeout_s
            while not dash.client.connected and not stop.is_set():
                if proc.poll() is not None:
                    print(f"dobtune demo: the controller exited with code {proc.returncode}",
                          file=sys.stderr, flush=True)
                    return 1
                if time.monotonic() > deadline:
                    print("dobtune demo: no status from the controller within "
                          f"{opts.startup_timeout_s:.0f} s", file=sys.stderr, flush=True)
                    return 1
                stop.wait(0.1)
            print(f"dobtune demo: open {dash.url}  (simulated rig '{opts.rig_name}', "
                  f"controller on {endpoint}; Ctrl-C stops both)", flush=True)
            while not stop.wait(0.5):
                if proc.poll() is not None:
                    print(f"dobtune demo: the controller exited with code {proc.returncode}",
                          file=sys.stderr, flush=True)
                    code = 1
                    break
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    print("dobtune demo: stopped", flush=True)
    return code
