"""TLS: the controller presents a certificate of the auth directory's authority; a client of
that directory reaches it, and refuses a rogue peer that listens at an address with a
certificate of another authority (the dashboard and every client authenticate the
controller). Real processes, real Zenoh TLS on loopback."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh
from helpers import answers
from procs import ControllerProcess, free_port, wait_until

from controller import protocol as proto
from controller.auth import init_auth_dir, new_users
from controller.client import ClientOptions, ControllerClient, ControllerUnavailable
from controller.client.session import zenoh_config
from controller.tls import SERVER_CERT, SERVER_KEY, make_tls


def _auth(dir_: Path) -> Path:
    init_auth_dir(dir_, new_users([("op", "operator"), ("view", "viewer")]))
    make_tls(dir_, ["127.0.0.1", "localhost"])
    return dir_


def _client(auth: Path, endpoint: str) -> ControllerClient:
    return ControllerClient(ClientOptions(connect=(endpoint,), rig_name="tls", auth=auth,
                                          user="op", query_timeout_s=3.0, connect_timeout_s=5.0))


def test_a_client_reaches_the_certified_controller_and_refuses_a_rogue(
    tmp_path: Path, start_controller_factory: Callable[..., ControllerProcess],
) -> None:
    auth = _auth(tmp_path / "auth")
    port = free_port()  # the controller also listens on its tcp/ port (procs' default)
    proc = start_controller_factory(
        rig="tls", extra_args=("--auth", str(auth), "--listen", f"tls/127.0.0.1:{port}"),
    )
    tls_ep = f"tls/127.0.0.1:{port}"
    client = None
    deadline = time.monotonic() + 60.0
    while client is None:  # until the controller is up (its start takes seconds)
        assert proc.proc.poll() is None, proc.log()
        try:
            client = _client(auth, tls_ep).__enter__()
        except ControllerUnavailable:
            assert time.monotonic() < deadline, proc.log()
    try:
        assert wait_until(lambda: answers(client), 30.0), proc.log()
        assert client.knowledge().ok
    finally:
        client.__exit__(None, None, None)
    # A rogue peer with a certificate of another authority, at another address.
    rogue_dir = _auth(tmp_path / "rogue")
    rport = free_port()
    conf = zenoh_config([f"tls/127.0.0.1:{rport}"], [])
    conf.insert_json5("transport/link/tls/listen_certificate",
                      json.dumps(str(rogue_dir / SERVER_CERT)))
    conf.insert_json5("transport/link/tls/listen_private_key",
                      json.dumps(str(rogue_dir / SERVER_KEY)))
    with zenoh.open(conf) as rogue:
        fake = rogue.declare_queryable(proto.user_key(proto.key_config("tls"), "op"),
                                       lambda q: q.reply(q.key_expr, b"fake"))
        try:
            with pytest.raises(ControllerUnavailable, match="no connection"):
                _client(auth, f"tls/127.0.0.1:{rport}").__enter__()
        finally:
            fake.undeclare()
