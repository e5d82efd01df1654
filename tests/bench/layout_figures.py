"""The layout in numbers: modules per package and their sizes, and the package dependency graph
(every import counted, as tests/test_layout.py counts them); optionally for an older commit too.

    .venv/bin/python tests/bench/layout_figures.py [--before REV] [--doc]

Also: the largest class of each package (lines, methods), package cycles (packages that import
each other), `Any` in the signatures of `server/` (annotations of parameters and returns), and
the private-attribute reaches: `x._name` where x is not `self`/`cls` (another object's or
module's private part), counted per package with the modules that make them, and beside
them the reaches by name (`getattr(x, "_name")`, `setattr`) and the imports of another
library's private module or name (`from viser._messages import ...`). `--doc` writes
this tree's table into docs/architecture.md between the `layout-figures` markers (the doc's
numbers are this script's, never typed by hand).

A package is a folder of `controller/` or `server/` (`controller.protocol` and the other
top-level modules stand alone). Lines are physical lines of the .py files. The graph lists,
for each package, the packages it imports (`a -> b, c`); the module-level cycle check is the
test's (`test_no_import_cycles`), run here on the same graph and printed as a count.
"""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
import tarfile
import tempfile
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))

from test_layout import (  # noqa: E402
    PACKAGES,
    any_in_signatures,
    import_cycles,
    module_graph,
    modules,
)

DOC = REPO / "docs" / "architecture.md"
BEGIN, END = "<!-- layout-figures: begin -->", "<!-- layout-figures: end -->"


def package_of(mod: str, mods: dict[str, Path]) -> str:
    """The folder a module lives in (a package's __init__ belongs to that package)."""
    if mods[mod].name == "__init__.py":
        return mod
    parent = mod.rsplit(".", 1)[0]
    return parent if parent not in PACKAGES else mod


def classes(path: Path) -> list[tuple[int, int, str]]:
    """(lines, methods, name) of every class of a module."""
    tree = ast.parse(path.read_text())
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef):
            n = (node.end_lineno or node.lineno) - node.lineno + 1
            methods = sum(isinstance(b, ast.FunctionDef | ast.AsyncFunctionDef) for b in node.body)
            out.append((n, methods, node.name))
    return out


def private_reaches(path: Path) -> int:
    """`x._name` (not dunder) where x is not `self` or `cls`: a reach into another object's or
    module's private part."""
    count = 0
    for node in ast.walk(ast.parse(path.read_text())):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                and not node.attr.startswith("__")
                and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
            count += 1
    return count


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_reaches_other(path: Path) -> tuple[int, int]:
    """Reaches the attribute count misses: (by name: `getattr`/`setattr`/`hasattr`/`delattr`
    with a private name's literal, imports of a private module or name of another library:
    `from viser._messages import X`, `from viser._gui_handles import _GuiHandle`; type-only
    imports count too)."""
    by_name = imported = 0
    for node in ast.walk(ast.parse(path.read_text())):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                and node.func.id in ("getattr", "setattr", "hasattr", "delattr")
                and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
                and isinstance(node.args[1].value, str) and _private(node.args[1].value)):
            by_name += 1
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and (
                node.module.split(".")[0] not in PACKAGES) and (
                any(_private(part) for part in node.module.split("."))
                or any(_private(a.name) for a in node.names)):
            imported += 1
    return by_name, imported


def package_cycles(pkg_graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """Pairs of packages that import each other (directly)."""
    return sorted((a, b) for a in pkg_graph for b in pkg_graph[a]
                  if a < b and a in pkg_graph.get(b, set()))


def table(root: Path) -> str:
    """The per-package table (markdown) of the tree at `root`."""
    mods = modules(root)
    rows: dict[str, list[tuple[int, str, Path]]] = defaultdict(list)
    for mod, path in mods.items():
        folder = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
        key = folder.replace(".", "/") + ("/*.py" if folder in PACKAGES else "/")
        rows[key].append((len(path.read_text().splitlines()), mod, path))
    out = ["| folder | files | lines | largest module | largest class (lines, methods) |",
           "|---|---|---|---|---|"]
    for pkg in sorted(rows):
        rs = rows[pkg]
        n, big, _ = max(rs)
        cls = max(((*c, m) for _, m, p in rs for c in classes(p)), default=None)
        cell = (f"`{cls[2]}` ({cls[3].rsplit('.', 1)[-1]}.py, {cls[0]}, {cls[1]})"
                if cls else "-")
        out.append(f"| `{pkg}` | {len(rs)} | {sum(r for r, _, _ in rs)} | "
                   f"`{big.rsplit('.', 1)[-1]}` {n} | {cell} |")
    return "\n".join(out)


def write_doc() -> None:
    doc = DOC.read_text()
    head, rest = doc.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    DOC.write_text(f"{head}{BEGIN}\n{table(REPO)}\n{END}{tail}")


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
    pc = package_cycles(pkg_graph)
    print(f"package cycles (packages as listed above, each top-level module its own): {len(pc)} "
          + ", ".join(f"{a} <-> {b}" for a, b in pc))
    print(f"module import cycles: {len(import_cycles(graph))}; "
          f"module import edges: {sum(len(v) for v in graph.values())}")
    def folder(m: str) -> str:
        return m if mods[m].name == "__init__.py" else m.rsplit(".", 1)[0]

    edges: dict[tuple[str, str], int] = defaultdict(int)
    for m, targets in graph.items():
        for t in targets:
            if folder(m) != folder(t) and t not in PACKAGES:
                edges[folder(m), folder(t)] += 1
    cyc = sorted((a, b) for a, b in edges if a < b and (b, a) in edges)
    print("folder cycles (folders importing each other, imports each way; `controller` is its "
          f"top-level modules together: __main__, auth, protocol, ...): {len(cyc)} "
          + ", ".join(f"{a} {edges[a, b]} -> {b}, {edges[b, a]} back" for a, b in cyc))
    print("largest class per package (lines, methods):")
    for pkg in sorted(sizes):
        cls = max(((*c, m) for m in mods if package_of(m, mods) == pkg
                   for c in classes(mods[m])), default=None)
        if cls:
            print(f"  {pkg:28s} {cls[2]} ({cls[3]}): {cls[0]} lines, {cls[1]} methods")
    anys = {m: any_in_signatures(p) for m, p in mods.items() if m.startswith("server")}
    print(f"Any in server/ signatures: {sum(anys.values())} "
          f"({', '.join(f'{m} {n}' for m, n in sorted(anys.items()) if n)})")
    reach = {m: private_reaches(p) for m, p in mods.items()}
    by_pkg: dict[str, int] = defaultdict(int)
    for m, n in reach.items():
        by_pkg[".".join(m.split(".")[:2])] += n
    print(f"private-attribute reaches (x._name, x not self/cls): {sum(reach.values())}; "
          + ", ".join(f"{k} {v}" for k, v in sorted(by_pkg.items()) if v))
    print("  where (server/): " + ", ".join(
        f"{m} {n}" for m, n in sorted(reach.items()) if n and m.startswith("server")))
    other = {m: private_reaches_other(p) for m, p in mods.items()}
    print("  besides (by name in getattr/setattr, private modules or names of a library "
          f"imported): {sum(a for a, _ in other.values())} by name, "
          f"{sum(b for _, b in other.values())} imports; "
          + ", ".join(f"{m} {a}+{b}" for m, (a, b) in sorted(other.items()) if a or b))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", help="also the tree of this commit (git archive)")
    ap.add_argument("--doc", action="store_true",
                    help="write this tree's table into docs/architecture.md")
    args = ap.parse_args()
    if args.doc:
        write_doc()
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
