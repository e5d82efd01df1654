"""Benchmark: apply round trip (get with a candidate -> reply) against a real controller.

    .venv/bin/python tests/bench/bench_apply_roundtrip.py [--n N] [--realtime]

Each accepted apply runs the stability analysis in the controller, saves the configuration
(fsync), waits for the loop's tick boundary and logs the change. Also measured: a rejected
candidate (analysis only), a plain GET, and the loop's overruns during the whole run.
Target: apply p99 <= 50 ms.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))

from procs import Client, start_controller

from controller.core.config import LoopConfig


def _timed(n: int, fn: Callable[[int], bool]) -> np.ndarray:
    out = np.zeros(n)
    for i in range(n):
        t0 = time.perf_counter()
        ok = fn(i)
        out[i] = (time.perf_counter() - t0) * 1e3
        if not ok:
            raise SystemExit(f"unexpected reply at {i}")
    return out


def _fmt(name: str, ms: np.ndarray) -> str:
    return (
        f"{name:9s} n={len(ms)}: p50 {np.percentile(ms, 50):.1f} ms, p99 "
        f"{np.percentile(ms, 99):.1f} ms, max {ms.max():.1f} ms"
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--n", type=int, default=200, help="requests per kind (default 200)")
    p.add_argument("--realtime", action="store_true", help="controller with SCHED_FIFO")
    a = p.parse_args()
    extra = ("--realtime-priority",) if a.realtime else ()
    good = [LoopConfig(q_cutoff_hz=0.5 + 0.01 * (i % 40)) for i in range(41)]
    bad = LoopConfig(cv_kp=20.0)
    with tempfile.TemporaryDirectory(prefix="dobtune-bench-") as d:
        proc = start_controller(Path(d) / "state", extra_args=extra)
        try:
            with Client(proc.endpoint, proc.rig) as c:
                c.wait_ready(proc)
                for _ in range(5):  # warm up both sides
                    c.get_config()
                st0 = c.fresh_status()
                apply_ms = _timed(a.n, lambda i: c.apply(good[(i + 1) % 41]).accepted)
                reject_ms = _timed(a.n, lambda i: not c.apply(bad).accepted)
                get_ms = _timed(a.n, lambda i: c.get_config().accepted)
                st1 = c.fresh_status()
        finally:
            proc.stop()
    print(_fmt("apply", apply_ms) + ("  (target p99 <= 50 ms)"))
    print(_fmt("rejected", reject_ms))
    print(_fmt("get", get_ms))
    d_ticks = st1.timing.ticks - st0.timing.ticks
    d_over = st1.timing.overruns - st0.timing.overruns
    print(f"loop overruns during the run: {d_over} / {d_ticks} ticks")
    return 0


if __name__ == "__main__":
    sys.exit(main())
