"""ControllerClient's waits: an apply waits `apply_timeout_s` for its reply (the controller's
gate may load its worker and save first), every read `query_timeout_s`."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest
from helpers import wait_until

from controller.client.controller_client import (
    ClientOptions,
    ControllerClient,
    ControllerUnavailable,
)
from controller.core.config import LoopConfig


@pytest.fixture(scope="module")
def zenoh_session() -> Iterator[Any]:
    """A real Zenoh session that reaches nothing (no scouting, no endpoints): what the client
    takes its session's id from (an EntityGlobalId has no constructor)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    with zenoh.open(conf) as s:
        yield s


class _SilentSession:
    """A session whose queries get no reply; it records the timeout and the source info of
    each get."""

    def __init__(self, real: Any) -> None:
        self.real = real
        self.timeouts: list[float] = []
        self.sources: list[Any] = []

    def declare_querier(self, key: str) -> Any:
        return self.real.declare_querier(key)

    def get(self, key: str, payload: bytes, timeout: float, source_info: Any = None) -> list[Any]:
        self.timeouts.append(timeout)
        self.sources.append(source_info)
        return []


def test_an_apply_waits_longer_than_a_read(zenoh_session: Any) -> None:
    client = ControllerClient(ClientOptions(query_timeout_s=3.0, apply_timeout_s=30.0))
    session = _SilentSession(zenoh_session)
    client._session = session
    with pytest.raises(ControllerUnavailable, match=r"within 3\.0 s"):
        client.get_config()
    with pytest.raises(ControllerUnavailable, match=r"within 30\.0 s"):
        client.apply(LoopConfig(q_cutoff_hz=0.8), confirm=True)
    with pytest.raises(ControllerUnavailable, match=r"within 3\.0 s"):
        client.history()
    assert session.timeouts == [3.0, 30.0, 3.0]


def test_adopting_knowledge_waits_as_long_as_an_apply(zenoh_session: Any) -> None:
    """Adopting plant knowledge judges the active configuration through the gate, as an apply
    does: a plain read's wait timed out on a loaded machine while the controller adopted it."""
    from controller import protocol as proto
    from controller.core.config import NominalModel
    from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord

    client = ControllerClient(ClientOptions(query_timeout_s=3.0, apply_timeout_s=30.0))
    session = _SilentSession(zenoh_session)
    client._session = session
    rec = KnowledgeRecord(version=1, source="test", model=NominalModel(),
                          bound=COMMISSIONING_BOUND)
    for req, wait in ((None, r"3\.0"), (proto.KnowledgeRequest(record=rec), r"30\.0"),
                      (proto.KnowledgeRequest(adopt_run=1), r"30\.0")):
        with pytest.raises(ControllerUnavailable, match=rf"within {wait} s"):
            client.knowledge(req)
    assert session.timeouts == [3.0, 30.0, 30.0]


def test_every_query_names_the_clients_session(zenoh_session: Any) -> None:
    """The controller's per-session budget keys on the Zenoh id a query's source info names
    (controller/process/budget.py): one id per client, numbered queries."""
    client = ControllerClient(ClientOptions(query_timeout_s=3.0, apply_timeout_s=30.0))
    session = _SilentSession(zenoh_session)
    client._session = session
    for _ in range(3):
        with pytest.raises(ControllerUnavailable):
            client.get_config()
    ids = {str(si.source_id.zid) for si in session.sources}
    assert ids == {str(zenoh_session.zid())}
    assert [si.source_sn for si in session.sources] == [1, 2, 3]


def test_zenohs_own_timeout_reads_as_no_reply() -> None:
    """A controller that holds a query past its timeout: Zenoh ends the get with an error
    reply of its own ('Timeout'); the client says no reply came in that time, not that the
    controller answered with an error (it read "controller replied with an error: Timeout")."""
    import socket

    import zenoh

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    def conf(listen: list[str], connect: list[str]) -> Any:
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("listen/endpoints", json.dumps(listen))
        c.insert_json5("connect/endpoints", json.dumps(connect))
        return c

    held: list[Any] = []  # never answered, never dropped while the get waits
    with zenoh.open(conf([f"tcp/127.0.0.1:{port}"], [])) as ctl_side, \
            zenoh.open(conf([], [f"tcp/127.0.0.1:{port}"])) as client_side:
        q = ctl_side.declare_queryable("**", held.append)
        client = ControllerClient(ClientOptions(query_timeout_s=0.5))
        client._session = client_side
        errors: list[str] = []

        def held_one() -> bool:
            """A get (until one reaches the queryable: its declaration takes a moment)."""
            with pytest.raises(ControllerUnavailable) as exc:
                client.get_config()
            errors.append(str(exc.value))
            return bool(held)

        assert wait_until(held_one, 20.0, poll_s=0.0)
        assert "within 0.5 s" in errors[-1] and "replied" not in errors[-1], errors[-1]
        q.undeclare()
        held.clear()
