"""Autotune against a dense sweep (issue 15): how long `autotune` takes and how far its
suggestion is from the best point of a dense sweep of the same objective.

    .venv/bin/python tests/bench/bench_autotune.py [--dense 40] [--json]

For each scenario (trajectory, disturbance) it runs `controller.tune.autotune.autotune` with
its defaults (10 log-spaced cut-offs per Q type, 4 refinements, 15 s runs), then scores a
dense log grid of cut-offs 0.1-20 Hz per Q type in the same way (the gate first: a rejected
candidate is not run; only accepted ones count). Printed: run times, the two best points and
the relative excess of autotune's score over the dense best (0 = as good).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from controller.core.config import LoopConfig
from controller.core.trajectory import default_trajectory
from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
from controller.sim.disturbance import disturbance_from_name
from controller.sim.nonlinear_check import findings
from controller.tune.autotune import autotune

SCENARIOS = (("sine", "none"), ("hold", "step"))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--dense", type=int, default=40, help="cut-offs per Q type in the sweep")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    plant = PlantKnowledge(bound=COMMISSIONING_BOUND, source="simulated rig model")
    out = []
    for traj_name, dist_name in SCENARIOS:
        traj, dist = default_trajectory(traj_name), disturbance_from_name(dist_name)
        t0 = time.perf_counter()
        res = autotune(LoopConfig(), plant, traj, disturbance=dist, nonlinear=findings)
        t_auto = time.perf_counter() - t0
        t0 = time.perf_counter()
        dense = autotune(LoopConfig(), plant, traj, disturbance=dist, nonlinear=findings,
                         points=args.dense, refine=0)
        t_dense = time.perf_counter() - t0
        a, d = res.best, dense.best
        excess = (a.score / d.score - 1.0) if (a is not None and d is not None) else math.nan
        row = {
            "trajectory": traj_name, "disturbance": dist_name,
            "autotune_s": round(t_auto, 2), "autotune_runs": len(res.curve) + 1,
            "dense_s": round(t_dense, 2), "dense_runs": len(dense.curve) + 1,
            "autotune_best": None if a is None else (a.q_type, round(a.q_cutoff_hz, 4),
                                                     a.score),
            "dense_best": None if d is None else (d.q_type, round(d.q_cutoff_hz, 4), d.score),
            "score_excess": excess,
            "baseline_dob_off": res.baseline.score,
            "dob_helps": res.dob_helps, "dense_dob_helps": dense.dob_helps,
        }
        out.append(row)
        if not args.json:
            print(f"{traj_name}/{dist_name}: autotune {t_auto:.1f} s ({row['autotune_runs']} "
                  f"runs) best {row['autotune_best']}; dense {t_dense:.1f} s "
                  f"({row['dense_runs']} runs) best {row['dense_best']}; excess "
                  f"{100 * excess:.3f} %; DOB off {res.baseline.score:.5g}; DOB helps: "
                  f"{res.dob_helps} (dense: {dense.dob_helps})", flush=True)
    if args.json:
        print(json.dumps(out, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
