"""The transport's message size limit (issue 31 item 2): set in every session the project
opens, large enough for every legitimate message, and enforced by Zenoh before a message is
assembled (two real sessions on loopback; the controller's own case is in
tests/integration/test_oversized.py)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from helpers import free_port

from controller import protocol as proto
from controller.auth import init_auth_dir, new_users
from controller.client.session import (
    MAX_MESSAGE_BYTES,
    SessionOptions,
    client_config,
    server_config,
    session_config,
)
from controller.core.config import LoopConfig
from controller.core.verdict import Verdict, VerdictMargins
from controller.process.history import MAX_LAST


def _limit(conf: object) -> int:
    return int(json.loads(conf.get_json("transport/link/rx/max_message_size")))  # type: ignore[attr-defined]


def test_every_kind_of_session_refuses_oversized_messages(tmp_path: Path) -> None:
    auth = tmp_path / "auth"
    init_auth_dir(auth, new_users([("op", "operator"), ("ctl", "controller")], ("r",)))
    confs = {
        "controller": session_config(SessionOptions(listen=("tcp/127.0.0.1:7001",))),
        "client": session_config(SessionOptions(connect=("tcp/127.0.0.1:7001",))),
        "router": session_config(SessionOptions(listen=("tcp/127.0.0.1:7001",), mode="router")),
        "auth controller": server_config(auth, ["r"], listen=["tcp/127.0.0.1:7001"]),
        "auth router": server_config(auth, ["r"], listen=["tcp/127.0.0.1:7001"], mode="router"),
        "auth client": client_config(auth, "op", ["tcp/127.0.0.1:7001"]),
        "controller behind a router": client_config(auth, "ctl", ["tcp/127.0.0.1:7001"],
                                                    mode="client"),
    }
    for name, conf in confs.items():
        assert _limit(conf) == MAX_MESSAGE_BYTES, name
    assert MAX_MESSAGE_BYTES < 1 << 30  # Zenoh's default, which assembled 200 MB queries


def test_the_largest_legitimate_message_fits() -> None:
    """A history reply of the most entries a request may ask for, each with a verdict far
    wordier than the gate writes (24 reasons of 300 characters), fits with room to spare;
    a request fits the controller's own 64 KiB limit by far."""
    verdict = Verdict(
        verdict="reject", rejections=tuple("r" * 300 for _ in range(12)),
        cautions=tuple("c" * 300 for _ in range(12)), margins=VerdictMargins.unknown(),
        knowledge="k" * 300,
    )
    entry = proto.HistoryEntry(version=2**53 - 1, time_s=1.7e9, client="c" * 100,
                               config=LoopConfig(), verdict=verdict)
    size = len(proto.encode(proto.HistoryReply(ok=True, entries=[entry] * MAX_LAST)))
    assert 4_000_000 < size < MAX_MESSAGE_BYTES / 1.5


_RECEIVER = textwrap.dedent("""
    import sys
    from controller.client.session import SessionOptions, connect
    got = []
    def hwm_mb():
        with open("/proc/self/status") as f:
            return [int(l.split()[1]) for l in f if l.startswith("VmHWM")][0] // 1024
    def on_query(q):
        n = len(q.payload.to_bytes()) if q.payload is not None else 0
        got.append(n)
        q.reply(q.key_expr, str(n).encode())
    def on_put(s):
        got.append(len(s.payload.to_bytes()))
    with connect(SessionOptions(listen=(sys.argv[1],))) as s:
        qa = s.declare_queryable("limits/q", on_query)
        sb = s.declare_subscriber("limits/p", on_put)
        print("ready", hwm_mb(), flush=True)
        sys.stdin.readline()
        print(" ".join(map(str, got)), "|", hwm_mb(), flush=True)
""")


@pytest.mark.slow
def test_an_oversized_message_is_dropped_before_assembly_and_the_session_serves_on() -> None:
    """A session opened by `connect` receives a message 8 times the limit (a query, then a
    put) from a peer with Zenoh's defaults: neither reaches it, its peak memory grows by far
    less than the message's size, and it answers the next small query."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    receiver = subprocess.Popen(
        [sys.executable, "-c", _RECEIVER, endpoint], stdin=subprocess.PIPE,
        stdout=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[1],
    )
    try:
        assert receiver.stdout is not None and receiver.stdin is not None
        word, _, hwm_before = receiver.stdout.readline().partition(" ")
        assert word == "ready"
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        big = b"x" * (8 * MAX_MESSAGE_BYTES)
        with zenoh.open(conf) as s:
            # Wait until the receiver's queryable is reachable (a small query answered).
            for _ in range(100):
                if any(r.ok is not None for r in s.get("limits/q", payload=b"hi", timeout=1)):
                    break
            else:
                pytest.fail("the receiver's queryable never answered")
            big_replies = list(s.get("limits/q", payload=big, timeout=5))
            s.put("limits/p", big)
            small = [r.ok.payload.to_bytes() for r in s.get("limits/q", payload=b"after",
                                                              timeout=10) if r.ok is not None]
        receiver.stdin.write("\n")
        receiver.stdin.flush()
        sizes_text, _, hwm_text = receiver.stdout.readline().partition("|")
        sizes = [int(x) for x in sizes_text.split()]
        assert [r for r in big_replies if r.ok is not None] == []
        assert small == [b"5"]
        assert len(big) not in sizes and sizes[-1] == 5 and max(sizes) < MAX_MESSAGE_BYTES
        # The message was never whole in the receiver: its peak grew by far less than its size
        # (Zenoh's default limit: by more than the whole message).
        assert int(hwm_text) - int(hwm_before) < len(big) / 2**20 / 2, (hwm_before, hwm_text)
    finally:
        receiver.kill()
        receiver.wait()
