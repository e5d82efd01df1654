"""The dependency rules of the layout (docs/architecture.md), checked on the source (AST).

Every import counts, also the ones inside functions: a lazy import is still a dependency.
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("controller", "server")

#: Pure packages: math and plain data, no I/O frameworks, no threads, no processes.
PURE = (
    "controller.core", "controller.gate", "controller.sim", "controller.ident", "controller.tune",
    "controller.twin", "controller.watch",
)
#: What a pure package may not import (top-level module names).
IMPURE_LIBS = {
    "zenoh", "can", "viser", "threading", "multiprocessing", "subprocess", "socket",
    "asyncio", "concurrent", "playwright", "signal", "logging",
}
#: Which project packages each pure package may import (besides itself).
PURE_MAY_IMPORT = {
    "controller.core": (),
    "controller.gate": ("controller.core",),
    "controller.sim": ("controller.core",),
    "controller.ident": ("controller.core", "controller.gate", "controller.sim"),
    "controller.tune": ("controller.core", "controller.gate", "controller.sim", "controller.ident",
                        "controller.twin"),
    "controller.twin": ("controller.core", "controller.gate", "controller.sim", "controller.ident"),
    "controller.watch": ("controller.core", "controller.gate", "controller.sim", "controller.twin"),
}
#: The wire contract imports only plain data types.
PROTOCOL_MAY_IMPORT = ("controller.core", "controller.ident.spec", "controller.gate.knowledge")
#: What the dashboard may take from the controller side.
SERVER_MAY_IMPORT = (
    *PURE,
    "controller.protocol", "controller.client", "controller.logs",
    # the users file and the client-side Zenoh credentials (the dashboard gives each user of
    # an auth directory a URL and logs in as them)
    "controller.auth",
    # recordings (MCAP files) and their metrics: the Recordings panel lists and compares them
    "controller.recording",
    # a file replaced whole or not at all: the dashboard's kept candidates
    "controller.files",
)


def module_name(path: Path, root: Path = ROOT) -> str:
    rel = path.relative_to(root).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def modules(root: Path = ROOT) -> dict[str, Path]:
    """The project's modules by dotted name (of the tree at `root`)."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            out[module_name(path, root)] = path
    return out


MODULES = modules()


def resolve(mod: str, node: ast.ImportFrom, mods: dict[str, Path] = MODULES) -> str:
    if node.level == 0:
        return node.module or ""
    is_pkg = mods[mod].name == "__init__.py"
    base = mod.split(".")
    base = base if is_pkg else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports(mod: str, mods: dict[str, Path] = MODULES) -> Iterator[tuple[str, int, list[str]]]:
    """(imported module, line, names imported from it) for every import in `mod`."""
    tree = ast.parse(mods[mod].read_text(), filename=str(mods[mod]))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno, []
        elif isinstance(node, ast.ImportFrom):
            target = resolve(mod, node, mods)
            names = [a.name for a in node.names]
            # `from pkg import module` imports the module
            sub = [n for n in names if f"{target}.{n}" in mods]
            for n in sub:
                yield f"{target}.{n}", node.lineno, []
            rest = [n for n in names if n not in sub]
            if rest or not sub:
                yield target, node.lineno, rest


