"""Issue 31 item 2: an oversized payload is refused by the transport before it is assembled.

Before: a 200 MB query was assembled whole by Zenoh (its default limit is 1 GiB) before the
controller's 64 KiB request limit refused it; four of them took the controller to 1.34 GB and
left it at 1.2 GB. Now every session of the project (controller/client/session.py) drops a
message over MAX_MESSAGE_BYTES while its fragments arrive. The figures before and after:
tests/bench/bench_oversized.py.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import zenoh
from procs import Client, start_controller, wait_until

from controller import protocol as proto
from controller.client.session import MAX_MESSAGE_BYTES

pytestmark = pytest.mark.integration


def _memory_mb(pid: int) -> dict[str, float]:
    out: dict[str, float] = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0]) / 1024
    return out


def test_oversized_query_and_estop_put_are_dropped_and_the_controller_serves_on(
    tmp_path: Path,
) -> None:
    proc = start_controller(tmp_path / "state", rig="oversized")
    try:
        with Client(proc.endpoint, proc.rig) as client:
            client.wait_ready(proc)
            edges: list[int] = []
            assert wait_until(lambda: edges.extend(
                int(p) for p in re.findall(r"edge process (\d+) serving", proc.log())) or edges,
                30.0), proc.log()[-2000:]
            pids = {"loop": proc.proc.pid, "edge": edges[-1]}
            before = {name: _memory_mb(pid) for name, pid in pids.items()}
            st0 = client.fresh_status()
            # The attacker's own session with Zenoh's defaults (a client configures what it
            # likes): 128 MB, eight times the limit, on the config key and the e-stop key.
            conf = zenoh.Config()
            conf.insert_json5("mode", '"peer"')
            conf.insert_json5("scouting/multicast/enabled", "false")
            conf.insert_json5("connect/endpoints", json.dumps([proc.endpoint]))
            big = b"\xa5" * (8 * MAX_MESSAGE_BYTES)
            with zenoh.open(conf) as attacker:
                replies = list(attacker.get(proto.key_config(proc.rig), payload=big,
                                            timeout=5.0))
                attacker.put(proto.key_estop(proc.rig), big)
                # A small query from the same session, after both: when it is answered the
                # controller has read past them on that link.
                small = [r for r in attacker.get(proto.key_config(proc.rig), timeout=10.0)
                         if r.ok is not None]
            del big
            after = {name: _memory_mb(pid) for name, pid in pids.items()}
            # Still serving: a config GET and a fresh status, and the oversized put never
            # reached the e-stop subscriber (it was not assembled).
            assert client.get_config().accepted is not False
            st1 = client.fresh_status()
    finally:
        proc.stop()
    assert [r for r in replies if r.ok is not None] == []
    assert len(small) == 1
    assert proto.decode(small[0].ok.payload.to_bytes(), proto.ConfigReply).version >= 1
    assert (st1.mode, st1.estop_seq) == (st0.mode, st0.estop_seq)
    # Neither process ever held the message: the peak grew by far less than its 128 MB
    # (before: by the whole message, for each one in flight).
    for name in pids:
        grown = after[name]["VmHWM"] - before[name]["VmRSS"]
        assert grown < 64, (name, before[name], after[name])
