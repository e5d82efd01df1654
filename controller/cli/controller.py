"""`dobtune controller` / `python -m controller`: the controller process."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from controller.cli.common import add_parent_pid, end_with_parent


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plant", choices=("sim", "can"), default="sim", help="default: sim")
    p.add_argument("--rig", type=Path, default=None, help="rig file (TOML), required for can")
    p.add_argument("--rig-name", default="demo", help="Zenoh key chunk (default: demo)")
    p.add_argument(
        "--listen",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="Zenoh listen endpoint (repeatable; default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT")
    p.add_argument("--config", type=Path, default=None, help="initial LoopConfig (JSON)")
    p.add_argument(
        "--state-dir",
        type=Path,
        default=None,
        help="where the active config and the applied-changes log live (default ./var/<rig>)",
    )
    p.add_argument("--rate-hz", type=float, default=None, help="loop rate (default: config)")
    p.add_argument("--seed", type=int, default=0, help="simulated plant noise seed")
    p.add_argument("--realtime-priority", action="store_true", help="try SCHED_FIFO")
    p.add_argument(
        "--disturbance",
        action="append",
        default=[],
        metavar="NAME",
        help="with --plant sim: a named disturbance of the simulated rig (repeatable; those of "
        "dobtune experiment, e.g. article-rig: the rate disturbances at P's input and the "
        "belt varying with position)",
    )
    p.add_argument(
        "--auth",
        type=Path,
        default=None,
        metavar="DIR",
        help="authenticate every client with the users of DIR (`dobtune auth init DIR`): "
        "access control per role, the operator lease per user",
    )
    p.add_argument(
        "--user",
        default="",
        metavar="NAME",
        help="with --auth and --connect ROUTER: the account (role controller) to log in to an "
        "authenticating router with; the controller then listens nowhere",
    )
    p.add_argument(
        "--request-budget",
        type=float,
        default=50.0,
        metavar="N",
        help="with --auth: requests a second each user may send (bursts of 2N); beyond, a "
        "request is refused at once, naming the budget (default: 50)",
    )
    p.add_argument(
        "--insecure",
        action="store_true",
        help="allow a non-loopback --listen or --connect without --auth (anyone who reaches "
        "it may act)",
    )
    p.add_argument(
        "--no-watch",
        action="store_true",
        help="do not start the watch beside the loop (`dobtune watch`: the plant's drift, and "
        "the twin's prediction checked after each Apply). By default it starts once the loop "
        "runs, niced, in its own process, and stops with the controller; not with --auth "
        "(start it by hand with an account of its own)",
    )
    add_parent_pid(p, "controller")
    p.add_argument(
        "--sim-drive-node",
        action="store_true",
        help="with --plant can: answer on the rig file's bus with a simulated CiA 402 drive "
        "(python-can virtual bus) — rehearse the CAN path without hardware",
    )


def run(args: argparse.Namespace) -> int:
    def say(text: str) -> None:
        print(f"dobtune controller: {text}", file=sys.stderr, flush=True)

    end_with_parent(args.parent_pid, say)

    try:
        return _run(args, say)
    except KeyboardInterrupt:  # Ctrl-C while it was still loading: nothing runs yet
        say("stopped (interrupted while starting)")
        return 0


def _run(args: argparse.Namespace, say: Callable[[str], None]) -> int:
    from controller.logs import setup_logging
    from controller.process.main import StartupError, run_controller
    from controller.process.options import ControllerOptions

    setup_logging(args.log_level, args.rig_name)

    behind_router = args.auth is not None and bool(args.connect)
    default_listen = [] if behind_router else ["tcp/127.0.0.1:7447"]
    listen = args.listen if args.listen is not None else default_listen
    opts = ControllerOptions(
        plant=args.plant,
        rig_file=args.rig,
        rig_name=args.rig_name,
        listen=tuple(listen),
        connect=tuple(args.connect),
        config_path=args.config,
        state_dir=args.state_dir,
        rate_hz=args.rate_hz,
        seed=args.seed,
        sim_disturbances=tuple(args.disturbance),
        realtime_priority=args.realtime_priority,
        sim_drive_node=args.sim_drive_node,
        auth_dir=args.auth,
        auth_user=args.user,
        insecure=args.insecure,
        request_budget_per_s=args.request_budget,
    )
    watch = None
    if not args.no_watch and args.auth is None and listen:
        from controller.cli.watch_child import WatchChild, loopback_endpoint

        watch = WatchChild(loopback_endpoint(listen[0]), args.rig_name, opts.state_path,
                           tuple(args.disturbance), args.log_level)

    def ready(text: str) -> None:
        say(text)
        if watch is not None:
            watch.start()
            say(f"the watch runs beside the loop (pid {watch.proc.pid if watch.proc else '-'}"
                f"; trend and prediction checks in {opts.state_path / 'trend'}; --no-watch: "
                "not started)")

    try:
        code = run_controller(opts, ready=ready)
    except StartupError as exc:
        say(str(exc))
        return 2
    finally:
        if watch is not None:
            watch.stop()
    say("stopped")
    return code