def project_target(name: str, mods: dict[str, Path] = MODULES) -> str | None:
    """The project module an import refers to (the longest known prefix)."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        cand = ".".join(parts[:i])
        if cand in mods:
            return cand
    return None


def within(mod: str, prefixes: tuple[str, ...]) -> bool:
    return any(mod == p or mod.startswith(p + ".") for p in prefixes)


def bad_imports(of: Callable[[str], bool], bad: Callable[[str, str], bool]) -> list[str]:
    """'<module> line <n>: <import>' for every import `name` of each module `mod` with
    `of(mod)` for which `bad(mod, name)`."""
    return [f"{mod} line {line}: {name}" for mod in MODULES if of(mod)
            for name, line, _ in imports(mod) if bad(mod, name)]


def test_the_layout_has_the_packages() -> None:
    for pkg in (*PURE, "controller.rig", "controller.process", "controller.cli",
                "controller.protocol", "controller.client", "server.panels"):
        assert pkg in MODULES, f"{pkg} is missing"


@pytest.mark.parametrize("mod", sorted(m for m in MODULES if within(m, PURE)))
def test_pure_packages_import_no_io_and_point_one_way(mod: str) -> None:
    own = next(p for p in PURE if within(mod, (p,)))
    allowed = (own, *PURE_MAY_IMPORT[own])
    bad = []
    for name, line, _ in imports(mod):
        top = name.split(".")[0]
        outside = top in PACKAGES and not within(project_target(name) or name, allowed)
        if top in IMPURE_LIBS or outside:
            bad.append(f"line {line}: {name}")
    assert not bad, f"{mod} imports {bad}"


def test_protocol_imports_only_plain_data() -> None:
    bad = [
        f"line {line}: {name}"
        for name, line, _ in imports("controller.protocol")
        if name.split(".")[0] in PACKAGES
        and not within(project_target(name) or name, PROTOCOL_MAY_IMPORT)
    ]
    assert not bad, bad


#: The commands that run the dashboard: the only controller modules that import `server`, and
#: only inside a function (when the command runs), never at import time.
LOADS_THE_DASHBOARD = ("controller.cli.dashboard", "controller.cli.demo")


def module_level_imports(mod: str) -> set[str]:
    """The modules `mod` imports at import time (statements at module level, not in a
    function or class body)."""
    out: set[str] = set()
    tree = ast.parse(MODULES[mod].read_text())
    for node in tree.body:
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            out.add(resolve(mod, node))
    return out


def test_controller_never_imports_server() -> None:
    bad = bad_imports(lambda mod: mod.startswith("controller"),
                      lambda mod, name: name.split(".")[0] == "viser"
                      or (name.split(".")[0] == "server" and mod not in LOADS_THE_DASHBOARD))
    assert not bad, bad
    eager = [f"{mod}: {name}" for mod in LOADS_THE_DASHBOARD
             for name in module_level_imports(mod) if name.split(".")[0] == "server"]
    assert not eager, eager


def test_server_imports_only_the_controllers_public_side() -> None:
    def outside(mod: str, name: str) -> bool:
        target = project_target(name) or name
        return name.startswith("controller") and not within(target, SERVER_MAY_IMPORT)

    bad = bad_imports(lambda mod: mod.startswith("server"), outside)
    assert not bad, bad


def module_graph(mods: dict[str, Path] = MODULES) -> dict[str, set[str]]:
    """Each module's project imports (every import counts: a module's import of its own
    package's __init__ too)."""
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod in mods:
        for name, _, _ in imports(mod, mods):
            target = project_target(name, mods)
            if target and target != mod:
                graph[mod].add(target)
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return cycles


def test_no_import_cycles() -> None:
    cycles = import_cycles(module_graph())
    assert not cycles, cycles


def any_in_signatures(path: Path) -> int:
    """Parameters and returns annotated with `Any` (alone or inside), of every function."""
    count = 0
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            a = node.args
            anns = [x.annotation for x in (*a.posonlyargs, *a.args, *a.kwonlyargs,
                                           *([a.vararg] if a.vararg else []),
                                           *([a.kwarg] if a.kwarg else []))]
            anns.append(node.returns)
            count += sum(1 for t in anns if t is not None and "Any" in {
                n.id for n in ast.walk(t) if isinstance(n, ast.Name)} | {
                n.attr for n in ast.walk(t) if isinstance(n, ast.Attribute)})
    return count


#: The dashboard's modules whose signatures may name `Any`, and how many (issue 32: 185 at
#: the start; 0 now: viser's handles, websockets' connections, requests and responses, and
#: viser's message classes have their own types, uPlot's options are `dict[str, object]`).
SERVER_ANY_CEILING: dict[str, int] = {}


def test_any_does_not_return_to_the_dashboards_signatures() -> None:
    """Viser's handles have types (`viser.GuiApi`, `ClientHandle`, `Gui*Handle`; the few
    assignments its hints miss are typed once in server/gui.py): a signature of `server/`
    that names `Any` where its module had none, or more than its ceiling, fails."""
    over = [f"{m}: {n} (at most {SERVER_ANY_CEILING.get(m, 0)})"
            for m, path in MODULES.items() if m == "server" or m.startswith("server.")
            if (n := any_in_signatures(path)) > SERVER_ANY_CEILING.get(m, 0)]
    assert not over, f"Any in server/ signatures: {over}"


#: The most lines a class of the dashboard may have (issue 32: a class that holds widgets,
#: threads, state and HTML is split along its seams before it grows past this).
SERVER_CLASS_MAX_LINES = 300


def test_no_class_in_server_over_300_lines() -> None:
    big = [f"{m}.{node.name}: {n} lines"
           for m, path in MODULES.items() if m == "server" or m.startswith("server.")
           for node in ast.walk(ast.parse(path.read_text())) if isinstance(node, ast.ClassDef)
           if (n := (node.end_lineno or node.lineno) - node.lineno + 1) > SERVER_CLASS_MAX_LINES]
    assert not big, big


