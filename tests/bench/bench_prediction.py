"""How far the twin's prediction lands from the rig (issue 35 item 5): the tolerances of
`controller.tune.prediction` rest on these figures.

The demo's rig (article-rig) is identified offline at 3 positions, its twin built
(`plant_for`, as Suggest and the preview use it), and for several configurations and
trajectories the twin's prediction (`predict`) is set against the true simulated rig run with
other noise seeds over the same window of steady running (`figures_of` on both sides).

    .venv/bin/python tests/bench/bench_prediction.py [--seeds 3]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.sim.experiment import run_experiment
from controller.sim.rig_disturbances import build_rig, rig_setup
from controller.tune.plant import plant_for

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_twin_fit import demo_knowledge

from controller.tune.prediction import (
    SETTLE_S,
    TOLERANCE_REL,
    check_window_s,
    figures_of,
    judge,
    predict,
)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    setup = rig_setup(("article-rig",))
    cfg = LoopConfig()
    plant = plant_for(demo_knowledge(setup, cfg), setup)
    print(f"plant: {plant.source}; load {os.getloadavg()[0]:.1f}")
    configs = (("DOB off", cfg.with_(dob_on=False)), ("default (Q31 0.5 Hz)", cfg),
               ("Q20 3.85 Hz", cfg.with_(q_type="q20", q_cutoff_hz=3.85)))
    trajs = (("sine", Trajectory(kind="sine")),
             ("fast sine", Trajectory(kind="sine", amplitude_deg=5.0, omega_rad_s=2.0)),
             ("ramp", Trajectory(kind="ramp", slope_deg_s=1.0)))
    worst: dict[str, float] = {k: 0.0 for k in TOLERANCE_REL}
    states: list[str] = []
    for tname, traj in trajs:
        window = check_window_s(traj)
        lead = SETTLE_S if traj.period_s is None else check_window_s(traj, SETTLE_S)
        for cname, c in configs:
            p = predict(c, traj, plant, window)
            n = round(window * c.rate_hz)
            for seed in range(1, args.seeds + 1):
                rig = build_rig(setup, rate_hz=c.rate_hz, seed=seed,
                                initial_position_deg=traj.at(0.0)[0])
                true = run_experiment(c, traj, lead + window, rig=rig)
                m = figures_of(np.asarray(true.error_deg)[-n:],
                               np.asarray(true.command_deg_s)[-n:], c.rate_hz)
                j = judge(p, m)
                states.append(j.state)
                for name, v in j.off_rel.items():
                    worst[name] = max(worst[name], abs(v))
                print(f"{tname:9s} {cname:22s} seed {seed}: " + ", ".join(
                    f"{name} {p.main()[name]:.4g}->{m.main()[name]:.4g} ({v:+.1%})"
                    for name, v in j.off_rel.items()) + f" => {j.state}")
    print("worst |relative error|: " + ", ".join(
        f"{k} {v:.1%} (tolerance {TOLERANCE_REL[k]:.0%})" for k, v in worst.items()))
    print(f"held {states.count('held')}/{len(states)}")


if __name__ == "__main__":
    main()
