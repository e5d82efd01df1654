"""3-D view: the timing-belt turntable built once from viser primitives, then only rotated.

Load pulley and turntable share the load axis (origin); the motor pulley sits beside it. The
belt is drawn as a closed loop around both pulleys with markers that travel along it as the
load turns; the reference angle is a translucent ghost marker on the turntable rim.
"""

from __future__ import annotations

import asyncio
import functools
import math
import time

import numpy as np
import viser

from server.workers import run_logged

__all__ = ["TurntableScene", "belt_path"]

TABLE_R = 0.20
TABLE_Z = 0.12
LOAD_PULLEY_R = 0.07
MOTOR_PULLEY_R = 0.025
MOTOR_X = 0.36
BELT_Z = 0.05
N_BELT_MARKERS = 16
#: The scene moves at most this often (the live refresh runs faster): each move is four
#: messages to every browser and a redraw of its 3-D view (software WebGL on a machine without
#: a GPU); at 25 Hz they were ~100 messages/s to each page, shown or not.
SCENE_RATE_HZ = 10.0
#: ... and only when the load or the reference turned this far since the last move: about the
#: smallest change the view shows (the table's rim, 0.2 m out, moves 3.5 mm per degree: a pixel
#: or two in the view's default framing). viser's page draws frames for 250 ms after each
#: change it gets (its "settle" window): a scene moved 10 times a second was drawn all the time
#: (~30 ms a frame in software WebGL: a third of a core), a still one once a second.
SCENE_STEP_DEG = 1.0


def _quat_z(angle_rad: float) -> tuple[float, float, float, float]:
    return (math.cos(angle_rad / 2.0), 0.0, 0.0, math.sin(angle_rad / 2.0))