def test_no_private_names_across_modules() -> None:
    bad = []
    for mod in MODULES:
        tree = ast.parse(MODULES[mod].read_text())
        aliases: dict[str, str] = {}
        for name, line, names in imports(mod):
            target = project_target(name)
            if target is None or target == mod:
                continue
            bad += [f"{mod} line {line}: {target}.{n}" for n in names
                    if n.startswith("_") and not n.startswith("__")]
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if project_target(a.name) == a.name:
                        aliases[a.asname or a.name] = a.name
            elif isinstance(node, ast.ImportFrom):
                target = resolve(mod, node)
                for a in node.names:
                    if f"{target}.{a.name}" in MODULES:
                        aliases[a.asname or a.name] = f"{target}.{a.name}"
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in aliases
                and node.attr.startswith("_")
                and not node.attr.startswith("__")
            ):
                bad.append(f"{mod} line {node.lineno}: {aliases[node.value.id]}.{node.attr}")
    assert not bad, bad


#: Only the rig package talks to CAN hardware (python-can).
CAN_IMPORTERS = ("controller.rig",)
#: File I/O calls that a pure package may not make (it computes and returns result objects).
FILE_IO_ATTRS = {"read_text", "write_text", "read_bytes", "write_bytes", "mkdir", "unlink",
                 "touch", "rmdir"}
#: Where key strings (`dobtune/...`) may be written.
KEY_OWNER = "controller.protocol"


def test_only_the_rig_package_imports_python_can() -> None:
    bad = bad_imports(lambda mod: not within(mod, CAN_IMPORTERS),
                      lambda _mod, name: name.split(".")[0] == "can")
    assert not bad, bad


@pytest.mark.parametrize("mod", sorted(m for m in MODULES if within(m, PURE)))
def test_pure_packages_do_no_file_io(mod: str) -> None:
    tree = ast.parse(MODULES[mod].read_text())
    bad = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        if isinstance(f, ast.Name) and f.id == "open":
            bad.append(f"line {node.lineno}: open()")
        elif isinstance(f, ast.Attribute) and f.attr in FILE_IO_ATTRS | {"open"}:
            bad.append(f"line {node.lineno}: .{f.attr}()")
    assert not bad, f"{mod}: {bad}"


