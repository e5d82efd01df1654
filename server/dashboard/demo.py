"""`dobtune demo`: a simulated-plant controller subprocess plus the dashboard, in one go.

The controller runs as its own process (as on a real rig), listening on loopback; the dashboard
connects to it. Ctrl-C / SIGTERM stops the dashboard, then the controller (SIGINT, then SIGTERM,
then SIGKILL if it does not exit), and removes the temporary state directory. The children are
started with `--parent-pid`: a demo killed outright (SIGKILL) leaves no controller or router
running (they stop themselves; only the temporary state directory stays).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from controller.core.errors import ConfigError
from controller.core.heap import freeze_startup_heap
from controller.sim.rig_disturbances import DEFAULT_RIG_NAMES, rig_setup
from server.dashboard.app import (
    Dashboard,
    DashboardOptions,
    PortBusy,
    check_port_free,
    stop_requested,
)

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
    #: While the controller starts (however long it takes: it is never given up on while its
    #: process runs), a progress line this often.
    progress_every_s: float = 5.0
    verbose: bool = True
    #: The controller's --log-level.
    log_level: str = "info"
    #: More than 1: a Zenoh router on `zenoh_port` and this many simulated rigs (rig1..rigN,
    #: each listening on zenoh_port + i, different noise seeds and drive gains) behind it; the
    #: dashboard shows rig1 through the router (`dobtune ctl --connect ... rigs` lists all).
    rigs: int = 1
    #: Where the dashboard keeps each user's candidates (`DashboardOptions.candidates_dir`).
    candidates_dir: Path | None = None
    #: The simulated rig's named disturbances (`controller.sim.rig_disturbances`), given to
    #: the controller and to the dashboard's previews and Suggest alike.
    disturbances: tuple[str, ...] = DEFAULT_RIG_NAMES


def controller_command(
    endpoint: str, rig_name: str, state_dir: Path, log_level: str = "info",
    extra: tuple[str, ...] = (),
) -> list[str]:
    return [
        sys.executable, "-m", "controller",
        "--plant", "sim",
        "--listen", endpoint,
        "--rig-name", rig_name,
        "--state-dir", str(state_dir),
        "--log-level", log_level,
        *extra,
    ]


def _disturbance_args(names: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(a for n in names for a in ("--disturbance", n))


def router_command(endpoint: str, log_level: str = "info",
                   extra: tuple[str, ...] = ()) -> list[str]:
    code = ("import sys; from controller.cli.main import dobtune_main; "
            "sys.exit(dobtune_main(['router', *sys.argv[1:]]))")
    return [sys.executable, "-c", code, "--listen", endpoint, "--log-level", log_level, *extra]


def _with_us() -> tuple[str, ...]:
    """A child of the demo stops itself once the demo is gone (also when it was SIGKILLed)."""
    return ("--parent-pid", str(os.getpid()))


@contextlib.contextmanager
def fleet_processes(opts: DemoOptions, state_root: Path) -> Iterator[list[subprocess.Popen[bytes]]]:
    """A router on zenoh_port and opts.rigs controllers behind it; stopped on exit."""
    router_ep = f"tcp/127.0.0.1:{opts.zenoh_port}"
    procs: list[subprocess.Popen[bytes]] = []
    try:
        procs.append(subprocess.Popen(router_command(router_ep, opts.log_level, _with_us())))
        for i in range(1, opts.rigs + 1):
            ep = f"tcp/127.0.0.1:{opts.zenoh_port + i}"
            procs.append(subprocess.Popen(controller_command(
                ep, f"rig{i}", state_root / f"rig{i}", opts.log_level,
                ("--connect", router_ep, "--seed", str(i),
                 *_disturbance_args(opts.disturbances), *_with_us()),
            )))
        yield procs
    finally:
        for p in reversed(procs):
            stop_process(p)


def stop_process(proc: subprocess.Popen[bytes], timeout_s: float = 5.0) -> int:
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
    endpoint: str, rig_name: str, state_dir: Path | None = None, log_level: str = "info",
    disturbances: tuple[str, ...] = (),
    watch: bool = False,
) -> Iterator[subprocess.Popen[bytes]]:
    """The simulated controller as a child process (with the simulated rig's named
    `disturbances`; `watch`: with the watch beside it, as `dobtune demo` runs it), stopped
    on exit."""
    with contextlib.ExitStack() as stack:
        if state_dir is None:
            state_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="dobtune-")))
        proc = subprocess.Popen(controller_command(
            endpoint, rig_name, state_dir, log_level,
            (*_disturbance_args(disturbances), *_with_us(),
             *(() if watch else ("--no-watch",)))))
        try:
            yield proc
        finally:
            stop_process(proc)


def run_demo(opts: DemoOptions) -> int:
    """Start both, print the URL, run until Ctrl-C / SIGTERM; returns the exit code."""
    endpoint = f"tcp/127.0.0.1:{opts.zenoh_port}"
    ports = [("--port", opts.host, opts.port), ("--zenoh-port", "127.0.0.1", opts.zenoh_port)]
    ports += [("--zenoh-port", "127.0.0.1", opts.zenoh_port + i)
              for i in range(1, opts.rigs + 1) if opts.rigs > 1]
    try:
        rig_setup(list(opts.disturbances))
    except ConfigError as exc:
        print(f"dobtune demo: --disturbance: {exc}", flush=True)
        return 2
    for what, host, port in ports:
        try:
            check_port_free(host, port, what)
        except PortBusy as exc:
            print(f"dobtune demo: {exc}", flush=True)
            return 2
    if opts.rigs > 1:
        return _run_fleet(opts, endpoint)
    with contextlib.ExitStack() as stack:
        # Made here, so that the dashboard's Trends tab reads the trend its watch writes.
        state_dir = opts.state_dir or Path(stack.enter_context(
            tempfile.TemporaryDirectory(prefix="dobtune-")))
        return _run_one(opts, endpoint, state_dir)


def _run_one(opts: DemoOptions, endpoint: str, state_dir: Path) -> int:
    code = 0
    with stop_requested() as stop, controller_process(
        endpoint, opts.rig_name, state_dir, opts.log_level, opts.disturbances, watch=True
    ) as proc, Dashboard(
        DashboardOptions(
            connect=(endpoint,), rig_name=opts.rig_name, host=opts.host, port=opts.port,
            verbose=opts.verbose, sim_disturbances=opts.disturbances,
            candidates_dir=opts.candidates_dir, trend_dirs=(state_dir / "trend",),
        )
    ) as dash:
        freeze_startup_heap()
        print(f"dobtune demo: open {dash.url}  (simulated rig '{opts.rig_name}', "
              f"disturbances: {'+'.join(opts.disturbances) or 'none'}, "
              f"controller on {endpoint}; Ctrl-C stops both)", flush=True)
        if not wait_for_controller(dash, proc, stop, opts.progress_every_s) and proc.poll():
            return 1
        while not stop.wait(0.5):
            if proc.poll() is not None:
                log.error("the controller exited with code %s", proc.returncode)
                code = 1
                break
    print("dobtune demo: stopped", flush=True)
    return code


def wait_for_controller(
    dash: Dashboard, proc: subprocess.Popen[bytes], stop: threading.Event,
    progress_every_s: float
) -> bool:
    """Wait for the controller's first status however long its start takes (a busy machine
    can make it tens of seconds), saying so every `progress_every_s`; False when its process
    exited (logged) or a stop was requested first."""
    t0 = time.monotonic()
    next_note = 0.0
    while not dash.client.connected:
        if proc.poll() is not None:
            log.error("the controller exited with code %s before it was ready", proc.returncode)
            return False
        waited = time.monotonic() - t0
        if waited >= next_note:
            print(f"dobtune demo: controller starting ({waited:.0f} s): waiting for its first "
                  "status (the dashboard shows it when it answers)", flush=True)
            next_note = waited + progress_every_s
        if stop.wait(0.1):
            return False
    print(f"dobtune demo: controller ready after {time.monotonic() - t0:.1f} s", flush=True)
    return True


def _run_fleet(opts: DemoOptions, router_ep: str) -> int:
    with contextlib.ExitStack() as stack:
        root = opts.state_dir or Path(stack.enter_context(
            tempfile.TemporaryDirectory(prefix="dobtune-fleet-")))
        stop = stack.enter_context(stop_requested())
        procs = stack.enter_context(fleet_processes(opts, root))
        dash = stack.enter_context(Dashboard(DashboardOptions(
            connect=(router_ep,), rig_name="rig1", host=opts.host, port=opts.port,
            verbose=opts.verbose, fleet=True, sim_disturbances=opts.disturbances,
            candidates_dir=opts.candidates_dir,
            trend_dirs=tuple(root / f"rig{i}" / "trend" for i in range(1, opts.rigs + 1)))))
        freeze_startup_heap()
        print(f"dobtune demo: {opts.rigs} rigs behind the router {router_ep}; dashboard of rig1 "
              "(its Fleet tab shows them all): "
              f"{dash.url}; list them with: dobtune ctl --connect {router_ep} rigs", flush=True)
        while not stop.wait(0.5):
            dead = [p for p in procs if p.poll() is not None]
            if dead:
                log.error("a fleet process exited with code %s", dead[0].returncode)
                return 1
    return 0
