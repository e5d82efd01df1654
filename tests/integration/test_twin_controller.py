"""The rig's twin in the controller (issue 35 item 1): a real controller process over Zenoh on
loopback builds the twin when it adopts plant knowledge (off the tick, before the apply lock)
and gives it with the knowledge reply; `dobtune ctl twin` prints its fit per position."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
from helpers import wait_until
from procs import APPLY_TIMEOUT_S, Client, ControllerProcess, run_ctl

from controller import protocol as proto
from controller.client.recorder import Recorder, RecordOptions
from controller.gate.knowledge import (
    COMMISSIONING_BOUND,
    KnowledgeRecord,
    MeasuredResponse,
    PlantKnowledge,
)
from controller.recording.mcap_io import read_recording
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import RigFaults
from controller.twin.fit import rig_response
from controller.twin.model import decode, from_builtins

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]


def _knowledge(c: Client, req: proto.KnowledgeRequest | None = None) -> proto.KnowledgeReply:
    payload = proto.encode(req) if req is not None else None
    timeout_s = APPLY_TIMEOUT_S if req is not None else None
    return proto.decode(c.query_raw(proto.key_knowledge(c.rig), payload, timeout_s),
                        proto.KnowledgeReply)



def test_adopted_knowledge_comes_with_its_twin(controller: ControllerProcess,
                                               client: Client) -> None:
    before = _knowledge(client)
    assert before.twin == "" and "nothing measured" in before.twin_note
    # Responses of a rig with 1.3x the load inertia and 2 ticks of delay (the exact linear
    # response of the simulated article rig so changed), at three positions.
    truth = rig_setup(("article-rig",)).params
    truth = type(truth)(**{**{f: getattr(truth, f) for f in truth.__dataclass_fields__},
                           "load_inertia_kg_m2": 0.104, "command_delay_ticks": 2})
    f = np.geomspace(0.2, 20.0, 25)
    measured = tuple(MeasuredResponse(f"pos{i}_{p:g}deg", f,
                                      rig_response(truth, RigFaults(), f, p))
                     for i, p in enumerate((0.0, 120.0, 240.0)))
    rec = KnowledgeRecord.of(PlantKnowledge(measured=measured, bound=COMMISSIONING_BOUND,
                                            source="test"))
    reply = _knowledge(client, proto.KnowledgeRequest(record=rec))
    assert reply.ok, reply.message
    # built in the twin's worker after the adoption: the reply says so until it is done
    assert reply.twin or "being built" in reply.twin_note, reply.twin_note
    assert wait_until(lambda: _knowledge(client).twin or "being built" not in
                      _knowledge(client).twin_note, timeout_s=180.0)
    reply = _knowledge(client)
    assert reply.twin, reply.twin_note
    twin = decode(reply.twin)
    assert twin.knowledge_version == reply.record.version
    assert twin.matches(reply.record.to_knowledge())
    assert [p.position_deg for p in twin.positions] == [0.0, 120.0, 240.0]
    assert all(p.rms_db < 0.1 and p.rms_deg < 1.0 for p in twin.positions), twin.describe()
    assert twin.fitted["delay_ticks"] == 2.0
    assert twin.fitted["inertia_factor"] == pytest.approx(1.3, rel=0.1)
    # A plain query gives the same twin (kept, not rebuilt differently).
    assert decode(_knowledge(client).twin) == twin
    code, text = run_ctl(controller, "twin")
    assert code == 0, text
    for p in twin.positions:
        assert p.describe() in text
    code, text = run_ctl(controller, "--json", "twin")
    assert code == 0 and json.loads(text)["knowledge_version"] == reply.record.version


def test_a_recording_carries_the_twin(controller: ControllerProcess, client: Client,
                                      tmp_path: Path) -> None:
    """`dobtune record`: a `twin` event for the knowledge held when it starts (none: said so)
    and after each adoption, with the twin as plain data (`from_builtins` reads it back)."""
    f = np.geomspace(0.2, 20.0, 20)
    params = rig_setup(()).params
    measured = tuple(MeasuredResponse(f"pos{i}_{p:g}deg", f,
                                      rig_response(params, RigFaults(), f, p))
                     for i, p in enumerate((0.0, 180.0)))
    rec_k = KnowledgeRecord.of(PlantKnowledge(measured=measured, bound=COMMISSIONING_BOUND))
    stop = threading.Event()
    out = tmp_path / "run.mcap"
    recorder = Recorder(RecordOptions(connect=(controller.endpoint,), out=out,
                                      rig_name=controller.rig, timeout_s=60.0))
    th = threading.Thread(target=recorder.run, args=(stop,))
    th.start()
    try:
        assert wait_until(lambda: recorder.twins_recorded, timeout_s=120.0)
        first = recorder.twins_recorded[0]
        reply = _knowledge(client, proto.KnowledgeRequest(record=rec_k))
        assert reply.ok
        adopted = reply.record.version
        assert adopted > first
        assert wait_until(lambda: adopted in recorder.twins_recorded, timeout_s=120.0)
    finally:
        stop.set()
        th.join(timeout=60.0)
    got = read_recording(out)
    twins = [e for e in got.events if e["kind"] == "twin"]
    assert [e["knowledge_version"] for e in twins] == [first, adopted]
    assert twins[0]["twin"] is None and "nothing measured" in twins[0]["text"]
    tw = from_builtins(twins[1]["twin"])
    assert tw.knowledge_version == adopted and tw.matches(reply.record.to_knowledge())
    assert tw == decode(_knowledge(client).twin)
