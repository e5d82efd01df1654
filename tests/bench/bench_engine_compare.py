"""Server-side slider latency of the tuning views: `TuningEngine.compare` (gate analysis,
verdict, every Bode chart's data) plus `charts.nyquist_svg`, over slider-like candidate
changes (a new Q cut-off each time, as the cut-off slider sends them), p50/p99.

Run: .venv/bin/python tests/bench/bench_engine_compare.py [--n 200] [--baseline REV] [--rounds 4]

`--baseline REV` measures the same loop, in the same run, with `server/charts.py` and
`server/engine.py` as they are at git revision REV (read with `git show`, run from a temporary
directory in a subprocess; the controller side is the work tree's): the figure before a change.
Before and now alternate in `--rounds` rounds of n / rounds candidates (the same candidates
for both), so that a shared machine's load falls on both alike.
Both are measured on the plant model alone and with three measured responses (one per
position, as an identification run adopts them). Last, the new views' own share (both Nyquist
loops, the plant chart, the two-panel SVG), timed alone.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# A baseline run puts its own `server` package first (DOBTUNE_BENCH_SERVER_DIR).
_FIRST = os.environ.get("DOBTUNE_BENCH_SERVER_DIR")
sys.path.insert(0, str(ROOT))
if _FIRST:
    sys.path.insert(0, _FIRST)

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
    """compare + nyquist_svg for `n` slider-like candidates: (wall, this process's CPU) ms
    each (CPU time is what a loaded, shared machine disturbs least)."""
    from controller.core.config import LoopConfig
    from server import charts
    from server.engine import TuningEngine

    eng = TuningEngine()
    eng.set_knowledge(_knowledge(measured))  # type: ignore[arg-type]
    active = LoopConfig()
    eng.compare(active.with_(q_cutoff_hz=0.77), active)  # warm-up: caches, first imports
    rng = np.random.default_rng(seed)
    lat = []
    for x in rng.uniform(-1.3, 1.6, n):  # log10 of the cut-off, as the slider moves it
        cand = active.with_(q_cutoff_hz=float(10.0 ** round(float(x), 3)))
        t0, c0 = time.perf_counter(), time.process_time()
        cmp = eng.compare(cand, active)
        charts.nyquist_svg(cmp.candidate.curves, cmp.active.curves)
        lat.append(((time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3))
    return lat


def summary(ms: list[tuple[float, float]] | list[list[float]]) -> dict[str, float]:
    a = np.asarray(ms, dtype=np.float64).reshape(-1, 2)
    wall, cpu = a[:, 0], a[:, 1]
    return {"p50_ms": float(np.percentile(wall, 50)), "p99_ms": float(np.percentile(wall, 99)),
            "max_ms": float(wall.max()), "cpu_p50_ms": float(np.percentile(cpu, 50)),
            "cpu_p99_ms": float(np.percentile(cpu, 99)), "n": int(a.shape[0])}


def measure_new_parts(n: int, measured: bool) -> dict[str, float]:
    """What the issue-13 views add to one uncached evaluation: both Nyquist loops with their
    refined margins, the plant chart's curves and data, and the two-panel SVG (work tree
    only: these do not exist before)."""
    from controller.core.config import LoopConfig
    from controller.gate.knowledge import KnowledgeRecord
    from server import charts, engine

    record = _knowledge(measured)
    assert isinstance(record, KnowledgeRecord)
    plant = record.to_knowledge()
    eng = engine.TuningEngine()
    eng.set_knowledge(record)
    active = eng.evaluate(LoopConfig()).curves
    f = eng.freq_hz
    rng = np.random.default_rng(1)
    lat = []
    for x in rng.uniform(-1.3, 1.6, n):
        cfg = LoopConfig(q_cutoff_hz=float(10.0 ** round(float(x), 3)))
        cand = eng.evaluate(cfg).curves
        t0, c0 = time.perf_counter(), time.process_time()
        engine.speed_loop(cfg, plant.model, f, dob=True)
        engine.speed_loop(cfg, plant.model, f, dob=False)
        engine.plant_curves(plant, f, cfg.rate_hz)
        charts.bode_data("plant", cand, active)
        charts.nyquist_svg(cand, active)
        lat.append(((time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3))
    return summary(lat)


CASES = (("model only", False), ("3 measured responses", True))


def _subprocess(server_dir: str | None, n: int, seed: int) -> dict[str, list[list[float]]]:
    env = dict(os.environ)
    env.pop("DOBTUNE_BENCH_SERVER_DIR", None)
    if server_dir is not None:
        env["DOBTUNE_BENCH_SERVER_DIR"] = server_dir
    out = subprocess.run([sys.executable, __file__, "--n", str(n), "--seed", str(seed),
                          "--inner"], env=env, check=True, capture_output=True, text=True).stdout
    return json.loads(out)  # type: ignore[no-any-return]


def _extract(rev: str, tmp: str) -> None:
    """server/{__init__,charts,engine}.py of git revision `rev` into tmp/server."""
    pkg = Path(tmp) / "server"
    pkg.mkdir()
    for name in ("__init__.py", "charts.py", "engine.py"):
        text = subprocess.run(["git", "show", f"{rev}:server/{name}"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
        (pkg / name).write_text(text)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=200, help="candidate changes per measurement")
    ap.add_argument("--baseline", metavar="REV", help="also measure server/ at this revision")
    ap.add_argument("--rounds", type=int, default=4,
                    help="with --baseline: alternate before/now in this many rounds (a shared "
                         "machine's load then hits both alike)")
    ap.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.inner:
        print(json.dumps({name: latencies_ms(args.n, m, args.seed) for name, m in CASES}))
        return 0
    out: dict[str, object] = {}
    if args.baseline:
        before: dict[str, list[list[float]]] = {name: [] for name, _ in CASES}
        now: dict[str, list[list[float]]] = {name: [] for name, _ in CASES}
        per = max(1, args.n // args.rounds)
        with tempfile.TemporaryDirectory() as tmp:
            _extract(args.baseline, tmp)
            for r in range(args.rounds):
                for acc, where in ((before, tmp), (now, None)):
                    for name, lat in _subprocess(where, per, seed=r).items():
                        acc[name] += lat
        out[f"before ({args.baseline})"] = {k: summary(v) for k, v in before.items()}
        out["now (work tree)"] = {k: summary(v) for k, v in now.items()}
    else:
        out["now (work tree)"] = {name: summary(latencies_ms(args.n, m)) for name, m in CASES}
    out["now: the new views alone"] = {name: measure_new_parts(args.n, m) for name, m in CASES}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
