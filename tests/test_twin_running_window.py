"""The twin's window of normal running from the controller's held state batches
(controller/process/twin_running.py `recent_running`): the newest unbroken stretch, cut where
the sequence numbers jump, the configuration version or the mode changes, and where the
reference is not the loop's trajectory (the approach onto it, an identification); the reasons
when there is none; `twin_with_running` saying in the twin's notes what a window that tells
nothing leaves; and the drive offset the twin lacks from a window that starts mid-trajectory
(`disturbance_lacking` from a later trajectory tick), against a simulated rig's own."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import PlantKnowledge
from controller.process.twin_running import (
    BASE_RIG,
    OFFSET_KEPT,
    RecentRunning,
    recent_running,
    twin_with_running,
)
from controller.sim.experiment import run_experiment
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import RigFaults, RigParams, SimRig
from controller.twin.fit import twin_from_knowledge
from controller.twin.model import RigTwin
from controller.twin.replay import disturbance_lacking

N = 20  # samples per batch


def _batch(seq0: int, version: int = 1, mode: str = "running") -> proto.StateBatch:
    cols = {name: [float(seq0 + i) for i in range(N)] for name in
            ("ref_deg", "pos_deg", "speed_deg_s", "speed_ref_deg_s", "command_deg_s",
             "d_hat_deg_s", "error_deg")}
    return proto.StateBatch(rig="r", seq0=seq0, rate_hz=1000.0, config_version=version,
                            t_s=[(seq0 + i) / 1000.0 for i in range(N)], epoch_s=1.0e9,
                            mode=mode, **cols)


def test_the_newest_unbroken_stretch_is_the_window() -> None:
    held = [_batch(s) for s in range(0, 200, N)] + [_batch(s) for s in range(400, 1000, N)]
    got = recent_running(held, seconds=10.0)
    assert isinstance(got, RecentRunning)
    assert got.pos_deg == [float(s) for s in range(400, 1000)]  # cut at the seq jump
    assert got.command_deg_s == got.pos_deg and got.speed_deg_s == got.pos_deg
    assert "seq 400-999" in got.label and "0.6 s" in got.label and "v1" in got.label
    # at most `seconds`: the newest samples
    short = recent_running(held, seconds=0.1)
    assert isinstance(short, RecentRunning) and short.pos_deg[0] == 900.0
    assert len(short.pos_deg) == 100
    # a change of configuration or a stop cuts it too
    mixed = [_batch(s, version=1 if s < 500 else 2) for s in range(0, 1000, N)]
    got = recent_running(mixed, seconds=10.0)
    assert isinstance(got, RecentRunning) and got.pos_deg[0] == 500.0 and "v2" in got.label
    stopped = [_batch(s, mode="stopped" if s < 300 else "running") for s in range(0, 1000, N)]
    got = recent_running(stopped, seconds=10.0)
    assert isinstance(got, RecentRunning) and got.pos_deg[0] == 300.0


def test_no_window_is_said() -> None:
    assert "no state batches" in str(recent_running([]))
    assert "estop" in str(recent_running([_batch(0), _batch(N, mode="estop")]))


def _twin() -> RigTwin:
    return RigTwin(knowledge_version=1, knowledge_digest="d", source="t", rate_hz=1000.0,
                   params=RigParams(), faults=RigFaults())


def test_a_window_that_tells_nothing_or_none_is_said_in_the_notes() -> None:
    tw = twin_with_running(_twin(), "the loop is stopped, not running")
    assert tw.notes[-1] == f"{BASE_RIG}: no window of normal running: the loop is stopped, " \
        "not running"
    assert tw.params == RigParams()
    n = 3000  # a hold: the command never reverses
    still = RecentRunning(1000.0, [1.0] * n, [0.0] * n, [2.0] * n, "the test's hold")
    tw = twin_with_running(_twin(), still)
    assert tw.notes[-1].startswith(f"{BASE_RIG}: the test's hold tells nothing: ")
    assert "never reverses" in tw.notes[-1] and tw.params == RigParams()
    short = RecentRunning(1000.0, [1.0] * 10, [0.0] * 10, [2.0] * 10, "ten samples")
    tw = twin_with_running(_twin(), short)
    assert "ten samples tells nothing: window: 10 samples" in tw.notes[-1]
    assert tw.params == RigParams()


def _sine_batches(s0: int, approach_until: int, end: int) -> list[proto.StateBatch]:
    """Batches of seq 0..end-1 whose reference is the article's sine with time 0 at seq
    `s0`, except before `approach_until` (the approach onto it: something else)."""
    traj = Trajectory()
    out = []
    for b0 in range(0, end, N):
        ref = [traj.at((s - s0) * 1.0e-3)[0] if s >= approach_until else 20.0 - 0.01 * s
               for s in range(b0, b0 + N)]
        cols = {name: ref for name in ("ref_deg", "pos_deg", "speed_deg_s", "speed_ref_deg_s",
                                       "command_deg_s", "d_hat_deg_s", "error_deg")}
        out.append(proto.StateBatch(rig="r", seq0=b0, rate_hz=1000.0, config_version=3,
                                    t_s=[s / 1000.0 for s in range(b0, b0 + N)],
                                    epoch_s=1.0e9, mode="running", **cols))
    return out


def test_the_window_is_where_the_loop_follows_its_trajectory() -> None:
    held = _sine_batches(s0=100, approach_until=437, end=2000)
    cfg = LoopConfig()
    for guess in (99, 100, 101):  # the runtime's seq0 is read off its thread: a tick either way
        got = recent_running(held, seconds=10.0, following=(Trajectory(), guess, 1.0e-3),
                             config=(cfg, 3))
        assert isinstance(got, RecentRunning), got
        assert len(got.pos_deg) == 2000 - 437  # the approach cut off
        assert got.trajectory == Trajectory() and got.trajectory_tick == 437 - 100
        assert got.d_hat_deg_s == got.pos_deg and got.config == cfg
        assert "seq 437-1999" in got.label and "sine from its 0.337 s" in got.label
    # the configuration is kept only if its version is the window's
    other = recent_running(held, following=(Trajectory(), 100, 1.0e-3), config=(cfg, 4))
    assert isinstance(other, RecentRunning) and other.config is None
    # the newest sample is not the trajectory's (an identification's excitation, say)
    moved = _sine_batches(s0=100, approach_until=437, end=2000)
    moved[-1].ref_deg[-1] += 1e-9
    why = recent_running(moved, following=(Trajectory(), 100, 1.0e-3))
    assert isinstance(why, str) and "not its trajectory's" in why
    # another trajectory than the one the samples follow
    why = recent_running(held, following=(Trajectory(amplitude_deg=4.0), 100, 1.0e-3))
    assert isinstance(why, str) and "not its trajectory's" in why


def test_the_offset_the_twin_lacks_from_a_window_mid_trajectory() -> None:
    """A rig whose drive offset is 3 rpm above the twin's: the d_hat of 15 s of its running
    from the sine's 8th second, less the twin's own from the same trajectory tick, tells it
    (tests/test_twin_disturbance.py's tolerance), as a window from the start does."""
    base = rig_setup(("article-rig",)).params
    true = replace(base, drive_offset_rpm=base.drive_offset_rpm + 3.0)
    twin = twin_from_knowledge(PlantKnowledge(), base=base)
    cfg, sine = LoopConfig(), Trajectory()
    rec = run_experiment(cfg, sine, 23.0, rig=SimRig(true, seed=3))
    d = np.asarray(rec.d_hat_deg_s)
    est = disturbance_lacking(twin, cfg, sine, d[8000:], start_tick=8000, seed=5)
    rpm, sd = (v * base.gear_ratio / 6.0 for v in (est.mean_deg_s, est.mean_std_deg_s or 0.0))
    assert rpm == pytest.approx(3.0, abs=0.5) and abs(rpm - 3.0) <= 4 * sd + 0.05, (rpm, sd)
    whole = disturbance_lacking(twin, cfg, sine, d, seed=5).mean_deg_s * base.gear_ratio / 6.0
    assert rpm == pytest.approx(whole, abs=0.3)
    with pytest.raises(ValueError, match="start_tick"):
        disturbance_lacking(twin, cfg, sine, d, start_tick=-1)
    # twin_with_running says why it keeps the twin's offset where the window cannot tell it
    n = 3000
    off = RecentRunning(1000.0, [1.0] * n, [0.0] * n, [2.0] * n, "a window", [0.0] * n,
                        sine, 5000, cfg.with_(dob_on=False))
    tw = twin_with_running(twin, off)
    assert any(t.startswith(f"{OFFSET_KEPT}: a window: the DOB is off") for t in tw.notes)
