"""Slider to every chart and the verdict, server side: what the tuning panel does on a cut-off
slider move (`TuningPanel._update`): `TuningEngine.compare` (the analysis, the verdict with
the nonlinear check, every Bode chart's data), `charts.nyquist_svg` and the verdict box's
HTML, over slider-like candidate changes (a new Q cut-off each time, as the slider sends
them), p50/p99 wall and CPU.

Run: .venv/bin/python tests/bench/bench_engine_compare.py [--n 200] [--before REV] [--rounds 4]

`--before REV` measures the same loop, in the same run, on the whole tree at git revision REV
(`git archive` into a temporary directory, run there in a subprocess: controller and server
as they were): the figure before a change. Before and now alternate in `--rounds` rounds of
n / rounds candidates (the same candidates for both), so that a shared machine's load falls
on both alike; the load average is printed before and after. Both are measured on the plant
model alone and with three measured responses (one per position, as an identification run
adopts them). Last, the Nyquist views' and the plant chart's own share, timed alone (work
tree only).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# A run of another revision puts its tree first (DOBTUNE_BENCH_TREE).
_TREE = os.environ.get("DOBTUNE_BENCH_TREE")
sys.path.insert(0, _TREE or str(ROOT))

import numpy as np  # noqa: E402


def _knowledge(measured: bool) -> object:
    from controller.core.config import NominalModel
    from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord, PlantKnowledge
    from controller.gate.knowledge import MeasuredResponse as M
    from controller.gate.loop_model import nominal_continuous_response

    responses: tuple[M, ...] = ()
    if measured:
        f = np.geomspace(0.1, 40.0, 60)
        g = nominal_continuous_response(NominalModel(), f)
        responses = tuple(
            M(f"pos{k}", f, (1.0 + 0.1 * k) * g * np.exp(-2j * np.pi * f * 1e-3),
              spread=np.full(f.size, 0.05 + 0.05 * k))
            for k in range(3))
    return KnowledgeRecord.of(PlantKnowledge(responses, COMMISSIONING_BOUND, version=1,
                                             source="bench"))


def latencies_ms(n: int, measured: bool, seed: int = 0) -> list[tuple[float, float]]:
    """compare + nyquist_svg + the verdict box for `n` slider-like candidates: (wall, this
    process's CPU) ms each (CPU time is what a loaded, shared machine disturbs least)."""
    from controller.core.config import LoopConfig
    from server import charts
    from server.engine import TuningEngine
    from server.panels.tuning import format_gate_html

    eng = TuningEngine()
    eng.set_knowledge(_knowledge(measured))  # type: ignore[arg-type]
    active = LoopConfig()
    eng.compare(active.with_(q_cutoff_hz=0.77), active)  # warm-up: caches, first imports
    # What the tuning panel's second worker does after a move, off the slider path: the whole
    # recommended cut-off search for these gains (the slider's 'max' mark).
    eng.recommended_max_cutoff_hz(active)
    rng = np.random.default_rng(seed)
    lat = []
    for x in rng.uniform(-1.3, 1.6, n):  # log10 of the cut-off, as the slider moves it
        cand = active.with_(q_cutoff_hz=float(10.0 ** round(float(x), 3)))
        t0, c0 = time.perf_counter(), time.process_time()
        cmp = eng.compare(cand, active)
        charts.nyquist_svg(cmp.candidate.curves, cmp.active.curves)
        format_gate_html(cmp.candidate)
        lat.append(((time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3))
    return lat


def summary(ms: list[tuple[float, float]] | list[list[float]]) -> dict[str, float]:
    a = np.asarray(ms, dtype=np.float64).reshape(-1, 2)
    wall, cpu = a[:, 0], a[:, 1]
    return {"p50_ms": float(np.percentile(wall, 50)), "p99_ms": float(np.percentile(wall, 99)),
            "max_ms": float(wall.max()), "cpu_p50_ms": float(np.percentile(cpu, 50)),
            "cpu_p99_ms": float(np.percentile(cpu, 99)), "n": int(a.shape[0])}


def measure_views(n: int, measured: bool) -> dict[str, float]:
    """The Nyquist views (the loop without the DOB, cached across cut-offs; the candidate's
    own from its analysis), the plant chart's data and the two-panel SVG of one evaluation,
    timed alone (work tree only)."""
    from controller.core.config import LoopConfig
    from controller.gate.analysis import analyse
    from controller.gate.knowledge import KnowledgeRecord
    from server import charts, engine

    record = _knowledge(measured)
    assert isinstance(record, KnowledgeRecord)
    plant = record.to_knowledge()
    eng = engine.TuningEngine()
    eng.set_knowledge(record)
    active = eng.evaluate(LoopConfig()).curves
    nodob = engine.speed_loop(LoopConfig(), plant.model, engine.default_grid(1000.0), dob=False)
    rng = np.random.default_rng(1)
    lat = []
    for x in rng.uniform(-1.3, 1.6, n):
        cfg = LoopConfig(q_cutoff_hz=float(10.0 ** round(float(x), 3)))
        a = analyse(cfg, plant)
        t0, c0 = time.perf_counter(), time.process_time()
        cand = engine.curves_from_analysis(a, plant, other_loop=nodob, plant_chart=active.plant)
        charts.bode_data("plant", cand, active)
        charts.nyquist_svg(cand, active)
        lat.append(((time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3))
    return summary(lat)


CASES = (("model only", False), ("3 measured responses", True))


def _subprocess(tree: str | None, n: int, seed: int) -> dict[str, list[list[float]]]:
    env = dict(os.environ)
    env.pop("DOBTUNE_BENCH_TREE", None)
    env["PYTHONPATH"] = tree or str(ROOT)
    if tree is not None:
        env["DOBTUNE_BENCH_TREE"] = tree
    out = subprocess.run([sys.executable, __file__, "--n", str(n), "--seed", str(seed),
                          "--inner"], env=env, check=True, capture_output=True, text=True,
                         cwd=tree or ROOT).stdout
    return json.loads(out.splitlines()[-1])  # type: ignore[no-any-return]


def export_tree(rev: str, into: Path) -> str:
    """`rev` of this repository as files under `into` (no .git)."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True,
                             capture_output=True).stdout
    tar = into / "tree.tar"
    tar.write_bytes(archive)
    out = into / "tree"
    out.mkdir()
    with tarfile.open(tar) as t:
        t.extractall(out, filter="data")
    return str(out)


def _load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=200, help="candidate changes per measurement")
    ap.add_argument("--before", metavar="REV", help="also measure the tree at this revision")
    ap.add_argument("--rounds", type=int, default=4,
                    help="with --before: alternate before/now in this many rounds (a shared "
                         "machine's load then hits both alike)")
    ap.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.inner:
        print(json.dumps({name: latencies_ms(args.n, m, args.seed) for name, m in CASES}))
        return 0
    out: dict[str, object] = {"load before": _load(), "cpus": os.cpu_count()}
    if args.before:
        before: dict[str, list[list[float]]] = {name: [] for name, _ in CASES}
        now: dict[str, list[list[float]]] = {name: [] for name, _ in CASES}
        per = max(1, args.n // args.rounds)
        with tempfile.TemporaryDirectory() as tmp:
            tree = export_tree(args.before, Path(tmp))
            for r in range(args.rounds):
                for acc, where in ((before, tree), (now, None)):
                    for name, lat in _subprocess(where, per, seed=r).items():
                        acc[name] += lat
        out[f"before ({args.before})"] = {k: summary(v) for k, v in before.items()}
        out["now (work tree)"] = {k: summary(v) for k, v in now.items()}
    else:
        out["now (work tree)"] = {name: summary(latencies_ms(args.n, m)) for name, m in CASES}
    out["now: the Nyquist views and the plant chart alone"] = {
        name: measure_views(args.n, m) for name, m in CASES}
    out["load after"] = _load()
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
