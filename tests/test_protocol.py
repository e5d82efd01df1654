"""Protocol decoding: every rejection names the field by its path from the message root."""

from __future__ import annotations

import math

import msgspec
import pytest
from statuses import status

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.core.verdict import Verdict, VerdictMargins

ENC = msgspec.msgpack.encode
V = proto.PROTOCOL_VERSION  # the version this side speaks


def test_round_trip_of_each_request() -> None:
    req = proto.ConfigRequest(candidate=LoopConfig(q_cutoff_hz=2.0), client="t")
    assert proto.decode(proto.encode(req), proto.ConfigRequest) == req
    cmd = proto.Command(body=proto.SetTrajectory(trajectory=Trajectory(kind="ramp")))
    assert proto.decode(proto.encode(cmd), proto.Command) == cmd


@pytest.mark.parametrize(
    ("payload", "kind", "field"),
    [
        (b"\xc1", proto.ConfigRequest, "payload"),
        (ENC([1, 2]), proto.ConfigRequest, "payload"),
        (ENC({"candidate": {}}), proto.ConfigRequest, "v"),
        (ENC({"v": 1}), proto.ConfigRequest, "v"),
        (ENC({"v": True}), proto.ConfigRequest, "v"),
        (ENC({"v": V, "candidate": {"cv_kp": "x"}}), proto.ConfigRequest, "candidate.cv_kp"),
        (ENC({"v": V, "candidate": {"cv_kp": -1.0}}), proto.ConfigRequest, "candidate.cv_kp"),
        (
            ENC({"v": V, "candidate": {"q_cutoff_hz": float("nan")}}),
            proto.ConfigRequest,
            "candidate.q_cutoff_hz",
        ),
        (
            ENC({"v": V, "candidate": {"nominal": {"pn_den": [1.0, -1.0, 1.0]}}}),
            proto.ConfigRequest,
            "candidate.nominal.pn_den",
        ),
        (
            ENC({"v": V, "candidate": {"nominal": {"mn_den": [1.0, 1.0, 0.0]}}}),
            proto.ConfigRequest,
            "candidate.nominal.mn_den[2]",
        ),
        (ENC({"v": V, "candidate": {"gain": 1.0}}), proto.ConfigRequest, "candidate.gain"),
        (ENC({"v": V, "body": {"type": "nuke"}}), proto.Command, "body.type"),
        (ENC({"v": V}), proto.Command, "body"),
        (
            ENC({"v": V, "body": {"type": "trajectory", "trajectory": {"kind": "zigzag"}}}),
            proto.Command,
            "body.trajectory.kind",
        ),
    ],
)
def test_rejections_name_the_field(payload: bytes, kind: type, field: str) -> None:
    with pytest.raises(proto.ProtocolError) as info:
        proto.decode(payload, kind)
    assert info.value.field == field, str(info.value)
    assert str(info.value).startswith(f"{field}: ")


# -- the verdict, nested (protocol 2) ---------------------------------------------------------

MARGINS = VerdictMargins(gain_margin_db=math.inf, phase_margin_deg=48.5, peak_sensitivity_db=3.2,
                         small_gain_peak=0.41, max_pole_radius=0.998,
                         noise_to_command_peak_db=17.0, gain_margin_up_db=math.inf,
                         gain_reduction_margin_db=math.inf)
VERDICT = Verdict(verdict="caution", rejections=(), cautions=("phase margin 28 deg < 30",),
                  margins=MARGINS, recommended_max_cutoff_hz=1.7,
                  knowledge="plant knowledge v4 (identification run 2: ...)", knowledge_version=4)


