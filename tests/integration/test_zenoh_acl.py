"""controller.auth on real Zenoh sessions (loopback, explicit free ports, no scouting).

A fake controller opens a session with `server_config` and serves rigs a and b the way the real
one does (publishers on state/status, queryables on config/cmd/identify, subscribers on estop,
each also in the every-user form `dobtune/<rig>/@user/*/...`), plus "trap" subscribers on keys
nobody may write. Clients then try everything adversarially. A denied message is dropped
silently, so every negative check is bracketed by a positive one on the same path that proves
the window was long enough: a denied get runs in the same batch as an allowed one, a denied put
is followed by an allowed put (same session, delivered in order), a denied subscription waits
while an allowed one receives. No sleeps: every wait polls a condition until a deadline.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh
from procs import free_port, wait_until

from controller import protocol as proto
from controller.auth import (
    any_user_key,
    init_auth_dir,
    new_users,
    user_key,
    user_of_key,
)
from controller.client.session import client_config, server_config, zenoh_config

pytestmark = pytest.mark.integration

RIGS = ("a", "b")
WAIT_S = 10.0  # deadline of every positive wait (loaded CI machines)
GET_S = 2.0  # timeout of the gets of one batch
FROM_CONTROLLER = b"from-controller"


def reads(rig: str) -> tuple[str, ...]:
    return proto.key_config(rig), proto.key_identify(rig), proto.key_state_replay(rig)


def queryable_keys(rig: str) -> tuple[str, ...]:
    public = (proto.key_config(rig), proto.key_command(rig), proto.key_identify(rig),
              proto.key_state_replay(rig))
    return public + tuple(any_user_key(k) for k in public)


def trap_keys(rig: str) -> tuple[str, ...]:
    """Keys with a subscriber that no user may put on (only the controller publishes there;
    requests are queries)."""
    return (proto.key_command(rig), proto.key_config(rig), proto.key_state(rig),
            proto.key_status(rig), proto.key_identify(rig))


class FakeController:
    """A session serving RIGS like the controller; one thread of ours serves the queries."""

    def __init__(self, conf: zenoh.Config) -> None:
        self._stack = contextlib.ExitStack()
        self.session = self._stack.enter_context(zenoh.open(conf))
        self.arrived: list[tuple[str, bytes]] = []  # (sample key, payload) of client puts
        self._lock = threading.Lock()
        self._stop = threading.Event()
        s = self.session
        self._queryables = [
            (k, s.declare_queryable(k, zenoh.handlers.FifoChannel(64)))
            for rig in RIGS for k in queryable_keys(rig)
        ]
        estops = [k for rig in RIGS for k in (proto.key_estop(rig),
                                               any_user_key(proto.key_estop(rig)))]
        self._subs = [s.declare_subscriber(k, zenoh.handlers.FifoChannel(256))
                      for k in estops + [k for rig in RIGS for k in trap_keys(rig)]]
        self.publishers = {k: s.declare_publisher(k) for rig in RIGS
                           for k in (proto.key_state(rig), proto.key_status(rig))}
        self.extra: list[Any] = []  # what a test declares on the session besides
        self._thread = threading.Thread(target=self._serve, name="fake-controller", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            busy = False
            for declared, q in self._queryables:
                query = q.try_recv()
                if query is not None:
                    busy = True
                    who = user_of_key(query.key_expr) or ""
                    query.reply(query.key_expr, f"{declared}|{who}".encode())
                    query.drop()
            for sub in self._subs:
                sample = sub.try_recv()
                if sample is not None:
                    busy = True
                    data = sample.payload.to_bytes()
                    if not data.startswith(FROM_CONTROLLER):  # its own state/status puts
                        with self._lock:
                            self.arrived.append((str(sample.key_expr), data))
            if not busy:
                self._stop.wait(0.002)

    def puts_from(self, tag: str) -> list[str]:
        """The keys on which payloads tagged `tag` arrived."""
        with self._lock:
            return [k for k, data in self.arrived if data.decode(errors="replace").startswith(tag)]

    def publish(self, key: str) -> None:
        self.publishers[key].put(FROM_CONTROLLER)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        for _, q in self._queryables:
            q.undeclare()
        for e in self.extra:
            e.undeclare()
        self._stack.close()


@dataclass
class Net:
    auth_dir: Path
    endpoint: str
    controller: FakeController
    stack: contextlib.ExitStack = field(default_factory=contextlib.ExitStack)

    def open(self, conf: zenoh.Config) -> Any:
        return self.stack.enter_context(zenoh.open(conf))

    def login(self, user: str, password: str | None = None) -> Any:
        creds: Path | str = self.auth_dir if password is None else password
        # peer mode: wrong credentials open a session that reaches nothing (what is tested);
        # in client mode (the default of dobtune's clients) opening itself fails, see below.
        return self.open(client_config(creds, user, [self.endpoint], mode="peer"))


def get_all(session: Any, keys: list[str]) -> dict[str, list[str]]:
    """Every key's replies ("<queryable>|<attributed user>"); the gets run concurrently."""
    pending = [(k, session.get(k, timeout=GET_S)) for k in keys]
    out: dict[str, list[str]] = {}
    for k, replies in pending:
        out[k] = [r.ok.payload.to_string() if r.ok is not None else "error" for r in replies]
    return out


