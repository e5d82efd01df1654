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
from controller.cli.main import dobtune_main
for name in {names!r}:
    try:
        dobtune_main([name, "--help"])
    except SystemExit:
        pass
print(sorted({{m.split(".")[0] for m in sys.modules}} & {{"viser", "zenoh"}}),
      sorted(m for m in sys.modules if m == "server" or m.startswith("server.")))
"""


@pytest.mark.slow
def test_the_entry_point_loads_no_dashboard_for_controller_commands() -> None:
    names = sorted(controller_commands())
    out = subprocess.run([sys.executable, "-c", PROBE.format(names=names)], cwd=ROOT,
                         capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.strip().splitlines()[-1] == "[] []", out


LOADED = """
import sys
from controller.cli.main import dobtune_main
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


def test_ctl_json_is_strict_json_also_for_a_verdict_without_figures() -> None:
    """A verdict refused before the analysis has NaN margins: `ctl ... --json` writes them as
    null (json.dumps with allow_nan=False raised 'Out of range float values', exit 2)."""
    import io
    import json

    from controller import protocol as proto
    from controller.cli.ctl import _emit
    from controller.core.config import LoopConfig
    from controller.core.verdict import Verdict

    refused = Verdict.refused("command_limit_deg_s 500 deg/s > the rig's limit", 3)
    reply = proto.ConfigReply(accepted=False, version=3, config=LoopConfig(),
                              reasons=list(refused.reasons), verdict=refused)
    out = io.StringIO()
    _emit(out, True, reply, "")
    got = json.loads(out.getvalue())  # strict: no NaN, no Infinity
    assert got["verdict"]["verdict"] == "reject" and got["verdict"]["knowledge_version"] == 3
    assert got["verdict"]["margins"]["gain_margin_db"] is None
    assert got["reasons"] == list(refused.reasons) and got["v"] == proto.PROTOCOL_VERSION