def test_round_trip_of_each_message_with_a_nested_verdict() -> None:
    reply = proto.ConfigReply(accepted=True, version=3, config=LoopConfig(q_cutoff_hz=0.8),
                              reasons=list(VERDICT.reasons), verdict=VERDICT)
    st = status(knowledge_version=4, knowledge="v4 ...", verdict=VERDICT)
    history = proto.HistoryReply(ok=True, entries=[
        proto.HistoryEntry(version=1, time_s=1.0, client="startup (defaults)",
                           config=LoopConfig()),  # a change logged without a verdict
        proto.HistoryEntry(version=2, time_s=2.0, client="alice", config=LoopConfig(),
                           verdict=VERDICT),
    ])
    for msg in (reply, st, history):
        back = proto.decode(proto.encode(msg), type(msg))
        assert back == msg, type(msg).__name__
    got = proto.decode(proto.encode(st), proto.Status).verdict
    assert isinstance(got, Verdict) and got.margins.gain_margin_db == math.inf
    assert got.reasons == VERDICT.reasons and got.knowledge_version == 4
    # The wire form is the Verdict's own fields, nested under `verdict` (no copies beside it).
    raw = msgspec.msgpack.decode(proto.encode(reply))
    assert raw["v"] == proto.PROTOCOL_VERSION == 2
    assert raw["verdict"] == msgspec.msgpack.decode(msgspec.msgpack.encode(VERDICT))
    assert not {"margins", "knowledge_version"} & set(raw)
    refused = proto.ConfigReply(accepted=False, version=3, config=LoopConfig(), field="lease",
                                reasons=["lease: held by bob"])  # refused before the gate ran
    assert proto.decode(proto.encode(refused), proto.ConfigReply).verdict is None


def _with(msg: msgspec.Struct, path: tuple[str | int, ...], value: object) -> bytes:
    """`msg` encoded with the value at `path` replaced (a hostile or broken sender)."""
    raw = msgspec.to_builtins(msg)
    node = raw
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return ENC(raw)


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        (("verdict", "verdict"), "maybe", "verdict.verdict"),
        (("verdict", "verdict"), None, "verdict.verdict"),
        (("verdict", "margins", "gain_margin_db"), "big", "verdict.margins.gain_margin_db"),
        (("verdict", "margins"), None, "verdict.margins"),
        (("verdict", "rejections"), [3], "verdict.rejections[0]"),
        (("verdict", "cautions"), "one", "verdict.cautions"),
        (("verdict", "knowledge_version"), True, "verdict.knowledge_version"),
        (("verdict", "recommended_max_cutoff_hz"), "1", "verdict.recommended_max_cutoff_hz"),
        (("verdict",), "accept", "verdict"),  # protocol 1's kind string in a protocol 2 message
        (("verdict",), [1, 2], "verdict"),
    ],
)
def test_a_malformed_nested_verdict_is_rejected_naming_the_field(
    path: tuple[str, ...], value: object, field: str
) -> None:
    reply = proto.ConfigReply(accepted=True, version=1, config=LoopConfig(), verdict=VERDICT)
    history = proto.HistoryReply(ok=True, entries=[proto.HistoryEntry(
        version=1, time_s=1.0, client="a", config=LoopConfig(), verdict=VERDICT)])
    cases: list[tuple[bytes, type[proto.Message], str]] = [
        (_with(reply, path, value), proto.ConfigReply, field),
        (_with(status(verdict=VERDICT), path, value), proto.Status, field),
        (_with(history, ("entries", 0, *path), value), proto.HistoryReply, f"entries[0].{field}"),
    ]
    for payload, kind, named in cases:
        with pytest.raises(proto.ProtocolError) as info:
            proto.decode(payload, kind)
        assert info.value.field == named, (kind.__name__, str(info.value))
        assert str(info.value).startswith(f"{named}: ")


def test_a_message_of_an_older_peer_is_refused_naming_both_versions() -> None:
    # What a protocol 1 controller sent: the verdict's fields side by side.
    margins = msgspec.to_builtins(MARGINS)
    old_reply = {"v": 1, "accepted": True, "version": 3, "config": {}, "reasons": [],
                 "margins": margins, "field": "", "verdict": "accept", "knowledge_version": 4}
    old_status = {**msgspec.to_builtins(status()), "v": 1, "margins": margins,
                  "verdict": "accept"}
    old_history = {"v": 1, "ok": True, "entries": [{"version": 1, "time_s": 1.0, "client": "a",
                                                    "verdict": "accept", "config": {},
                                                    "margins": margins}]}
    for raw, kind in ((old_reply, proto.ConfigReply), (old_status, proto.Status),
                      (old_history, proto.HistoryReply)):
        with pytest.raises(proto.ProtocolError) as info:
            proto.decode(ENC(raw), kind)
        assert info.value.field == "v"
        text = str(info.value)
        assert "unsupported protocol version 1" in text and "this side speaks 2" in text, text
    # The same fields under this version's number are refused too: never half-read.
    with pytest.raises(proto.ProtocolError) as info:
        proto.decode(ENC({**old_reply, "v": 2}), proto.ConfigReply)
    assert info.value.field in ("margins", "verdict", "knowledge_version"), str(info.value)
