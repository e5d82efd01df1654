"""Benchmark of the compiled offline loop (a script, not a test; issue 23 item 3).

    .venv/bin/python tests/bench/bench_offline_loop.py [--users] [--before REV] [--paper]

Prints, in one run:
- numba's one-off start in a fresh process (registries + the rig's cached kernel), the offline
  kernel's cache load after it, and a fresh compile of the offline kernel (no cache);
- the article's sine (5 sin(0.5 t) deg, 30 s) on the reference rig, DOB off / on / on + FF:
  the Python tick (`ServoLoop.tick` + `SimRig.step`, as before) and the compiled loop
  (`controller.sim.offline.run_ticks`), x real time, best of 3, and that they agree bit for bit;
- with --users: the offline users timed in subprocesses on this tree and on REV (git archive;
  default the commit before the compiled loop): the nonlinear check (best of 5 after a first
  run), Suggest (the dashboard's settings), the autotune (its defaults, sine, with the
  nonlinear check), and with --paper `dobtune paper` (quick and full).
The machine's load is printed with each part.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

TICKS = 30_000
REPEATS = 3
BEFORE_REV = "6c210a4~1"


def _load() -> str:
    return "load " + " ".join(f"{x:.1f}" for x in os.getloadavg())


def _fresh_process_start() -> str:
    code = textwrap.dedent("""
        import time
        t0 = time.perf_counter()
        from controller.core.config import LoopConfig
        from controller.core.loop import LoopCoefficients, ServoLoop
        from controller.core.trajectory import Trajectory
        from controller.sim import offline
        from controller.sim.sim_rig import SimRig
        t1 = time.perf_counter()
        rig = SimRig()
        t2 = time.perf_counter()
        offline.run_ticks(ServoLoop(LoopCoefficients.build(LoopConfig())), rig, Trajectory(), 1)
        t3 = time.perf_counter()
        hit = bool(offline._kernel.stats.cache_hits)
        print(f"imports {t1 - t0:.2f} s; numba start + the rig's cached kernel {t2 - t1:.2f} s;"
              f" offline kernel {'cache load' if hit else 'COMPILE (no cache)'} {t3 - t2:.2f} s")
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       cwd=ROOT, check=True)
    return r.stdout.strip()


def compile_figures() -> None:
    import numba

    from controller.sim import offline

    print(f"fresh process: {_fresh_process_start()}  ({_load()})")
    fresh = numba.njit(cache=False)(offline._kernel.py_func)
    from controller.core.config import LoopConfig
    from controller.core.loop import LoopCoefficients, ServoLoop
    from controller.core.trajectory import Trajectory
    from controller.sim.sim_rig import SimRig

    loop = ServoLoop(LoopCoefficients.build(LoopConfig()))
    rig = SimRig()
    saved = offline._kernel
    offline._kernel = fresh
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        offline.run_ticks(loop, rig, Trajectory(), 1)
        t_compile, c_compile = time.perf_counter() - t0, time.process_time() - c0
    finally:
        offline._kernel = saved
    print(f"fresh compile of the offline kernel (no cache; the rig's functions compiled in): "
          f"{t_compile:.2f} s, {c_compile:.2f} s CPU  ({_load()})")


def _python_sine(loop: object, rig: object, n: int, ts: float) -> np.ndarray:
    from controller.core.trajectory import Trajectory

    traj = Trajectory()
    at, tick, read, step = traj.at, loop.tick, rig.read, rig.step  # type: ignore[attr-defined]
    out = np.empty((6, n))
    for k in range(n):
        r, rr = at(k * ts)
        p, w = read()
        u = tick(r, rr, p, w)
        step(u)
        out[0, k] = r
        out[1, k] = p
        out[2, k] = w
        out[3, k] = loop.speed_ref_deg_s  # type: ignore[attr-defined]
        out[4, k] = u
        out[5, k] = loop.d_hat  # type: ignore[attr-defined]
    return out


