"""The whole-loop tune on the default simulated rig against today's default loop and the
article's figures (issue 35 "Measure and report").

    .venv/bin/python tests/bench/bench_whole_loop.py [--disturbance NAME ...]

Tunes twice with `dobtune tune`'s defaults on the simulated rig's model with the commissioning
bound (nothing measured: the built-in model), the article's 5 sin(0.5 t) deg, RMSE: without
feedforward and with it. Then runs the starting loop (`LoopConfig()`) and each candidate,
each with the DOB as tuned and with it off, on the article rig (default `--disturbance
article-rig`): sine RMSE and peak |error|, the static error after a 5 deg move (mean |error|
over the last quarter of 10 s), the command noise (RMS > 20 Hz, deg/s); and prints the tune's
time to candidate and the article's figures beside them.
"""

from __future__ import annotations

import argparse
import sys
import time

from controller.core.config import LoopConfig
from controller.core.trajectory import default_trajectory
from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
from controller.sim.experiment import ARTICLE_SINE
from controller.sim.rig_disturbances import rig_setup
from controller.tune.autotune import command_noise_deg_s, run_point
from controller.tune.plant import SimPlant
from controller.tune.whole_loop import Objective, tune_whole_loop


def _row(name: str, cfg: LoopConfig, setup: object) -> str:
    sine = run_point(cfg, default_trajectory("sine"), 15.0, setup=setup)  # type: ignore[arg-type]
    step = run_point(cfg, default_trajectory("step"), 10.0, setup=setup)  # type: ignore[arg-type]
    noise = command_noise_deg_s(sine.command_deg_s, cfg.rate_hz)
    static = step.metrics.static_error_deg or 0.0
    return (f"{name:44} {sine.rmse_deg:8.4f} {sine.peak_error_deg:8.4f} {static:10.5f} "
            f"{noise:8.3f}")


def main(names: list[str]) -> int:
    setup = rig_setup(tuple(names))
    knowledge = PlantKnowledge(bound=COMMISSIONING_BOUND)
    plant = SimPlant.of_setup(setup)
    tuned = {}
    for ff in (False, True):
        t0 = time.perf_counter()
        res = tune_whole_loop(LoopConfig(), knowledge, plant, Objective(feedforward=ff))
        print(f"tune ({'with' if ff else 'without'} feedforward): {time.perf_counter() - t0:.1f}"
              f" s to candidate, {res.runs} runs")
        for line in res.explanation:
            print(f"  - {line}")
        assert res.best is not None
        tuned[ff] = res.best.config
    print(f"\nrig: {setup.label}; metric columns: sine RMSE deg, sine peak deg, static error "
          f"after a 5 deg move deg, command noise deg/s")
    print(f"{'loop':44} {'RMSE':>8} {'peak':>8} {'static':>10} {'noise':>8}")
    start = LoopConfig()
    print(_row("starting loop, DOB off", start.with_(dob_on=False), setup))
    print(_row("starting loop, DOB Q31 0.5 Hz", start, setup))
    print(_row("starting loop, DOB Q31 0.5 Hz + FF 1", start.with_(ff_on=True), setup))
    for ff, cfg in tuned.items():
        tag = "tuned + FF" if ff else "tuned"
        dob = f"{cfg.q_type} {cfg.q_cutoff_hz:g} Hz" if cfg.dob_on else "DOB off"
        print(_row(f"{tag}, as tuned ({dob})", cfg, setup))
        other = cfg.with_(dob_on=not cfg.dob_on)
        dob2 = f"{other.q_type} {other.q_cutoff_hz:g} Hz" if other.dob_on else "DOB off"
        print(_row(f"{tag}, {dob2}", other, setup))
    for k, v in ARTICLE_SINE.items():
        pk = "-" if v["peak_error_deg"] is None else f"{v['peak_error_deg']:8.4f}"
        print(f"{'article: ' + k:44} {v['rmse_deg']:8.4f} {pk:>8}")
    print("article: static error at 40 deg about 2x smaller with the DOB (no figure given)")
    return 0


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--disturbance", action="append", default=None, metavar="NAME")
    a = p.parse_args()
    sys.exit(main(a.disturbance or ["article-rig"]))
