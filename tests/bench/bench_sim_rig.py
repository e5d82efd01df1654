"""Benchmark of the simulated rig (a script, not a test): `python tests/bench/bench_sim_rig.py`.

Prints the kernel's first-call and fresh-compile times, plant-only stepping speed for 30 s
simulated (30000 ticks), the same command sequence through python-control's linear M(s)P(s)
(batch `forced_response`, `input_output_response`, and a per-tick discrete state-space step in
numpy, which is what a closed loop could use), and the closed 30 s sine test with ServoLoop.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

TICKS = 30_000
PERIOD_S = 1e-3
REPEATS = 3


def _best_of(fn: Callable[[], object], repeats: int = REPEATS) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _line(name: str, wall_s: float, ref_wall_s: float | None = None) -> None:
    sim_s = TICKS * PERIOD_S
    extra = "" if ref_wall_s is None else f"   {wall_s / ref_wall_s:7.1f}x the rig's wall time"
    print(
        f"  {name:<44} {wall_s * 1e3:9.1f} ms  {sim_s / wall_s:9.0f} sim s/wall s"
        f"  {wall_s / TICKS * 1e6:8.2f} us/tick{extra}"
    )


def main() -> None:
    t0 = time.perf_counter()
    import numba

    import controller.sim.sim_rig as sim_rig
    from controller.sim.sim_rig import SimRig

    t_import = time.perf_counter() - t0
    t0 = time.perf_counter()
    rig = SimRig()
    rig.step(0.0)
    t_first = time.perf_counter() - t0
    fresh = numba.njit(cache=False)(sim_rig.advance_tick.py_func)
    x, p = np.zeros_like(rig._x), rig._p.copy()
    sim_rig._reset_kernel(x, p, 0.0, 0.0)
    t0 = time.perf_counter()
    fresh(x, p, 0.0, 0.0, 0.0)
    t_compile = time.perf_counter() - t0
    print(f"import {t_import:.2f} s; first SimRig + step (compile or cache load) {t_first:.2f} s;")
    print(f"fresh compile of the tick kernel, no cache: {t_compile:.2f} s")

    k = np.arange(TICKS)
    u = 20.0 + 2.0 * np.sin(2 * math.pi * 1.0 * k * PERIOD_S)  # deg/s, one-way motion
    u_list = u.tolist()

    def plant_only() -> None:
        rig.reset()
        step = rig.step
        for c in u_list:
            step(c)

    def plant_read_step() -> None:
        rig.reset()
        for c in u_list:
            rig.read()
            rig.step(c)

    print(f"\n{TICKS} ticks = {TICKS * PERIOD_S:.0f} s simulated, best of {REPEATS}:")
    wall_rig = _best_of(plant_only)
    _line("SimRig.step (nonlinear, 10 kHz sub-steps)", wall_rig)
    _line("SimRig.read + step", _best_of(plant_read_step), wall_rig)

    from controller.sim.rig_disturbances import rig_setup

    every = SimRig(rig_setup(["article-rig"]).params)  # every motor-side effect on

    def plant_every_effect() -> None:
        every.reset()
        step = every.step
        for c in u_list:
            step(c)

    _line("SimRig.step, article-rig (every effect on)", _best_of(plant_every_effect), wall_rig)

    import control as ct

    m = ct.tf([1.0], [1.013e-05, 0.004501, 1.0])
    pl = ct.tf([1.013e-05, 0.004501, 1.0], [0.0005169, 0.03215, 1.0])
    mp = ct.ss(ct.minreal(m * pl, verbose=False))
    t = k * PERIOD_S
    _line(
        "control.forced_response M P (batch, open loop)",
        _best_of(lambda: ct.forced_response(mp, t, u)),
        wall_rig,
    )
    _line(
        "control.input_output_response M P",
        _best_of(lambda: ct.input_output_response(mp, t, u), repeats=1),
        wall_rig,
    )
    mpd = ct.c2d(mp, PERIOD_S, method="zoh")
    a, b, c, d = (np.asarray(v, dtype=float) for v in (mpd.A, mpd.B, mpd.C, mpd.D))

    def numpy_per_tick() -> None:
        xs = np.zeros((a.shape[0], 1))
        for uk in u_list:
            _ = float((c @ xs)[0, 0] + d[0, 0] * uk)
            xs = a @ xs + b * uk

    _line("numpy discrete M P, stepped per tick", _best_of(numpy_per_tick), wall_rig)

    try:
        from controller.core.config import LoopConfig
        from controller.core.loop import LoopCoefficients, ServoLoop
        from controller.core.trajectory import Trajectory
    except ImportError as exc:  # the loop lives in another module; the rig bench stands alone
        print(f"\nclosed loop skipped: {exc}")
        return
    print("\nclosed loop, article sine 5 sin(0.5 t) deg, 30 s, ServoLoop + SimRig:")
    for dob_on, ff_on in ((False, False), (True, False), (True, True)):
        loop = ServoLoop(LoopCoefficients.build(LoopConfig(dob_on=dob_on, ff_on=ff_on)))
        traj = Trajectory()
        rig.reset()
        err = np.empty(TICKS)
        t0 = time.perf_counter()
        for i in range(TICKS):
            ref, ref_rate = traj.at(i * PERIOD_S)
            pos, w = rig.read()
            err[i] = ref - pos
            rig.step(loop.tick(ref, ref_rate, pos, w))
        wall = time.perf_counter() - t0
        e = err[5000:]
        print(
            f"  dob={dob_on!s:<5} ff={ff_on!s:<5} {TICKS * PERIOD_S / wall:6.0f}x real time;"
            f"  after 5 s: peak |e| {np.max(np.abs(e)):.4f} deg, RMSE {np.sqrt(np.mean(e**2)):.4f}"
        )


if __name__ == "__main__":
    main()
