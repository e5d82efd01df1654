"""`dobtune tune`: the candidate it prints is accepted by the gate and applies nothing; bad
input exits 2 naming the field, as `dobtune check` does."""

from __future__ import annotations

import io
import json
from pathlib import Path

from controller.cli.commands import controller_commands
from controller.cli.common import build_parser
from controller.cli.tune import tune_main
from controller.core.config import config_from_builtins
from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
from controller.gate.verdict import judge


def _run(*argv: str) -> tuple[int, str]:
    args = build_parser("dobtune", None, controller_commands()).parse_args(["tune", *argv])
    out, err = io.StringIO(), io.StringIO()
    return tune_main(args, out, err), out.getvalue()


def test_tune_prints_an_accepted_candidate_and_says_what_it_ran_on() -> None:
    code, text = _run("--json", "--disturbance", "article-rig", "--no-ff", "--duration", "8")
    assert code == 0
    obj = json.loads(text)
    cfg = config_from_builtins(obj["candidate"]["config"])
    assert not cfg.ff_on
    assert judge(cfg, PlantKnowledge(bound=COMMISSIONING_BOUND)).verdict == "accept"
    assert obj["candidate"]["verdict"] == "accept"
    assert obj["candidate"]["rmse_deg"] < obj["start"]["rmse_deg"]
    assert "built-in model" in obj["plant"]  # nothing measured: it says so
    assert obj["speed_loop"]["crossover_hz"] > 4 * obj["position_loop"]["crossover_hz"] * 0.95
    assert any("speed loop: crosses over" in line for line in obj["explanation"])


def test_bad_input_exits_2_naming_the_field(tmp_path: Path) -> None:
    code, text = _run("--json", "--noise-budget", "-1")
    assert code == 2 and "noise_budget_deg_s" in json.loads(text)["error"]
    code, text = _run("--knowledge", str(tmp_path / "missing.json"))
    assert code == 2 and "missing.json" in text
    code, text = _run("--disturbance", "no-such-thing")
    assert code == 2 and "disturbance" in text
