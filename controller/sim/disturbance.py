"""External load-torque disturbance profiles for the simulated rig.

A disturbance is a torque in N m acting on the load (positive = the load's positive direction),
as a function of simulated time. The rig samples it once per control tick and holds it for the
tick, so profiles must be smooth on a 1 ms scale or accept that hold.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from controller.core.errors import ConfigError
from controller.core.validate import number

__all__ = [
    "DISTURBANCES",
    "Disturbance",
    "NoDisturbance",
    "SineTorque",
    "StepTorque",
    "StepsTorque",
    "SumTorque",
    "disturbance_from_name",
]


# -- the profiles' arithmetic: plain-float functions, so that the compiled offline loop
# (`controller.sim.offline`) samples them with this one definition.


def sine_torque(amplitude_n_m: float, freq_hz: float, phase_deg: float, time_s: float) -> float:
    arg = 2.0 * math.pi * freq_hz * time_s + math.radians(phase_deg)
    return amplitude_n_m * math.sin(arg)


def step_torque(amplitude_n_m: float, at_s: float, time_s: float) -> float:
    return amplitude_n_m if time_s >= at_s else 0.0


def steps_torque(
    times_s: Sequence[float] | np.ndarray, levels_n_m: Sequence[float] | np.ndarray,
    start: int, stop: int, time_s: float,
) -> float:
    """`levels_n_m[i]` from `times_s[i]` on, for i in start..stop-1 (0 before the first)."""
    out = 0.0
    for i in range(start, stop):
        if time_s < times_s[i]:
            break
        out = levels_n_m[i]
    return out


@runtime_checkable
class Disturbance(Protocol):
    """Anything with `torque_n_m(time_s) -> float` can disturb the rig."""

    def torque_n_m(self, time_s: float) -> float: ...


@dataclass(frozen=True, slots=True)
class NoDisturbance:
    """Zero torque."""

    def torque_n_m(self, time_s: float) -> float:
        return 0.0


@dataclass(frozen=True, slots=True)
class SineTorque:
    """amplitude * sin(2 pi f t + phase): a slow one is what the DOB's Q rejects best."""

    amplitude_n_m: float
    freq_hz: float
    phase_deg: float = 0.0

    def __post_init__(self) -> None:
        number(self.amplitude_n_m, "amplitude_n_m")
        number(self.freq_hz, "freq_hz")
        number(self.phase_deg, "phase_deg")
        if self.freq_hz <= 0.0:
            raise ConfigError("freq_hz", f"must be > 0, got {self.freq_hz!r}")

    def torque_n_m(self, time_s: float) -> float:
        return sine_torque(self.amplitude_n_m, self.freq_hz, self.phase_deg, time_s)


@dataclass(frozen=True, slots=True)
class StepTorque:
    """0 before `time_s`, `amplitude_n_m` from then on."""

    amplitude_n_m: float
    time_s: float

    def __post_init__(self) -> None:
        number(self.amplitude_n_m, "amplitude_n_m")
        number(self.time_s, "time_s")
        if self.time_s < 0.0:
            raise ConfigError("time_s", f"must be >= 0, got {self.time_s!r}")

    def torque_n_m(self, time_s: float) -> float:
        return step_torque(self.amplitude_n_m, self.time_s, time_s)


@dataclass(frozen=True, slots=True)
class StepsTorque:
    """Piecewise constant: `levels_n_m[i]` from `times_s[i]` on (0 before the first time)."""

    times_s: tuple[float, ...]
    levels_n_m: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.times_s) != len(self.levels_n_m) or not self.times_s:
            raise ConfigError("times_s", "needs as many times as levels, at least one")
        for i, (t, v) in enumerate(zip(self.times_s, self.levels_n_m, strict=True)):
            number(t, f"times_s[{i}]")
            number(v, f"levels_n_m[{i}]")
            if t < 0.0 or (i and t <= self.times_s[i - 1]):
                raise ConfigError(f"times_s[{i}]", "times must be >= 0 and increasing")

    def torque_n_m(self, time_s: float) -> float:
        return steps_torque(self.times_s, self.levels_n_m, 0, len(self.times_s), time_s)


