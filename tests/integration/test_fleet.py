"""Many rigs through a Zenoh router: controllers announce themselves (liveliness), `dobtune ctl
rigs` through the router lists them with their state, a dead controller leaves the list, and a
controller keeps working (and is listed again) after the router restarts."""

from __future__ import annotations

import io
import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from procs import REPO, ControllerProcess, free_port, wait_until

from controller.cli import build_parser, controller_commands

ROUTER_CODE = ("import sys; from server.__main__ import dobtune_main; "
               "sys.exit(dobtune_main(['router', *sys.argv[1:]]))")


def _router(port: int, log: Path) -> subprocess.Popen[bytes]:
    with open(log, "ab") as f:
        return subprocess.Popen([sys.executable, "-c", ROUTER_CODE, "--listen",
                                 f"tcp/127.0.0.1:{port}"], cwd=REPO, stdout=f, stderr=f)


def _stop(p: subprocess.Popen[bytes]) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(timeout=15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _rigs(router_ep: str) -> list[dict[str, Any]]:
    from controller.cli.ctl import ctl_main

    cmds = controller_commands()
    args = build_parser("dobtune", None, cmds).parse_args(
        ["ctl", "--connect", router_ep, "--json", "--timeout-s", "2", "--listen-s", "0.6",
         "rigs"])
    out = io.StringIO()
    assert ctl_main(args, out) == 0, out.getvalue()
    return json.loads(out.getvalue())  # type: ignore[no-any-return]


@pytest.fixture
def router(tmp_path: Path) -> Iterator[tuple[str, Callable[[], None]]]:
    port = free_port()
    procs = [_router(port, tmp_path / "router.log")]

    def restart() -> None:
        _stop(procs[-1])
        procs.append(_router(port, tmp_path / "router.log"))

    yield f"tcp/127.0.0.1:{port}", restart
    for p in procs:
        _stop(p)


def test_rigs_through_a_router(
    router: tuple[str, Callable[[], None]],
    start_controller_factory: Callable[..., ControllerProcess],
) -> None:
    ep, restart = router
    a = start_controller_factory(rig="rig_a", extra_args=("--connect", ep))
    b = start_controller_factory(rig="rig_b", extra_args=("--connect", ep))
    rows: dict[str, Any] = {}

    def both_running() -> bool:
        rows.clear()
        rows.update({r["rig"]: r for r in _rigs(ep)})
        return set(rows) == {"rig_a", "rig_b"} and all(
            r["mode"] == "running" and r["error_rms_deg"] is not None for r in rows.values())

    assert wait_until(both_running, 60.0), a.log() + b.log()
    assert rows["rig_a"]["config_version"] == 1
    assert rows["rig_a"]["error_rms_deg"] is not None and rows["rig_a"]["error_rms_deg"] < 1.0
    # A controller that dies leaves the list within a few seconds.
    b.proc.kill()
    t0 = time.monotonic()
    assert wait_until(lambda: {r["rig"] for r in _rigs(ep)} == {"rig_a"}, 15.0)
    print(f"\n  dead rig left the list after {time.monotonic() - t0:.1f} s")
    # The router restarts: the controller reconnects (it keeps running meanwhile).
    restart()
    t0 = time.monotonic()
    assert wait_until(lambda: [r["rig"] for r in _rigs(ep)] == ["rig_a"], 30.0)
    print(f"  listed again {time.monotonic() - t0:.1f} s after the router restart")
    assert a.proc.poll() is None
