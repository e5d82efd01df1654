"""Benchmark: the state stream of a real controller process, seen by a separate Zenoh peer.

    .venv/bin/python tests/bench/bench_state_stream.py [--duration S] [--realtime]

Prints the loss (samples missing by sequence number) and the latency from the loop sample
(tick start, on the controller's clock; same machine) to this process's subscriber
callback: per sample (includes waiting for its batch of 20 to fill, up to 19 ms) and per
batch (from the batch's last sample: the transport alone).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: helpers, for procs
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))

from procs import Client, start_controller


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--duration", type=float, default=30.0, help="seconds (default 30)")
    p.add_argument("--realtime", action="store_true", help="controller with SCHED_FIFO")
    a = p.parse_args()
    extra = ("--realtime-priority",) if a.realtime else ()
    with tempfile.TemporaryDirectory(prefix="dobtune-bench-") as d:
        proc = start_controller(Path(d) / "state", extra_args=extra)
        try:
            with Client(proc.endpoint, proc.rig) as c:
                c.wait_ready(proc)
                with c.state() as col:
                    t_end = time.monotonic() + a.duration
                    while time.monotonic() < t_end:
                        time.sleep(0.2)
                st = c.fresh_status()
        finally:
            proc.stop()
    batches = col.batches()
    if not batches:
        print("no state received")
        return 1
    first = batches[0][1].seq0
    expected = first
    missing = 0
    per_sample: list[float] = []
    per_batch: list[float] = []
    for recv_s, b in batches:
        if b.seq0 > expected:
            missing += b.seq0 - expected
        expected = b.seq0 + len(b.t_s)
        per_sample += [recv_s - (b.epoch_s + t) for t in b.t_s]
        per_batch.append(recv_s - (b.epoch_s + b.t_s[-1]))
    total = expected - first
    ms = np.asarray(per_sample) * 1e3
    mb = np.asarray(per_batch) * 1e3
    print(
        f"state stream {a.duration:.0f} s: {total} samples in {len(batches)} batches, "
        f"missing {missing} ({100.0 * missing / max(total, 1):.3f} %); controller dropped "
        f"{st.timing.dropped_samples}, overruns {st.timing.overruns}/{st.timing.ticks}"
    )
    print(
        f"latency per sample p50 {np.percentile(ms, 50):.2f} ms, p99 "
        f"{np.percentile(ms, 99):.2f} ms, max {ms.max():.2f} ms; per batch (last sample) p50 "
        f"{np.percentile(mb, 50):.2f} ms, p99 {np.percentile(mb, 99):.2f} ms, max "
        f"{mb.max():.2f} ms"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