def test_key_strings_only_in_protocol() -> None:
    """No `dobtune/...` key literal (plain or the head of an f-string) outside protocol."""
    bad = []
    for mod in MODULES:
        if mod == KEY_OWNER:
            continue
        for node in ast.walk(ast.parse(MODULES[mod].read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                text = node.value
                if text.startswith("dobtune/") and " " not in text:
                    bad.append(f"{mod} line {node.lineno}: {text!r}")
    assert not bad, bad


def test_server_never_imports_the_cli() -> None:
    bad = bad_imports(lambda mod: mod.startswith("server"),
                      lambda _mod, name: within(name, ("controller.cli",)))
    assert not bad, bad


#: The dashboard's folders in layers, top first: each imports only its own and those after it.
#: `server/dashboard/` is the composition (the `Dashboard`, each browser's candidate panels, the
#: demo), `server/panels/` the views, `server/*.py` the helpers the views use.
SERVER_LAYERS = ("server.dashboard", "server.panels", "server")


def server_layer(mod: str) -> int:
    """The layer of a dashboard module (its folder's place in SERVER_LAYERS)."""
    folder = mod if MODULES[mod].name == "__init__.py" else mod.rsplit(".", 1)[0]
    return SERVER_LAYERS.index(folder)


def test_the_dashboards_folders_point_one_way() -> None:
    """composition (server/dashboard/) -> panels (server/panels/) -> helpers (server/*.py):
    no import from a lower folder to a higher one, so no two folders import each other."""
    bad = [f"{mod} line {line}: {name}"
           for mod in MODULES if mod.startswith("server.")
           for name, line, _ in imports(mod)
           if (t := project_target(name)) is not None and t.startswith("server.")
           and server_layer(t) < server_layer(mod)]
    assert not bad, bad


def test_the_docs_show_the_rules_the_tests_enforce() -> None:
    doc = (ROOT / "docs" / "architecture.md").read_text()
    for row in RULES:
        assert row in doc, f"docs/architecture.md lacks the rule: {row}"


#: The rules table of docs/architecture.md, row by row (each enforced by a test above).
RULES = (
    "| pure packages (`core`, `gate`, `sim`, `ident`, `tune`, `twin`, `watch`) import no zenoh, "
    "can, viser, threading, multiprocessing, subprocess, socket, asyncio, concurrent, signal, "
    "logging |",
    "| pure packages do no file I/O |",
    "| `gate` imports `core`; `sim` imports `core`; `ident` imports `core`, `gate`, `sim`; "
    "`twin` imports `core`, `gate`, `sim`, `ident`; `tune` imports those and `twin`; `watch` "
    "imports `core`, `gate`, `sim`, `twin` |",
    "| `controller/protocol.py` imports only `core`, `ident.spec`, `gate.knowledge` |",
    "| `controller` never imports `server` or `viser`, but `controller/cli/dashboard.py` and "
    "`demo.py` (`dobtune dashboard`, `dobtune demo`) load `server` when they run (inside a "
    "function, never at import time) |",
    "| only `controller/rig` imports python-can |",
    "| key strings (`dobtune/...`) only in `controller/protocol.py` |",
    "| `server` imports from the controller side only the pure packages, `protocol`, `client`, "
    "`logs`, `auth`, `recording`, `files` |",
    "| `server` never imports `controller/cli` (the command line's root is the CLI package: "
    "`dobtune dashboard` and `demo` load `server` when they run) |",
    "| each package imports exactly what its row of the packages table says it may import "
    "(nothing else, and nothing listed goes unused) |",
    "| `server/` in layers, one direction: `server/dashboard/` (the composition: `app`, "
    "`candidates`, `demo`) imports `server/panels/` (the views), which import `server/*.py` (the "
    "helpers); a helper never imports a panel or the composition, a panel never the composition |",
    "| no import cycles between modules (every import counted: lazy ones, package `__init__`) |",
    "| no private name (`_x`) imported from or accessed on another module |",
)


# -- the packages table's "may import" column, both ways -------------------------------------


def packages_table(doc: str | None = None) -> dict[str, tuple[str, ...]]:
    """The packages table of docs/architecture.md: each row's package or module (dotted) ->
    what it may import (dotted, the backticked names of the last column: `x` is controller.x,
    `server...` the dashboard's)."""
    import re

    doc = doc if doc is not None else (ROOT / "docs" / "architecture.md").read_text()
    section = doc.split("## Packages", 1)[1].split("\n## ", 1)[0]
    rows: dict[str, tuple[str, ...]] = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 3 or not cells[0].startswith("`"):
            continue
        path = cells[0].strip("`").removesuffix("/").removesuffix(".py")
        names = re.findall(r"`([^`]+)`", cells[2])
        rows[path.replace("/", ".")] = tuple(
            n.replace("/", ".") if n.startswith("server") else f"controller.{n}" for n in names)
    return rows


def row_of(mod: str, rows: dict[str, tuple[str, ...]]) -> str | None:
    """The table row a module belongs to (the longest row prefix)."""
    best = [r for r in rows if within(mod, (r,))]
    return max(best, key=len) if best else None


def row_imports(rows: dict[str, tuple[str, ...]], mods: dict[str, Path] = MODULES
                ) -> dict[str, set[str]]:
    """Each row's imports of project modules outside the row (every import counted; for the
    dashboard's rows, only those of the controller side)."""
    graph = module_graph(mods)
    out: dict[str, set[str]] = {r: set() for r in rows}
    for mod, targets in graph.items():
        r = row_of(mod, rows)
        if r is None:
            continue
        for t in targets:
            if within(t, (r,)) or row_of(t, rows) == r:
                continue
            if r.startswith("server") and not t.startswith("controller"):
                continue  # (the dashboard's own parts: the server rows' rules)
            out[r].add(t)
    return out


def test_every_module_has_a_row_in_the_packages_table() -> None:
    rows = packages_table()
    missing = sorted(m for m in MODULES if m not in PACKAGES and row_of(m, rows) is None)
    assert not missing, f"docs/architecture.md's packages table has no row for {missing}"


def test_each_package_imports_what_its_row_says_and_nothing_else() -> None:
    """The "may import" column is true both ways: every import is listed, and every listed
    name is imported (a stale claim fails too)."""
    rows = packages_table()
    got = row_imports(rows)
    unlisted, unused = [], []
    for r, allowed in rows.items():
        unlisted += [f"{r} imports {t}" for t in sorted(got[r]) if not within(t, allowed)]
        unused += [f"{r} lists {a}" for a in allowed if not any(within(t, (a,)) for t in got[r])]
    assert not unlisted, f"not in the packages table's 'may import' column: {unlisted}"
    assert not unused, f"listed in 'may import' but not imported: {unused}"
