"""A test run killed outright (SIGKILL: a suite stopped at its timeout) leaves no process it
started running: the controllers and routers its helpers start (`helpers.spawn`), and the
controller's own analysis worker with them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import children, free_port, gone, spawn
from procs import REPO, wait_until

pytestmark = pytest.mark.integration

#: A test run that starts a controller (the integration helper) and a router (the demo's
#: command, as the fleet tests start theirs), writes their pids, then waits to be killed.
INNER = '''
import os
import threading
from pathlib import Path

from helpers import spawn
from procs import start_controller
from server.dashboard.demo import router_command


def test_starts_processes_then_waits(tmp_path):
    c = start_controller(tmp_path / "state", rig="orphans")
    r = spawn(router_command("tcp/127.0.0.1:" + os.environ["ROUTER_PORT"], "warning"))
    Path(os.environ["PIDS_FILE"]).write_text(f"{c.proc.pid} {r.pid}")
    threading.Event().wait()  # until killed
'''


def test_a_killed_test_run_leaves_no_process_behind(tmp_path: Path) -> None:
    (tmp_path / "test_inner.py").write_text(INNER)
    pids_file = tmp_path / "pids"
    tests = REPO / "tests"
    env = {**os.environ, "PIDS_FILE": str(pids_file), "ROUTER_PORT": str(free_port()),
           "PYTHONPATH": os.pathsep.join((str(REPO), str(tests), str(tests / "integration")))}
    with open(tmp_path / "inner.log", "wb") as log:
        run = spawn([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                     "-p", "no:xdist", "--rootdir", str(tmp_path), "test_inner.py"],
                    cwd=tmp_path, env=env, stdout=log, stderr=log)
    try:
        assert wait_until(lambda: pids_file.exists() and pids_file.read_text() != "", 180.0), \
            (tmp_path / "inner.log").read_text()
        controller, router = (int(x) for x in pids_file.read_text().split())
        # The controller's analysis worker starts early in its start-up.
        assert wait_until(lambda: children(controller), 180.0), "no analysis worker"
        started = [controller, router, *children(controller)]
        assert not any(gone(p) for p in started)
        run.send_signal(signal.SIGKILL)
        run.wait()
        assert wait_until(lambda: all(gone(p) for p in started), 30.0), \
            [p for p in started if not gone(p)]
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()


#: A launcher (as `dobtune demo` starts its fleet's router): starts a router with its own pid
#: as `--parent-pid`, prints the router's pid, then waits to be killed.
LAUNCHER = '''
import os, subprocess, sys, threading
from server.dashboard.demo import router_command

with open(sys.argv[2], "wb") as log:
    r = subprocess.Popen(router_command("tcp/127.0.0.1:" + sys.argv[1], "info",
                                        ("--parent-pid", str(os.getpid()))),
                         stdout=log, stderr=log)
print(r.pid, flush=True)
threading.Event().wait()
'''


def test_a_router_stops_itself_when_its_launcher_is_killed(tmp_path: Path) -> None:
    port, log = free_port(), tmp_path / "router.log"
    launcher = spawn([sys.executable, "-c", LAUNCHER, str(port), str(log)], cwd=REPO,
                     stdout=subprocess.PIPE, text=True)
    try:
        assert launcher.stdout is not None
        router = int(launcher.stdout.readline())
        assert wait_until(lambda: "listening on" in log.read_text(), 120.0), log.read_text()
        launcher.kill()
        launcher.wait()
        assert wait_until(lambda: gone(router), 30.0), log.read_text()
        text = log.read_text()
        assert f"the process that started this one (pid {launcher.pid}) is gone: stopping" \
            in text and "dobtune router: stopped" in text, text
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.wait()


@pytest.mark.parametrize("command", ["router", "controller"])
def test_a_bad_parent_pid_is_refused_naming_it(command: str, capsys: pytest.CaptureFixture[str]
                                               ) -> None:
    from controller.cli.main import dobtune_main

    for bad in ("0", "-3", "x"):
        with pytest.raises(SystemExit) as exc:
            dobtune_main([command, "--parent-pid", bad])
        assert exc.value.code == 2
        assert f"--parent-pid: expected a process id (> 0), got '{bad}'" in capsys.readouterr().err
