"""The identification program the loop runs tick by tick: preplanned columns, preallocated
records, limits checked every tick. Pure: the controller's runtime calls `step` from its tick.
"""

from __future__ import annotations

from array import array
from collections.abc import Sequence

from controller.core.loop import ServoLoop


class ExcitationProgram:
    """A preplanned per-tick program run inside the tick (identification); the columns are
    sequences the tick only indexes (lists, or array.array: no Python object per element).

    Tick i of the program is either a *move* (``kind[i] == 0``: the position loop follows
    ``ref = start + (target[i] - start) * a[i]``, rate ``(target[i] - start) * b[i]``, where
    ``start`` is the position at the first tick of the move, ``first[i]``) or an *excitation*
    tick (``kind[i] == 1``: offset ``a[i]``, excitation ``b[i]``; open mode ``u = a + b``,
    closed mode ``u = loop.tick_speed(a, w) + b`` with ``loop.u_prev = u``). Limits checked
    every tick: ``|b| <= amplitude_limit`` on excitation ticks, ``|pos - center[i]| <=
    window_deg`` where ``window[i]``, elapsed time ``<= max_duration_s``. The records (u, w,
    pos of every executed tick) are preallocated arrays; the tick only indexes.

    State: ``pending`` -> ``running`` -> ``done`` | ``aborted`` (``reason``), written by the tick
    only; ``n_done`` ticks were executed.
    """

    def __init__(
        self,
        kind: Sequence[int],
        a: Sequence[float],
        b: Sequence[float],
        target: Sequence[float],
        first: Sequence[int] | Sequence[bool],
        center: Sequence[float],
        window: Sequence[int] | Sequence[bool],
        *,
        closed: bool,
        window_deg: float,
        amplitude_limit: float,
        max_duration_s: float,
        command_limit: float,
    ) -> None:
        n = len(kind)
        if n == 0 or any(len(c) != n for c in (a, b, target, first, center, window)):
            raise ValueError("program: all columns must have the same, non-zero length")
        self.n = n
        self.kind, self.a, self.b, self.target = kind, a, b, target
        self.first, self.center, self.window = first, center, window
        self.closed = closed
        self.window_deg = window_deg
        self.amplitude_limit = amplitude_limit
        self.max_duration_s = max_duration_s
        self.command_limit = command_limit
        # array('d'): storing a float keeps no object alive (a list slot would)
        self.rec_u = array("d", bytes(8 * n))
        self.rec_w = array("d", bytes(8 * n))
        self.rec_pos = array("d", bytes(8 * n))
        self.n_done = 0
        self.state = "pending"
        self.reason = ""
        self.limit = ""
        self.start_seq = -1
        self.ref = 0.0
        self.r = 0.0
        self._t0 = -1.0
        self._move_start = 0.0

    def step(self, t_s: float, pos: float, w: float, loop: ServoLoop) -> float:
        """One tick; returns the command. Sets state done/aborted (then the caller holds)."""
        i = self.n_done
        if self._t0 < 0.0:
            self._t0 = t_s
            self.state = "running"
        if t_s - self._t0 > self.max_duration_s:
            self._abort(f"maximum duration {self.max_duration_s:g} s reached", "duration")
            return 0.0
        c = self.center[i]
        if self.window[i] and abs(pos - c) > self.window_deg:
            self._abort(
                f"position window: {pos:.3f} deg is outside {c:g} +- {self.window_deg:g} deg",
                "window",
            )
            return 0.0
        if self.kind[i] == 0:
            if self.first[i]:
                loop.reset()
                self._move_start = pos
            start = self._move_start
            dist = self.target[i] - start
            ref = start + dist * self.a[i]
            u = loop.tick(ref, dist * self.b[i], pos, w)
            self.ref = ref
            self.r = loop.speed_ref_deg_s
        else:
            off = self.a[i]
            x = self.b[i]
            if x > self.amplitude_limit or x < -self.amplitude_limit:
                self._abort(f"amplitude: |{x:.3g}| deg/s over the limit", "amplitude")
                return 0.0
            u = (loop.tick_speed(off, w) if self.closed else off) + x
            limit = self.command_limit
            if u > limit:
                u = limit
            elif u < -limit:
                u = -limit
            if self.closed:
                loop.u_prev = u
            self.ref = pos
            self.r = off
        self.rec_u[i] = u
        self.rec_w[i] = w
        self.rec_pos[i] = pos
        i += 1
        self.n_done = i
        if i == self.n:
            self.state = "done"
        return u

    def _abort(self, reason: str, limit: str) -> None:
        self.reason = reason
        self.limit = limit
        self.state = "aborted"

    @property
    def over(self) -> bool:
        return self.state in ("done", "aborted")
