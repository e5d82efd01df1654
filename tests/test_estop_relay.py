"""The e-stop relayed by the edge process (issue 31 item 1): the edge's callback raises a flag
in shared memory that the tick reads, its audit lines coalesced per sender (`repeats`).

Unit level, on the real shared array (`edge.estop_flag`) and the runtime on a fake clock; the
whole path over Zenoh is tests/integration/test_estop.py and test_flood_isolation.py.
"""

from __future__ import annotations

import json
import threading
import time
import tracemalloc
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from test_runtime import fake_runtime, more

from controller import protocol as proto
from controller.process.audit import AUDIT_FILE, AuditLog, verify
from controller.process.edge import ESTOP_ARRIVAL, ESTOP_FLAG, _Edge, estop_flag
from controller.process.requests import ResetFault, Start
from controller.process.runtime import ESTOP


class _Sample(SimpleNamespace):
    pass


def _sample(key: str, client: str = "flood") -> Any:
    body = proto.encode(proto.Command(body=proto.EStop(), client=client))
    return _Sample(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: body),
                   source_info=None)


def _edge(flag: Any) -> Any:
    spec = SimpleNamespace(auth_dir=Path("/nonexistent"), budget_per_s=None,
                           state_dir=Path("/nonexistent"), max_pending_queries=8)
    edge = _Edge(spec, {}, None, flag)  # type: ignore[arg-type]
    sent: list[Any] = []
    edge.send_control = sent.append  # type: ignore[method-assign]
    return edge, sent


def test_the_edge_callback_raises_the_flag_and_the_tick_latches_on_it() -> None:
    flag = estop_flag()
    rt, rig = fake_runtime()
    rt.estop_flag = flag
    rt.run(max_ticks=100)
    assert rt.mode != ESTOP and abs(rig.commands[99]) > 0.0
    edge, _ = _edge(flag)
    before = time.monotonic_ns()
    edge.on_estop(_sample("dobtune/r/estop"))
    stamp = flag[ESTOP_ARRIVAL]
    assert flag[ESTOP_FLAG] == 1 and stamp >= before
    more(rt, 3)
    assert rt.mode == ESTOP and rt.estop_source == "estop key" and rt.estop_seq == 100
    assert flag[ESTOP_FLAG] == 0  # taken by the tick
    assert rig.commands[-3:] == [0.0] * 3
    # A start is refused; a reset that arrived before the relayed e-stop is refused too.
    early = stamp - 1  # arrived just before the relayed e-stop
    with rt.arrival_scope(early):
        late_reset = rt.submit(ResetFault(rt.estop_seq))
    start = rt.submit(Start())
    more(rt, 2)
    assert not start.ok and not late_reset.ok and rt.mode == ESTOP


def test_an_estop_raised_while_the_tick_takes_the_previous_one_is_not_lost() -> None:
    """The tick clears the flag before it reads the stamp: an e-stop raised in between is
    taken by the next tick (a new estop_seq), never dropped."""
    flag = estop_flag()
    rt, _ = fake_runtime()
    rt.estop_flag = flag
    rt.run(max_ticks=10)
    edge, _ = _edge(flag)
    edge.on_estop(_sample("dobtune/r/estop"))
    more(rt, 1)
    first = rt.estop_seq
    # Raised again right after the tick cleared the flag (as if during its read).
    edge.on_estop(_sample("dobtune/r/estop"))
    more(rt, 1)
    assert rt.estop_seq == first + 1 and flag[ESTOP_FLAG] == 0


def test_reading_the_flag_on_the_tick_allocates_nothing() -> None:
    flag = estop_flag()
    rt, _ = fake_runtime()
    rt.estop_flag = flag
    rt.run(max_ticks=400)
    read = rt._tick.__self__.estop_flag  # the read the tick makes
    tracemalloc.start()
    try:
        b = tracemalloc.get_traced_memory()[0]
        for _ in range(10_000):
            if read[0]:
                raise AssertionError("no e-stop was raised")
        a = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    assert a - b < 512


