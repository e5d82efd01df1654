"""The twin's window of normal running from the controller's held state batches
(controller/process/twin_running.py `recent_running`): the newest unbroken stretch, cut where
the sequence numbers jump, the configuration version or the mode changes; the reasons when
there is none; and `twin_with_running` saying in the twin's notes what a window that tells
nothing leaves."""

from __future__ import annotations

from controller import protocol as proto
from controller.process.twin_running import (
    BASE_RIG,
    RecentRunning,
    recent_running,
    twin_with_running,
)
from controller.sim.sim_rig import RigFaults, RigParams
from controller.twin.model import RigTwin

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
