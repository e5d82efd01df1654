"""Benchmark: the CPU time of the recommended cut-off's decision for new gains (what a
new-gains apply asks the search: is the candidate's cut-off below the recommendation?), this
tree against an older commit, in one run.

    PYTHONPATH=$PWD .venv/bin/python tests/bench/bench_decision_ab.py --before 7177a83
        [--rounds 4] [--n 25] [--reps 2]

Knowledge with three measured responses (tests/plant_evidence.py, as the apply bench); `--n`
random gains (cv_kp 0.35-0.8, pos_kp 3-12 /s), each with a cut-off 0.3-1.0 x its
recommendation (found beforehand, so the design caches are warm as in a running worker);
each decision a fresh `RecommendationSearch(...).decide`. The two trees run in alternating
subprocesses (`--rounds`, the order swapped each round), so they share the load; CPU time
(process_time) is what the load stretches least. The answers must be equal.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))


def child(seed: int, n: int, reps: int) -> None:
    """Print the CPU ms of each decision and its answer (PYTHONPATH is the tree timed)."""
    from plant_evidence import three_positions

    from controller.core.config import LoopConfig
    from controller.gate.search import RecommendationSearch

    plant = three_positions(source="bench")
    rng = np.random.default_rng(seed)
    cfgs = []
    for _ in range(n):
        base = LoopConfig(cv_kp=float(rng.uniform(0.35, 0.8)),
                          pos_kp_per_s=float(rng.uniform(3.0, 12.0)))
        rec = RecommendationSearch(base, plant).value()
        cfgs.append(base.with_(q_cutoff_hz=(rec or 0.5) * float(rng.uniform(0.3, 1.0))))
    ms, answers = [], []
    for _ in range(reps):
        for cfg in cfgs:
            t0 = time.process_time()
            got = RecommendationSearch(cfg, plant).decide(
                lambda r, fc=cfg.q_cutoff_hz: not fc > r * 1.0001)
            ms.append((time.process_time() - t0) * 1e3)
            answers.append(got)
    print(json.dumps({"ms": ms, "answers": answers}))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", default="main", help="the commit compared with (default main)")
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--n", type=int, default=25, help="random gains per round")
    p.add_argument("--reps", type=int, default=2, help="decisions per gains per round")
    p.add_argument("--child", nargs=3, type=int, help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.child:
        child(*a.child)
        return 0
    from bench_startup import export_tree

    with tempfile.TemporaryDirectory(prefix="dobtune-decision-") as d:
        trees = {a.before: export_tree(a.before, Path(d)), "this tree": REPO}
        ms: dict[str, list[float]] = {k: [] for k in trees}
        answers: dict[str, list[object]] = {k: [] for k in trees}
        load0 = os.getloadavg()[0]
        for r in range(a.rounds):
            for name in (list(trees) if r % 2 == 0 else list(trees)[::-1]):
                env = {**os.environ, "PYTHONPATH": str(trees[name])}
                out = subprocess.run(
                    [sys.executable, str(Path(__file__).resolve()), "--child", str(r),
                     str(a.n), str(a.reps)], env=env, check=True, capture_output=True,
                    text=True).stdout
                got = json.loads(out.strip().splitlines()[-1])
                ms[name] += got["ms"]
                answers[name] += got["answers"]
    print(f"load average {load0:.1f} -> {os.getloadavg()[0]:.1f}")
    for name, x in ms.items():
        v = np.asarray(x)
        print(f"  {name:12s} CPU ms per decision: p50 {np.median(v):6.2f}  mean {v.mean():6.2f}"
              f"  p90 {np.percentile(v, 90):6.2f}  p99 {np.percentile(v, 99):6.2f} (n={v.size})")
    old, new = (np.asarray(ms[k]) for k in trees)
    print(f"  this tree / {a.before}: mean x{new.mean() / old.mean():.3f}, "
          f"p50 x{np.median(new) / np.median(old):.3f}, "
          f"p99 x{np.percentile(new, 99) / np.percentile(old, 99):.3f}")
    same = answers[a.before] == answers["this tree"]
    print(f"  answers {'equal' if same else 'DIFFER'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
