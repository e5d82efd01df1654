"""The earlier default loop, Cv = 0.5 (1 + 55/s) (examples/loop_cv_0.5_55.json, the design
notes' first guess): the loop for which control.md states its margins and for which several
tests' expectations (margins, counter-examples, watchdog faults) were worked out."""

from __future__ import annotations

from pathlib import Path

from controller.cli.inputs import load_config

OLD_LOOP_PATH = Path(__file__).resolve().parents[1] / "examples" / "loop_cv_0.5_55.json"
OLD_LOOP = load_config(OLD_LOOP_PATH)