def test_an_estop_flood_through_the_edge_is_reported_once_per_sender_with_its_count(
        tmp_path: Path) -> None:
    flag = estop_flag()
    edge, sent = _edge(flag)
    n = 5000
    t_first = time.time()
    threads = [threading.Thread(target=lambda: [edge.on_estop(_sample("dobtune/r/@user/view/estop"))
                                                for _ in range(n)]) for _ in range(2)]
    edge.on_estop(_sample("dobtune/r/@user/op1/estop", client="op"))
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    reporter = threading.Thread(target=edge.report_estops)
    reporter.start()
    deadline = time.monotonic() + 30.0
    while not sent and time.monotonic() < deadline:
        time.sleep(0.01)
    edge.stop.set()
    edge._estop_event.set()
    reporter.join(10.0)
    assert not reporter.is_alive()
    ((what, entries),) = sent
    assert what == "estop"
    by_user = {who: (key, claims, count, arrived_s)
               for who, key, claims, count, arrived_s in entries}
    assert by_user["view"][2] == 2 * n and by_user["op1"][2] == 1
    # The first arrival's wall time (op1's came before the flood's threads started).
    assert t_first - 0.01 <= by_user["op1"][3] <= by_user["view"][3] <= time.time()
    assert by_user["view"][1]["claimed_client"] == "flood"
    # The loop process writes them as edge_link does: the audit counts the coalesced ones.
    path = tmp_path / AUDIT_FILE
    with AuditLog(path, rig="r") as log:
        for who, key, claims, count, arrived_s in entries:
            log.record("estop", who, "accepted", source="estop key", key=key, relayed="edge",
                       arrived_s=arrived_s, **claims,
                       **({"repeats": count - 1} if count > 1 else {}))
        log.record("reset", "op1", "accepted", estop_seq=3)
    recs = [json.loads(x) for x in path.read_bytes().splitlines()]
    assert [r["action"] for r in recs] == ["estop", "estop", "estop.repeated", "reset"]
    assert all("repeats" not in r for r in recs)
    (rep,) = [r for r in recs if r["action"] == "estop.repeated"]
    assert rep["count"] == 2 * n - 1 and rep["by_user"] == {"view": 2 * n - 1}
    assert verify(path).ok


def test_the_edge_serves_its_configuration_snapshot_only_while_the_loop_runs_its_version(
) -> None:
    """A watchdog rollback's new snapshot can reach the edge after the status that shows the
    rollback: until it does, the edge's snapshot is of another version than the one the loop
    wrote into the shared array, and the loop process answers the GET instead (issue 31)."""
    from controller.core.config import LoopConfig
    from controller.core.loop import LoopCoefficients
    from controller.process.edge import ACTIVE_VERSION, EdgeSnapshot
    from controller.process.requests import ApplyCoefficients

    flag = estop_flag()
    rt, _ = fake_runtime()
    rt.estop_flag = flag
    rt.run(max_ticks=10)
    assert flag[ACTIVE_VERSION] == 1  # written by the loop
    edge, _ = _edge(flag)
    edge.take(EdgeSnapshot(0, b"config v1", b"knowledge", 1))
    assert edge.read_locally("config", b"") == b"config v1"
    ticket = rt.submit(ApplyCoefficients(LoopCoefficients.build(LoopConfig(q_cutoff_hz=2.0), 2)))
    more(rt, 3)
    assert ticket.ok and flag[ACTIVE_VERSION] == 2
    assert edge.read_locally("config", b"") is None  # stale: forwarded, not served
    assert edge.read_locally("knowledge", b"") == b"knowledge"  # not versioned with it
    edge.take(EdgeSnapshot(1, b"config v2", b"knowledge", 2))
    assert edge.read_locally("config", b"") == b"config v2"