def belt_path(n: int = 200) -> tuple[np.ndarray, float]:
    """Closed belt polyline (n, 3) around both pulleys (open-belt tangents), and its length."""
    r1, r2, dx = LOAD_PULLEY_R, MOTOR_PULLEY_R, MOTOR_X
    beta = math.asin((r1 - r2) / dx)  # tangent angle of an open belt
    # Arc on the big pulley: angles from pi/2+beta to 3pi/2-beta (the side away from the motor).
    a1 = np.linspace(math.pi / 2 + beta, 3 * math.pi / 2 - beta, n // 2)
    a2 = np.linspace(-math.pi / 2 + beta, math.pi / 2 - beta, n // 2)
    p1 = np.stack([r1 * np.cos(a1), r1 * np.sin(a1)], axis=1)
    p2 = np.stack([dx + r2 * np.cos(a2), r2 * np.sin(a2)], axis=1)
    loop = np.concatenate([p1, p2, p1[:1]], axis=0)
    pts = np.concatenate([loop, np.full((len(loop), 1), BELT_Z)], axis=1)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    return pts, float(seg.sum())


def _add_pulley(scene: viser.SceneApi, wheel: str, mark: str, radius: float,
                mark_width: float) -> None:
    """A pulley at belt height in its parent frame, with a radial mark to see it turn."""
    scene.add_cylinder(wheel, radius=radius, height=0.025, color=(180, 140, 60),
                       position=(0.0, 0.0, BELT_Z))
    scene.add_box(mark, dimensions=(radius, mark_width, 0.028), color=(90, 60, 20),
                  position=(radius / 2, 0.0, BELT_Z))


class TurntableScene:
    """Scene handles; `update(load_deg, ref_deg)` only moves existing nodes (at most
    SCENE_RATE_HZ times a second, and only by SCENE_STEP_DEG or more).

    `loop`: viser's event loop (`ViserServer.get_event_loop()`); the moves are made on it. viser
    wakes its senders with an `asyncio.Event` set by whichever thread queues a message, and an
    Event is not thread-safe: set from the live refresh's thread it raised "deque mutated during
    iteration" now and then (the loop thread was adding a waiter), and that refresh was lost.
    None: moved in the caller's thread (a scene without a running server)."""

    def __init__(self, scene: viser.SceneApi,
                 loop: asyncio.AbstractEventLoop | None = None) -> None:
        self.scene = scene
        self._loop = loop
        self.moves = 0
        """The moves sent (each four messages to every browser)."""
        self._path, self._length = belt_path()
        seg = np.linalg.norm(np.diff(self._path, axis=0), axis=1)
        self._arc = np.concatenate([[0.0], np.cumsum(seg)])
        scene.set_up_direction("+z")
        # Flat lighting: viser's default shadows (cascaded shadow maps) and its environment map
        # made each redraw cost ~100 ms of the page's main thread in software WebGL (a browser
        # without a GPU, as in CI): the page was busy 100 % of the time and every click or
        # keystroke waited 0.3-0.5 s. Without them, ~30 ms (the page's main thread: `busy_pct` of
        # tests/bench/bench_dashboard.py --page).
        scene.configure_default_lights(enabled=True, cast_shadow=False)
        scene.configure_environment_map(hdri=None)
        scene.add_grid("/grid", width=1.2, height=1.2, cell_size=0.1, position=(0.15, 0.0, 0.0))
        scene.add_box("/base", dimensions=(0.7, 0.4, 0.02), color=(70, 74, 82),
                      position=(0.16, 0.0, 0.01))
        scene.add_cylinder("/shaft", radius=0.012, height=TABLE_Z, color=(150, 150, 150),
                           position=(0.0, 0.0, TABLE_Z / 2))
        scene.add_cylinder("/motor", radius=0.03, height=0.06, color=(40, 40, 40),
                           position=(MOTOR_X, 0.0, 0.03))
        self.load = scene.add_frame("/load", show_axes=False)
        scene.add_cylinder("/load/table", radius=TABLE_R, height=0.02, color=(200, 205, 215),
                           position=(0.0, 0.0, TABLE_Z))
        scene.add_box("/load/pointer", dimensions=(TABLE_R * 0.9, 0.02, 0.012),
                      color=(31, 119, 180), position=(TABLE_R * 0.45, 0.0, TABLE_Z + 0.016))
        _add_pulley(scene, "/load/pulley", "/load/pulley_mark", LOAD_PULLEY_R, 0.008)
        self.motor = scene.add_frame("/motor_pulley", show_axes=False, position=(MOTOR_X, 0, 0))
        _add_pulley(scene, "/motor_pulley/wheel", "/motor_pulley/mark", MOTOR_PULLEY_R, 0.006)
        segs = np.stack([self._path[:-1], self._path[1:]], axis=1)
        scene.add_line_segments("/belt", points=segs, colors=(30, 30, 30), thickness=0.006)
        self.markers = scene.add_point_cloud(
            "/belt_markers", points=self._markers(0.0), colors=(240, 240, 240),
            point_size=0.008, point_shape="circle",
        )
        self.ref = scene.add_frame("/reference", show_axes=False)
        scene.add_box("/reference/ghost", dimensions=(0.05, 0.03, 0.03), color=(230, 126, 34),
                      opacity=0.45, position=(TABLE_R + 0.03, 0.0, TABLE_Z))
        scene.add_label("/reference/ghost/label", "reference",
                        position=(0.0, 0.0, 0.03))
        self._last: tuple[float, float] | None = None
        self._moved_at = -math.inf

    def _markers(self, load_deg: float) -> np.ndarray:
        # The belt moves by load angle * load pulley radius (positive angle: counter-clockwise).
        shift = math.radians(load_deg) * LOAD_PULLEY_R
        s = (np.arange(N_BELT_MARKERS) * self._length / N_BELT_MARKERS - shift) % self._length
        pts = np.stack([np.interp(s, self._arc, self._path[:, i]) for i in range(3)], axis=1)
        pts[:, 2] += 0.008
        return pts.astype(np.float32)

    def update(self, load_deg: float, ref_deg: float, now_s: float | None = None) -> bool:
        """Rotate the load and the motor pulley to `load_deg`, the ghost to `ref_deg`, if
        either turned SCENE_STEP_DEG or more since the last move and that was 1/SCENE_RATE_HZ
        ago or more (`now_s`: time.monotonic() unless given). True: a move was sent."""
        now = time.monotonic() if now_s is None else now_s
        last = self._last
        if now - self._moved_at < 1.0 / SCENE_RATE_HZ or (
                last is not None and abs(load_deg - last[0]) < SCENE_STEP_DEG
                and abs(ref_deg - last[1]) < SCENE_STEP_DEG):
            return False
        self._last, self._moved_at = (load_deg, ref_deg), now
        self.moves += 1
        if self._loop is None:
            self._move(load_deg, ref_deg)
            return True
        try:
            self._loop.call_soon_threadsafe(
                functools.partial(run_logged, self._move, load_deg, ref_deg, what="3-D scene"))
        except RuntimeError:  # viser's loop is closed: the server stopped, nothing to show
            return False
        return True

    def _move(self, load_deg: float, ref_deg: float) -> None:
        a = math.radians(load_deg)
        self.load.wxyz = _quat_z(a)
        self.motor.wxyz = _quat_z(a * LOAD_PULLEY_R / MOTOR_PULLEY_R)
        self.ref.wxyz = _quat_z(math.radians(ref_deg))
        self.markers.points = self._markers(load_deg)
