"""`dobtune` console script (all subcommands) and `python -m server` (the dashboard)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from controller.__main__ import COMMANDS as CONTROLLER_COMMANDS


def add_dashboard_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--connect",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="controller's Zenoh endpoint (repeatable; default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--rig-name", default="demo")
    p.add_argument("--host", default="127.0.0.1", help="HTTP bind address (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080)


def run_dashboard_args(args: argparse.Namespace) -> int:
    from server.app import DashboardOptions, run_dashboard

    connect = args.connect if args.connect is not None else ["tcp/127.0.0.1:7447"]
    return run_dashboard(
        DashboardOptions(
            connect=tuple(connect), rig_name=args.rig_name, host=args.host, port=args.port
        )
    )


def add_demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8080)
    p.add_argument("--zenoh-port", type=int, default=7447)
    p.add_argument("--rig-name", default="demo")


def run_demo_args(args: argparse.Namespace) -> int:
    from server.demo import DemoOptions, run_demo

    return run_demo(
        DemoOptions(
            host=args.host, port=args.port, zenoh_port=args.zenoh_port, rig_name=args.rig_name
        )
    )


Command = tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]
COMMANDS: dict[str, Command] = {
    **CONTROLLER_COMMANDS,
    "dashboard": ("run the dashboard (viser)", add_dashboard_arguments, run_dashboard_args),
    "demo": ("simulated controller + dashboard, prints the URL", add_demo_arguments, run_demo_args),
}


def dobtune_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="dobtune", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (help_text, add_args, _run) in COMMANDS.items():
        add_args(sub.add_parser(name, help=help_text, description=help_text))
    args = parser.parse_args(argv)
    return COMMANDS[args.command][2](args)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m server", description="dobtune dashboard")
    add_dashboard_arguments(parser)
    return run_dashboard_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
