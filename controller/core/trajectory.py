"""Reference trajectories (pure): position and its derivative at time t, load-side degrees."""

from __future__ import annotations

import math
from typing import Annotated, Literal

import msgspec

from controller.core.validate import check_fields, one_of, within

TrajectoryKind = Literal["sine", "step", "ramp", "hold"]
TRAJECTORY_KINDS: tuple[str, ...] = ("sine", "step", "ramp", "hold")
#: The kind as the number `trajectory_at` takes.
KIND_CODE: dict[str, int] = {k: i for i, k in enumerate(TRAJECTORY_KINDS)}


def trajectory_at(
    kind_code: int,
    amplitude_deg: float,
    omega_rad_s: float,
    offset_deg: float,
    slope_deg_s: float,
    step_time_s: float,
    t_s: float,
) -> tuple[float, float]:
    """(position deg, rate deg/s) at time t_s of the trajectory with these fields (`KIND_CODE`
    numbers the kind): a plain-float function, so that the compiled offline loop
    (`controller.sim.offline`) runs this one definition too."""
    if kind_code == 0:  # sine
        wt = omega_rad_s * t_s
        return (offset_deg + amplitude_deg * math.sin(wt),
                amplitude_deg * omega_rad_s * math.cos(wt))
    if kind_code == 1:  # step
        return offset_deg + (amplitude_deg if t_s >= step_time_s else 0.0), 0.0
    if kind_code == 2:  # ramp
        return offset_deg + slope_deg_s * t_s, slope_deg_s
    return offset_deg, 0.0


class Trajectory(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """sine: offset + amplitude sin(omega t); step: offset, then offset + amplitude at step_time_s;
    ramp: offset + slope t; hold: offset. Default: the article's 5 sin(0.5 t) deg."""

    kind: Annotated[str, one_of(TRAJECTORY_KINDS, "trajectory")] = "sine"
    amplitude_deg: Annotated[float, within(-3600.0, 3600.0)] = 5.0
    omega_rad_s: Annotated[float, within(0.0, 100.0)] = 0.5
    offset_deg: Annotated[float, within(-1e6, 1e6)] = 0.0
    slope_deg_s: Annotated[float, within(-1000.0, 1000.0)] = 1.0
    step_time_s: Annotated[float, within(0.0, 1e6)] = 0.5

    def __post_init__(self) -> None:
        check_fields(self)

    @property
    def period_s(self) -> float | None:
        if self.kind == "sine" and self.omega_rad_s > 0:
            return 2.0 * math.pi / self.omega_rad_s
        return None

    def at(self, t_s: float) -> tuple[float, float]:
        """(position deg, rate deg/s) at time t_s."""
        return trajectory_at(KIND_CODE[self.kind], self.amplitude_deg, self.omega_rad_s,
                             self.offset_deg, self.slope_deg_s, self.step_time_s, t_s)


def default_trajectory(kind: str) -> Trajectory:
    """The article's tests: 5 sin(0.5 t), a 5 deg step, a 1 deg/s ramp, hold at 40 deg."""
    if kind == "hold":
        return Trajectory(kind="hold", offset_deg=40.0)
    if kind == "step":
        return Trajectory(kind="step", amplitude_deg=5.0)
    return Trajectory(kind=kind)
