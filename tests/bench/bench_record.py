"""Recording cost: MCAP write throughput against the loop's 1 kHz, file size per hour, and the
loop's timing with and without a recording running.

    .venv/bin/python tests/bench/bench_record.py [--live-s 60]

1. Synthetic: 60 s of StateBatches (1 kHz, batches of 20) written with `Recorder`:
   messages per second and bytes per sample -> MB per hour.
2. Live (with --live-s > 0): a simulated controller process; its Status timing (period p99,
   overruns) for 10 s without, then during a `dobtune record` of --live-s seconds, and the
   recording's sample count and gaps.
"""

from __future__ import annotations

import argparse
import io
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))

from controller import protocol as proto
from controller.recording.mcap_io import Recorder, read_recording


def synthetic(seconds: float = 60.0) -> None:
    n = round(seconds * 1000)
    batches = []
    for seq0 in range(0, n, 20):
        t = np.arange(seq0, seq0 + 20) / 1000.0
        cols = [t, 5 * np.sin(0.5 * t), 5 * np.sin(0.5 * t) + 1e-3, np.cos(t), np.cos(t),
                np.cos(t), 0.01 * t, 1e-3 * np.ones(20)]
        batches.append(proto.state_batch(rig="b", seq0=seq0, rate_hz=1000.0, config_version=1,
                                         columns=[c.tolist() for c in cols], epoch_s=1.7e9,
                                         mode="running"))
    buf = io.BytesIO()
    t0 = time.perf_counter()
    with Recorder(buf) as r:
        for b in batches:
            r.state(b)
    dt = time.perf_counter() - t0
    size = len(buf.getvalue())
    print(f"synthetic: {n} samples in {dt:.2f} s = {n / dt:,.0f} messages/s "
          f"({n / dt / 1000:.1f}x the loop's 1 kHz); {size / n:.1f} B/sample -> "
          f"{size / seconds * 3600 / 1e6:.0f} MB per hour")


def live(seconds: float) -> None:
    from procs import Client, free_port, start_controller

    with tempfile.TemporaryDirectory() as d:
        proc = start_controller(Path(d) / "state", port=free_port())
        try:
            with Client(proc.endpoint, proc.rig) as c:
                c.wait_ready(proc)

                def timing(s: float) -> tuple[float, int]:
                    p99, over0 = [], c.fresh_status().timing.overruns
                    end = time.monotonic() + s
                    while time.monotonic() < end:
                        st = c.fresh_status()
                        p99.append(st.timing.period_p99_us)
                    return statistics.median(p99), st.timing.overruns - over0

                base = timing(10.0)
                out = Path(d) / "live.mcap"
                cmd = [sys.executable, "-c", "from server.__main__ import dobtune_main; "
                       "import sys; sys.exit(dobtune_main(sys.argv[1:]))", "record",
                       "--connect", proc.endpoint, "--rig-name", proc.rig, "--out", str(out),
                       "--duration", str(seconds)]
                r = subprocess.Popen(cmd)
                time.sleep(2.0)
                during = timing(min(10.0, seconds - 3.0))
                r.wait(timeout=seconds + 60)
            got = read_recording(out)
            seq = got.state["seq"]
            print(f"live: loop period p99 {base[0]:.0f} us without, {during[0]:.0f} us with a "
                  f"recording; overruns {base[1]} / {during[1]} in 10 s; recorded {got.n} "
                  f"samples in {seconds:g} s, {int(np.sum(np.diff(seq) - 1))} lost; "
                  f"{out.stat().st_size / got.n:.1f} B/sample")
        finally:
            proc.stop()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--live-s", type=float, default=0.0)
    a = ap.parse_args()
    synthetic()
    if a.live_s > 0:
        live(a.live_s)