def received(sub: Any) -> list[str]:
    out = []
    while (sample := sub.try_recv()) is not None:
        out.append(str(sample.key_expr))
    return out


def ready(session: Any, key: str) -> Any:
    """`session` once a get on `key` is answered (the controller's declarations arrived)."""

    def answered() -> bool:
        return any(r.ok is not None for r in session.get(key, timeout=0.5))

    assert wait_until(answered, WAIT_S), f"no reply on {key}"
    return session


def deliver(net: Net, session: Any, key: str, tag: str) -> None:
    """Put `tag` on `key` until it arrives: everything the session put before has arrived too
    (one transport, one priority: delivered in order)."""

    def arrived() -> bool:
        session.put(key, tag.encode())
        return key in net.controller.puts_from(tag)

    assert wait_until(arrived, WAIT_S, poll_s=0.05), f"{tag} never arrived on {key}"


def only_its_estop_arrives(net: Net, session: Any, user: str, forbidden: list[str]) -> None:
    """`session`, logged in as `user` of rig a, puts on each `forbidden` key and on rig a's
    e-stop in its own scope: once a later put on the public e-stop key has arrived, the e-stop in
    its scope has arrived, attributed to `user`, and nothing put on a forbidden key has."""
    for k in forbidden:
        session.put(k, f"{user}-forbidden".encode())
    session.put(user_key(proto.key_estop("a"), user), f"{user}-own".encode())
    deliver(net, session, proto.key_estop("a"), f"{user}-estop")
    assert net.controller.puts_from(f"{user}-own") == [user_key(proto.key_estop("a"), user)]
    assert net.controller.puts_from(f"{user}-forbidden") == []


@pytest.fixture
def net(tmp_path: Path) -> Iterator[Net]:
    users = new_users([("op_a", "operator"), ("view_a", "viewer")], ("a",))
    users += new_users([("op_b", "operator")], ("b",))
    users += new_users([("ctl", "controller")])
    init_auth_dir(tmp_path / "auth", users)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = server_config(tmp_path / "auth", RIGS, listen=[endpoint])
    controller = FakeController(conf)
    n = Net(tmp_path / "auth", endpoint, controller)
    try:
        yield n
    finally:
        n.stack.close()
        controller.close()


def all_keys() -> list[str]:
    return [*(k for rig in RIGS for k in queryable_keys(rig)),
            "dobtune/**", "dobtune/*/cmd", "dobtune/a/**"]


