"""`dobtune tune`: tune the whole loop (speed PI, position PI, feedforward, the DOB's Q type and
cut-off) on the plant knowledge and its simulated plant (command body).

    dobtune tune [CONFIG] [--knowledge FILE] [--trajectory sine|step|ramp|hold]
                 [--disturbance NAME ...] [--objective rmse|peak] [--noise-weight W]
                 [--noise-budget DEG_S] [--no-ff] [--duration S] [--json]

The procedure and its targets: `controller.tune.whole_loop`. The gate judges on the knowledge
(`--knowledge`, default the simulated rig's model with the commissioning bound); the candidates
run on the rig's twin when the knowledge holds measured responses, else on the built-in model
(the output says which). Nothing is applied: the candidate and its explanation are printed
(`--json`: one object, `candidate` the configuration or null). Exit codes as `dobtune check`:
0 a candidate the gate accepts, 1 none found, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, TextIO

__all__ = ["tune_main"]


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _cand(c: Any) -> dict[str, Any] | None:
    from controller.core.config import config_to_builtins

    if c is None:
        return None
    return {"config": config_to_builtins(c.config), "verdict": c.verdict,
            "rmse_deg": _finite(c.rmse_deg), "peak_error_deg": _finite(c.peak_error_deg),
            "command_noise_deg_s": _finite(c.command_noise_deg_s), "score": _finite(c.score)}


def tune_main(args: argparse.Namespace, out: TextIO, err: TextIO) -> int:
    from controller.cli.common import progress_printer
    from controller.cli.inputs import BadInput, load_config, load_knowledge
    from controller.core.errors import ConfigError
    from controller.core.trajectory import default_trajectory
    from controller.sim.nonlinear_check import findings
    from controller.sim.rig_disturbances import rig_names, rig_setup
    from controller.tune.plant import plant_for
    from controller.tune.whole_loop import Objective, tune_whole_loop

    try:
        base = load_config(args.config)
        knowledge = load_knowledge(args.knowledge)
        names = [args.disturbance] if isinstance(args.disturbance, str) else args.disturbance
        setup = rig_setup(rig_names(names))
        objective = Objective(default_trajectory(args.trajectory), args.objective,
                              args.duration, args.noise_weight, args.noise_budget,
                              not args.no_ff)
        res = tune_whole_loop(base, knowledge, plant_for(knowledge, setup), objective,
                              nonlinear=findings, progress=progress_printer(err, "tune"))
    except (BadInput, ConfigError, ValueError) as exc:
        out.write(json.dumps({"error": str(exc)}) + "\n" if args.json else f"error: {exc}\n")
        return 2
    code = 0 if res.best is not None else 1
    if args.json:
        sp, po = res.speed, res.position
        out.write(json.dumps({
            "candidate": _cand(res.best),
            "start": _cand(res.start),
            "designed": _cand(res.designed),
            "speed_loop": {"kp": sp.kp, "ki_per_s": sp.ki_per_s,
                           "crossover_hz": sp.crossover_hz, "corner_hz": sp.corner_hz,
                           "limit": sp.limit,
                           "command_filter": sp.command_filter.describe()},
            "position_loop": {"kp_per_s": po.kp_per_s, "ki_per_s": po.ki_per_s,
                              "crossover_hz": po.crossover_hz, "ratio": po.ratio,
                              "limit": po.limit},
            "plant": res.plant_source,
            "explanation": list(res.explanation),
            "runs": res.runs,
            "elapsed_s": res.elapsed_s,
        }, allow_nan=False) + "\n")
        return code
    for line in res.explanation:
        out.write(f"- {line}\n")
    if res.best is not None:
        from controller.core.config import config_to_builtins

        out.write("candidate (not applied):\n")
        out.write(json.dumps(config_to_builtins(res.best.config), indent=2) + "\n")
    return code


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", type=Path, default=None,
                   help="LoopConfig JSON the tune starts from (rate, DOB model, limit)")
    p.add_argument("--knowledge", type=Path, default=None, metavar="FILE")
    p.add_argument("--trajectory", choices=("sine", "step", "ramp", "hold"), default="sine")
    p.add_argument("--disturbance", action="append", default=None, metavar="NAME",
                   help="a named disturbance of the simulated plant, repeatable (as for "
                   "`dobtune experiment`; default article-rig, ideal: the reference rig alone)")
    p.add_argument("--objective", choices=("rmse", "peak"), default="rmse")
    p.add_argument("--noise-weight", type=float, default=0.001,
                   help="deg of error a deg/s RMS of command noise (>20 Hz) costs")
    p.add_argument("--noise-budget", type=float, default=None, metavar="DEG_S",
                   help="most command noise (>20 Hz, RMS deg/s) a candidate may have "
                   "(default: twice the designed loop's without DOB)")
    p.add_argument("--no-ff", action="store_true", help="keep velocity feedforward off")
    p.add_argument("--duration", type=float, default=15.0, help="simulated seconds per run")
    p.add_argument("--json", action="store_true")


def run(args: argparse.Namespace) -> int:
    return tune_main(args, sys.stdout, sys.stderr)
