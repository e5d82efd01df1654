"""`dobtune experiment`: offline runs on the simulated rig, printed next to the article's."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

from controller.cli import Command, on_off
from controller.core.config import LoopConfig, config_to_builtins
from controller.core.errors import ConfigError
from controller.core.trajectory import default_trajectory
from controller.sim.disturbance import disturbance_from_name
from controller.sim.experiment import ARTICLE_SINE, ExperimentResult, run_experiment


def progress_printer(err: TextIO, label: str) -> Callable[[float], None] | None:
    if not err.isatty():
        return None
    last = [-1]

    def show(fraction: float) -> None:
        pct = int(fraction * 100)
        if pct != last[0]:
            last[0] = pct
            bar = "#" * (pct // 4)
            err.write(f"\r{label:<10} [{bar:<25}] {pct:3d} %")
            if pct >= 100:
                err.write("\n")
            err.flush()

    return show


def result_to_json(res: ExperimentResult, wall_s: float) -> dict[str, Any]:
    m = res.metrics
    return {
        "test": res.trajectory.kind,
        "peak_error_deg": m.peak_error_deg,
        "rmse_deg": m.rmse_deg,
        "metrics_window_s": list(m.window_s),
        "rise_time_s": m.rise_time_s,
        "overshoot_pct": m.overshoot_pct,
        "static_error_deg": m.static_error_deg,
        "peak_command_deg_s": m.peak_command_deg_s,
        "saturated_fraction": m.saturated_fraction,
        "duration_s": res.duration_s,
        "seed": res.seed,
        "disturbance": res.disturbance,
        "trajectory": config_to_builtins(res.trajectory),  # type: ignore[arg-type]
        "config": config_to_builtins(res.config),
        "wall_time_s": wall_s,
        "realtime_factor": res.duration_s / wall_s if wall_s > 0 else None,
    }


def _fmt(v: float | None, spec: str = ".4f") -> str:
    return "-" if v is None else format(v, spec)


def experiment_main(
    *,
    test: str,
    dob_on: bool,
    ff_on: bool,
    q_type: str,
    cutoff_hz: float,
    duration_s: float | None,
    seed: int,
    disturbance: str,
    as_json: bool,
    out: TextIO,
    err: TextIO,
) -> int:
    """Exit code 0 on a completed run, 2 on bad input (message names the parameter)."""
    try:
        base = LoopConfig(q_type=q_type, q_cutoff_hz=cutoff_hz, dob_on=dob_on, ff_on=ff_on)
        dist = disturbance_from_name(disturbance)
        kind = "sine" if test == "compare" else test
        traj = default_trajectory(kind)
        dur = duration_s if duration_s is not None else (30.0 if kind in ("sine", "ramp") else 10.0)
        if test == "compare":
            runs = {
                "no DOB": base.with_(dob_on=False, ff_on=False),
                "DOB": base.with_(dob_on=True, ff_on=False),
                "DOB + FF": base.with_(dob_on=True, ff_on=True),
            }
        else:
            runs = {"run": base}
        results: dict[str, tuple[ExperimentResult, float]] = {}
        for label, cfg in runs.items():
            t0 = time.perf_counter()
            res = run_experiment(
                cfg,
                traj,
                dur,
                seed=seed,
                disturbance=dist,
                disturbance_name=disturbance,
                progress=progress_printer(err, label),
            )
            results[label] = (res, time.perf_counter() - t0)
    except (ConfigError, ValueError) as exc:
        err.write(f"dobtune experiment: error: {exc}\n")
        return 2
    if as_json:
        if test == "compare":
            payload: dict[str, Any] = {
                "test": "compare",
                "runs": {k: result_to_json(r, w) for k, (r, w) in results.items()},
                "article": ARTICLE_SINE,
                "duration_s": dur,
                "config": config_to_builtins(base),
            }
        else:
            payload = result_to_json(*results["run"])
        out.write(json.dumps(payload) + "\n")
        return 0
    _print_table(out, test, traj.kind, results, dur, disturbance)
    return 0


def _print_table(
    out: TextIO,
    test: str,
    kind: str,
    results: dict[str, tuple[ExperimentResult, float]],
    duration_s: float,
    disturbance: str,
) -> None:
    any_res = next(iter(results.values()))[0]
    c = any_res.config
    m0 = any_res.metrics
    out.write(
        f"{kind} test, {duration_s:g} s simulated at {c.rate_hz:g} Hz, disturbance {disturbance}, "
        f"Q {c.q_type} {c.q_cutoff_hz:g} Hz; metrics over {m0.window_s[0]:g}-"
        f"{m0.window_s[1]:.3g} s\n"
    )
    head = f"{'run':<10} {'DOB':<4} {'FF':<4} {'peak|e| deg':>12} {'RMSE deg':>10}"
    if kind == "step":
        head += f" {'rise s':>8} {'overshoot %':>12}"
    if kind in ("step", "hold"):
        head += f" {'static deg':>11}"
    head += f" {'x real time':>12}"
    if test == "compare":
        head += f" {'article peak':>13} {'article RMSE':>13}"
    out.write(head + "\n")
    for label, (res, wall) in results.items():
        m = res.metrics
        cfg = res.config
        row = (
            f"{label:<10} {'on' if cfg.dob_on else 'off':<4} {'on' if cfg.ff_on else 'off':<4} "
            f"{m.peak_error_deg:>12.4f} {m.rmse_deg:>10.4f}"
        )
        if kind == "step":
            row += f" {_fmt(m.rise_time_s, '.3f'):>8} {_fmt(m.overshoot_pct, '.1f'):>12}"
        if kind in ("step", "hold"):
            row += f" {_fmt(m.static_error_deg, '.5f'):>11}"
        row += f" {res.duration_s / wall:>12.0f}"
        if test == "compare":
            art = ARTICLE_SINE[label]
            row += f" {_fmt(art['peak_error_deg']):>13} {_fmt(art['rmse_deg']):>13}"
        out.write(row + "\n")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "test",
        nargs="?",
        default="sine",
        choices=("sine", "step", "ramp", "hold", "compare"),
        help="trajectory, or compare: no DOB / DOB / DOB + feedforward (default sine)",
    )
    p.add_argument("--dob", type=on_off, default=True, metavar="on|off")
    p.add_argument("--ff", type=on_off, default=False, metavar="on|off")
    p.add_argument("--q", dest="q_type", default="q31", metavar="q20|q31")
    p.add_argument("--cutoff-hz", type=float, default=0.5)
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="simulated seconds (default: 30 for sine/ramp, 10 otherwise)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--disturbance", default="none", metavar="NAME")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    return experiment_main(
        test=args.test,
        dob_on=args.dob,
        ff_on=args.ff,
        q_type=args.q_type,
        cutoff_hz=args.cutoff_hz,
        duration_s=args.duration,
        seed=args.seed,
        disturbance=args.disturbance,
        as_json=args.json,
        out=sys.stdout,
        err=sys.stderr,
    )


COMMAND = Command("experiment", "offline experiment on the simulated rig", add_arguments, run)
