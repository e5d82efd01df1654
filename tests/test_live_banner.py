"""The live banner says E-STOP as soon as the state stream does (server/panels/live.py
banner_html, controller/client StateRing.mode): the Status comes every 0.2 s, the state
batches several times as often; issue 33 (E-STOP click to the page showing it, p99 467 ms)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from statuses import status

from controller import protocol as proto
from controller.client.controller_client import ClientOptions, StateRing
from server.panels.live import banner_html


def _batch(seq0: int, mode: str, n: int = 20) -> proto.StateBatch:
    cols = [[float(seq0 + i) / 1000.0 for i in range(n)] for _ in proto.STATE_COLUMNS]
    return proto.state_batch(rig="r", seq0=seq0, rate_hz=1000.0, config_version=1,
                             columns=cols, epoch_s=0.0, mode=mode)


def test_the_ring_keeps_the_newest_batchs_mode() -> None:
    ring = StateRing(capacity=1000)
    assert ring.mode == ""
    ring.append(_batch(0, "running"))
    assert ring.mode == "running"
    ring.append(_batch(20, "estop"))
    assert ring.mode == "estop"
    ring.append(_batch(40, "stopped"))
    assert ring.mode == "stopped"


def _client(st: proto.Status, ring: StateRing) -> Any:
    """What banner_html reads of a ControllerClient: its status, counters, options, ring."""
    return SimpleNamespace(status=st, counters=SimpleNamespace(version_mismatch=""), connected=True,
                           status_age_s=0.0, opts=ClientOptions(rig_name="r"), ring=ring)


def test_the_banner_says_estop_when_the_stream_does_before_the_status() -> None:
    ring = StateRing(capacity=1000)
    ring.append(_batch(0, "running"))
    running = status(mode="running")
    assert "dt-ok" in banner_html(_client(running, ring))
    ring.append(_batch(20, "estop"))  # the stream has it; the status still says running
    shown = banner_html(_client(running, ring))
    assert "dt-estop" in shown and "E-STOP ACTIVE" in shown
    # After a reset the stream moves on first; the status's e-stop still shows until it does.
    ring.append(_batch(40, "stopped"))
    assert "dt-estop" in banner_html(_client(status(mode="estop"), ring))
    assert "dt-estop" not in banner_html(_client(status(mode="stopped"), ring))
