"""ControllerClient's waits: an apply waits `apply_timeout_s` for its reply (the controller's
gate may load its worker and save first), every read `query_timeout_s`."""

from __future__ import annotations

from typing import Any

import pytest

from controller.client.controller_client import (
    ClientOptions,
    ControllerClient,
    ControllerUnavailable,
)
from controller.core.config import LoopConfig


class _SilentSession:
    """A session whose queries get no reply; it records the timeout of each get."""

    def __init__(self) -> None:
        self.timeouts: list[float] = []

    def get(self, key: str, payload: bytes, timeout: float) -> list[Any]:
        self.timeouts.append(timeout)
        return []


def test_an_apply_waits_longer_than_a_read() -> None:
    client = ControllerClient(ClientOptions(query_timeout_s=3.0, apply_timeout_s=30.0))
    session = _SilentSession()
    client._session = session
    with pytest.raises(ControllerUnavailable, match=r"within 3\.0 s"):
        client.get_config()
    with pytest.raises(ControllerUnavailable, match=r"within 30\.0 s"):
        client.apply(LoopConfig(q_cutoff_hz=0.8), confirm=True)
    with pytest.raises(ControllerUnavailable, match=r"within 3\.0 s"):
        client.history()
    assert session.timeouts == [3.0, 30.0, 3.0]


def test_adopting_knowledge_waits_as_long_as_an_apply() -> None:
    """Adopting plant knowledge judges the active configuration through the gate, as an apply
    does: a plain read's wait timed out on a loaded machine while the controller adopted it."""
    from controller import protocol as proto
    from controller.core.config import NominalModel
    from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord

    client = ControllerClient(ClientOptions(query_timeout_s=3.0, apply_timeout_s=30.0))
    session = _SilentSession()
    client._session = session
    rec = KnowledgeRecord(version=1, source="test", model=NominalModel(),
                          bound=COMMISSIONING_BOUND)
    for req, wait in ((None, r"3\.0"), (proto.KnowledgeRequest(record=rec), r"30\.0"),
                      (proto.KnowledgeRequest(adopt_run=1), r"30\.0")):
        with pytest.raises(ControllerUnavailable, match=rf"within {wait} s"):
            client.knowledge(req)
    assert session.timeouts == [3.0, 30.0, 30.0]
