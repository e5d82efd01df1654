"""`dobtune identify --connect` where no controller of the rig is (issue 33 smaller item):
the error says what is missing, at once, instead of after the requests' 10 s of timeouts."""

from __future__ import annotations

import subprocess
import sys
import time

from helpers import free_port
from procs import Client, ControllerProcess

from controller.cli.identify import _PEER_WAIT_S, _TOKEN_WAIT_S, _no_controller
from controller.client import ClientOptions, ControllerClient


def _identify(endpoint: str, rig: str) -> tuple[int, str, float]:
    t0 = time.monotonic()
    run = subprocess.run(
        [sys.executable, "-c", "import sys; from controller.cli.main import dobtune_main; "
         "sys.exit(dobtune_main())", "identify", "--connect", endpoint, "--rig-name", rig],
        capture_output=True, text=True, timeout=120)
    return run.returncode, run.stdout + run.stderr, time.monotonic() - t0


def test_nothing_at_the_endpoint_is_said_at_once() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    code, out, took_s = _identify(endpoint, "demo")
    print(f"\n  nothing at {endpoint}: error after {took_s:.1f} s (waits {_PEER_WAIT_S:g} s "
          "for a peer, after the interpreter's start)")
    assert code != 0
    assert f"--connect: nothing answers at {endpoint}" in out, out
    assert "no Zenoh peer or router there" in out and "no reply from rig" not in out, out


def test_a_controller_of_another_rig_is_named(controller: ControllerProcess) -> None:
    with Client(controller.endpoint, controller.rig) as c:
        c.wait_ready(controller)
    # The rig's own name passes the check (the run then starts as before).
    opts = ClientOptions(connect=(controller.endpoint,), rig_name=controller.rig,
                         client_name="identify", subscribe=False)
    with ControllerClient(opts) as cc:
        assert _no_controller(cc.session, controller.endpoint, controller.rig) is None
    code, out, took_s = _identify(controller.endpoint, "nosuch")
    print(f"\n  rig 'nosuch' at a controller of {controller.rig!r}: error after {took_s:.1f} s "
          f"(waits {_TOKEN_WAIT_S:g} s for its token)")
    assert code != 0
    assert (f"--connect: no controller of rig 'nosuch' at {controller.endpoint} (a Zenoh "
            f"session answers there; rigs alive: {controller.rig!r})") in out, out