@pytest.mark.parametrize(
    "login",
    [
        pytest.param(lambda n: n.open(zenoh_config((), [n.endpoint])), id="anonymous"),
        pytest.param(lambda n: n.login("view_a", "not-the-password"), id="wrong-password"),
        pytest.param(lambda n: n.login("mallory", "whatever-password"), id="unknown-user"),
    ],
)
def test_without_valid_credentials_nothing_is_reached(
    net: Net, login: Callable[[Net], Any]
) -> None:
    intruder = login(net)
    viewer = ready(net.login("view_a"), proto.key_config("a"))  # the control
    assert list(viewer.info.peers_zid()), "the control session did not connect"
    assert list(intruder.info.peers_zid()) == []

    got = get_all(intruder, all_keys())
    assert get_all(viewer, [proto.key_config("a")])[proto.key_config("a")], "control get failed"
    assert all(not r for r in got.values()), got

    spy = intruder.declare_subscriber(proto.key_state("a"), zenoh.handlers.FifoChannel(64))
    control = viewer.declare_subscriber(proto.key_state("a"), zenoh.handlers.FifoChannel(64))
    seen: list[str] = []

    def control_got_three() -> bool:
        net.controller.publish(proto.key_state("a"))
        seen.extend(received(control))
        return len(seen) >= 3

    assert wait_until(control_got_three, WAIT_S)
    assert received(spy) == []

    intruder.put(proto.key_estop("a"), b"intruder")
    deliver(net, viewer, proto.key_estop("a"), "viewer-marker")
    assert net.controller.puts_from("intruder") == []


def test_a_client_with_wrong_credentials_does_not_open(net: Net) -> None:
    """dobtune's clients log in in client mode: refused credentials fail at once, with Zenoh's
    error (in peer mode the session would open and reach nothing, silently)."""
    with pytest.raises(zenoh.ZError):
        zenoh.open(client_config("not-the-password", "view_a", [net.endpoint],
                                 fail_after_s=2.0))
    ok = zenoh.open(client_config(net.auth_dir, "view_a", [net.endpoint], fail_after_s=5.0))
    ok.close()


def test_viewer_watches_reads_and_estops_only_its_rig(net: Net) -> None:
    viewer = ready(net.login("view_a"), proto.key_config("a"))
    mine = {k: user_key(k, "view_a") for k in reads("a")}
    allowed = [*reads("a"), *mine.values()]
    denied = [
        proto.key_command("a"),
        user_key(proto.key_command("a"), "view_a"),
        *[user_key(k, "op_a") for k in (*reads("a"), proto.key_command("a"))],  # impersonation
        *queryable_keys("b"),
        user_key(proto.key_config("b"), "view_a"),
        any_user_key(proto.key_config("a")),
        "dobtune/**", "dobtune/*/cmd", "dobtune/*/config", "dobtune/a/**", "dobtune/a/*",
    ]
    got = get_all(viewer, allowed + denied)
    for k in reads("a"):
        assert got[k] == [f"{k}|"], k
        assert got[mine[k]] == [f"{any_user_key(k)}|view_a"], mine[k]
    assert {k: got[k] for k in denied} == {k: [] for k in denied}

    # Subscriptions: its rig's state and status arrive; rig b's never, not even through a
    # wildcard subscription (the fleet overview subscribes to dobtune/*/...: the router's
    # egress rules pass on this rig's samples only). A second session holds the wildcards.
    wild = ready(net.login("view_a"), proto.key_config("a"))
    wild_keys = ("dobtune/**", "dobtune/a/*", "dobtune/*/state")
    subs = {(viewer, k): viewer.declare_subscriber(k, zenoh.handlers.FifoChannel(256)) for k in (
        proto.key_state("a"), proto.key_status("a"), proto.key_state("b"), proto.key_status("b"),
    )}
    subs |= {(wild, k): wild.declare_subscriber(k, zenoh.handlers.FifoChannel(256))
             for k in wild_keys}
    seen: dict[str, list[str]] = {k: [] for _, k in subs}

    def own_streams_arrived() -> bool:
        for k in (proto.key_state("b"), proto.key_status("b"), proto.key_state("a"),
                  proto.key_status("a")):
            net.controller.publish(k)
        for (_, k), sub in subs.items():
            seen[k] += received(sub)
        return len(seen[proto.key_state("a")]) >= 3 and len(seen[proto.key_status("a")]) >= 3

    assert wait_until(own_streams_arrived, WAIT_S), seen
    for k in (proto.key_state("b"), proto.key_status("b")):
        assert seen[k] == [], k
    own = {proto.key_state("a"), proto.key_status("a")}
    for k in wild_keys:
        assert set(seen[k]) <= own, k

    # Puts: only the e-stop arrives (public and in its own scope, attributed).
    forbidden = [*trap_keys("a"), proto.key_estop("b"), "dobtune/*/estop", "dobtune/**",
                 "dobtune/a/*", user_key(proto.key_estop("a"), "op_a"),
                 user_key(proto.key_estop("b"), "view_a")]
    only_its_estop_arrives(net, viewer, "view_a", forbidden)


