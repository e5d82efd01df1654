"""The controller's Zenoh edge without Zenoh: payload -> domain request -> service -> reply,
against a runtime ticking in a thread (the gate in this process)."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from pathlib import Path

import msgspec
import pytest

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.process import requests as rq
from controller.process.gate_worker import GateRunner
from controller.process.node import ZenohNode, to_request
from controller.process.options import ControllerOptions
from controller.process.persistence import StateStore
from controller.process.runtime import Runtime
from controller.process.service import ControllerService


class NullRig:
    def read(self) -> tuple[float, float]:
        return 0.0, 0.0

    def step(self, command_deg_s: float) -> None:
        pass


@pytest.fixture
def node(tmp_path: Path) -> Iterator[ZenohNode]:
    cfg = LoopConfig()
    store = StateStore(tmp_path)
    store.save(cfg, 1)
    rt = Runtime(ServoLoop(LoopCoefficients.build(cfg, 1)), NullRig())
    runner = GateRunner(subprocess=False)
    opts = ControllerOptions(rig_name="unit", state_dir=tmp_path, gate_in_subprocess=False)
    margins = runner.check(cfg).margins
    service = ControllerService(opts, rt, store, runner, margins, [])
    loop = threading.Thread(target=rt.run, daemon=True)
    loop.start()
    assert rt.running.wait(5.0)
    try:
        yield ZenohNode(service)
    finally:
        rt.stop()
        loop.join(5.0)


def command(node: ZenohNode, body: proto.CommandBody) -> proto.CommandReply:
    data = proto.encode(proto.Command(body=body, client="unit"))
    return proto.decode(node.handle_command(data), proto.CommandReply)


def apply(node: ZenohNode, candidate: LoopConfig) -> proto.ConfigReply:
    data = proto.encode(proto.ConfigRequest(candidate=candidate, client="unit"))
    return proto.decode(node.handle_config(data), proto.ConfigReply)


@pytest.mark.parametrize(
    ("wire", "domain"),
    [
        (proto.Start(), rq.Start()),
        (proto.Stop(), rq.Stop()),
        (proto.EStop(), rq.EStop()),
        (proto.ResetFault(), rq.ResetFault()),
        (
            proto.SetTrajectory(trajectory=Trajectory(kind="hold")),
            rq.SetTrajectory(Trajectory(kind="hold")),
        ),
        (proto.IdentifyAbort(), rq.AbortProgram("aborted by unit")),
    ],
)
def test_wire_commands_become_domain_requests(wire: proto.CommandBody, domain: object) -> None:
    assert to_request(wire, "unit") == domain


def test_commands_reach_the_tick_and_are_logged(
    node: ZenohNode, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="controller.process")
    stop = command(node, proto.Stop())
    assert stop.ok and stop.mode == "stopped" and stop.seq >= 0
    estop = command(node, proto.EStop())
    assert estop.ok and estop.mode == "estop" and node.rt.estop_source == "command"
    assert not command(node, proto.Start()).ok
    reset = command(node, proto.ResetFault())
    assert reset.ok and reset.mode == "stopped"
    node.events.poll()
    text = caplog.text
    assert "command EStop from unit: ok (mode estop" in text
    assert "command Start from unit: refused: mode is estop" in text
    assert "e-stop (command) at seq" in text


def test_apply_swaps_at_a_tick_boundary_and_logs_the_change(
    node: ZenohNode, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="controller.process")
    reply = apply(node, LoopConfig(q_cutoff_hz=1.0))
    assert reply.accepted and reply.version == 2
    assert node.rt.loop.active.version == 2
    assert node.rt.loop.active.config.q_cutoff_hz == 1.0
    for _ in range(3):  # the same rejected candidate again and again: logged once
        rejected = apply(node, LoopConfig(q_cutoff_hz=1.0, cv_kp=20.0))
        assert not rejected.accepted and rejected.version == 2
    assert "config v2 applied at seq" in caplog.text
    assert "q_cutoff_hz 0.5 -> 1.0" in caplog.text
    assert caplog.text.count("candidate from unit rejected") == 1


def test_malformed_payloads_name_the_field(node: ZenohNode) -> None:
    bad = proto.decode(node.handle_command(b"\xc1"), proto.CommandReply)
    assert not bad.ok and bad.field == "payload"
    start = {"v": 1, "body": {"type": "identify_start", "spec": {"f_min_hz": -1.0}}}
    reply = proto.decode(node.handle_command(msgspec.msgpack.encode(start)), proto.CommandReply)
    assert not reply.ok and reply.field == "body.spec.f_min_hz"
