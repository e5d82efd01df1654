"""Protocol decoding: every rejection names the field by its path from the message root."""

from __future__ import annotations

import msgspec
import pytest

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory

ENC = msgspec.msgpack.encode


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
        (ENC({"v": 2}), proto.ConfigRequest, "v"),
        (ENC({"v": True}), proto.ConfigRequest, "v"),
        (ENC({"v": 1, "candidate": {"cv_kp": "x"}}), proto.ConfigRequest, "candidate.cv_kp"),
        (ENC({"v": 1, "candidate": {"cv_kp": -1.0}}), proto.ConfigRequest, "candidate.cv_kp"),
        (
            ENC({"v": 1, "candidate": {"q_cutoff_hz": float("nan")}}),
            proto.ConfigRequest,
            "candidate.q_cutoff_hz",
        ),
        (
            ENC({"v": 1, "candidate": {"nominal": {"pn_den": [1.0, -1.0, 1.0]}}}),
            proto.ConfigRequest,
            "candidate.nominal.pn_den",
        ),
        (
            ENC({"v": 1, "candidate": {"nominal": {"mn_den": [1.0, 1.0, 0.0]}}}),
            proto.ConfigRequest,
            "candidate.nominal.mn_den[2]",
        ),
        (ENC({"v": 1, "candidate": {"gain": 1.0}}), proto.ConfigRequest, "candidate.gain"),
        (ENC({"v": 1, "body": {"type": "nuke"}}), proto.Command, "body.type"),
        (ENC({"v": 1}), proto.Command, "body"),
        (
            ENC({"v": 1, "body": {"type": "trajectory", "trajectory": {"kind": "zigzag"}}}),
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
