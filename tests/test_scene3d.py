"""The 3-D view's moves (server/scene3d.py): sent only when the turntable or the reference
turned a visible step, at most SCENE_RATE_HZ times a second, and made on viser's event loop
(issue 33: moved 10 times a second whatever the rig did, each move redrawn by every page for
250 ms; and set from the live refresh's thread, viser's asyncio.Event raised "deque mutated
during iteration")."""

from __future__ import annotations

import asyncio
import math
import threading
from collections.abc import Iterator

import numpy as np
import pytest
import viser
from helpers import free_port, wait_for

from server.scene3d import SCENE_RATE_HZ, SCENE_STEP_DEG, TurntableScene

GAP_S = 1.0 / SCENE_RATE_HZ


@pytest.fixture
def server() -> Iterator[viser.ViserServer]:
    s = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        yield s
    finally:
        s.stop()


def _angle_deg(wxyz: np.ndarray) -> float:
    """The rotation about z of a quaternion (w, 0, 0, z), in degrees."""
    return math.degrees(2.0 * math.atan2(float(wxyz[3]), float(wxyz[0])))


def test_a_still_rig_sends_nothing_and_a_visible_step_one_move(
        server: viser.ViserServer) -> None:
    scene = TurntableScene(server.scene)
    t = 1000.0
    assert scene.update(10.0, 10.0, now_s=t)  # the first pose is always sent
    # Still (noise well under a step) for a long time: no move at all.
    rng = np.random.default_rng(1)
    for k in range(1, 200):
        load, ref = 10.0 + rng.uniform(-0.9, 0.9) * SCENE_STEP_DEG, 10.0
        assert not scene.update(load, ref, now_s=t + k * GAP_S), k
    assert scene.moves == 1
    # The load a step away: one move, and the view shows that angle.
    assert scene.update(10.0 + SCENE_STEP_DEG, 10.0, now_s=t + 300 * GAP_S)
    assert _angle_deg(scene.load.wxyz) == pytest.approx(10.0 + SCENE_STEP_DEG)
    # The reference alone a step away: a move too (the ghost follows it).
    assert scene.update(10.0 + SCENE_STEP_DEG, 10.0 + SCENE_STEP_DEG, now_s=t + 302 * GAP_S)
    assert _angle_deg(scene.ref.wxyz) == pytest.approx(10.0 + SCENE_STEP_DEG)
    assert scene.moves == 3


def test_a_moving_rig_moves_the_view_at_most_at_the_scene_rate(
        server: viser.ViserServer) -> None:
    scene = TurntableScene(server.scene)
    # 10 deg/s for 5 s, offered 1000 times a second: at most SCENE_RATE_HZ moves a second.
    sent = [scene.update(0.01 * k, 0.01 * k, now_s=k * 1e-3) for k in range(5000)]
    assert scene.moves == sum(sent)
    assert 0.8 * 5 * SCENE_RATE_HZ <= scene.moves <= 5 * SCENE_RATE_HZ + 1
    assert _angle_deg(scene.load.wxyz) == pytest.approx(50.0, abs=10.0 / SCENE_RATE_HZ + 0.01)


def test_moves_are_made_on_visers_event_loop(server: viser.ViserServer) -> None:
    """With the loop given, a move is made by the loop: while the loop is held, the handle
    keeps its old pose; released, it takes the new one."""
    loop = server.get_event_loop()
    scene = TurntableScene(server.scene, loop)
    assert scene.update(0.0, 0.0, now_s=0.0)
    wait_for(lambda: _angle_deg(scene.load.wxyz) == pytest.approx(0.0, abs=1e-9))
    held, release = threading.Event(), threading.Event()

    async def hold() -> None:
        held.set()
        release.wait(30.0)  # blocks the loop's thread on purpose

    asyncio.run_coroutine_threadsafe(hold(), loop)
    try:
        assert held.wait(30.0)
        assert scene.update(30.0, 0.0, now_s=1.0)
        assert _angle_deg(scene.load.wxyz) == pytest.approx(0.0, abs=1e-9)  # not by this thread
    finally:
        release.set()
    wait_for(lambda: _angle_deg(scene.load.wxyz) == pytest.approx(30.0), 30.0,
             "the move queued on the loop was never made")
