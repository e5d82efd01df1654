"""Command line of the controller side: `python -m controller` runs the controller process.

The `dobtune` console script (server/__main__.py) reuses the subcommand builders below.
Argument parsing lives only here and in server/__main__.py.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _on_off(value: str) -> bool:
    if value not in ("on", "off"):
        raise argparse.ArgumentTypeError(f"expected on or off, got {value!r}")
    return value == "on"


def add_controller_arguments(p: argparse.ArgumentParser) -> None:
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
        "--sim-drive-node",
        action="store_true",
        help="with --plant can: answer on the rig file's bus with a simulated CiA 402 drive "
        "(python-can virtual bus) — rehearse the CAN path without hardware",
    )


def run_controller_args(args: argparse.Namespace) -> int:
    from controller.process.node import ControllerOptions, run_controller

    listen = args.listen if args.listen is not None else ["tcp/127.0.0.1:7447"]
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
        realtime_priority=args.realtime_priority,
        sim_drive_node=args.sim_drive_node,
    )
    return run_controller(opts)


def add_experiment_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "test",
        nargs="?",
        default="sine",
        choices=("sine", "step", "ramp", "hold", "compare"),
        help="trajectory, or compare: no DOB / DOB / DOB + feedforward (default sine)",
    )
    p.add_argument("--dob", type=_on_off, default=True, metavar="on|off")
    p.add_argument("--ff", type=_on_off, default=False, metavar="on|off")
    p.add_argument("--q", dest="q_type", default="q31", metavar="q20|q31")
    p.add_argument("--cutoff-hz", type=float, default=0.5)
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="simulated seconds (default: 30 for sine/ramp, 10 otherwise)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--disturbance", default="none", metavar="NAME")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")


def run_experiment_args(args: argparse.Namespace) -> int:
    from controller.cli.experiment import experiment_main

    return experiment_main(
        test=args.test,
        dob_on=args.dob,
        ff_on=args.ff,
        q_type=args.q_type,
        cutoff_hz=args.cutoff_hz,
        duration_s=args.duration,
        seed=args.seed,
        disturbance=args.disturbance,
        as_json=args.json,
        out=sys.stdout,
        err=sys.stderr,
    )


def add_check_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", type=Path, default=None, help="LoopConfig JSON file")
    p.add_argument("--q", dest="q_type", default=None, metavar="q20|q31")
    p.add_argument("--cutoff-hz", type=float, default=None)
    p.add_argument(
        "--frd",
        type=Path,
        action="append",
        default=[],
        metavar="FILE",
        help="measured response CSV freq_hz,mag_db,phase_deg (repeatable)",
    )
    p.add_argument("--json", action="store_true")


def run_check_args(args: argparse.Namespace) -> int:
    from controller.cli.check import check_main

    return check_main(args.config, args.q_type, args.cutoff_hz, args.frd, args.json, sys.stdout)


def add_identify_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plant", default=None, metavar="sim", help="offline simulated rig (default)")
    p.add_argument("--connect", default=None, metavar="ENDPOINT", help="running controller")
    p.add_argument("--rig-name", default=None, metavar="NAME", help="with --connect")
    p.add_argument("--mode", default="open", metavar="open|closed", help="default: open")
    p.add_argument("--signal", default="sine", metavar="sine|multisine", help="default: sine")
    p.add_argument("--f-min", dest="f_min_hz", type=float, default=0.1, metavar="HZ")
    p.add_argument("--f-max", dest="f_max_hz", type=float, default=20.0, metavar="HZ")
    p.add_argument("--positions", type=int, default=3, metavar="N", help="default: 3")
    p.add_argument("--amplitude", dest="amplitude_deg_s", type=float, default=10.0, metavar="DEG_S")
    p.add_argument("--out", type=Path, default=Path("identify-out"), metavar="DIR")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")


def run_identify_args(args: argparse.Namespace) -> int:
    from controller.cli.identify import identify_main

    return identify_main(
        plant=args.plant,
        connect=args.connect,
        rig_name=args.rig_name,
        mode=args.mode,
        signal=args.signal,
        f_min_hz=args.f_min_hz,
        f_max_hz=args.f_max_hz,
        positions=args.positions,
        amplitude_deg_s=args.amplitude_deg_s,
        out_dir=args.out,
        as_json=args.json,
        out=sys.stdout,
        err=sys.stderr,
    )


COMMANDS = {
    "experiment": (
        "offline experiment on the simulated rig",
        add_experiment_arguments,
        run_experiment_args,
    ),
    "check": ("stability check of a configuration", add_check_arguments, run_check_args),
    "controller": ("run the controller process", add_controller_arguments, run_controller_args),
    "identify": (
        "measure the plant's frequency response, fit Mn Pn, recommend Q cut-offs",
        add_identify_arguments,
        run_identify_args,
    ),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m controller", description="dobtune controller process"
    )
    add_controller_arguments(parser)
    args = parser.parse_args(argv)
    return run_controller_args(args)


if __name__ == "__main__":
    sys.exit(main())
