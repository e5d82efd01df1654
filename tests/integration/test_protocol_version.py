"""Peers of another protocol version (docs/protocol.md, Versions): each side refuses the other's
messages by their `v`, naming both versions; nothing is half-read, nothing crashes.

- an older client (protocol 1) reaching this controller: every request is refused (field `v`),
  the rig does not change, and the reply is in this side's version;
- this client reaching an older controller (a real Zenoh peer that answers and publishes what
  a protocol 1 controller sent: the verdict's fields side by side): `dobtune ctl` exits 4
  naming both versions, the client's queries raise ProtocolError on `v`, and the dashboard's
  banner says so instead of waiting for a status; the fleet watcher lists the rig with why its
  status is not read.
"""

from __future__ import annotations

import io
import threading
from collections.abc import Iterator
from typing import Any

import msgspec
import pytest
from procs import Client, ControllerProcess, free_port, wait_until

from controller import protocol as proto
from controller.client import ClientOptions, ControllerClient
from controller.client.fleet import FleetMonitor
from controller.client.session import SessionOptions, connect
from controller.core.config import LoopConfig, config_to_builtins
from controller.core.trajectory import Trajectory

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

ENC = msgspec.msgpack.encode
RIG = "oldrig"
MARGINS = {"gain_margin_db": 12.0, "phase_margin_deg": 48.0, "peak_sensitivity_db": 3.5,
           "small_gain_peak": 0.4, "max_pole_radius": 0.99}
#: What a protocol 1 controller sent (its docs/protocol.md, version 1).
OLD_REPLY = {"v": 1, "accepted": True, "version": 3, "config": config_to_builtins(LoopConfig()),
             "reasons": [], "margins": MARGINS, "field": "", "verdict": "accept",
             "knowledge_version": 1}
OLD_STATUS = {
    "v": 1, "rig": RIG, "plant": "sim", "mode": "running", "t_s": 1.0, "seq": 1000,
    "trajectory": msgspec.to_builtins(Trajectory()), "config_version": 3,
    "config": config_to_builtins(LoopConfig()),
    "timing": {"period_p50_us": 1000.0, "period_p99_us": 1010.0, "period_max_us": 1100.0,
               "compute_p50_us": 10.0, "compute_p99_us": 20.0, "compute_max_us": 30.0,
               "ticks": 1000, "overruns": 0, "skipped_ticks": 0},
    "faults": [], "knowledge_version": 1, "knowledge": "v1 default", "margins": MARGINS,
    "verdict": "accept",
}
BOTH = "unsupported protocol version 1; this side speaks 2"


def test_an_older_client_is_refused_by_the_controller_naming_both_versions(
    controller: ControllerProcess, client: Client
) -> None:
    before = client.get_config()
    old_apply = {"v": 1, "candidate": {"q_cutoff_hz": 0.9}, "client": "old"}
    old_start = {"v": 1, "body": {"type": "stop"}, "client": "old"}
    for key, payload in ((proto.key_config(controller.rig), old_apply),
                         (proto.key_command(controller.rig), old_start),
                         (proto.key_history(controller.rig), {"v": 1, "last": 5})):
        raw = msgspec.msgpack.decode(client.query_raw(key, ENC(payload)))  # any reader reads it
        assert raw["v"] == proto.PROTOCOL_VERSION and raw["field"] == "v", (key, raw)
        text = " ".join(raw.get("reasons", [])) + raw.get("message", "")
        assert BOTH in text, (key, raw)
    after = client.get_config()
    assert after.version == before.version and after.config == before.config
    assert client.fresh_status().mode == "running"  # the old client's stop was not read


class OldController:
    """A Zenoh peer on its own loopback port that answers and publishes as a protocol 1
    controller of rig RIG did."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session = connect(SessionOptions(listen=(self.endpoint,)))
        s = self.session
        self.queries = 0
        self._entities = [
            s.declare_queryable(proto.key_config(RIG), self._answer),
            s.declare_queryable(proto.key_lease(RIG), self._answer),
            s.liveliness().declare_token(proto.key_alive(RIG)),
        ]
        self._status = s.declare_publisher(proto.key_status(RIG))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._publish, name="old-status", daemon=True)
        self._thread.start()

    def _answer(self, query: Any) -> None:
        self.queries += 1
        query.reply(query.key_expr, ENC(OLD_REPLY))

    def _publish(self) -> None:  # a status every 50 ms, as long as the test runs
        while not self._stop.wait(0.05):
            self._status.put(ENC(OLD_STATUS))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        for e in [*self._entities, self._status]:
            e.undeclare()
        self.session.close()


@pytest.fixture
def old_controller() -> Iterator[OldController]:
    old = OldController()
    try:
        yield old
    finally:
        old.close()


def test_this_client_refuses_an_older_controller_clearly(old_controller: OldController) -> None:
    from controller.cli.commands import controller_commands
    from controller.cli.common import build_parser
    from controller.cli.ctl import ctl_main
    from server.panels.fleet import fleet_table_html
    from server.panels.live import banner_html

    ep = old_controller.endpoint
    opts = ClientOptions(connect=(ep,), rig_name=RIG, client_name="new", connect_timeout_s=10.0,
                         query_timeout_s=10.0)
    with ControllerClient(opts) as c:
        assert wait_until(lambda: c.counters.version_mismatch != "", 30.0), c.counters
        assert c.status is None  # never half-read
        assert BOTH in c.counters.version_mismatch
        banner = banner_html(c)
        assert "CONTROLLER OF ANOTHER VERSION" in banner and BOTH in banner, banner
        with pytest.raises(proto.ProtocolError) as info:
            c.get_config()
        assert info.value.field == "v" and BOTH in str(info.value)
    parser = build_parser("dobtune", None, controller_commands())
    for action in (["status"], ["status", "--json"], ["apply", "q_cutoff_hz=0.9"]):
        out = io.StringIO()
        args = parser.parse_args(["ctl", "--connect", ep, "--rig-name", RIG,
                                  "--timeout-s", "10", *action])
        code = ctl_main(args, out)
        text = out.getvalue()
        assert code == 4 and BOTH in text and "cannot be read" in text, (action, code, text)
    assert old_controller.queries >= 3
    # The fleet watcher (`dobtune ctl rigs`, the Fleet tab) lists the rig, alive, and why its
    # status is not read.
    out = io.StringIO()
    args = parser.parse_args(["ctl", "--connect", ep, "--timeout-s", "10", "--listen-s", "1.0",
                              "rigs"])
    assert ctl_main(args, out) == 0
    assert f"{RIG}: ? (?)" in out.getvalue() and f"status not read: v: {BOTH}" in out.getvalue()
    with connect(SessionOptions(connect=(ep,))) as s, FleetMonitor(s) as fleet:
        assert wait_until(lambda: any(r.unread for r in fleet.rows()), 30.0), fleet.rows()
        row = next(r for r in fleet.rows() if r.rig == RIG)
        assert row.alive and row.mode == "" and BOTH in row.unread
        assert f"status not read: v: {BOTH}" in fleet_table_html([row])
