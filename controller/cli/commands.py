"""The controller side's `dobtune` commands. Each module (`controller.cli.<name>`: its
`add_arguments` and `run`) is imported only when its command is used (`lazy_command`), so
listing them loads no analysis, no numba, no scipy, no Zenoh and no dashboard, and one command
loads only its own code (`dashboard` and `demo` load `server/` when they run)."""

from __future__ import annotations

from controller.cli.common import Command, lazy_command

__all__ = ["all_commands", "controller_commands"]

#: (name, module under controller.cli, help, long-running: takes --log-level).
_COMMANDS = (
    ("experiment", "experiment", "offline experiment on the simulated rig", False),
    ("check", "check",
     "the gate's verdict on a configuration: exit 0 accept, 3 caution, 1 reject, 2 bad input",
     False),
    ("controller", "controller", "run the controller process", True),
    ("identify", "identify",
     "measure the plant's frequency response, fit Mn Pn, recommend Q cut-offs", False),
    ("audit", "audit", "show or verify a controller's audit log", False),
    ("auth", "auth", "users for Zenoh authentication and access control", False),
    ("ctl", "ctl", "every controller action from the command line", False),
    ("record", "record", "record a running controller into an MCAP file", False),
    ("watch", "watch", "the twin beside a running controller: drift state, alarms, trends",
     True),
    ("report", "report", "HTML report (and CSV) of one or two recordings", False),
    ("router", "router", "a Zenoh router for many rigs and sites", True),
    ("autotune", "autotune", "search the Q type and cut-off on the simulated rig", False),
    ("tune", "tune",
     "tune the whole loop (PIs, feedforward, Q) on the plant: exit 0 candidate, 1 none, 2 bad "
     "input", False),
    ("paper", "paper", "the article's experiments on the simulated rig: report.md + PNGs", False),
)
#: The commands that run the dashboard (their modules load `server/` when they run).
_DASHBOARD_COMMANDS = (
    ("dashboard", "dashboard", "run the dashboard (viser)", True),
    ("demo", "demo", "simulated controller + dashboard, prints the URL", True),
)


def controller_commands() -> dict[str, Command]:
    """Every controller-side command by name."""
    return {name: lazy_command(name, help, f"controller.cli.{module}", long_running=long)
            for name, module, help, long in _COMMANDS}


def all_commands() -> dict[str, Command]:
    """Every `dobtune` command by name: the controller side's, then the dashboard's."""
    return {**controller_commands(),
            **{name: lazy_command(name, help, f"controller.cli.{module}", long_running=long)
               for name, module, help, long in _DASHBOARD_COMMANDS}}
