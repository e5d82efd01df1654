"""Benchmark: e-stop latency, from a Zenoh put on `dobtune/<rig>/estop` to the first tick that
commands 0, against a real controller (simulated rig). Prints figures; not a test.

    .venv/bin/python tests/bench/bench_estop.py [--n N] [--busy]

Each trial: the loop runs (reset + start), the client notes the wall time and puts the e-stop;
the state stream gives the wall time of the first sample in mode estop with command 0
(epoch_s + t_s: the tick's own clock, same machine). `--busy` keeps the command worker busy
with a stream of Stop/Start commands meanwhile (the e-stop must not wait behind them).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: helpers, for procs
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))

from procs import Client, start_controller, wait_until

from controller import protocol as proto


def _first_estop_tick_wall_s(client: Client, col: object, after_seq: int) -> float | None:
    samples = col.samples()  # type: ignore[attr-defined]
    for seq in sorted(s for s in samples if s > after_seq):
        s = samples[seq]
        if s["mode"] == "estop" and s["command_deg_s"] == 0.0:
            return float(s["wall_s"])
    return None


def start_running(client: Client, col: Any) -> int:
    """Reset and start the loop; returns the last sequence number the state stream `col` holds
    once it holds any."""
    client.reset()
    client.command(proto.Start())
    assert wait_until(lambda: col.last_seq() >= 0, 5.0)
    return int(col.last_seq())


def estop_tick_wall_s(client: Client, col: Any, after_seq: int, timeout_s: float,
                      trial: str) -> float:
    """The wall time of the first tick after `after_seq` in mode estop with command 0, waited
    for up to `timeout_s`; exits naming `trial` when none comes."""
    found: list[float] = []

    def seen() -> bool:
        w = _first_estop_tick_wall_s(client, col, after_seq)
        if w is not None:
            found.append(w)
        return bool(found)

    if not wait_until(seen, timeout_s, poll_s=0.005):
        raise SystemExit(f"{trial}: no e-stop tick seen")
    return found[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--busy", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        proc = start_controller(Path(tmp) / "state", rig="bench-estop")
        try:
            with Client(proc.endpoint, proc.rig) as client:
                client.wait_ready(proc)
                stop_busy = threading.Event()
                busy_count = [0]

                def busy() -> None:
                    with Client(proc.endpoint, proc.rig) as other:
                        while not stop_busy.is_set():
                            other.command(proto.Stop())
                            other.command(proto.Start())
                            busy_count[0] += 2

                if args.busy:
                    threading.Thread(target=busy, daemon=True).start()
                lat_ms = []
                with client.state() as col:
                    for i in range(args.n):
                        seq_before = start_running(client, col)
                        time.sleep(0.02)  # a few ticks in mode running
                        t_put = time.time()
                        client.put_estop()
                        t_tick = estop_tick_wall_s(client, col, seq_before, 5.0, f"trial {i}")
                        lat_ms.append((t_tick - t_put) * 1e3)
                        col.clear()
                stop_busy.set()
        finally:
            proc.stop()
    a = np.asarray(lat_ms)
    busy_text = f", command worker busy: {busy_count[0]} commands" if args.busy else ""
    print(
        f"e-stop latency, Zenoh put -> first tick with command 0 ({args.n} trials"
        f"{busy_text}): "
        f"p50 {np.percentile(a, 50):.2f} ms, p99 {np.percentile(a, 99):.2f} ms, "
        f"max {a.max():.2f} ms, min {a.min():.2f} ms"
    )


if __name__ == "__main__":
    main()
