"""`dobtune experiment`: offline runs on the simulated rig, printed next to the article's.

`sine|step|ramp|hold|compare`: one trajectory (compare: no DOB / DOB / DOB + FF); `fig8` ...
`fig17`, `sensitivity`, `disturbances`: the article's experiments (`controller.sim.paper`),
each with the article's numbers and a statement of agreement. `--disturbance NAME` (several
allowed) names timing-belt disturbances (`controller.sim.rig_disturbances`); `--config FILE`
runs any LoopConfig JSON (the flags given override it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

from controller.cli.common import on_off, progress_printer
from controller.core.config import LoopConfig, config_to_builtins
from controller.core.errors import ConfigError
from controller.core.trajectory import default_trajectory
from controller.ident.paper_fig13 import EXPERIMENTS
from controller.sim.experiment import ARTICLE_SINE, ExperimentResult, run_experiment
from controller.sim.paper import FigureResult, Options
from controller.sim.rig_disturbances import (
    DEFAULT_RIG_NAMES,
    RIG_DISTURBANCES,
    build_rig,
    rig_setup,
)

TRAJECTORY_TESTS = ("sine", "step", "ramp", "hold", "compare")
TESTS = (*TRAJECTORY_TESTS, *EXPERIMENTS)


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


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def figure_to_json(f: FigureResult) -> dict[str, Any]:
    return {
        "figure": f.figure,
        "title": f.title,
        "setup": f.setup,
        "columns": list(f.columns),
        "rows": [list(r) for r in f.rows],
        "article": [
            {"quantity": a.quantity, "run": a.run, "value": a.value, "unit": a.unit,
             "text": a.text}
            for a in f.article
        ],
        "agreement": f.agreement,
        "reason": f.reason,
        "numbers": {k: _finite(v) for k, v in f.numbers.items()},
    }


def print_figure(out: TextIO, f: FigureResult) -> None:
    """A figure's result as plain text: ours, the article's, the agreement."""
    out.write(f"{f.figure}: {f.title}\n  {f.setup}\n\n")
    widths = [max(len(c), *(len(r[i]) for r in f.rows)) for i, c in enumerate(f.columns)]
    out.write("  " + "  ".join(c.ljust(w) for c, w in zip(f.columns, widths, strict=True)) + "\n")
    for r in f.rows:
        out.write("  " + "  ".join(x.ljust(w) for x, w in zip(r, widths, strict=True)) + "\n")
    out.write("\n  article (control.md):\n")
    for a in f.article:
        out.write(f"    {a.quantity} [{a.run}]: {a.text}\n")
    out.write(f"\n  {f.agreement.upper()}: {f.reason}\n\n")


def _figure_main(
    test: str, base: LoopConfig, names: tuple[str, ...], seed: int, quick: bool,
    as_json: bool, out: TextIO, err: TextIO,
) -> int:
    def say(what: str) -> None:
        if err.isatty():
            err.write(f"\r\x1b[K{what}")
            err.flush()

    opts = Options(cfg=base, disturbances=names, quick=quick, seed=seed, progress=say)
    t0 = time.perf_counter()
    figures = EXPERIMENTS[test](opts)
    if err.isatty():
        err.write("\r\x1b[K")
    if as_json:
        out.write(json.dumps({
            "test": test, "quick": quick, "disturbances": list(names),
            "config": config_to_builtins(base), "wall_time_s": time.perf_counter() - t0,
            "figures": [figure_to_json(f) for f in figures],
        }) + "\n")
        return 0
    for f in figures:
        print_figure(out, f)
    return 0


def experiment_main(
    *,
    test: str,
    dob_on: bool | None,
    ff_on: bool | None,
    q_type: str | None,
    cutoff_hz: float | None,
    duration_s: float | None,
    seed: int,
    disturbance: str | Sequence[str] | None,
    as_json: bool,
    out: TextIO,
    err: TextIO,
    config_path: Path | None = None,
    quick: bool = False,
) -> int:
    """Exit code 0 on a completed run, 2 on bad input (message names the parameter).
    None for a setting: the configuration file's (or the default's) value."""
    from controller.cli.inputs import BadInput, load_config

    try:
        if test not in TESTS:
            raise ConfigError("test", f"unknown experiment {test!r}; expected one of "
                              f"{', '.join(TESTS)}")
        base = load_config(config_path)
        changes: dict[str, Any] = {}
        for key, value in (("q_type", q_type), ("q_cutoff_hz", cutoff_hz), ("dob_on", dob_on),
                           ("ff_on", ff_on)):
            if value is not None:
                changes[key] = value
        if changes:
            base = base.with_(**changes)
        if disturbance is None:
            # the article's figures keep their own rigs; a time-domain test runs the default
            names: tuple[str, ...] = () if test in EXPERIMENTS else DEFAULT_RIG_NAMES
        elif isinstance(disturbance, str):
            names = (disturbance,)
        else:
            names = tuple(disturbance)
        setup = rig_setup(names)
        if test in EXPERIMENTS:
            if duration_s is not None:
                raise ConfigError("duration_s", f"--duration applies to "
                                  f"{', '.join(TRAJECTORY_TESTS)}, not to {test}")
            return _figure_main(test, base, setup.names, seed, quick, as_json, out, err)
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
            rig = build_rig(setup, rate_hz=cfg.rate_hz, seed=seed,
                            initial_position_deg=traj.at(0.0)[0])
            res = run_experiment(
                cfg,
                traj,
                dur,
                seed=seed,
                disturbance_name=setup.label,
                progress=progress_printer(err, label),
                rig=rig,
            )
            results[label] = (res, time.perf_counter() - t0)
    except BadInput as exc:
        err.write(f"dobtune experiment: error: {exc}\n")
        return 2
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
    _print_table(out, test, traj.kind, results, dur, setup.label)
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
    columns = _table_columns(test, kind)
    out.write(" ".join(f"{title:{width}}" for title, width in columns) + "\n")
    for label, (res, wall) in results.items():
        cells = _table_cells(label, res, wall)
        out.write(" ".join(f"{cells[title]:{width}}" for title, width in columns) + "\n")


def _table_columns(test: str, kind: str) -> list[tuple[str, str]]:
    """(title, alignment and width) of each column the results table of `kind` runs shows."""
    columns = [("run", "<10"), ("DOB", "<4"), ("FF", "<4"), ("peak|e| deg", ">12"),
               ("RMSE deg", ">10")]
    if kind == "step":
        columns += [("rise s", ">8"), ("overshoot %", ">12")]
    if kind in ("step", "hold"):
        columns.append(("static deg", ">11"))
    columns.append(("x real time", ">12"))
    if test == "compare":
        columns += [("article peak", ">13"), ("article RMSE", ">13")]
    return columns


def _table_cells(label: str, res: ExperimentResult, wall_s: float) -> dict[str, str]:
    """Every cell of a run's row of the results table, by column title."""
    m = res.metrics
    article = ARTICLE_SINE.get(label, {})
    return {
        "run": label,
        "DOB": "on" if res.config.dob_on else "off",
        "FF": "on" if res.config.ff_on else "off",
        "peak|e| deg": f"{m.peak_error_deg:.4f}",
        "RMSE deg": f"{m.rmse_deg:.4f}",
        "rise s": _fmt(m.rise_time_s, ".3f"),
        "overshoot %": _fmt(m.overshoot_pct, ".1f"),
        "static deg": _fmt(m.static_error_deg, ".5f"),
        "x real time": f"{res.duration_s / wall_s:.0f}",
        "article peak": _fmt(article.get("peak_error_deg")),
        "article RMSE": _fmt(article.get("rmse_deg")),
    }


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "test",
        nargs="?",
        default="sine",
        choices=TESTS,
        help="trajectory, compare (no DOB / DOB / DOB + feedforward), or one of the "
        "article's experiments: fig8 ... fig17, sensitivity (eqs. 28-29), disturbances "
        "(where the DOB helps) (default sine)",
    )
    p.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="a LoopConfig JSON (as dobtune check takes); the flags below override it")
    p.add_argument("--dob", type=on_off, default=None, metavar="on|off")
    p.add_argument("--ff", type=on_off, default=None, metavar="on|off")
    p.add_argument("--q", dest="q_type", default=None, metavar="q20|q31")
    p.add_argument("--cutoff-hz", type=float, default=None)
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="simulated seconds (default: 30 for sine/ramp, 10 otherwise)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--disturbance", action="append", default=None, metavar="NAME",
                   help="timing-belt disturbance, repeatable (default for the time-domain "
                   f"tests: {'+'.join(DEFAULT_RIG_NAMES)}; ideal: the reference rig alone): "
                   + ", ".join(sorted(RIG_DISTURBANCES)))
    p.add_argument("--quick", action="store_true",
                   help="the article's experiments: shorter runs, fewer points")
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
        config_path=args.config,
        quick=args.quick,
    )