def closed_loop() -> None:
    from controller.core.config import LoopConfig
    from controller.core.loop import LoopCoefficients, ServoLoop
    from controller.core.trajectory import Trajectory
    from controller.sim.offline import run_ticks
    from controller.sim.sim_rig import SimRig

    ts = 1e-3
    print(f"\narticle sine 5 sin(0.5 t) deg, {TICKS * ts:.0f} s, reference rig, best of "
          f"{REPEATS} ({_load()}):")
    print("  x real time by the wall clock (and per CPU second of this process: what a free core")
    print("  would give; the load shares the two cores)")
    print(f"  {'':<14} {'Python tick':>20} {'compiled':>20} {'speed-up':>9}  bit for bit")
    for dob_on, ff_on in ((False, False), (True, False), (True, True)):
        cfg = LoopConfig(dob_on=dob_on, ff_on=ff_on)
        walls, cpus = [], []
        outs = []
        for compiled in (False, True):
            best = best_cpu = math.inf
            for _ in range(REPEATS):
                loop = ServoLoop(LoopCoefficients.build(cfg))
                rig = SimRig(initial_position_deg=0.0)
                t0, c0 = time.perf_counter(), time.process_time()
                if compiled:
                    out = run_ticks(loop, rig, Trajectory(), TICKS, period_s=ts).out
                else:
                    out = _python_sine(loop, rig, TICKS, ts)
                best = min(best, time.perf_counter() - t0)
                best_cpu = min(best_cpu, time.process_time() - c0)
            walls.append(best)
            cpus.append(best_cpu)
            outs.append(out)
        same = all(np.array_equal(a, b) for a, b in zip(outs[0], outs[1], strict=True))
        label = f"DOB {'on' if dob_on else 'off'}{' + FF' if ff_on else ''}"
        sim = TICKS * ts
        print(f"  {label:<14} {sim / walls[0]:>7.0f}x ({sim / cpus[0]:>5.0f}x cpu)"
              f" {sim / walls[1]:>7.0f}x ({sim / cpus[1]:>5.0f}x cpu)"
              f" {walls[0] / walls[1]:>8.1f}x  {same}")


USERS = textwrap.dedent("""
    import sys, time
    from controller.core.config import LoopConfig
    from controller.core.trajectory import default_trajectory
    from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
    from controller.sim.nonlinear_check import findings, nonlinear_check
    from controller.tune.autotune import autotune
    from server.suggest import suggest
    def clock():
        return time.perf_counter(), time.process_time()
    def since(t):
        return f"{time.perf_counter() - t[0]:.2f} s ({time.process_time() - t[1]:.2f} s CPU)"
    t = clock(); nonlinear_check(LoopConfig()); first = since(t)
    best = min(nonlinear_check(LoopConfig()).run_time_s for _ in range(5))
    print(f"nonlinear check {best * 1e3:.0f} ms best of 5 (first in the process {first})")
    plant = PlantKnowledge(bound=COMMISSIONING_BOUND, source="simulated rig model")
    t = clock(); suggest(LoopConfig(), plant, default_trajectory("sine"))
    print(f"Suggest {since(t)}")
    t = clock(); autotune(LoopConfig(), plant, default_trajectory("sine"), nonlinear=findings)
    print(f"autotune {since(t)}")
    if "paper" in sys.argv:
        from controller.sim.paper import Options, run_paper
        for quick in (True, False):
            t = clock(); run_paper(Options(quick=quick))
            print(f"paper {'--quick' if quick else 'full'} {since(t)}")
""")


def _users(tree: Path, paper: bool) -> list[str]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    args = [sys.executable, "-c", USERS] + (["paper"] if paper else [])
    subprocess.run([*args[:2], "import controller.sim.sim_rig"], env=env, cwd=tree, check=True)
    r = subprocess.run(args, capture_output=True, text=True, env=env, cwd=tree, check=True)
    return r.stdout.strip().splitlines()


def users(before: str, paper: bool) -> None:
    with tempfile.TemporaryDirectory(prefix="bench-offline-") as tmp:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", before],
                                 capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        print(f"\noffline users (each in a fresh process; {_load()}):")
        rows_before = _users(Path(tmp), paper)  # cold numba caches: the first-run figure
        rows_before = _users(Path(tmp), paper)  # warm, like this tree's
        print(f"  before ({before}, {_load()}):")
        for r in rows_before:
            print(f"    {r}")
        rows_after = _users(ROOT, paper)
        print(f"  after (this tree, {_load()}):")
        for r in rows_after:
            print(f"    {r}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--users", action="store_true", help="time the offline users too")
    ap.add_argument("--paper", action="store_true", help="with --users: dobtune paper too")
    ap.add_argument("--before", default=BEFORE_REV, help="the tree to compare the users with")
    a = ap.parse_args()
    compile_figures()
    closed_loop()
    if a.users:
        users(a.before, a.paper)


if __name__ == "__main__":
    main()
