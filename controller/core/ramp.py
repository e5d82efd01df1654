"""A bounded-speed, bounded-acceleration approach from where the rig is onto a trajectory.

After a reset (or a stop) the rig may sit far from where the trajectory starts: following the
trajectory at once would step the position reference and hold the speed command at its limit.
`Ramp` instead moves its own reference from the present position towards the trajectory's
reference with |speed| <= `speed_max_deg_s` and |acceleration| <= `accel_max_deg_s2` (it brakes
in time: the speed it aims at is what it can still stop from, sqrt(2 a |distance|), plus the
target's own speed), and hands over to the trajectory once it has caught it (position and speed
within one tick's worth). Pure: scalar floats on preallocated slots, nothing allocated per step.
"""

from __future__ import annotations

import math

__all__ = ["Ramp", "ramp_step"]


class Ramp:
    """A rate- and acceleration-limited follower of a moving reference (one per loop)."""

    __slots__ = (
        "accel_max_deg_s2",
        "active",
        "period_s",
        "pos_deg",
        "speed_deg_s",
        "speed_max_deg_s",
    )

    def __init__(
        self, period_s: float, speed_max_deg_s: float = 20.0, accel_max_deg_s2: float = 40.0
    ) -> None:
        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ValueError(f"period_s: {period_s!r} must be > 0")
        if not (math.isfinite(speed_max_deg_s) and speed_max_deg_s > 0.0):
            raise ValueError(f"speed_max_deg_s: {speed_max_deg_s!r} must be > 0")
        if not (math.isfinite(accel_max_deg_s2) and accel_max_deg_s2 > 0.0):
            raise ValueError(f"accel_max_deg_s2: {accel_max_deg_s2!r} must be > 0")
        self.period_s = period_s
        self.speed_max_deg_s = speed_max_deg_s
        self.accel_max_deg_s2 = accel_max_deg_s2
        self.active = False
        """True while the ramp's reference, not the trajectory's, is followed."""
        self.pos_deg = 0.0
        self.speed_deg_s = 0.0

    def begin(self, pos_deg: float, speed_deg_s: float = 0.0) -> None:
        """Start from `pos_deg` moving at `speed_deg_s` (clamped to the speed bound)."""
        vmax = self.speed_max_deg_s
        self.pos_deg = pos_deg
        self.speed_deg_s = (
            vmax if speed_deg_s > vmax else -vmax if speed_deg_s < -vmax else speed_deg_s
        )
        self.active = True

    def cancel(self) -> None:
        self.active = False

    def step(self, target_deg: float, target_speed_deg_s: float) -> float:
        """Advance one period towards (`target_deg`, `target_speed_deg_s`); returns the
        reference position; `speed_deg_s` is the reference speed. Once caught, `active` turns
        False and the target itself is returned."""
        ref, self.pos_deg, self.speed_deg_s, self.active = ramp_step(
            self.pos_deg, self.speed_deg_s, target_deg, target_speed_deg_s, self.period_s,
            self.speed_max_deg_s, self.accel_max_deg_s2,
        )
        return ref


def ramp_step(
    pos_deg: float,
    speed_deg_s: float,
    target_deg: float,
    target_speed_deg_s: float,
    period_s: float,
    speed_max_deg_s: float,
    accel_max_deg_s2: float,
) -> tuple[float, float, float, bool]:
    """`Ramp.step` as a plain-float function (the compiled offline loop,
    `controller.sim.offline`, runs it too): (reference, new position, new speed, still
    active)."""
    dt = period_s
    a_dt = accel_max_deg_s2 * dt
    vmax = speed_max_deg_s
    # The distance left if the ramp moved at the target's speed this period.
    err = target_deg - (pos_deg + target_speed_deg_s * dt)
    v = speed_deg_s
    # Caught: stepping onto the target changes the speed by at most one period's worth
    # of the acceleration bound.
    if abs(target_speed_deg_s - v) + abs(err) / dt <= a_dt:
        return target_deg, target_deg, target_speed_deg_s, False
    # The speed to aim at: the target's speed plus what still stops in the distance left.
    brake = math.sqrt(2.0 * accel_max_deg_s2 * abs(err))
    want = target_speed_deg_s + (brake if err > 0.0 else -brake)
    want = vmax if want > vmax else -vmax if want < -vmax else want
    dv = want - v
    dv = a_dt if dv > a_dt else -a_dt if dv < -a_dt else dv
    v += dv
    pos = pos_deg + v * dt
    return pos, pos, v, True
