"""Gate latency as the controller pays it: `AnalysisWorker.check_and_build` in the niced worker
process (the verdict: analysis on all evidence, recommended cut-off, nonlinear check when
wired; then the filter design), p50/p99 over candidates like a tuning session sends them.

    .venv/bin/python tests/bench/bench_gate_latency.py [--n 100]

Two plant knowledges: the commissioning model with its bound, and the same plus three
measured responses as identification hands them over (0.1-20 Hz, 10 points per decade).
"Same base" candidates change only the Q cut-off (the recommended cut-off's search is cached
per base), "new base" candidates change the gains too (a new search each time).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: plant_evidence

from plant_evidence import three_positions

from controller.core.config import LoopConfig
from controller.gate.knowledge import (
    COMMISSIONING_BOUND,
    KnowledgeRecord,
    PlantKnowledge,
)
from controller.process.analysis_worker import AnalysisWorker


def _percentiles(xs: list[float]) -> str:
    xs = sorted(xs)
    p99 = xs[min(len(xs) - 1, int(0.99 * len(xs)))]
    return f"p50 {1e3 * statistics.median(xs):7.1f} ms   p99 {1e3 * p99:7.1f} ms"


def main(n: int) -> None:
    model = KnowledgeRecord.of(PlantKnowledge(bound=COMMISSIONING_BOUND, version=1,
                                              source="bench: model"))
    runner = AnalysisWorker(subprocess=True)
    rng = np.random.default_rng(1)
    try:
        runner.check(LoopConfig(), model)  # start the worker
        measured = KnowledgeRecord.of(three_positions(source="bench: 3 positions"))
        for name, record in (("model + bound", model), ("3 measured (ident)", measured)):
            runner.check(LoopConfig(), record)
            for label, new_base in (("same base", False), ("new base", True)):
                times: list[float] = []
                verdicts: dict[str, int] = {}
                for k in range(n):
                    cfg = LoopConfig(q_cutoff_hz=float(np.exp(rng.uniform(-2.3, 2.3))))
                    if new_base:
                        cfg = cfg.with_(cv_kp=float(rng.uniform(0.2, 0.7)),
                                        pos_kp_per_s=float(rng.uniform(3.0, 12.0)))
                    t0 = time.perf_counter()
                    v, _ = runner.check_and_build(cfg, k + 10, record)
                    times.append(time.perf_counter() - t0)
                    verdicts[v.verdict] = verdicts.get(v.verdict, 0) + 1
                print(f"{name:<20} {label:<10} {_percentiles(times)}   verdicts {verdicts}")
    finally:
        runner.close()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=100)
    main(ap.parse_args().n)
