"""What every `dobtune` subcommand shares: the `Command` record, the parser that builds them
(options anywhere on the line), `--log-level`, on/off switches, progress and tables."""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TextIO

__all__ = [
    "LOG_LEVELS",
    "Command",
    "IntermixedParser",
    "add_log_level",
    "build_parser",
    "lazy_command",
    "markdown_table",
    "on_off",
    "progress_printer",
]


@dataclass(frozen=True)
class Command:
    """One subcommand: `add_arguments` declares its options, `run` returns the exit code."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    long_running: bool = False


class IntermixedParser(argparse.ArgumentParser):
    """A parser whose options may come anywhere among its positionals, as in every common CLI
    (`dobtune ctl ... apply --expect-version 1 q_cutoff_hz=0.8`): its parses are
    `parse_known_intermixed_args`, also when it is a subcommand's parser."""

    _intermixing = False
    #: Declares this parser's options on its first parse (`build_parser`: a subcommand's
    #: options, and the imports they need, only for the subcommand that is run).
    declare: Callable[[], None] | None = None

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: Any = None
    ) -> tuple[argparse.Namespace, list[str]]:
        declare, self.declare = self.declare, None
        if declare is not None:
            declare()
        if self._intermixing or self._subparsers is not None:
            return super().parse_known_args(args, namespace)
        self._intermixing = True
        try:
            return self.parse_known_intermixed_args(args, namespace)
        finally:
            self._intermixing = False


def on_off(value: str) -> bool:
    """argparse type for `on|off` switches."""
    if value not in ("on", "off"):
        raise argparse.ArgumentTypeError(f"expected on or off, got {value!r}")
    return value == "on"


LOG_LEVELS = ("debug", "info", "warning", "error")


def add_log_level(p: argparse.ArgumentParser) -> None:
    """`--log-level` for long-running commands (logs go to stderr)."""
    p.add_argument(
        "--log-level", choices=LOG_LEVELS, default="info", help="stderr log level (default info)"
    )


def _pid(text: str) -> int:
    try:
        pid = int(text)
    except ValueError:
        pid = 0
    if pid <= 0:
        raise argparse.ArgumentTypeError(f"expected a process id (> 0), got {text!r}")
    return pid


def add_parent_pid(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument(
        "--parent-pid", type=_pid, default=None, metavar="PID",
        help=f"stop (as on SIGTERM) once process PID, which started this {what}, is gone: a "
        f"launcher killed outright (SIGKILL) leaves no {what} running (`dobtune demo` passes "
        "its own)",
    )


def end_with_parent(parent_pid: int | None, say: Callable[[str], None]) -> None:
    """With `--parent-pid`: stop this process (SIGTERM to itself) when that parent is gone."""
    if parent_pid is None:
        return
    from controller.process.parent_watch import stop_self, watch_parent

    def gone() -> None:
        say(f"the process that started this one (pid {parent_pid}) is gone: stopping")
        stop_self()

    watch_parent(parent_pid, gone)


def build_parser(
    prog: str, description: str | None, commands: dict[str, Command]
) -> argparse.ArgumentParser:
    """A parser with one subparser per command (each takes its options anywhere). A
    subcommand's options are declared when it is parsed: `dobtune ctl ...` imports nothing of
    `check`'s (with `lazy_command`, not even its module)."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=IntermixedParser)
    for cmd in commands.values():
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        assert isinstance(p, IntermixedParser)
        p.declare = lambda p=p, cmd=cmd: _declare(p, cmd)  # type: ignore[misc]
    return parser


def _declare(p: argparse.ArgumentParser, cmd: Command) -> None:
    cmd.add_arguments(p)
    if cmd.long_running:
        add_log_level(p)


def lazy_command(name: str, help: str, module: str, *, long_running: bool = False) -> Command:
    """A command whose module (its `add_arguments` and `run`, and what they import) is imported
    only when the command is used: `dobtune check` never loads the experiments' or the
    identification's code (scipy.optimize, the paper's figures)."""

    def add_arguments(p: argparse.ArgumentParser) -> None:
        importlib.import_module(module).add_arguments(p)

    def run(args: argparse.Namespace) -> int:
        code: int = importlib.import_module(module).run(args)
        return code

    return Command(name, help, add_arguments, run, long_running)


def progress_printer(err: TextIO, label: str) -> Callable[[float], None] | None:
    """A progress bar on `err` when it is a terminal (None otherwise)."""
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


def markdown_table(columns: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A GitHub-flavoured markdown table (pipes in cells escaped)."""

    def cell(x: str) -> str:
        return str(x).replace("|", "\\|")

    lines = ["| " + " | ".join(cell(c) for c in columns) + " |",
             "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(c) for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"
