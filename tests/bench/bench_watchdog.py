"""Benchmark: the watchdog's per-tick `step()` against the control tick it rides on, and the
simulated rig's step with and without injected faults. Prints figures; not a test.

    .venv/bin/python tests/bench/bench_watchdog.py [--ticks N]

Per-call figures are timed one call at a time with perf_counter_ns (as bench_tick.py does; the
timer's own cost, printed first, is included in every figure); the batch figure is a loop of N
calls divided by N (no timer inside).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.watchdog import Watchdog
from controller.sim.sim_rig import RigFaults, SimRig


def _percentiles_ns(samples_ns: list[int]) -> tuple[float, float, float]:
    a = np.sort(np.asarray(samples_ns, float))
    return float(a[len(a) // 2]), float(a[int(len(a) * 0.99)]), float(a[-1])


def _per_call(fn: Callable[[int], object], n: int) -> tuple[float, float, float]:
    pc = time.perf_counter_ns
    out = [0] * n
    for k in range(n):
        t0 = pc()
        fn(k)
        out[k] = pc() - t0
    return _percentiles_ns(out)


def _batch_ns(fn: Callable[[int], object], n: int) -> float:
    t0 = time.perf_counter_ns()
    for k in range(n):
        fn(k)
    return (time.perf_counter_ns() - t0) / n


def _line(label: str, fig: tuple[float, float, float], batch: float) -> None:
    p50, p99, mx = fig
    print(
        f"{label:<44s} p50 {p50:7.0f} ns  p99 {p99:7.0f} ns  max {mx / 1e3:6.1f} us"
        f"  batch {batch:7.0f} ns"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--ticks", type=int, default=200_000)
    n = ap.parse_args().ticks
    rng = np.random.default_rng(0)
    # A realistic input: the article's command (2.5 deg/s at 0.08 Hz) plus a small oscillation
    # and noise, below every threshold, so every detector runs its no-trip path.
    k = np.arange(n)
    u = (
        2.5 * np.cos(0.5e-3 * k)
        + 0.8 * np.sin(2 * np.pi * 9e-3 * k)
        + 0.05 * rng.standard_normal(n)
    ).tolist()
    e = (0.05 * np.sin(0.5e-3 * k)).tolist()
    pos = rng.standard_normal(n).tolist()
    spd = rng.standard_normal(n).tolist()

    empty = _per_call(lambda i: None, n)
    print(f"timer + call overhead (empty lambda): p50 {empty[0]:.0f} ns  p99 {empty[1]:.0f} ns")

    wd = Watchdog()
    wd_step = wd.step
    fig_wd = _per_call(lambda i: wd_step(u[i], e[i]), n)
    wd.reset()
    batch_wd = _batch_ns(lambda i: wd_step(u[i], e[i]), n)
    assert wd.code == 0, wd.trip

    loop = ServoLoop(LoopCoefficients.build(LoopConfig()))
    tick = loop.tick
    fig_tick = _per_call(lambda i: tick(1.0, 0.5, pos[i], spd[i]), n)
    batch_tick = _batch_ns(lambda i: tick(1.0, 0.5, pos[i], spd[i]), n)

    loop2 = ServoLoop(LoopCoefficients.build(LoopConfig()))
    wd2 = Watchdog()
    tick2, wd2_step = loop2.tick, wd2.step

    def both(i: int) -> int:
        return wd2_step(tick2(1.0, 0.5, pos[i], spd[i]), e[i])

    fig_both = _per_call(both, n)
    wd2.reset()
    loop2.reset()
    batch_both = _batch_ns(both, n)

    _line("watchdog.step (all detectors)", fig_wd, batch_wd)
    _line("loop.tick (pos PI + Cv + DOB)", fig_tick, batch_tick)
    _line("loop.tick + watchdog.step", fig_both, batch_both)
    print(
        f"-> the watchdog adds {fig_wd[0] / fig_tick[0] * 100:.0f} % to the tick at p50 "
        f"({batch_wd / batch_tick * 100:.0f} % in batch); {batch_wd / 1e3:.2f} us of the "
        f"1000 us period"
    )

    m = min(n, 50_000)
    cmd = (20.0 + 2.0 * np.sin(2 * np.pi * 1e-3 * np.arange(m))).tolist()
    for label, faults in (
        ("rig.step, no fault", RigFaults()),
        ("rig.step, gain + backlash + 15 Hz mode", RigFaults(1.5, 0.1, 15.0)),
    ):
        rig = SimRig()
        rig.set_faults(faults)

        def rig_step(i: int, step: Callable[[float], None] = rig.step) -> None:
            step(cmd[i])

        _batch_ns(rig_step, m)  # warm-up: numba cache load, faults taken over
        rig.reset()
        fig = _per_call(rig_step, m)
        rig.reset()
        _line(label, fig, _batch_ns(rig_step, m))


if __name__ == "__main__":
    main()