@dataclass(frozen=True, slots=True)
class SumTorque:
    """The sum of several profiles (several named disturbances at once)."""

    parts: tuple[Disturbance, ...]

    def torque_n_m(self, time_s: float) -> float:
        return sum(d.torque_n_m(time_s) for d in self.parts)


#: Named profiles offered to users. Open loop, 1 N m deflects the belt by ~0.3 deg (stiffness
#: 186 N m/rad), several times the article's position errors. Closed around the starting
#: position PI and Cv, a 0.05 Hz load torque is already rejected to ~1e-4 deg without the DOB
#: (the belt turns torque into a rate disturbance ~ s T / k); the 0.5 Hz one sits at Q31's
#: cut-off, where the DOB amplifies slightly (waterbed).
DISTURBANCES: dict[str, Disturbance] = {
    "none": NoDisturbance(),
    "sine-0.05hz": SineTorque(amplitude_n_m=1.0, freq_hz=0.05),
    "sine-0.5hz": SineTorque(amplitude_n_m=0.5, freq_hz=0.5),
    "step": StepTorque(amplitude_n_m=0.5, time_s=1.0),
}


#: Kinds of a flattened profile's parts (`flatten`).
SINE, STEP, STEPS, ZERO = 0, 1, 2, 3


@dataclass(frozen=True)
class FlatProfile:
    """A profile of the classes above as arrays (for compiled sampling): per part its kind and
    three parameters (sine: amplitude, frequency, phase; step: amplitude, time; steps: the
    part's first and end index into `times_s` / `levels_n_m`); `summed`: the parts are added
    (`SumTorque`, in order) rather than one profile alone."""

    kinds: np.ndarray
    params: np.ndarray
    times_s: np.ndarray
    levels_n_m: np.ndarray
    summed: bool


def flatten(d: Disturbance) -> FlatProfile | None:
    """`d` as a FlatProfile; None for a profile of another class (or a sum of sums)."""
    kinds: list[int] = []
    params: list[tuple[float, float, float]] = []
    times: list[float] = []
    levels: list[float] = []

    def add(p: Disturbance) -> bool:
        if isinstance(p, SineTorque):
            kinds.append(SINE)
            params.append((p.amplitude_n_m, p.freq_hz, p.phase_deg))
        elif isinstance(p, StepTorque):
            kinds.append(STEP)
            params.append((p.amplitude_n_m, p.time_s, 0.0))
        elif isinstance(p, StepsTorque):
            kinds.append(STEPS)
            params.append((float(len(times)), float(len(times) + len(p.times_s)), 0.0))
            times.extend(p.times_s)
            levels.extend(p.levels_n_m)
        elif isinstance(p, NoDisturbance):
            kinds.append(ZERO)
            params.append((0.0, 0.0, 0.0))
        else:
            return False
        return True

    # A sum of sums is not flattened: float addition is not associative.
    if not all(add(p) for p in (d.parts if isinstance(d, SumTorque) else (d,))):
        return None
    return FlatProfile(np.array(kinds, dtype=np.int64),
                       np.array(params, dtype=np.float64).reshape(-1, 3),
                       np.array(times, dtype=np.float64), np.array(levels, dtype=np.float64),
                       isinstance(d, SumTorque))


def flat_torque(kinds: np.ndarray, params: np.ndarray, times_s: np.ndarray,
                levels_n_m: np.ndarray, summed: bool, time_s: float) -> float:
    """The torque of a FlatProfile at `time_s` (what the profile's `torque_n_m` gives)."""
    acc = 0.0
    for i in range(len(kinds)):
        k = kinds[i]
        if k == SINE:
            v = sine_torque(params[i, 0], params[i, 1], params[i, 2], time_s)
        elif k == STEP:
            v = step_torque(params[i, 0], params[i, 1], time_s)
        elif k == STEPS:
            v = steps_torque(times_s, levels_n_m, int(params[i, 0]), int(params[i, 1]), time_s)
        else:
            v = 0.0
        if summed:
            acc += v
        else:
            return v
    return acc


def disturbance_from_name(name: str) -> Disturbance:
    """The registered profile called `name`; ValueError (ConfigError) listing valid names."""
    try:
        return DISTURBANCES[name]
    except KeyError:
        valid = ", ".join(sorted(DISTURBANCES))
        raise ConfigError("disturbance", f"unknown name {name!r}; valid: {valid}") from None
