"""The simulated rig's command delay (`RigParams.command_delay_ticks`): a rig delayed by d
ticks is the undelayed rig fed the same commands d ticks later, bit for bit, and the compiled
offline loop runs it as the Python tick does."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import default_trajectory
from controller.sim import offline
from controller.sim.sim_rig import RigParams, SimRig


def _commands(n: int) -> list[float]:
    return [20.0 * math.sin(0.02 * k) + 3.0 * ((k // 37) % 2) for k in range(n)]


@pytest.mark.parametrize("delay", [1, 3])
def test_a_delayed_rig_is_the_plain_rig_fed_later(delay: int) -> None:
    n = 600
    cmds = _commands(n)
    late = SimRig(RigParams(command_delay_ticks=delay), seed=4, initial_position_deg=1.0)
    plain = SimRig(RigParams(), seed=4, initial_position_deg=1.0)
    a, b = [], []
    for k in range(n):
        late.step(cmds[k])
        plain.step(0.0 if k < delay else cmds[k - delay])
        a.append(late.read())
        b.append(plain.read())
    assert a == b
    # and the delay is really there: without it the runs differ
    plain2 = SimRig(RigParams(), seed=4, initial_position_deg=1.0)
    c = []
    for k in range(n):
        plain2.step(cmds[k])
        c.append(plain2.read())
    assert c != a


def test_reset_clears_the_delay_line() -> None:
    rig = SimRig(RigParams(command_delay_ticks=2))
    for _ in range(5):
        rig.step(50.0)
    rig.reset(0.0)
    ref = SimRig(RigParams(command_delay_ticks=2))
    for _ in range(4):
        rig.step(0.0)
        ref.step(0.0)
    assert rig.read() == ref.read()


def test_compiled_loop_runs_the_delay_as_python_does() -> None:
    cfg = LoopConfig()
    traj = default_trajectory("sine")
    n = 1500
    params = RigParams(command_delay_ticks=2)
    rig_py = SimRig(params, seed=1, initial_position_deg=traj.at(0.0)[0])
    loop_py = ServoLoop(LoopCoefficients.build(cfg))
    pos_py = np.empty(n)
    for k in range(n):
        r, rr = traj.at(k * cfg.period_s)
        p, w = rig_py.read()
        pos_py[k] = p
        rig_py.step(loop_py.tick(r, rr, p, w))
    rig_c = SimRig(params, seed=1, initial_position_deg=traj.at(0.0)[0])
    run = offline.run_ticks(ServoLoop(LoopCoefficients.build(cfg)), rig_c, traj, n)
    assert np.array_equal(run.pos_deg, pos_py)
    assert rig_c.read() == rig_py.read()


def test_bad_delay_is_rejected_naming_the_field() -> None:
    for bad in (-1, 101, 1.5):
        with pytest.raises(ConfigError, match="command_delay_ticks"):
            RigParams(command_delay_ticks=bad)  # type: ignore[arg-type]
