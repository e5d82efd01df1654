"""The controller's Zenoh edge without Zenoh: payload -> domain request -> service -> reply,
against a runtime ticking in a thread (the gate in this process)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord, PlantKnowledge
from controller.process import requests as rq
from controller.process.analysis_worker import AnalysisWorker
from controller.process.node import SHUTDOWN, ZenohNode, to_request
from controller.process.options import ControllerOptions
from controller.process.persistence import StateStore
from controller.process.runtime import Runtime
from controller.process.service import ControllerService

V = proto.PROTOCOL_VERSION  # the version this side speaks


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
    runner = AnalysisWorker(subprocess=False)
    opts = ControllerOptions(rig_name="unit", state_dir=tmp_path, gate_in_subprocess=False)
    k = KnowledgeRecord.of(PlantKnowledge(bound=COMMISSIONING_BOUND, version=1))
    verdict = runner.check(cfg, k)
    service = ControllerService(opts, rt, store, runner, verdict, [], k)
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
        (proto.ResetFault(estop_seq=3), rq.ResetFault(3)),
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
    reset = command(node, proto.ResetFault(estop_seq=node.rt.estop_seq))
    assert reset.ok and reset.mode == "stopped"
    node.events.poll()
    text = caplog.text
    assert "command EStop from local: ok (mode estop" in text
    assert "command Start from local: refused: mode is estop" in text
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
        rejected = apply(node, LoopConfig(q_cutoff_hz=1.0, cv_kp=30.0))  # unstable
        assert not rejected.accepted and rejected.version == 2
    assert "config v2 applied at seq" in caplog.text
    assert "q_cutoff_hz 0.5 -> 1.0" in caplog.text
    assert caplog.text.count("candidate from local rejected") == 1


def test_every_reply_carries_the_one_verdict_and_history_reads_older_lines(
    node: ZenohNode,
) -> None:
    svc = node.service
    # A change log an older version wrote (the verdict's kind and margins side by side), and a
    # line no version can read: it is left out, and the reply says which and why.
    old = ('{"time_s":1.0,"version":1,"old_version":null,"old":null,"new":{},"margins":{"gain'
           '_margin_db":12.0,"phase_margin_deg":48.0,"peak_sensitivity_db":3.5,"small_gain_peak"'
           ':null,"max_pole_radius":0.99},"client":"dash","verdict":"accept"}\n'
           '{"time_s":1.5,"version":1,"new":{},"client":"x","verdict":{"verdict":"fine"}}\n')
    svc.store.log_path.write_text(old)
    got = apply(node, LoopConfig(q_cutoff_hz=1.0))
    assert got.accepted and got.verdict is not None and got.verdict.knowledge_version == 1
    assert got.verdict.verdict in ("accept", "caution") and got.verdict.margins.max_pole_radius < 1
    status = node.status()
    assert status.verdict == got.verdict  # the running configuration's verdict, the same one
    assert proto.decode(node.handle_config(b""), proto.ConfigReply).verdict == got.verdict
    refused = proto.encode(proto.ConfigRequest(candidate=LoopConfig(), expect_version=1))
    stale = proto.decode(node.handle_config(refused), proto.ConfigReply)
    assert not stale.accepted and stale.field == "expect_version" and stale.verdict is None
    h = proto.decode(node.handle_history(b""), proto.HistoryReply)
    assert h.ok and [e.version for e in h.entries] == [1, 2]
    first, mine = h.entries
    assert first.verdict is not None and first.verdict.verdict == "accept"
    assert first.verdict.margins.phase_margin_deg == 48.0 and first.verdict.reasons == ()
    assert mine.verdict == got.verdict  # whole: reasons, margins, knowledge judged on
    assert h.message.startswith("1 entry of the change log not shown (v1: verdict.verdict:")


def test_malformed_payloads_name_the_field(node: ZenohNode) -> None:
    bad = proto.decode(node.handle_command(b"\xc1"), proto.CommandReply)
    assert not bad.ok and bad.field == "payload"
    start = {"v": V, "body": {"type": "identify_start", "spec": {"f_min_hz": -1.0}}}
    reply = proto.decode(node.handle_command(msgspec.msgpack.encode(start)), proto.CommandReply)
    assert not reply.ok and reply.field == "body.spec.f_min_hz"


# -- bad input, the latch, and the order of arrival ------------------------------------------------


def test_invalid_utf8_is_a_rejection_naming_the_payload(node: ZenohNode) -> None:
    bad_string = b"\x82\xa1v\x02\xa4body\x81\xa4type\xa2\xff\xfe"
    reply = proto.decode(node.handle_command(bad_string), proto.CommandReply)
    assert not reply.ok and reply.field == "payload" and "UTF-8" in reply.message
    assert "UnicodeDecodeError" not in reply.message
    bad_client = b"\x82\xa1v\x02\xa6client\xa2\xff\xfe"
    cfg = proto.decode(node.handle_config(bad_client), proto.ConfigReply)
    assert not cfg.accepted and cfg.field == "payload"


@pytest.mark.parametrize("body_type", ["start", "stop", "estop", "reset", "identify_abort"])
def test_unknown_fields_in_command_bodies_are_rejected(node: ZenohNode, body_type: str) -> None:
    data = msgspec.msgpack.encode({"v": V, "body": {"type": body_type, "spce": 3}})
    reply = proto.decode(node.handle_command(data), proto.CommandReply)
    assert not reply.ok and reply.field == "body.spce"
    assert node.rt.mode == "running"


@pytest.mark.parametrize("value", [1e300, 1e-300])
@pytest.mark.parametrize("name", ["mn_den", "pn_num", "pn_den"])
def test_absurd_model_coefficients_are_rejected_naming_the_field(
    node: ZenohNode, name: str, value: float
) -> None:
    for i in range(3):
        cfg = msgspec.to_builtins(LoopConfig())
        poly = list(cfg["nominal"][name])
        poly[i] = value
        cfg["nominal"][name] = poly
        data = msgspec.msgpack.encode({"v": V, "candidate": cfg})
        reply = proto.decode(node.handle_config(data), proto.ConfigReply)
        assert "Error" not in " ".join(reply.reasons), reply.reasons
        if value > 1.0 or i == 2:  # out of range: named
            assert not reply.accepted and reply.field.startswith(f"candidate.nominal.{name}")
        # (A negligible 1e-300 s term is a valid model: the gate judges it.)


class FakeQuery:
    def __init__(self, data: bytes) -> None:
        self.payload = self
        self.key_expr = "k"
        self.data = data
        self.replies: list[bytes] = []
        self.errors: list[bytes] = []

    def to_bytes(self) -> bytes:
        return self.data

    def reply(self, _key: object, data: bytes, encoding: str | None = None) -> None:
        self.replies.append(data)
        self.encoding = encoding

    def reply_err(self, data: bytes) -> None:
        self.errors.append(data)

    def drop(self) -> None:
        pass


def serve_one(node: ZenohNode, query: FakeQuery, arrival: int, handle: Any) -> None:
    import queue

    q: queue.SimpleQueue[Any] = queue.SimpleQueue()
    q.put((query, arrival))
    q.put(SHUTDOWN)
    node.serve_queue(q, handle)


def test_a_reset_that_arrived_before_an_estop_is_refused(node: ZenohNode) -> None:
    assert command(node, proto.EStop()).ok
    reset_arrival = node.rt.next_arrival()  # the reset's query arrives first ...
    node.rt.estop("estop key", node.rt.next_arrival())  # ... then an e-stop on the key
    seen = node.rt.estop_seq
    query = FakeQuery(proto.encode(proto.Command(body=proto.ResetFault(estop_seq=seen),
                                                 client="unit")))
    serve_one(node, query, reset_arrival, node.handle_command)
    reply = proto.decode(query.replies[0], proto.CommandReply)
    assert not reply.ok and "e-stop arrived after this reset" in reply.message
    assert node.rt.mode == "estop"


def test_a_reset_is_refused_when_a_newer_estop_exists_and_without_estop_seq(
    node: ZenohNode,
) -> None:
    """Issue 24: a reset clears only the e-stop its sender saw. An operator saw the e-stop at
    seq S; a viewer's e-stop reaches the controller first; the operator's reset (carrying S)
    is refused and the rig stays stopped. A reset without estop_seq (an older client) gets a
    refusal naming the field."""
    first = command(node, proto.EStop())
    assert first.ok and node.rt.estop_seq == first.seq
    seen = node.rt.estop_seq  # what the operator's Status showed
    second = command(node, proto.EStop())  # another session, while latched
    assert second.ok and second.seq > seen and node.rt.estop_seq == second.seq
    stale = command(node, proto.ResetFault(estop_seq=seen))
    assert not stale.ok and stale.mode == "estop" and stale.field == "body.estop_seq"
    assert f"seq {seen}" in stale.message and f"seq {second.seq}" in stale.message
    legacy = command(node, proto.ResetFault())
    assert not legacy.ok and legacy.field == "body.estop_seq" and legacy.mode == "estop"
    assert "estop_seq" in legacy.message
    assert node.rt.mode == "estop"
    # The reset that names the latest e-stop works.
    assert command(node, proto.ResetFault(estop_seq=second.seq)).ok
    assert node.rt.mode == "stopped"


def test_handler_errors_never_reach_the_client_as_text(node: ZenohNode) -> None:
    def broken(_data: bytes, _who: object = None) -> bytes:
        raise KeyError("secret internal detail")

    query = FakeQuery(b"")
    serve_one(node, query, node.rt.next_arrival(), broken)
    assert query.errors and b"secret" not in query.errors[0] and b"KeyError" not in query.errors[0]


def test_the_latch_is_written_and_cleared(node: ZenohNode) -> None:
    store = node.service.store
    assert command(node, proto.EStop()).ok
    node.write_latch()
    latch = store.load_latch()
    assert latch is not None and latch.mode == "estop" and latch.reason == "command"
    assert command(node, proto.ResetFault(estop_seq=node.rt.estop_seq)).ok
    node.write_latch()
    assert store.load_latch() is None


def test_a_failing_state_dir_is_reported_and_the_loop_runs_on(
    node: ZenohNode, monkeypatch: pytest.MonkeyPatch
) -> None:
    import errno
    import tempfile

    def read_only(*_a: object, **_k: object) -> None:
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    reply = apply(node, LoopConfig(q_cutoff_hz=1.0))
    assert not reply.accepted and reply.version == 1
    assert reply.field == "state_dir"  # as knowledge says it (issue 24: apply said "")
    assert any("state_dir" in r and "OSError" not in r for r in reply.reasons)
    k = node.service.handle_knowledge(proto.KnowledgeRequest(record=node.service.knowledge))
    assert not k.ok and k.field == "state_dir"
    node.service.warn("an unrelated problem")
    assert command(node, proto.EStop()).ok
    for _ in range(30):  # the latch writer retries every second
        node.write_latch()
    status = node.status()
    latch_lines = [n for n in status.notes if "latch was not saved" in n]
    assert len(latch_lines) == 1 and "(30 times)" in latch_lines[0], status.notes
    assert "an unrelated problem" in status.notes  # not pushed out by the repeats
    assert any("state_dir" in n for n in status.notes)
    seq = node.rt.seq
    deadline = time.monotonic() + 5.0
    while node.rt.seq < seq + 20 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert node.rt.seq >= seq + 20  # the loop runs on


def test_a_note_about_older_knowledge_is_cleared_by_newer_knowledge(node: ZenohNode) -> None:
    """Issue 24 item 9: "the running configuration is now judged reject" stayed in
    Status.notes after newer knowledge judged it fine again."""
    import numpy as np

    from controller.core.config import NominalModel
    from controller.gate.knowledge import MeasuredRecord
    from controller.gate.loop_model import nominal_continuous_response

    article = NominalModel()

    svc = node.service
    original = svc.knowledge
    f = np.geomspace(0.05, 400.0, 120)
    h = 15.0 * nominal_continuous_response(article, f)  # a plant 15x the model's gain
    measured = MeasuredRecord(name="pos0", freq_hz=f.tolist(), re=h.real.tolist(),
                              im=h.imag.tolist())
    stiff = KnowledgeRecord(model=article, bound=original.bound, measured=[measured])
    reply = svc.handle_knowledge(proto.KnowledgeRequest(record=stiff))
    assert reply.ok and "now judged reject" in reply.message
    assert sum("now judged" in n for n in node.status().notes) == 1
    reply = svc.handle_knowledge(proto.KnowledgeRequest(record=original))
    assert reply.ok and "now judged" not in reply.message, reply.message
    notes = node.status().notes
    assert not any("now judged" in n for n in notes), notes
    assert node.status().knowledge_version == 3


def test_a_refused_command_is_audited_with_what_it_claimed(
    node: ZenohNode, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The audit line names the command a payload claimed, read without trusting it: no
    hostile payload makes the audit (or the reply) fail."""
    seen: list[tuple[str, str, object, object]] = []

    def record(action: str, who: object, outcome: str, **fields: object) -> None:
        seen.append((action, outcome, fields.get("command"), fields.get("estop_seq")))

    monkeypatch.setattr(node.access, "record", record)
    hostile = [
        msgspec.msgpack.encode({"v": V, "body": ["reset"]}),
        msgspec.msgpack.encode({"v": V, "body": {"type": 5, "estop_seq": 7}}),
        msgspec.msgpack.encode([1, 2]),
        b"\xc1",  # a byte msgpack never uses
        b"\x82\xa1v\x02\xa4body\x81\xa4type\xa2\xff\xfe",  # invalid UTF-8
        b"\x91" * 100_000,  # nested deeper than any decoder recurses
    ]
    claimed = msgspec.msgpack.encode(
        {"v": V, "body": {"type": "reset", "estop_seq": 7, "bogus": 1}})
    for data in [claimed, *hostile]:
        reply = proto.decode(node.handle_command(data), proto.CommandReply)
        assert not reply.ok and reply.field
    assert seen[0] == ("reset", "refused", "reset", 7)
    assert seen[1:] == [("command", "refused", "", None)] * len(hostile)
    assert node.rt.mode == "running"
