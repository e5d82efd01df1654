"""`dobtune demo` as a user runs it: starts, prints the URL, and Ctrl-C (SIGINT to the whole
process group, as a terminal sends it) or SIGTERM stops both processes cleanly; a demo killed
outright (SIGKILL) leaves no controller running."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import urllib.request

import pytest
from helpers import children, gone, spawn
from procs import REPO, free_port, port_is_free, wait_until

pytestmark = pytest.mark.integration


def _demo(http_port: int, zenoh_port: int) -> list[str]:
    code = ("import sys; from controller.cli.main import dobtune_main; "
            "sys.exit(dobtune_main(sys.argv[1:]))")
    return [sys.executable, "-c", code, "demo", "--port", str(http_port),
            "--zenoh-port", str(zenoh_port)]


@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_demo_starts_serves_and_stops_cleanly(how: str) -> None:
    http_port, zenoh_port = free_port(), free_port()
    proc = spawn(
        _demo(http_port, zenoh_port),
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        assert proc.stdout is not None
        url = None
        for line in proc.stdout:
            if "dobtune demo: open " in line:
                url = line.split("open ", 1)[1].split()[0]
                break
        assert url.startswith(f"http://127.0.0.1:{http_port}/?token=")  # the access token
        for line in proc.stdout:  # the URL comes at once; the controller may still start
            if "dobtune demo: controller ready after" in line:
                break
        with urllib.request.urlopen(url, timeout=10) as resp:
            assert resp.status == 200
        if how == "ctrl-c":
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGTERM)
        rest = proc.stdout.read()
        assert proc.wait(timeout=30) == 0, rest
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert "Traceback" not in rest, rest
    assert "dobtune controller: stopped" in rest and "dobtune demo: stopped" in rest
    assert wait_until(lambda: port_is_free(http_port) and port_is_free(zenoh_port), 10.0)



def test_a_demo_killed_outright_leaves_no_process_running() -> None:
    """SIGKILL to the demo alone (no chance to stop its children): the controller it started
    (and the controller's analysis worker) stop by themselves (`--parent-pid`)."""
    http_port, zenoh_port = free_port(), free_port()
    proc = spawn(
        _demo(http_port, zenoh_port),
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True,
    )
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if "dobtune demo: controller ready after" in line:
                break
        started = [p for c in children(proc.pid) for p in (c, *children(c))]
        assert len(started) >= 2, started  # the controller and its analysis worker at least
        proc.kill()
        proc.wait()
        assert wait_until(lambda: all(gone(p) for p in started), 30.0), \
            [p for p in started if not gone(p)]
        assert wait_until(lambda: port_is_free(zenoh_port), 10.0)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
