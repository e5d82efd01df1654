"""The `dobtune` command line: options anywhere on the line, and an entry point that loads no
dashboard for the controller's commands."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from controller.cli.commands import controller_commands
from controller.cli.common import build_parser

ROOT = Path(__file__).resolve().parents[1]


def parse(line: str) -> object:
    return build_parser("dobtune", None, controller_commands()).parse_args(line.split())


def test_options_anywhere_on_the_line() -> None:
    a = parse("ctl --connect tcp/127.0.0.1:7447 apply --expect-version 1 q_cutoff_hz=0.8")
    assert (a.action, a.args, a.expect_version) == ("apply", ["q_cutoff_hz=0.8"], 1)  # type: ignore[attr-defined]
    b = parse("ctl apply q_cutoff_hz=0.8 --confirm dob_on=false --connect tcp/127.0.0.1:7447 "
              "--rig-name r2")
    assert b.args == ["q_cutoff_hz=0.8", "dob_on=false"] and b.confirm  # type: ignore[attr-defined]
    assert b.rig_name == "r2" and b.connect == ["tcp/127.0.0.1:7447"]  # type: ignore[attr-defined]


def test_unknown_options_are_still_refused() -> None:
    with pytest.raises(SystemExit) as exc:
        parse("ctl --connect tcp/127.0.0.1:7447 status --no-such-option")
    assert exc.value.code == 2


PROBE = """
import sys
from server.__main__ import dobtune_main
for name in {names!r}:
    try:
        dobtune_main([name, "--help"])
    except SystemExit:
        pass
print(sorted({{m.split(".")[0] for m in sys.modules}} & {{"viser", "zenoh"}}),
      sorted(m for m in sys.modules if m.startswith("server.") and m != "server.__main__"))
"""


@pytest.mark.slow
def test_the_entry_point_loads_no_dashboard_for_controller_commands() -> None:
    names = sorted(controller_commands())
    out = subprocess.run([sys.executable, "-c", PROBE.format(names=names)], cwd=ROOT,
                         capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.strip().splitlines()[-1] == "[] []", out


LOADED = """
import sys
from server.__main__ import dobtune_main
try:
    code = dobtune_main({argv!r})
except SystemExit as exc:
    code = exc.code
print(code, sorted(m for m in {modules!r} if m in sys.modules))
"""


def _loaded(argv: list[str], modules: tuple[str, ...]) -> str:
    code = LOADED.format(argv=argv, modules=modules)
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, timeout=120, check=True).stdout.strip().splitlines()[-1]


def test_a_command_loads_only_its_own_code() -> None:
    """`dobtune check` runs the gate (scipy.linalg, the nonlinear check's numba) but loads
    none of the experiments' or the identification's code (scipy.optimize: ~0.5 CPU s of every
    command before); `dobtune ctl` loads no analysis at all."""
    others = ("scipy.optimize", "controller.ident.engine", "controller.ident.model_fit",
              "controller.sim.paper", "controller.sim.experiment", "controller.process.audit")
    assert _loaded(["check"], others) == "0 []"
    analysis = ("numba", "scipy", "numpy.f2py", "controller.gate.analysis", *others)
    assert _loaded(["ctl", "--help"], analysis) == "0 []"
