"""The gate's answers of this tree against an older commit's, on the same random cases: every
analysis field (verdict, reasons, margins, every source's figures, every array, bit for bit),
the recommended cut-off's decision as the gate asks it and the whole search's value.

    PYTHONPATH=$PWD .venv/bin/python tests/bench/gate_answers_ab.py --before main [--n 300]

Each tree runs in a subprocess of its own (PYTHONPATH = the tree) and prints one digest per
case; the two lists must be equal. A speed-up of the gate that is meant to change nothing is
checked here against the code it replaces (the tests check it against slower reference paths
that stay in the repository).

`--quantify` is for a change that is meant to move numbers by rounding only (another matrix
exponential): where the digests differ, it prints the largest relative difference of each
number (margins, every array, relative to the array's largest magnitude; poles as a set: each
to the nearest of the other) and lists every answer that is not a number (verdict, reasons,
the search's decision) that changed: a changed verdict or decision is a change of meaning.
Exit 1 only on such a change.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))


def _numbers(v: object) -> object:
    import numpy as np

    if isinstance(v, np.ndarray):
        return plain(v.tolist())
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, complex):
        return {"re": plain(v.real), "im": plain(v.imag)}
    if isinstance(v, float):
        return v if np.isfinite(v) else repr(v)
    return NotImplemented


def plain(v: object) -> object:
    """A JSON-able form of `v` with its numbers as numbers (complex as [re, im]; non-finite
    floats as strings) for `--quantify`."""
    from gate_cases import json_form

    return json_form(v, _numbers)


def child(n: int, seed: int, searches: int, numbers: bool = False) -> None:
    """Print one digest per case (this process's PYTHONPATH is the tree judged); with
    `numbers`, the answers themselves (`plain`)."""
    from gate_cases import canon, knowledge_set, random_configs

    digest = plain if numbers else canon
    from controller.gate.analysis import analyse
    from controller.gate.search import RecommendationSearch

    plants = knowledge_set()
    t0 = time.process_time()
    for i, (cfg, k) in enumerate(random_configs(n, seed)):
        try:
            a: object = digest(analyse(cfg, plants[k]))
        except Exception as exc:  # the exception is the answer compared
            a = f"{type(exc).__name__}: {exc}"
        row: dict[str, object] = {"case": i, "analysis": a}
        if i < searches and cfg.dob_on:
            fc = cfg.q_cutoff_hz
            s = RecommendationSearch(cfg, plants[k])
            row["decide"] = s.decide(lambda r, fc=fc: not fc > r * 1.0001)
            row["value"] = digest(RecommendationSearch(cfg, plants[k]).value())
        print(json.dumps(row, sort_keys=True), flush=True)
    print(json.dumps({"cpu_s": time.process_time() - t0}), flush=True)


def _run(tree: Path, n: int, seed: int, searches: int,
         numbers: bool = False) -> tuple[list[str], float]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", str(n),
                          "--seed", str(seed), "--searches", str(searches)]
                         + (["--numbers"] if numbers else []),
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
    p.add_argument("--quantify", action="store_true",
                   help="where answers differ, how much (numbers) and whether in meaning")
    p.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--numbers", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.child is not None:
        child(a.child, a.seed, a.searches, a.numbers)
        return 0
    from bench_startup import export_tree

    with tempfile.TemporaryDirectory(prefix="gate-ab-") as d:
        before = export_tree(a.before, Path(d))
        old, old_cpu = _run(before, a.n, a.seed, a.searches)
        new, new_cpu = _run(REPO, a.n, a.seed, a.searches)
        if a.quantify:
            old_v, _ = _run(before, a.n, a.seed, a.searches, numbers=True)
            new_v, _ = _run(REPO, a.n, a.seed, a.searches, numbers=True)
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
    if a.quantify:
        return quantify([json.loads(old_v[i]) for i in differ],
                        [json.loads(new_v[i]) for i in differ])
    return 1 if differ else 0


def _leaves(v: object, path: str, out: dict[str, object]) -> None:
    """Every leaf of `v` by its path; a list of numbers (an array) is one leaf."""
    if isinstance(v, dict) and set(v) != {"re", "im"}:
        for k, x in v.items():
            _leaves(x, f"{path}.{k}" if path else k, out)
    elif isinstance(v, list) and not all(_is_number(x) for x in v):
        for i, x in enumerate(v):
            _leaves(x, f"{path}[{i}]", out)
    else:
        out[path] = v


def _is_number(x: object) -> bool:
    return (isinstance(x, (int, float)) and not isinstance(x, bool)) or (
        isinstance(x, dict) and set(x) == {"re", "im"})


def _flat(x: object) -> list[complex] | None:
    """The numbers of a leaf (None: not numbers, or a non-finite one)."""
    items = x if isinstance(x, list) else [x]
    out = []
    for v in items:
        if isinstance(v, dict) and set(v) == {"re", "im"} and all(
                isinstance(v[k], (int, float)) for k in ("re", "im")):
            out.append(complex(v["re"], v["im"]))
        elif _is_number(v) and not isinstance(v, dict):
            out.append(complex(v))
        else:
            return None
    return out


def quantify(old: list[dict], new: list[dict]) -> int:
    """Print the largest relative difference per field over the differing cases, and every
    changed answer that is not a number; 1 if any such change."""
    worst: dict[str, float] = {}
    changed: list[str] = []
    for x, y in zip(old, new, strict=True):
        lx: dict[str, object] = {}
        ly: dict[str, object] = {}
        _leaves(x, "", lx)
        _leaves(y, "", ly)
        for k in sorted(set(lx) | set(ly)):
            u, v = lx.get(k), ly.get(k)
            if u == v:
                continue
            fu, fv = _flat(u), _flat(v)
            if fu is None or fv is None or len(fu) != len(fv):
                changed.append(f"case {x['case']}: {k}: {u!r:.80} -> {v!r:.80}")
                continue
            scale = max(max(abs(z) for z in fu), max(abs(z) for z in fv))
            field = re.sub(r"\[\d+\]", "[]", k.split(".", 1)[1] if "." in k else k)
            if field.endswith("poles"):  # a set (eigenvalues): each to the nearest of the other
                rel = max(max(min(abs(p - q) for q in b) for p in a)
                          for a, b in ((fu, fv), (fv, fu))) / scale
            else:
                rel = max(abs(p - q) for p, q in zip(fu, fv, strict=True)) / scale
            worst[field] = max(worst.get(field, 0.0), rel)
    print(f"largest relative difference over the {len(old)} differing cases, by field:")
    for k, r in sorted(worst.items(), key=lambda kv: -kv[1]):
        print(f"  {r:9.2e}  {k}")
    print(f"answers that are not numbers and changed: {len(changed)}")
    for c in changed[:20]:
        print(f"  {c}")
    return 1 if changed else 0


if __name__ == "__main__":
    sys.exit(main())
