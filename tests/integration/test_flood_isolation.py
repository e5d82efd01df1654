"""A signed-in client's flood against the loop and the e-stop (issue 31 item 1), over real Zenoh
with `--auth`: the request queryables run in the controller's edge process, each user has a
request budget (here 20 requests/s, bursts of 40), the e-stops are taken by a process of
their own (the e-stop relay), the loop's process's own subscriber their fallback.

While a viewer floods every read it may send (and a candidate it may not apply) from 4
threads: its excess is refused, each refusal naming the budget, and the controller reports and
audits the refusals; another user is served meanwhile (budgets are per user), and so is the
viewer's own second session (a session gets a share of its user's budget); e-stops put
during the flood are applied, and a reset followed at once by an e-stop ends in e-stop (the
order of arrival holds across the processes); the loop keeps running. The edge process and
the relay end with the controller, and one that dies is started again while the loop runs on
and the e-stops go through (the relay's, or the fallback's while the relay is dead). No
timing is asserted (the latencies are `tests/bench/bench_flood.py`'s figures).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import children, gone
from procs import Client, ControllerProcess, start_controller, wait_until

from controller import protocol as proto
from controller.auth import init_auth_dir, new_users
from controller.client import ClientOptions, ControllerClient, ControllerUnavailable
from controller.core.config import LoopConfig

pytestmark = pytest.mark.integration

RIG = "flood"
BUDGET = 20
REFUSAL = f"request budget exceeded: {BUDGET} requests/s per user"


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    base = tmp_path_factory.mktemp("flood")
    auth = base / "auth"
    init_auth_dir(auth, new_users([("op1", "operator"), ("view", "viewer"),
                                   ("watch", "viewer")]))
    proc = start_controller(base / "state", rig=RIG, extra_args=(
        "--auth", str(auth), "--realtime-priority", "--request-budget", str(BUDGET)))
    try:
        assert wait_until(lambda: _answers(auth, proc), 180.0, poll_s=0.5), proc.log()
        yield {"auth": auth, "proc": proc}
    finally:
        proc.stop()


def _answers(auth: Path, proc: ControllerProcess) -> bool:
    assert proc.proc.poll() is None, proc.log()
    try:
        with _client(auth, proc, "watch") as c:
            c.get_config()
            return True
    except ControllerUnavailable:
        return False


@contextlib.contextmanager
def _client(auth: Path, proc: ControllerProcess, user: str) -> Iterator[ControllerClient]:
    opts = ClientOptions(connect=(proc.endpoint,), rig_name=RIG, auth=auth, user=user,
                         client_name=user, query_timeout_s=5.0, apply_timeout_s=10.0,
                         connect_timeout_s=30.0)
    with ControllerClient(opts) as c:
        yield c


def _status(c: ControllerClient) -> proto.Status:
    assert wait_until(lambda: c.status is not None, 10.0)
    st = c.status
    assert st is not None
    return st


def _fresh_status(c: ControllerClient) -> proto.Status:
    """The next status received after this call."""
    n = c.counters.status_count
    assert wait_until(lambda: c.counters.status_count > n, 10.0)
    return _status(c)


class Flood:
    """4 threads of the viewer's own session sending what a viewer may send, as fast as the
    replies come, at the lowest priority (they stand for another machine)."""

    def __init__(self, env: dict[str, Any]) -> None:
        self.env = env
        self.counts = {"answered": 0, "refused_budget": 0, "refused": 0, "no_answer": 0}
        self.other: list[str] = []
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.threads: list[threading.Thread] = []

    def __enter__(self) -> Flood:
        ready = threading.Barrier(5)
        self._ready = ready

        def work(c: ControllerClient, t: int) -> None:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
            asks = [c.get_config, lambda: c.history(1000), c.knowledge,
                    lambda: c.lease("status"), c.identify_status,
                    lambda: c.apply(LoopConfig(q_cutoff_hz=0.7))]
            ready.wait()
            i = t
            while not self.stop.is_set():
                i += 1
                try:
                    r = asks[i % len(asks)]()
                    ok = getattr(r, "accepted", getattr(r, "ok", True))
                    key = "answered" if ok else "refused"
                except ControllerUnavailable as exc:
                    text = str(exc)
                    if REFUSAL in text:
                        key = "refused_budget"
                    elif "no reply" in text:
                        key = "no_answer"
                    else:
                        with self.lock:
                            self.other.append(text)
                        continue
                with self.lock:
                    self.counts[key] += 1

        self._stack = contextlib.ExitStack()
        c = self._stack.enter_context(_client(self.env["auth"], self.env["proc"], "view"))
        for t in range(4):
            th = threading.Thread(target=work, args=(c, t), daemon=True)
            th.start()
            self.threads.append(th)
        ready.wait()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        for th in self.threads:
            th.join(30.0)
        self._stack.close()


def _estop_applied(watch: ControllerClient) -> int:
    """Put an e-stop (the public key's scope of `watch`) and wait until a status shows it."""
    before = _status(watch).estop_seq
    watch.put_estop()
    assert wait_until(lambda: watch.status is not None and watch.status.estop_seq != before,
                      15.0), "e-stop not applied during the flood"
    assert watch.status is not None and watch.status.mode == "estop"
    return watch.status.estop_seq


def test_a_viewers_flood_is_refused_by_budget_and_the_estop_goes_through(
    env: dict[str, Any],
) -> None:
    auth, proc = env["auth"], env["proc"]
    with _client(auth, proc, "watch") as watch, _client(auth, proc, "op1") as op1:
        assert op1.lease("acquire", 600.0).ok
        st0 = _status(watch)
        with Flood(env) as flood:
            # The flood is under way once the viewer's budget refuses it.
            assert wait_until(lambda: flood.counts["refused_budget"] > 0, 60.0), flood.counts
            deadline = time.monotonic() + 4.0
            seqs = [_estop_applied(watch)]
            # Another user is served meanwhile: the viewer's budget is its own.
            assert op1.get_config().version >= 1
            # And so is another session of the flooding viewer: one session may use only its
            # share of its user's budget, and the flood's refused requests take none of it.
            with _client(auth, proc, "view") as view2:
                assert view2.get_config().version >= 1
            # A reset, then at once an e-stop (not waiting for the reset's reply): the
            # e-stop, sent last, wins, whichever process each reached first.
            reset_msg = proto.Command(body=proto.ResetFault(estop_seq=seqs[-1]),
                                      client="op1", lease=op1.lease_token)
            replies = op1.session.get(op1.key(proto.key_command(RIG)),
                                      payload=proto.encode(reset_msg), timeout=10.0)
            watch.put_estop()
            got = [r for r in replies if r.ok is not None]
            assert got, "no reply to the reset"
            reset = proto.decode(got[0].ok.payload.to_bytes(), proto.CommandReply)
            assert wait_until(lambda: watch.status is not None
                              and watch.status.estop_seq > seqs[-1], 15.0)
            st = _fresh_status(watch)
            assert st.mode == "estop", (reset, st.mode)
            seqs.append(st.estop_seq)
            while time.monotonic() < deadline:
                seqs.append(_estop_applied(watch))
            assert not flood.other, flood.other[:3]
        st1 = _fresh_status(watch)
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs), seqs
        assert flood.counts["refused_budget"] > 0 and flood.counts["answered"] > 0, flood.counts
        # The loop kept running through it all.
        assert st1.timing.ticks - st0.timing.ticks > 1000, (st0.timing, st1.timing)
        assert st1.mode == "estop"
        # Reported and audited, as counts per user, never one record per refusal.
        assert wait_until(lambda: any("request budget" in n and "view" in n
                                      for n in (watch.status.notes if watch.status else [])),
                          10.0), watch.status
        reset = op1.reset(st1.estop_seq)
        assert reset.ok, reset
        assert op1.command(proto.Start()).ok
        op1.lease("release")

    def budget_records() -> list[dict[str, Any]]:
        path = proc.state_dir / "audit.jsonl"
        lines = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
        return [r for r in lines if r["action"] == "request.budget"]

    refused = flood.counts["refused_budget"]
    assert wait_until(lambda: sum(r["count"] for r in budget_records()) >= refused, 15.0), (
        budget_records()[-3:], flood.counts)
    records = budget_records()
    assert {r["user"] for r in records} == {"view"} and all(r["outcome"] == "refused"
                                                            for r in records)
    # Every refusal the viewer was told of, and at most those it waited out besides.
    assert refused <= sum(r["count"] for r in records) <= refused + flood.counts["no_answer"]
    assert len(records) < refused


