"""The controller owns the plant knowledge: a real controller process over Zenoh on loopback.

A candidate's `nominal` is never evidence (a lie about the plant is judged on the controller's
own model); a `caution` applies only with `confirm`; knowledge is fetched, adopted, numbered by
the controller, persisted across a restart, and hostile records are refused naming the field.
The verdicts are checked against an independent truth (tests/fuzz_truth.py, python-control).
"""

from __future__ import annotations

import json
import signal
import sys
from collections.abc import Callable
from pathlib import Path

import msgspec
import numpy as np
from procs import APPLY_TIMEOUT_S, Client, ControllerProcess, port_is_free, wait_until

from controller import protocol as proto
from controller.core.config import LoopConfig, NominalModel
from controller.core.verdict import kind_of
from controller.gate.knowledge import KnowledgeRecord, MeasuredRecord
from controller.gate.loop_model import nominal_continuous_response

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: the independent truth
from fuzz_truth import TruePlant, truth

V = proto.PROTOCOL_VERSION  # the version this side speaks

ARTICLE = NominalModel()


def _knowledge(c: Client, req: proto.KnowledgeRequest | None = None) -> proto.KnowledgeReply:
    payload = proto.encode(req) if req is not None else None
    # Adopting knowledge runs the gate (as an apply): an apply's time, as the product client
    # gives it (a plain query's 5 s timed out with two busy loops beside the suite).
    adopting = req is not None and (req.record is not None or req.adopt_run is not None)
    timeout_s = APPLY_TIMEOUT_S if adopting else None
    return proto.decode(
        c.query_raw(proto.key_knowledge(c.rig), payload, timeout_s), proto.KnowledgeReply
    )


def _apply(c: Client, cand: LoopConfig, confirm: bool = False) -> proto.ConfigReply:
    req = proto.ConfigRequest(candidate=cand, client="test", confirm=confirm)
    return c.config_raw(proto.encode(req), APPLY_TIMEOUT_S)


def test_a_lying_nominal_is_judged_on_the_controllers_model(
    controller: ControllerProcess, client: Client
) -> None:
    """The issue's case: `nominal` with the gain x0.11 makes F1 ~ 9x too large; on the real
    (simulated) rig that loop is unstable, and the controller must say so."""
    n = ARTICLE
    a, b, c = n.pn_num
    lie = NominalModel(mn_den=n.mn_den, pn_num=(0.11 * a, 0.11 * b, 0.11 * c), pn_den=n.pn_den)
    cand = LoopConfig(nominal=lie, q_cutoff_hz=4.0)
    assert not truth(TruePlant(), cand).stable  # the independent truth: unstable
    before = client.get_config()
    reply = _apply(client, cand, confirm=True)
    assert not reply.accepted and kind_of(reply.verdict) == "reject"
    assert any("simulated rig model" in r for r in reply.reasons), reply.reasons
    assert client.get_config().version == before.version
    # A P-only speed and position loop (zero integral gains) is a valid configuration.
    p_only = LoopConfig(cv_ki_per_s=0.0, pos_ki_per_s=0.0)
    assert truth(TruePlant(), p_only).stable
    reply = _apply(client, p_only, confirm=True)
    assert reply.accepted and kind_of(reply.verdict) in ("accept", "caution"), reply.reasons


def test_a_caution_applies_only_with_confirm(controller: ControllerProcess, client: Client) -> None:
    before = client.get_config()
    # Stable, calm on the nonlinear rig, thin margins in the whole servo (a Q31 at 12 Hz
    # chatters at standstill without decaying: rejected since, not cautioned).
    cand = before.config.with_(cv_kp=2.0, q_cutoff_hz=5.0)
    reply = _apply(client, cand)
    assert not reply.accepted and kind_of(reply.verdict) == "caution" and reply.field == "confirm"
    assert client.get_config().version == before.version
    assert any("whole servo" in r for r in reply.reasons)
    reply = _apply(client, cand, confirm=True)
    assert reply.accepted and kind_of(reply.verdict) == "caution"
    assert reply.version == before.version + 1
    assert reply.verdict is not None and reply.verdict.knowledge_version == 1
    st = client.fresh_status()
    assert st.config_version == reply.version and st.verdict == reply.verdict  # the same one
    assert st.knowledge_version == 1 and "simulated rig model" in st.knowledge
    assert st.verdict is not None and st.verdict.margins.phase_margin_deg > 0
    assert st.verdict.cautions


