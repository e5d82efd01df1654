"""Benchmark: a controller's memory under oversized payloads (issue 31 item 2).

    .venv/bin/python tests/bench/bench_oversized.py [--mb 200] [--queries 4] [--tree DIR]

One controller on the simulated rig (no authentication: loopback). An attacker's own Zenoh
session (Zenoh's defaults, not the project's: a client may configure what it likes) sends
`--queries` queries of `--mb` MB each on the config key, then one put of that size on the
e-stop key. Printed for the controller's loop process and its edge process (which answers the
queries): VmRSS before, VmHWM (peak) and VmRSS after, from /proc/<pid>/status; then whether
the controller still answers a config GET and publishes its status, and whether the oversized
e-stop put latched it.

`--tree DIR` runs the controller of another source tree (e.g. `git archive <commit> | tar -x
-C DIR`: the code before the transport limit); the attacker is the same.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: helpers
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))  # procs

from procs import Client, start_controller, wait_until

from controller import protocol as proto


def memory_mb(pid: int) -> dict[str, float]:
    """VmRSS and VmHWM of a process, in MB."""
    out: dict[str, float] = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0]) / 1024
    return out


def edge_pid(log: str) -> int | None:
    found = re.findall(r"edge process (\d+) serving", log)
    return int(found[-1]) if found else None


def attacker(endpoint: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(conf)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mb", type=int, default=200)
    ap.add_argument("--queries", type=int, default=4)
    ap.add_argument("--tree", type=Path, default=None)
    args = ap.parse_args()
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        proc = start_controller(Path(tmp) / "state", rig="oversized", tree=args.tree)
        try:
            with Client(proc.endpoint, proc.rig) as client:
                client.wait_ready(proc)
                wait_until(lambda: edge_pid(proc.log()) is not None, 30.0)
                pids = {"loop process": proc.proc.pid}
                edge = edge_pid(proc.log())
                if edge is not None:
                    pids["edge process"] = edge
                st = client.fresh_status()
                before = {name: memory_mb(pid) for name, pid in pids.items()}
                payload = b"\xa5" * (args.mb * 1_000_000)
                answered = 0
                t0 = time.monotonic()
                with attacker(proc.endpoint) as s:
                    for _ in range(args.queries):
                        replies = list(s.get(proto.key_config(proc.rig), payload=payload,
                                             timeout=30.0))
                        answered += sum(1 for r in replies if r.ok is not None)
                    s.put(proto.key_estop(proc.rig), payload)
                    del payload
                    # The put is sent when it returns; give the controller its chance to
                    # latch on it: wait for a status that says so, or 5 s of statuses.
                    wait_until(lambda: client.fresh_status().mode == "estop", 5.0)
                attack_s = time.monotonic() - t0
                after = {name: memory_mb(pid) for name, pid in pids.items()}
                served = client.get_config().version
                st_after = client.fresh_status()
        finally:
            proc.stop()
    print(f"controller tree: {args.tree or 'this one'}; {args.queries} queries of {args.mb} MB "
          f"on the config key, then a {args.mb} MB e-stop put ({attack_s:.1f} s)")
    print(f"{'process':<14} {'RSS before':>11} {'peak after':>11} {'RSS after':>10}")
    for name in pids:
        b, a = before[name], after[name]
        print(f"{name:<14} {b['VmRSS']:>8.0f} MB {a['VmHWM']:>8.0f} MB {a['VmRSS']:>7.0f} MB")
    print(f"oversized queries answered: {answered} of {args.queries}")
    print(f"afterwards: config GET answered (version {served}); status mode "
          f"{st.mode} -> {st_after.mode} (estop_seq {st.estop_seq} -> {st_after.estop_seq})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
