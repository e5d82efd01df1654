"""Benchmark: one control tick (position loop + Cv + DOB, no plant), the tick that swaps in new
coefficients, and the closed-loop simulator speed. Prints figures; not a test.

    .venv/bin/python tests/bench/bench_tick.py [--ticks N]

Baseline in the same process: the same filters run per sample through scipy.signal.sosfilt
with carried state (what a numpy-per-sample implementation costs), as a ratio.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import signal

from controller.core.command_filter import CommandFilter
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.sim.experiment import run_experiment


def _percentiles_us(samples_ns: list[int]) -> tuple[float, float, float]:
    a = np.sort(np.asarray(samples_ns, float)) / 1e3
    return float(a[len(a) // 2]), float(a[int(len(a) * 0.99)]), float(a[-1])


def bench_tick(n: int, cfg: LoopConfig | None = None) -> tuple[float, float, float]:
    loop = ServoLoop(LoopCoefficients.build(cfg if cfg is not None else LoopConfig()))
    rng = np.random.default_rng(0)
    pos = rng.standard_normal(n).tolist()
    spd = rng.standard_normal(n).tolist()
    tick = loop.tick
    pc = time.perf_counter_ns
    out = [0] * n
    for k in range(n):
        t0 = pc()
        tick(1.0, 0.5, pos[k], spd[k])
        out[k] = pc() - t0
    return _percentiles_us(out)


def bench_swap_tick(n: int, between: int = 5) -> tuple[float, float, float]:
    """The tick that performs a coefficient swap (Q31 0.5 Hz <-> 1 Hz, gains changed): the
    request is made before the timed tick, as the runtime does (in the requesting thread)."""
    a = LoopCoefficients.build(LoopConfig(), 1)
    b = LoopCoefficients.build(LoopConfig(q_cutoff_hz=1.0, cv_kp=0.6), 2)
    loop = ServoLoop(a)
    tick = loop.tick
    pc = time.perf_counter_ns
    out = [0] * n
    for k in range(n):
        for j in range(between):
            tick(1.0, 0.5, 0.01 * j, 0.1)
        loop.request(b if k % 2 == 0 else a)
        t0 = pc()
        tick(1.0, 0.5, 0.0, 0.1)
        out[k] = pc() - t0
    return _percentiles_us(out)


def bench_numpy_baseline(n: int) -> tuple[float, float, float]:
    dob = LoopCoefficients.build(LoopConfig()).dob
    # scipy's sosfilt refuses read-only buffers (the design cache shares read-only filters)
    f1_sos, f2_sos = np.array(dob.f1_sos), np.array(dob.f2_sos)
    z1 = np.zeros((f1_sos.shape[0], 2))
    z2 = np.zeros((f2_sos.shape[0], 2))
    x = np.zeros(1)
    pc = time.perf_counter_ns
    out = [0] * n
    for k in range(n):
        t0 = pc()
        x[0] = 0.1 * k
        y1, z1 = signal.sosfilt(f1_sos, x, zi=z1)
        y2, z2 = signal.sosfilt(f2_sos, x, zi=z2)
        _ = float(y1[0] - y2[0])
        out[k] = pc() - t0
    return _percentiles_us(out)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--ticks", type=int, default=200_000)
    args = ap.parse_args()
    p50, p99, mx = bench_tick(args.ticks)
    print(
        f"tick (pos PI + Cv + DOB): p50 {p50:.2f} us  p99 {p99:.2f} us  max {mx:.1f} us"
        f"  (target p99 <= 15 us)"
    )
    # The speed-command filter (issue 35): off (the default) and on, alternated in rounds so
    # that both see the same load.
    on_cfg = LoopConfig(command_filter=CommandFilter(kind="notch", notch_hz=31.0))
    rounds = 5
    res: dict[str, list[tuple[float, float, float]]] = {"off": [], "notch": []}
    for _ in range(rounds):
        res["off"].append(bench_tick(args.ticks // rounds))
        res["notch"].append(bench_tick(args.ticks // rounds, on_cfg))
    for label, rs in res.items():
        m50 = float(np.median([r[0] for r in rs]))
        m99 = float(np.median([r[1] for r in rs]))
        print(f"tick, command filter {label}: p50 {m50:.2f} us  p99 {m99:.2f} us "
              f"(median over {rounds} alternated rounds of {args.ticks // rounds} ticks)")
    s50, s99, smx = bench_swap_tick(min(args.ticks, 20_000))
    print(f"tick that swaps coefficients: p50 {s50:.2f} us  p99 {s99:.2f} us  max {smx:.1f} us")
    b50, b99, _ = bench_numpy_baseline(min(args.ticks, 50_000))
    print(
        f"baseline, DOB filters only via scipy sosfilt per sample: p50 {b50:.2f} us "
        f"p99 {b99:.2f} us -> the scalar tick is {b50 / p50:.1f}x faster at p50"
    )
    run_experiment(LoopConfig(), Trajectory(), 1.0, settle_s=0.0)  # numba cache load
    for label, cfg in (("no DOB", LoopConfig(dob_on=False)), ("DOB", LoopConfig())):
        t0 = time.perf_counter()
        run_experiment(cfg, Trajectory(), 30.0)
        wall = time.perf_counter() - t0
        print(
            f"closed loop 30 s sine ({label}): {wall:.3f} s wall -> {30.0 / wall:.0f}x real "
            f"time (target >= 200x)"
        )


if __name__ == "__main__":
    main()
