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


def test_identify_takes_the_simulated_rigs_disturbances() -> None:
    """`dobtune identify --disturbance NAME`: the offline rig gets the named parameters (the belt
    varying with position); with --connect, or an unknown name, a message naming the flag."""
    import argparse
    import io
    import json
    from contextlib import redirect_stdout

    from controller.cli.identify import _sim_rig_factory, add_arguments, run
    from controller.core.errors import ConfigError
    from controller.sim.rig_disturbances import rig_setup

    factory = _sim_rig_factory(["belt-tension"], None, None)
    assert factory is not None
    rig = factory()
    assert rig.params == rig_setup(["belt-tension"]).params  # type: ignore[attr-defined]
    assert rig.params.belt_stiffness_variation > 0  # type: ignore[attr-defined]
    default = _sim_rig_factory([], None, None)  # the one default rig: article-rig
    assert default is not None
    assert default().params == rig_setup(["article-rig"]).params  # type: ignore[attr-defined]
    ideal = _sim_rig_factory(["ideal"], None, None)
    assert ideal is not None
    assert ideal().params == rig_setup([]).params  # type: ignore[attr-defined]
    assert _sim_rig_factory([], "tcp/127.0.0.1:1", None) is None
    with pytest.raises(ConfigError, match="only with the offline"):
        _sim_rig_factory(["belt-tension"], "tcp/127.0.0.1:1", None)
    p = argparse.ArgumentParser()
    add_arguments(p)
    out = io.StringIO()
    with redirect_stdout(out):
        code = run(p.parse_args(["--disturbance", "no-such", "--json"]))
    assert code == 2
    assert "--disturbance" in json.loads(out.getvalue())["error"]
