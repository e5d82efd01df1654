"""`dobtune dashboard`: the dashboard (viser), a client of one controller.

The dashboard's package (`server/`) is loaded only when the command runs: `controller` imports
`server` nowhere else (docs/architecture.md, tests/test_layout.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["add_arguments", "add_candidates_argument", "candidates_dir", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
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
    p.add_argument("--trend-dir", action="append", type=Path, default=None, metavar="DIR",
                   help="where the Trends tab finds the rigs' trends: a controller's "
                   "<state-dir>/trend, DIR/<rig>/<hour>.mcap (repeatable; default "
                   "var/<rig-name>/trend, the controller's default state directory)")
    add_candidates_argument(p)


def add_candidates_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--candidates", type=Path, default=None, metavar="DIR",
                   help="where each user's tuning candidates are kept, so that they survive "
                   "a restart of the dashboard: DIR/<rig>/<user>.json (default "
                   "$XDG_DATA_HOME/dobtune/candidates, else ~/.local/share/dobtune/candidates)")


def candidates_dir(args: argparse.Namespace) -> Path:
    from server.options import default_candidates_dir

    return args.candidates if args.candidates is not None else default_candidates_dir()


def run(args: argparse.Namespace) -> int:
    from controller.logs import setup_logging
    from server.dashboard.app import DashboardOptions, run_dashboard

    setup_logging(args.log_level, args.rig_name)
    connect = args.connect if args.connect is not None else ["tcp/127.0.0.1:7447"]
    return run_dashboard(
        DashboardOptions(
            connect=tuple(connect), rig_name=args.rig_name, host=args.host, port=args.port,
            auth=args.auth, user=args.user, fleet=args.fleet,
            candidates_dir=candidates_dir(args),
            trend_dirs=tuple(args.trend_dir or [Path("var") / args.rig_name / "trend"]),
            **({"recordings_dir": args.recordings} if args.recordings is not None else {}),
        )
    )
