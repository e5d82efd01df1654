"""The gate's answers of this tree against an older commit's, on the same random cases: every
analysis field (verdict, reasons, margins, every source's figures, every array, bit for bit),
the recommended cut-off's decision as the gate asks it and the whole search's value.

    PYTHONPATH=$PWD .venv/bin/python tests/bench/gate_answers_ab.py --before main [--n 300]

Each tree runs in a subprocess of its own (PYTHONPATH = the tree) and prints one digest per
case; the two lists must be equal. A speed-up of the gate that is meant to change nothing is
checked here against the code it replaces (the tests check it against slower reference paths
that stay in the repository).
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

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))


def child(n: int, seed: int, searches: int) -> None:
    """Print one digest per case (this process's PYTHONPATH is the tree judged)."""
    from gate_cases import canon, knowledge_set, random_configs

    from controller.gate.analysis import analyse
    from controller.gate.search import RecommendationSearch

    plants = knowledge_set()
    t0 = time.process_time()
    for i, (cfg, k) in enumerate(random_configs(n, seed)):
        try:
            a: object = canon(analyse(cfg, plants[k]))
        except Exception as exc:  # the exception is the answer compared
            a = f"{type(exc).__name__}: {exc}"
        row: dict[str, object] = {"case": i, "analysis": a}
        if i < searches and cfg.dob_on:
            fc = cfg.q_cutoff_hz
            s = RecommendationSearch(cfg, plants[k])
            row["decide"] = s.decide(lambda r, fc=fc: not fc > r * 1.0001)
            row["value"] = canon(RecommendationSearch(cfg, plants[k]).value())
        print(json.dumps(row, sort_keys=True), flush=True)
    print(json.dumps({"cpu_s": time.process_time() - t0}), flush=True)


def _run(tree: Path, n: int, seed: int, searches: int) -> tuple[list[str], float]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", str(n),
                          "--seed", str(seed), "--searches", str(searches)],
                         env=env, check=True, capture_output=True, text=True, cwd=tree).stdout
    lines = out.splitlines()
    return lines[:-1], float(json.loads(lines[-1])["cpu_s"])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", default="main", help="the commit compared with (default main)")
    p.add_argument("--n", type=int, default=300, help="random cases (default 300)")
    p.add_argument("--searches", type=int, default=60,
                   help="of them, the first N with the DOB on also search (default 60)")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.child is not None:
        child(a.child, a.seed, a.searches)
        return 0
    from bench_startup import export_tree

    with tempfile.TemporaryDirectory(prefix="gate-ab-") as d:
        before = export_tree(a.before, Path(d))
        old, old_cpu = _run(before, a.n, a.seed, a.searches)
        new, new_cpu = _run(REPO, a.n, a.seed, a.searches)
    differ = [i for i, (x, y) in enumerate(zip(old, new, strict=True)) if x != y]
    print(f"{a.n} cases ({a.searches} first with a search): {len(differ)} differ; CPU "
          f"{a.before} {old_cpu:.1f} s, this tree {new_cpu:.1f} s")
    for i in differ[:5]:
        x, y = json.loads(old[i]), json.loads(new[i])
        keys = sorted(k for k in x if x.get(k) != y.get(k))
        detail = keys
        if "analysis" in keys and isinstance(x["analysis"], dict):
            detail = [f"analysis.{k}" for k in x["analysis"]
                      if x["analysis"][k] != y["analysis"].get(k)]
        print(f"  case {i}: {detail}")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
