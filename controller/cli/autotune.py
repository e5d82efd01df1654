"""`dobtune autotune`: search the Q type and cut-off on the simulated rig (command body).

    dobtune autotune [CONFIG] [--knowledge FILE] [--trajectory sine|step|ramp|hold]
                     [--disturbance NAME ...] [--objective rmse|peak] [--noise-weight W]
                     [--duration S] [--points N] [--json]

The runs are made on the rig's twin when the knowledge holds measured responses, on the
built-in model only when nothing was measured (the summary and `plant` say which). Every
candidate is judged by the gate first (only accepted ones can be the best unless
`--allow-caution`) (on the plant knowledge: `--knowledge`, default the
simulated rig's model with the commissioning bound); rejected ones are not run. `--json` prints
one object: `best` (config, rmse_deg, peak_error_deg, verdict), `baseline` (DOB off),
`dob_helps`, `plant`, `summary` and `curve` (q_type, q_cutoff_hz, rmse_deg, peak_error_deg,
verdict).
Nothing is applied. Exit codes: 0 done, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, TextIO

__all__ = ["autotune_main"]


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _point(p: Any, with_config: bool = False) -> dict[str, Any]:
    from controller.core.config import config_to_builtins

    out: dict[str, Any] = {
        "q_type": p.q_type, "q_cutoff_hz": p.q_cutoff_hz, "dob_on": p.config.dob_on,
        "rmse_deg": _finite(p.rmse_deg), "peak_error_deg": _finite(p.peak_error_deg),
        "command_noise_deg_s": _finite(p.command_noise_deg_s), "verdict": p.verdict,
    }
    if with_config:
        out["config"] = config_to_builtins(p.config)
    return out


def autotune_main(args: argparse.Namespace, out: TextIO, err: TextIO) -> int:
    from controller.cli.common import progress_printer
    from controller.cli.inputs import BadInput, load_config, load_knowledge
    from controller.core.errors import ConfigError
    from controller.core.trajectory import default_trajectory
    from controller.sim.nonlinear_check import findings
    from controller.sim.rig_disturbances import rig_names, rig_setup
    from controller.tune.autotune import autotune

    try:
        base = load_config(args.config)
        plant = load_knowledge(args.knowledge)
        traj = default_trajectory(args.trajectory)
        names = [args.disturbance] if isinstance(args.disturbance, str) else args.disturbance
        setup = rig_setup(rig_names(names))
        res = autotune(
            base, plant, traj, duration_s=args.duration, setup=setup,
            objective=args.objective, noise_weight=args.noise_weight, points=args.points,
            lowest_hz=args.lowest_hz, highest_hz=args.highest_hz, nonlinear=findings,
            allow_caution=args.allow_caution,
            progress=progress_printer(err, "autotune"),
        )
    except (BadInput, ConfigError, ValueError) as exc:
        out.write(json.dumps({"error": str(exc)}) + "\n" if args.json else f"error: {exc}\n")
        return 2
    if args.json:
        out.write(json.dumps({
            "best": _point(res.best, True) if res.best else None,
            "baseline": _point(res.baseline, True),
            "dob_helps": res.dob_helps,
            "plant": res.plant_source,
            "summary": res.summary(),
            "curve": [_point(p) for p in res.curve],
        }, allow_nan=False) + "\n")
        return 0
    for p in res.curve:
        rm = "-" if not math.isfinite(p.rmse_deg) else f"{p.rmse_deg:.4g}"
        pk = "-" if not math.isfinite(p.peak_error_deg) else f"{p.peak_error_deg:.4g}"
        out.write(f"  {p.q_type} {p.q_cutoff_hz:8.3g} Hz  RMSE {rm:>8}  peak {pk:>8}  "
                  f"{p.verdict}\n")
    out.write(res.summary() + "\n")
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", type=Path, default=None, help="LoopConfig JSON")
    p.add_argument("--knowledge", type=Path, default=None, metavar="FILE")
    p.add_argument("--trajectory", choices=("sine", "step", "ramp", "hold"), default="sine")
    p.add_argument("--disturbance", action="append", default=None, metavar="NAME",
                   help="a named disturbance of the simulated rig, repeatable (as for "
                   "`dobtune experiment`; default article-rig, ideal: the reference rig alone)")
    p.add_argument("--objective", choices=("rmse", "peak"), default="rmse")
    p.add_argument("--noise-weight", type=float, default=0.001,
                   help="deg of error a deg/s RMS of command noise (>20 Hz) costs")
    p.add_argument("--duration", type=float, default=15.0, help="simulated seconds per run")
    p.add_argument("--points", type=int, default=10, help="cut-offs per Q type (then refined)")
    p.add_argument("--lowest-hz", type=float, default=0.1)
    p.add_argument("--highest-hz", type=float, default=20.0)
    p.add_argument("--allow-caution", action="store_true",
                   help="let candidates with the verdict caution be the best (they are shown)")
    p.add_argument("--json", action="store_true")


def run(args: argparse.Namespace) -> int:
    return autotune_main(args, sys.stdout, sys.stderr)