def test_knowledge_is_adopted_numbered_persisted_and_hostile_records_refused(
    start_controller_factory: Callable[..., ControllerProcess], tmp_path: Path
) -> None:
    state = tmp_path / "k"
    first = start_controller_factory(state_dir=state)
    f = np.geomspace(0.05, 400.0, 120)
    # A plant 40x the model's gain (the default loop's gain margin is 26 dB, 20x).
    h = 40.0 * nominal_continuous_response(ARTICLE, f)
    measured = MeasuredRecord(name="pos0", freq_hz=f.tolist(), re=h.real.tolist(),
                              im=h.imag.tolist())
    with Client(first.endpoint, first.rig) as c:
        c.wait_ready(first)
        got = _knowledge(c)
        assert got.ok and got.record.version == 1 and got.record.source == "simulated rig model"
        # The client's version and source claims are not taken: the controller numbers.
        rec = KnowledgeRecord(version=999, source="measured on the rig", model=ARTICLE,
                              bound=got.record.bound, measured=[measured])
        reply = _knowledge(c, proto.KnowledgeRequest(record=rec))
        assert reply.ok and reply.record.version == 2, reply.message
        # The running (default) configuration is unstable on such a plant: said at once.
        assert "now judged reject" in reply.message
        assert not truth(TruePlant(gain=40.0), LoopConfig()).stable
        st = c.fresh_status()
        assert st.knowledge_version == 2 and kind_of(st.verdict) == "reject"
        assert st.verdict is not None and st.verdict.knowledge_version == 2  # re-judged on it
        assert any("now judged reject" in n for n in st.notes)
        # Any candidate is now judged on the measured response.
        r = _apply(c, LoopConfig(q_cutoff_hz=0.6), confirm=True)
        assert not r.accepted and r.verdict is not None and r.verdict.knowledge_version == 2
        assert any("measured response 'pos0'" in x for x in r.reasons), r.reasons
        # Hostile records: refused naming the field, nothing adopted.
        bad_f = [*f.tolist()[:-1], float("nan")]
        hostile = [
            KnowledgeRecord(measured=[MeasuredRecord(name="x", freq_hz=bad_f, re=h.real.tolist(),
                                                     im=h.imag.tolist())]),
            KnowledgeRecord(measured=[MeasuredRecord(name="x", freq_hz=[1.0, 2.0], re=[1.0],
                                                     im=[0.0, 0.0])]),
            KnowledgeRecord(measured=[measured, measured]),
        ]
        for bad in hostile:
            out = _knowledge(c, proto.KnowledgeRequest(record=bad))
            assert not out.ok and out.field == "record" and out.record.version == 2, out
        for payload, field in (
            (b"\xc1garbage", "payload"),
            (msgspec.msgpack.encode({"v": V, "recrod": {}}), "recrod"),
            (msgspec.msgpack.encode({"v": V, "adopt_run": 3}), "adopt_run"),
        ):
            out = proto.decode(c.query_raw(proto.key_knowledge(c.rig), payload),
                               proto.KnowledgeReply)
            assert not out.ok and field in out.field, out
            assert out.record.version == 2
    assert first.stop(signal.SIGTERM, timeout_s=60.0) == 0, first.log()
    assert wait_until(lambda: port_is_free(first.port), 5.0)
    saved = json.loads((state / "plant_knowledge.json").read_text())
    assert saved["version"] == 2 and saved["measured"][0]["name"] == "pos0"
    second = start_controller_factory(state_dir=state, port=first.port,
                                      extra_args=("--config", str(_stable_on(tmp_path))))
    with Client(second.endpoint, second.rig) as c:
        c.wait_ready(second)
        assert _knowledge(c).record.version == 2  # survives the restart
        assert c.fresh_status().knowledge_version == 2


def _stable_on(tmp_path: Path) -> Path:
    """A configuration stable on the 40x plant (the saved config is not): a low speed gain,
    checked against the truth."""
    cfg = LoopConfig(cv_kp=0.45 / 40.0, cv_ki_per_s=20.0, pos_kp_per_s=3.0, pos_ki_per_s=0.5,
                     q_cutoff_hz=0.3)
    assert truth(TruePlant(gain=40.0), cfg).stable
    path = tmp_path / "stable40.json"
    path.write_text(json.dumps({"cv_kp": cfg.cv_kp, "cv_ki_per_s": cfg.cv_ki_per_s,
                                "pos_kp_per_s": cfg.pos_kp_per_s,
                                "pos_ki_per_s": cfg.pos_ki_per_s, "q_cutoff_hz": 0.3}))
    return path
