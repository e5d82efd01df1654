"""`dobtune controller --disturbance NAME` (the demo's simulated rig with its rate disturbances):
bad names and combinations are refused at start, naming the flag, before anything opens. The
running case is the browser test tests/browser/test_demo_value_browser.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from controller.process.main import StartupError, run_controller
from controller.process.options import ControllerOptions


@pytest.mark.parametrize(
    ("plant", "names", "match"),
    [
        ("sim", ("no-such",), "--disturbance: .*unknown name 'no-such'"),
        ("sim", ("friction-change",), "--disturbance: friction-change schedules a friction"),
        ("can", ("article-rig",), "--disturbance: only with --plant sim"),
    ],
)
def test_bad_disturbances_are_refused_naming_the_flag(
    tmp_path: Path, plant: str, names: tuple[str, ...], match: str
) -> None:
    opts = ControllerOptions(plant=plant, sim_disturbances=names, state_dir=tmp_path,
                             listen=("tcp/127.0.0.1:1",))
    with pytest.raises(StartupError, match=match):
        run_controller(opts)
    assert not any(tmp_path.iterdir())  # refused before the state directory was touched