def _edge_pid(proc: ControllerProcess, pattern: str = r"edge process (\d+) serving") -> int:
    found: list[int] = []

    def logged() -> bool:
        found[:] = [int(p) for p in re.findall(pattern, proc.log())]
        return bool(found)

    assert wait_until(logged, 180.0), proc.log()[-2000:]  # a start at load 20+: a minute
    return found[-1]


RELAY = r"e-stop relay process (\d+) relaying"


def test_a_killed_edge_process_is_started_again_and_the_loop_runs_on(
    env: dict[str, Any],
) -> None:
    auth, proc = env["auth"], env["proc"]
    edge = _edge_pid(proc)
    assert edge in children(proc.proc.pid)
    with _client(auth, proc, "watch") as watch:
        st0 = _status(watch)
        os.kill(edge, signal.SIGKILL)
        assert wait_until(lambda: gone(edge), 10.0)
        # The e-stops are the relay's: the edge's death does not touch them.
        first = _estop_applied(watch)
        assert wait_until(lambda: _edge_pid(proc) != edge, 60.0), proc.log()[-2000:]
        assert wait_until(lambda: _answers(auth, proc), 60.0, poll_s=0.5)
        assert _estop_applied(watch) > first
        st1 = _fresh_status(watch)
        assert st1.mode == "estop" and st1.timing.ticks > st0.timing.ticks
        assert any("edge process ended" in n for n in st1.notes), st1.notes