def test_operator_does_everything_on_its_rig_as_itself_only(net: Net) -> None:
    op = ready(net.login("op_a"), proto.key_config("a"))
    allowed = [
        *[k for k in queryable_keys("a") if "@user" not in k],
        *[user_key(k, "op_a") for k in (*reads("a"), proto.key_command("a"))],
    ]
    denied = [
        *[user_key(k, "view_a") for k in (*reads("a"), proto.key_command("a"))],  # impersonation
        *queryable_keys("b"),
        user_key(proto.key_command("b"), "op_a"),
        any_user_key(proto.key_command("a")),
        "dobtune/**", "dobtune/*/cmd",
    ]
    got = get_all(op, [*allowed, "dobtune/a/**", *denied])
    for k in allowed:
        who = user_of_key(k) or ""
        declared = any_user_key(k.replace("/@user/op_a", "")) if who else k
        assert got[k] == [f"{declared}|{who}"], k
    # A wildcard within its rig reaches the rig's public queryables, never a user's scope.
    assert got["dobtune/a/**"], "no reply to dobtune/a/**"
    assert all(r.endswith("|") and "@user" not in r for r in got["dobtune/a/**"])
    assert {k: got[k] for k in denied} == {k: [] for k in denied}

    state_b = op.declare_subscriber(proto.key_state("b"), zenoh.handlers.FifoChannel(64))
    state_a = op.declare_subscriber(proto.key_state("a"), zenoh.handlers.FifoChannel(64))
    seen: list[str] = []

    def got_three() -> bool:
        net.controller.publish(proto.key_state("b"))
        net.controller.publish(proto.key_state("a"))
        seen.extend(received(state_a))
        return len(seen) >= 3

    assert wait_until(got_three, WAIT_S)
    assert received(state_b) == []

    # Puts: the e-stop only. Its own rig's published keys (state, status) and request keys
    # are the controller's: an operator's fake Status never reaches anyone (issue 24 item 3).
    forbidden = [proto.key_estop("b"), *trap_keys("b"), *trap_keys("a"),
                 user_key(proto.key_estop("a"), "view_a")]
    only_its_estop_arrives(net, op, "op_a", forbidden)


