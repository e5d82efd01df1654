"""`dobtune demo`: a simulated-plant controller subprocess plus the dashboard, in one go.

The controller runs as its own process (as on a real rig), listening on loopback; the dashboard
connects to it. Ctrl-C / SIGTERM stops the dashboard, then the controller (SIGINT, then SIGTERM,
then SIGKILL if it does not exit), and removes the temporary state directory.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from server.app import Dashboard, DashboardOptions, PortBusy, check_port_free, stop_requested

__all__ = ["DemoOptions", "controller_command", "controller_process", "run_demo", "stop_process"]

log = logging.getLogger(__name__)


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
    #: The controller's --log-level.
    log_level: str = "info"


def controller_command(
    endpoint: str, rig_name: str, state_dir: Path, log_level: str = "info"
) -> list[str]:
    return [
        sys.executable, "-m", "controller",
        "--plant", "sim",
        "--listen", endpoint,
        "--rig-name", rig_name,
        "--state-dir", str(state_dir),
        "--log-level", log_level,
    ]


def stop_process(proc: subprocess.Popen[Any], timeout_s: float = 5.0) -> int:
    """SIGINT, then SIGTERM, then SIGKILL; returns the exit code."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        if proc.poll() is not None:
            break
        with contextlib.suppress(ProcessLookupError):  # it exited meanwhile
            proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            log.warning("pid %d still running %.0f s after %s", proc.pid, timeout_s, sig.name)
    if proc.poll() is None:
        log.warning("pid %d: SIGKILL", proc.pid)
        proc.kill()
        proc.wait(timeout=timeout_s)
    return int(proc.returncode)


@contextlib.contextmanager
def controller_process(
    endpoint: str, rig_name: str, state_dir: Path | None = None, log_level: str = "info"
) -> Iterator[subprocess.Popen[Any]]:
    """The simulated controller as a child process, stopped on exit."""
    with contextlib.ExitStack() as stack:
        if state_dir is None:
            state_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="dobtune-")))
        proc = subprocess.Popen(controller_command(endpoint, rig_name, state_dir, log_level))
        try:
            yield proc
        finally:
            stop_process(proc)


def run_demo(opts: DemoOptions) -> int:
    """Start both, print the URL, run until Ctrl-C / SIGTERM; returns the exit code."""
    endpoint = f"tcp/127.0.0.1:{opts.zenoh_port}"
    code = 0
    for what, host, port in (("--port", opts.host, opts.port),
                             ("--zenoh-port", "127.0.0.1", opts.zenoh_port)):
        try:
            check_port_free(host, port, what)
        except PortBusy as exc:
            print(f"dobtune demo: {exc}", flush=True)
            return 2
    with stop_requested() as stop, controller_process(
        endpoint, opts.rig_name, opts.state_dir, opts.log_level
    ) as proc, Dashboard(
        DashboardOptions(
            connect=(endpoint,), rig_name=opts.rig_name, host=opts.host, port=opts.port,
            verbose=opts.verbose,
        )
    ) as dash:
        deadline = time.monotonic() + opts.startup_timeout_s
        while not dash.client.connected and not stop.is_set():
            if proc.poll() is not None:
                log.error("the controller exited with code %s", proc.returncode)
                return 1
            if time.monotonic() > deadline:
                log.error("no status from the controller within %.0f s",
                          opts.startup_timeout_s)
                return 1
            stop.wait(0.1)
        print(f"dobtune demo: open {dash.url}  (simulated rig '{opts.rig_name}', "
              f"controller on {endpoint}; Ctrl-C stops both)", flush=True)
        while not stop.wait(0.5):
            if proc.poll() is not None:
                log.error("the controller exited with code %s", proc.returncode)
                code = 1
                break
    print("dobtune demo: stopped", flush=True)
    return code
