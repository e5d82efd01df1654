"""The `dobtune` subcommands, one module each.

Every module exports `COMMAND`: its help line, the function that declares its options and the
function that runs it. Parsing happens only in `controller/__main__.py` and `server/__main__.py`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Command:
    """One subcommand: `add_arguments` declares its options, `run` returns the exit code."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    long_running: bool = False


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


def build_parser(
    prog: str, description: str | None, commands: dict[str, Command]
) -> argparse.ArgumentParser:
    """A parser with one subparser per command."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    sub = parser.add_subparsers(dest="command", required=True)
    for cmd in commands.values():
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        cmd.add_arguments(p)
        if cmd.long_running:
            add_log_level(p)
    return parser


def controller_commands() -> dict[str, Command]:
    """The controller side's commands (imports are light: each module imports its work lazily)."""
    from controller.cli import (
        audit,
        auth,
        autotune,
        check,
        controller,
        ctl,
        experiment,
        identify,
        paper,
        record,
        report,
        router,
    )

    return {c.name: c for c in (experiment.COMMAND, check.COMMAND, controller.COMMAND,
                                identify.COMMAND, audit.COMMAND, auth.COMMAND, ctl.COMMAND,
                                record.COMMAND, report.COMMAND, router.COMMAND,
                                autotune.COMMAND, paper.COMMAND)}
