"""`dobtune` console script (all subcommands) and `python -m server` (the dashboard)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from controller.cli.commands import controller_commands
from controller.cli.common import Command, add_log_level, build_parser


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
    p.add_argument("--auth", type=Path, default=None, metavar="DIR",
                   help="credentials for a controller with --auth: an auth directory (without "
                   "--user: one URL per user, each browser acting as its own user with its "
                   "role) or a password file (with --user)")
    p.add_argument("--user", default="",
                   help="with --auth: every browser acts as this one user")
    p.add_argument("--fleet", action="store_true",
                   help="also a Fleet tab: every rig reachable through --connect (a router)")
    p.add_argument("--recordings", type=Path, default=None, metavar="DIR",
                   help="the .mcap recordings the Recordings tab lists and compares "
                   "(default $XDG_DATA_HOME/dobtune/recordings, else "
                   "~/.local/share/dobtune/recordings)")
    add_candidates_argument(p)


def add_candidates_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--candidates", type=Path, default=None, metavar="DIR",
                   help="where each user's tuning candidates are kept, so that they survive "
                   "a restart of the dashboard: DIR/<rig>/<user>.json (default "
                   "$XDG_DATA_HOME/dobtune/candidates, else ~/.local/share/dobtune/candidates)")


def candidates_dir(args: argparse.Namespace) -> Path:
    from server.options import default_candidates_dir

    return args.candidates if args.candidates is not None else default_candidates_dir()


def run_dashboard_args(args: argparse.Namespace) -> int:
    from controller.logs import setup_logging
    from server.app import DashboardOptions, run_dashboard

    setup_logging(args.log_level, args.rig_name)
    connect = args.connect if args.connect is not None else ["tcp/127.0.0.1:7447"]
    return run_dashboard(
        DashboardOptions(
            connect=tuple(connect), rig_name=args.rig_name, host=args.host, port=args.port,
            auth=args.auth, user=args.user, fleet=args.fleet,
            candidates_dir=candidates_dir(args),
            **({"recordings_dir": args.recordings} if args.recordings is not None else {}),
        )
    )


def add_demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8080)
    p.add_argument("--zenoh-port", type=int, default=7447)
    p.add_argument("--rig-name", default="demo")
    p.add_argument("--rigs", type=int, default=1,
                   help="more than 1: a router on --zenoh-port and this many simulated rigs")
    p.add_argument("--disturbance", action="append", default=None, metavar="NAME",
                   help="the simulated rig's named disturbances (repeatable; default: "
                   "article-rig, the rate disturbances at P's input and the belt varying with "
                   "position; 'none' for the plain rig); the previews and Suggest use the same")
    add_candidates_argument(p)


def run_demo_args(args: argparse.Namespace) -> int:
    from controller.logs import setup_logging
    from server.demo import DemoOptions, run_demo

    setup_logging(args.log_level, args.rig_name)
    return run_demo(
        DemoOptions(
            host=args.host,
            port=args.port,
            zenoh_port=args.zenoh_port,
            rig_name=args.rig_name,
            log_level=args.log_level,
            rigs=args.rigs,
            disturbances=(DemoOptions.disturbances if args.disturbance is None else
                          tuple(d for d in args.disturbance if d != "none")),
            candidates_dir=candidates_dir(args),
        )
    )


DASHBOARD = Command(
    "dashboard", "run the dashboard (viser)", add_dashboard_arguments, run_dashboard_args,
    long_running=True,
)
DEMO = Command(
    "demo", "simulated controller + dashboard, prints the URL", add_demo_arguments,
    run_demo_args, long_running=True,
)


def commands() -> dict[str, Command]:
    return {**controller_commands(), DASHBOARD.name: DASHBOARD, DEMO.name: DEMO}


def dobtune_main(argv: list[str] | None = None) -> int:
    cmds = commands()
    args = build_parser("dobtune", __doc__, cmds).parse_args(argv)
    return cmds[args.command].run(args)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m server", description="dobtune dashboard")
    add_dashboard_arguments(parser)
    add_log_level(parser)
    return run_dashboard_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
