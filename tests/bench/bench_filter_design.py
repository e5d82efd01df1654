"""The speed-command filter the whole-loop tune designs, on rigs of the issue's family (issue 35
item 3): for each rig drawn from the seed, its exact responses at three positions as the
knowledge (`controller.tune.family.true_knowledge`), the speed loop's crossover without and
with the designed filter; where a filter is designed, the whole loop tuned with and without
it (`tune_whole_loop`, on the true rig or on the twin of the knowledge) and both run again on
the true rig with another noise seed.

    .venv/bin/python tests/bench/bench_filter_design.py [--seed N] [--rigs 20] [--plant true|twin]

Without --seed a fresh seed is drawn and printed. Prints one row per rig and the machine's
load.
"""

from __future__ import annotations

import argparse
import os
import random
import time

from controller.core.config import LoopConfig
from controller.core.trajectory import default_trajectory
from controller.gate.verdict import judge
from controller.sim.experiment import run_experiment
from controller.sim.rig_disturbances import rig_setup
from controller.tune.family import draw_family, true_knowledge
from controller.tune.filter_design import design_filter, mode_band_hz
from controller.tune.loop_design import design_speed
from controller.tune.plant import plant_for
from controller.tune.whole_loop import Objective, tune_whole_loop

RATE = 1000.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--rigs", type=int, default=20)
    ap.add_argument("--plant", choices=("true", "twin"), default="true",
                    help="what the tune runs its candidates on (the gate judges on the "
                    "true rig's responses either way)")
    args = ap.parse_args()
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(2**31)
    print(f"seed {seed}, {args.rigs} rigs, tune on the {args.plant} rig; load "
          f"{os.getloadavg()[0]:.1f}")
    traj = default_trajectory("sine")
    obj = Objective(feedforward=False)
    print("| rig | mode (measured) | crossover alone | filter | crossover with | RMSE with "
          "| RMSE without | gate | tune s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for rig in draw_family(seed, args.rigs):
        k = true_knowledge(rig.params, rig.faults, RATE)
        found = mode_band_hz(k)
        modes = f"{min(found[0]):.1f} Hz" if found else "none"
        plain = design_speed(k, RATE)
        fd = design_filter(k, RATE, plain)
        if fd is None:
            print(f"| {rig.index} {rig.describe()} | {modes} | {plain.crossover_hz:.2f} Hz "
                  f"| off | | | | | |")
            continue
        true_plant = rig.plant
        plant = (true_plant if args.plant == "true"
                 else plant_for(k, rig_setup(("article-rig",)), RATE))
        t0 = time.perf_counter()
        with_f = tune_whole_loop(LoopConfig(), k, plant, obj)
        tune_s = time.perf_counter() - t0
        without = tune_whole_loop(LoopConfig(), k, plant, obj, design_command_filter=False)
        rmse = []
        for r in (with_f, without):
            if r.best is None:
                rmse.append(float("nan"))
                continue
            run = run_experiment(r.best.config, traj, 15.0,
                                 rig=true_plant.rig_on(traj, RATE, seed=7),
                                 disturbance_name=true_plant.label)
            rmse.append(run.rmse_deg)
        kept = with_f.best.config.command_filter if with_f.best is not None else None
        words = ("no candidate" if kept is None else kept.describe() if kept.kind != "off"
                 else f"designed {fd.command_filter.describe()}, not kept")
        verdict = judge(with_f.best.config, k).verdict if with_f.best is not None else "-"
        print(f"| {rig.index} {rig.describe()} | {modes} | {plain.crossover_hz:.2f} Hz | "
              f"{words} | "
              f"{with_f.speed.crossover_hz:.2f} Hz | {rmse[0]:.4g} | {rmse[1]:.4g} | "
              f"{verdict} | {tune_s:.1f} |", flush=True)
    print(f"load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
