"""The layout in numbers: modules per package and their sizes, and the package dependency graph
(every import counted, as tests/test_layout.py counts them); optionally for an older commit too.

    .venv/bin/python tests/bench/layout_figures.py [--before REV]

A package is a folder of `controller/` or `server/` (`controller.protocol` and the other
top-level modules stand alone). Lines are physical lines of the .py files. The graph lists,
for each package, the packages it imports (`a -> b, c`); the module-level cycle check is the
test's (`test_no_import_cycles`), run here on the same graph and printed as a count.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tarfile
import tempfile
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))

from test_layout import PACKAGES, import_cycles, module_graph, modules  # noqa: E402


def package_of(mod: str, mods: dict[str, Path]) -> str:
    """The folder a module lives in (a package's __init__ belongs to that package)."""
    if mods[mod].name == "__init__.py":
        return mod
    parent = mod.rsplit(".", 1)[0]
    return parent if parent not in PACKAGES else mod


def report(root: Path, title: str) -> None:
    mods = modules(root)
    sizes: dict[str, list[tuple[int, str]]] = defaultdict(list)
    for mod, path in mods.items():
        sizes[package_of(mod, mods)].append((len(path.read_text().splitlines()), mod))
    print(f"== {title}: {len(mods)} modules, "
          f"{sum(n for v in sizes.values() for n, _ in v)} lines")
    print(f"{'package':28s} {'modules':>7s} {'lines':>6s} {'largest':>7s}  largest module")
    for pkg in sorted(sizes):
        rows = sizes[pkg]
        n, big = max(rows)
        print(f"{pkg:28s} {len(rows):7d} {sum(r for r, _ in rows):6d} {n:7d}  {big}")
    graph = module_graph(mods)
    pkg_graph: dict[str, set[str]] = defaultdict(set)
    for m, targets in graph.items():
        for t in targets:
            a, b = package_of(m, mods), package_of(t, mods)
            if a != b:
                pkg_graph[a].add(b)
    print("package imports (every import counted):")
    for pkg in sorted(sizes):
        print(f"  {pkg} -> {', '.join(sorted(pkg_graph[pkg])) or '-'}")
    print(f"module import cycles: {len(import_cycles(graph))}; "
          f"module import edges: {sum(len(v) for v in graph.values())}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", help="also the tree of this commit (git archive)")
    args = ap.parse_args()
    if args.before:
        with tempfile.TemporaryDirectory() as tmp:
            tar = Path(tmp) / "tree.tar"
            subprocess.run(["git", "-C", str(REPO), "archive", "-o", str(tar), args.before],
                           check=True)
            with tarfile.open(tar) as t:
                t.extractall(Path(tmp) / "tree", filter="data")
            report(Path(tmp) / "tree", f"before ({args.before})")
    report(REPO, "this tree")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