def test_through_a_router_the_same_rules_hold(net: Net) -> None:
    """A router with server_config(mode="router"); the controller connects with its account,
    everyone in client mode."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    net.open(server_config(net.auth_dir, RIGS, listen=[endpoint], mode="router"))
    served = FakeController(client_config(net.auth_dir, "ctl", [endpoint], mode="client"))
    try:
        config_a, cmd_a, cmd_b = (proto.key_config("a"), proto.key_command("a"),
                                  proto.key_command("b"))
        viewer = ready(net.open(client_config(net.auth_dir, "view_a", [endpoint], mode="client")),
                       config_a)
        op = ready(net.open(client_config(net.auth_dir, "op_b", [endpoint], mode="client")),
                   proto.key_config("b"))
        got = get_all(viewer, [config_a, cmd_a, cmd_b, "dobtune/**"])
        assert got == {config_a: [f"{config_a}|"], cmd_a: [], cmd_b: [], "dobtune/**": []}
        mine = user_key(cmd_b, "op_b")
        got = get_all(op, [cmd_b, mine, cmd_a])
        assert got == {cmd_b: [f"{cmd_b}|"], mine: [f"{any_user_key(cmd_b)}|op_b"], cmd_a: []}
        # The fleet overview's liveliness: each user sees the rigs it may reach, no other.
        ctl = net.open(client_config(net.auth_dir, "ctl", [endpoint], mode="client"))
        tokens = [ctl.liveliness().declare_token(proto.key_alive(r)) for r in ("a", "b")]

        def alive(session: Any) -> set[str]:
            return {str(r.ok.key_expr) for r in session.liveliness().get(
                "dobtune/*/alive", timeout=GET_S) if r.ok is not None}

        assert wait_until(lambda: alive(viewer) == {proto.key_alive("a")}, WAIT_S)
        assert wait_until(lambda: alive(op) == {proto.key_alive("b")}, WAIT_S)
        for t in tokens:
            t.undeclare()
    finally:
        served.close()


def test_through_a_router_a_viewer_receives_and_reads_the_watchs_drift(net: Net) -> None:
    """The watch (a controller account behind the router, as `dobtune watch --auth DIR --user
    ctl` logs in) publishes each rig's drift state, its drift alarms and the prediction checks,
    and answers for them. A viewer of rig a receives and reads rig a's (the fleet's drift
    column, the dashboard's alarm board, `ctl drift`, `ctl wait-alarm`, `ctl prediction`),
    also through the fleet overview's `dobtune/*/drift`, never rig b's; it cannot publish a
    drift state or an alarm of its own (only the watch's reach a subscriber)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    net.open(server_config(net.auth_dir, RIGS, listen=[endpoint], mode="router"))
    served = FakeController(client_config(net.auth_dir, "ctl", [endpoint], mode="client"))
    try:
        watched = {r: (proto.key_drift(r), proto.key_drift_alarm(r), proto.key_prediction(r))
                   for r in RIGS}
        s = served.session

        def answer(query: Any) -> None:
            query.reply(query.key_expr, b"from-watch")

        for r in RIGS:
            for k in watched[r]:
                served.publishers[k] = s.declare_publisher(k)
                served.extra.append(s.declare_queryable(k, zenoh.handlers.Callback(answer)))
        forged = s.declare_subscriber(proto.key_drift_alarm("a"),
                                      zenoh.handlers.FifoChannel(64))
        viewer = ready(net.open(client_config(net.auth_dir, "view_a", [endpoint],
                                              mode="client")), proto.key_config("a"))

        def read_all_of_a() -> bool:
            got = get_all(viewer, list(watched["a"]))
            return all(v == ["from-watch"] for v in got.values())

        assert wait_until(read_all_of_a, WAIT_S), get_all(viewer, list(watched["a"]))
        got = get_all(viewer, [*watched["a"], *watched["b"]])
        assert {k: got[k] for k in watched["b"]} == {k: [] for k in watched["b"]}

        fleet = "dobtune/*/drift"
        subs = {k: viewer.declare_subscriber(k, zenoh.handlers.FifoChannel(256))
                for k in (*watched["a"], *watched["b"], fleet)}
        seen: dict[str, list[str]] = {k: [] for k in subs}

        def a_arrived() -> bool:
            for r in ("b", "a"):
                for k in watched[r]:
                    served.publish(k)
            for k, sub in subs.items():
                seen[k] += received(sub)
            return all(len(seen[k]) >= 3 for k in (*watched["a"], fleet))

        assert wait_until(a_arrived, WAIT_S), {k: len(v) for k, v in seen.items()}
        assert {k: seen[k] for k in watched["b"]} == {k: [] for k in watched["b"]}
        assert set(seen[fleet]) == {proto.key_drift("a")}

        # A viewer's own drift alarm is dropped; its e-stop, put after it, arrives.
        viewer.put(proto.key_drift_alarm("a"), b"view_a-forged")
        deliver(Net(net.auth_dir, endpoint, served), viewer, proto.key_estop("a"),
                "view_a-estop")
        payloads = []
        while (sample := forged.try_recv()) is not None:
            payloads.append(sample.payload.to_bytes())
        assert payloads and b"view_a-forged" not in payloads  # the watch's own did arrive
    finally:
        served.close()
