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
from helpers import spawn
from procs import REPO, ControllerProcess, free_port, port_is_free, wait_until

from controller.cli.commands import controller_commands
from controller.cli.common import build_parser

ROUTER_CODE = ("import sys; from controller.cli.main import dobtune_main; "
               "sys.exit(dobtune_main(['router', *sys.argv[1:]]))")


def _router(port: int, log: Path, *extra: str) -> subprocess.Popen[bytes]:
    with open(log, "ab") as f:
        return spawn([sys.executable, "-c", ROUTER_CODE, "--listen",
                      f"tcp/127.0.0.1:{port}", *extra], cwd=REPO, stdout=f, stderr=f)


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

    assert wait_until(both_running, 300.0), a.log() + b.log()  # two start-ups, under load
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


def test_the_dashboards_fleet_overview(
    router: tuple[str, Callable[[], None]],
    start_controller_factory: Callable[..., ControllerProcess],
) -> None:
    """A dashboard on the router with the Fleet tab: a row per rig with its state and a live
    error trace, an E-STOP for one rig (the other runs on), the full view of another rig, and a
    dead rig shown as gone."""
    import urllib.request

    from controller.client import ClientOptions, ControllerClient
    from server.dashboard.app import Dashboard, DashboardOptions

    ep, _restart = router
    a = start_controller_factory(rig="rig_a", extra_args=("--connect", ep))
    b = start_controller_factory(rig="rig_b", extra_args=("--connect", ep))
    opts = DashboardOptions(connect=(ep,), rig_name="rig_a", port=free_port(), verbose=False,
                            fleet=True)
    with Dashboard(opts) as dash:
        assert dash.fleet is not None and dash._fleet_monitor is not None
        mon, panel = dash._fleet_monitor, dash.fleet

        def rows() -> dict[str, Any]:
            return {r.rig: r for r in mon.rows()}

        def both_live() -> bool:
            r = rows()
            return set(r) == {"rig_a", "rig_b"} and all(
                x.alive and x.mode == "running" and len(x.trace) > 100 for x in r.values())

        assert wait_until(both_live, 300.0), a.log() + b.log()  # two start-ups, under load
        first = rows()["rig_b"].trace
        assert wait_until(lambda: rows()["rig_b"].trace != first, 5.0)  # the trace moves
        assert wait_until(lambda: "rig_b" in panel.table.content
                          and panel.table.content.count("dt-spark") == 2, 5.0)
        assert tuple(panel.pick.options) == ("rig_a", "rig_b")
        # E-STOP of rig_b from the overview: rig_b stops, rig_a runs on.
        assert panel.estop("rig_b")
        assert wait_until(lambda: rows()["rig_b"].mode == "estop", 5.0)
        assert rows()["rig_a"].mode == "running"
        assert not panel.estop("no_such_rig")
        # The full view of rig_b: a dashboard of its own, on rig_b.
        url = panel.open("rig_b")
        assert url and "token=" in url and "rig_b" in panel.result.content
        with urllib.request.urlopen(url, timeout=10) as r:
            assert r.status == 200
        view = dash._views["rig_b"]
        assert wait_until(lambda: view.client.status is not None, 10.0)
        assert view.client.status is not None and view.client.status.rig == "rig_b"
        # A dead rig is shown as gone.
        b.proc.kill()
        assert wait_until(lambda: not rows()["rig_b"].alive, 15.0)
        assert wait_until(lambda: ">gone<" in panel.table.content, 5.0)
        # (the table is redrawn before the picker's options: wait for both)
        assert wait_until(lambda: tuple(panel.pick.options) == ("rig_a",), 5.0)
    with ControllerClient(ClientOptions(connect=(ep,), rig_name="rig_a")) as c:
        assert wait_until(lambda: c.status is not None, 10.0)
        assert c.status is not None and c.status.mode == "running"


def test_a_fleet_behind_an_authenticating_router(tmp_path: Path) -> None:
    """Router and controllers with --auth: the controllers log in to the router with a
    "controller" account and listen nowhere; a viewer's dashboard sees both rigs in the Fleet
    tab and may e-stop one; an operator changes a rig through the router as itself."""
    from procs import start_controller

    from controller import protocol as proto
    from controller.auth import init_auth_dir, new_users
    from controller.client import ClientOptions, ControllerClient
    from server.dashboard.app import Dashboard, DashboardOptions

    auth = tmp_path / "auth"
    init_auth_dir(auth, new_users([("op1", "operator"), ("view", "viewer"), ("ctl", "controller")]))
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    router = _router(port, tmp_path / "router.log", "--auth", str(auth),
                     "--rig-name", "rig_a", "--rig-name", "rig_b")
    procs = []
    try:
        assert wait_until(lambda: not port_is_free(port), 30.0), "the router did not listen"
        for rig in ("rig_a", "rig_b"):
            procs.append(start_controller(
                tmp_path / rig, rig=rig, listen=False,
                extra_args=("--auth", str(auth), "--connect", ep, "--user", "ctl")))
        opts = DashboardOptions(connect=(ep,), rig_name="rig_a", port=free_port(),
                                verbose=False, fleet=True, auth=auth)
        with Dashboard(opts) as dash:
            assert dash.fleet is not None and dash._fleet_monitor is not None
            assert dash.client.opts.user == "view"  # the streams come as the viewer
            mon = dash._fleet_monitor

            def running() -> bool:
                rows = {r.rig: r for r in mon.rows()}
                return set(rows) == {"rig_a", "rig_b"} and all(
                    r.alive and r.mode == "running" and r.trace for r in rows.values())

            ok = wait_until(running, 300.0)  # two start-ups, under load
            assert ok, (mon.rows(), dash.client.status, "".join(p.log() for p in procs))
            # The viewer's browser picks rig_b and presses its E-STOP (raw websocket: what
            # its page sends; the message gate lets every role do both).
            from viser_raw import connected

            from server.viser_adapter import control_uuid

            with connected(dash, dash.url_for("view")) as viewer:
                assert wait_until(lambda: "rig_b" in dash.fleet.pick.options, 10.0)
                viewer.update(control_uuid(dash.fleet.pick), {"value": "rig_b"})
                assert wait_until(lambda: dash.fleet.pick.value == "rig_b", 10.0)
                viewer.update(control_uuid(dash.fleet.estop_button), {"value": True})
                assert wait_until(
                    lambda: {r.rig: r.mode for r in mon.rows()}["rig_b"] == "estop", 10.0)
        copts = ClientOptions(connect=(ep,), rig_name="rig_a", auth=auth, user="op1",
                              client_name="op1", connect_timeout_s=10.0)
        with ControllerClient(copts) as op:
            assert op.lease("acquire", 60.0).ok
            before = op.get_config()
            reply = op.apply(before.config.with_(cv_kp=1.2), expect_version=before.version)
            assert reply.accepted, reply
            last = op.history(1).entries[-1]
            assert last.version == reply.version and "op1" in last.client
            assert op.command(proto.EStop()).ok
    finally:
        for p in procs:
            p.stop()
        _stop(router)
