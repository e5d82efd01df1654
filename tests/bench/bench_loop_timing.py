"""Benchmark: the 1 kHz loop's timing, idle and with one core busy. Prints figures.

    .venv/bin/python tests/bench/bench_loop_timing.py [--duration S] [--realtime]
        [--no-publish] [--only idle|busy]

Runs the real runtime (ServoLoop + simulated rig in lockstep) with its state publisher
putting every batch on a Zenoh session (loopback, nobody subscribed), as in the controller
process. "busy": a child process spins on one core for the whole run. Jitter is the tick
start's deviation from the nominal period; an overrun is a tick that ended after the next
deadline.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import threading
import time

import numpy as np

from controller import protocol as proto
from controller.client.session import SessionOptions, connect
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.process.runtime import Runtime, RuntimeOptions, try_realtime_priority
from controller.sim.sim_rig import SimRig


def run(duration_s: float, realtime: bool, publish: bool) -> dict[str, float]:
    cfg = LoopConfig()
    rt = Runtime(
        ServoLoop(LoopCoefficients.build(cfg, 1)),
        SimRig(rate_hz=cfg.rate_hz),
        options=RuntimeOptions(timing_capacity=1 << 22),
    )
    stop = threading.Event()
    with connect(SessionOptions()) as session:
        pub = session.declare_publisher(proto.key_state("bench"))

        def sink(seq0: int, version: int, mode: str, cols: list[list[float]]) -> None:
            if publish:
                msg = proto.state_batch(
                    rig="bench",
                    seq0=seq0,
                    rate_hz=1000.0,
                    config_version=version,
                    columns=cols,
                    epoch_s=rt.epoch_s,
                    mode=mode,
                )
                pub.put(proto.encode(msg))

        th = threading.Thread(target=rt.publisher, args=(sink, stop), daemon=True)
        th.start()
        note = try_realtime_priority() if realtime else "normal priority"
        rt.run(max_ticks=int(duration_s * cfg.rate_hz))
        stop.set()
        th.join()
        pub.undeclare()
    period_us, compute_us = rt.timing_history()
    jitter = np.abs(period_us - 1e6 / cfg.rate_hz)
    return {
        "note": note,  # type: ignore[dict-item]
        "ticks": rt.ticks,
        "jitter_p50_us": float(np.percentile(jitter, 50)),
        "jitter_p99_us": float(np.percentile(jitter, 99)),
        "jitter_max_us": float(jitter.max()),
        "compute_p50_us": float(np.percentile(compute_us, 50)),
        "compute_p99_us": float(np.percentile(compute_us, 99)),
        "overruns": rt.overruns,
        "overrun_rate": rt.overruns / max(rt.ticks, 1),
        "skipped_ticks": rt.skipped_ticks,
        "dropped_samples": rt.dropped_samples,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--duration", type=float, default=60.0, help="seconds per case (default 60)")
    p.add_argument("--realtime", action="store_true", help="SCHED_FIFO if permitted")
    p.add_argument("--no-publish", action="store_true", help="do not encode/put batches")
    p.add_argument("--only", choices=("idle", "busy"), default=None)
    a = p.parse_args()
    sys.setswitchinterval(0.0002)
    cases = [a.only] if a.only else ["idle", "busy"]
    for case in cases:
        hog = None
        if case == "busy":
            hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
            time.sleep(0.5)
        try:
            r = run(a.duration, a.realtime, not a.no_publish)
        finally:
            if hog is not None:
                hog.kill()
                hog.wait()
        print(
            f"{case:5s} {a.duration:.0f} s ({r['note']}): period jitter p50 "
            f"{r['jitter_p50_us']:.1f} us, p99 {r['jitter_p99_us']:.1f} us, max "
            f"{r['jitter_max_us']:.0f} us; compute p50 {r['compute_p50_us']:.1f} us, p99 "
            f"{r['compute_p99_us']:.1f} us; overruns {r['overruns']} / {r['ticks']} "
            f"({100 * r['overrun_rate']:.3f} %), skipped {r['skipped_ticks']}, "
            f"dropped samples {r['dropped_samples']}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