def test_a_killed_estop_relay_leaves_the_estop_to_the_fallback_and_is_started_again(
    env: dict[str, Any],
) -> None:
    auth, proc = env["auth"], env["proc"]
    relay = _edge_pid(proc, RELAY)
    assert relay in children(proc.proc.pid) and relay != _edge_pid(proc)
    with _client(auth, proc, "watch") as watch:
        os.kill(relay, signal.SIGKILL)
        assert wait_until(lambda: gone(relay), 10.0)
        # With the relay dead the loop process's own subscriber (the fallback) takes it.
        first = _estop_applied(watch)
        assert wait_until(lambda: _edge_pid(proc, RELAY) != relay, 60.0), proc.log()[-2000:]
        # And the new relay, once it relays (its pid logged once it does).
        assert _estop_applied(watch) > first
        st1 = _fresh_status(watch)
        assert any("e-stop relay process ended" in n for n in st1.notes), st1.notes
        assert _answers(auth, proc)  # requests were never the relay's


def test_the_edge_process_ends_with_the_controller(tmp_path: Path) -> None:
    proc = start_controller(tmp_path / "state", rig="edge-orphan")
    try:
        with Client(proc.endpoint, proc.rig) as c:
            c.wait_ready(proc, 180.0)
        edge, relay = _edge_pid(proc), _edge_pid(proc, RELAY)
        assert {edge, relay} <= set(children(proc.proc.pid))
        proc.proc.send_signal(signal.SIGKILL)
        proc.proc.wait(30)
        assert wait_until(lambda: gone(edge), 30.0), "the edge process outlived its controller"
        assert wait_until(lambda: gone(relay), 30.0), "the relay outlived its controller"
    finally:
        proc.stop()
