"""`dobtune demo`: a controller on the simulated rig and the dashboard; prints the URL.

The dashboard's package (`server/`) is loaded only when the command runs (as for
`dobtune dashboard`)."""

from __future__ import annotations

import argparse

from controller.cli.dashboard import add_candidates_argument, candidates_dir

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1",
                   help="the dashboard's address (default: %(default)s)")
    p.add_argument("--port", type=int, default=8080,
                   help="the dashboard's port (default: %(default)s)")
    p.add_argument("--zenoh-port", type=int, default=7447,
                   help="the controller's Zenoh port on 127.0.0.1 (default: %(default)s)")
    p.add_argument("--rig-name", default="demo", help="the rig's name (default: %(default)s)")
    p.add_argument("--rigs", type=int, default=1,
                   help="more than 1: a router on --zenoh-port and this many simulated rigs "
                   "(default: %(default)s)")
    p.add_argument("--disturbance", action="append", default=None, metavar="NAME",
                   help="the simulated rig's named disturbances (repeatable; default: "
                   "article-rig, the rate disturbances at P's input and the belt varying with "
                   "position; 'none' for the plain rig); the previews and Suggest use the same")
    add_candidates_argument(p)


def run(args: argparse.Namespace) -> int:
    from controller.logs import setup_logging
    from server.dashboard.demo import DemoOptions, run_demo

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
