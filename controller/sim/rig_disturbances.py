"""Named disturbances of a real timing belt, for experiments on the simulated rig.

A named disturbance is any mix of: an external load torque against time (`Disturbance`),
changed rig parameters (stronger tooth meshing, cogging, stiction), and a friction change at
a given time. Several can be combined (`--disturbance NAME` repeated); two that set the same
rig parameter are refused.

Note what the reference rig (control.md's model, `RigParams()`) already contains, always on:
tooth-periodic ripple torque 0.05 N m and transmission error 0.01 deg at 30 per revolution,
Stribeck friction (static 0.35 N m, Coulomb 0.25 N m, 0.2 deg/s), backlash 0.02 deg and a
bias torque 0.1 N m. The names below make these stronger or add what it lacks:

| name | what it does |
|---|---|
| tooth-meshing | ripple torque 0.05 -> 0.5 N m and transmission error 0.01 -> 0.03 deg (30/rev) |
| cogging | motor cogging 0.005 N m (2 % of the drive's torque limit), 12 per motor rev |
| load-steps | load torque +1 N m at 1 s, -1 N m at 11 s, 0 at 21 s |
| big-step | load torque step of 2 N m at 1 s (the "large disturbance" of Figs. 8-9) |
| friction-change | Coulomb and static friction x1.6 at 5 s (wear, temperature, lubrication) |
| stick-slip | static friction 0.35 -> 0.8 N m, Stribeck speed 0.2 -> 1 deg/s |
| sine-0.05hz, sine-0.5hz, step | the load-torque profiles of `controller.sim.disturbance` |

The ones above are load-side: the stiff drive turns a load torque into belt deflection that the
position loop sees, and the rate-difference DOB only a high-passed part of it. The article's
d is a RATE disturbance at P's input (the motor and gearbox side); these names add it, and the
plant variation with position that limits Q (the article's Fig. 13):

Values (ours; the article gives none):
- motor-friction: Coulomb 0.004 N m at the motor (no-load friction of a 40 W motor and a
  gearhead's input; 1.6 % of the drive's torque limit).
- gearbox: friction 25 % of the transmitted torque (efficiency 0.75, a 3-stage planetary) and
  backlash 0.03 deg at its output (a 2 arcmin gearhead).
- drive-offset: the drive's speed loop regulates to the command + 2 rpm (motor side; 0.09
  deg/s at the load).
- drive-droop: the drive's speed falls 500 rpm per N m of its torque (1 % of 5000 rpm at a
  40 W motor's 0.1 N m).
- ratio-ripple: transmission ratio 1 +- 0.2 % once per turntable revolution (belt tension,
  pulley run-out).
- belt-tension: belt stiffness 1 +- 20 % and damping 1 +- 30 % with cos(turntable angle): the
  plant varies with position (u -> w agrees within 0.1 dB below 1 Hz, spreads ~2 dB at 5 Hz).
- encoder: load encoder noise 3e-5 deg rms (0.1 arcsec) and interpolation error 5e-5 deg at
  16384 periods/rev.
- article-rig: all seven at once: the article's rig as we model it.

Values are our choices (control.md gives none for these disturbances): large enough to matter
next to the article's 0.02-0.1 deg errors, within what a 40 W drive and belt can meet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from controller.core.errors import ConfigError
from controller.sim.disturbance import (
    DISTURBANCES,
    Disturbance,
    StepsTorque,
    StepTorque,
    SumTorque,
)
from controller.sim.sim_rig import RigParams, SimRig

__all__ = [
    "DEFAULT_RIG_NAMES",
    "NO_EFFECTS",
    "RIG_DISTURBANCES",
    "FrictionChange",
    "RigDisturbance",
    "RigSetup",
    "ScheduledRig",
    "build_rig",
    "rig_names",
    "rig_setup",
]


@dataclass(frozen=True, slots=True)
class FrictionChange:
    """At `time_s`, the load's Coulomb and static friction are multiplied by `factor`."""

    time_s: float
    factor: float


@dataclass(frozen=True, slots=True)
class RigDisturbance:
    name: str
    description: str
    torque: Disturbance | None = None
    params: tuple[tuple[str, float], ...] = ()
    """RigParams fields set to these values."""
    friction_change: FrictionChange | None = None


#: Rate disturbances at P's input, the position-dependent belt and the encoder's errors.
_MOTOR_SIDE = (
    RigDisturbance(
        "motor-friction",
        "Coulomb friction 0.004 N m at the motor and gearbox input (motor side)",
        params=(("motor_coulomb_n_m", 0.004),),
    ),
    RigDisturbance(
        "gearbox",
        "gearbox friction 25 % of the transmitted torque, backlash 0.03 deg at its output",
        params=(("gearbox_friction_fraction", 0.25), ("gearbox_backlash_deg", 0.03)),
    ),
    RigDisturbance(
        "drive-offset",
        "drive speed-loop offset +2 rpm (motor side)",
        params=(("drive_offset_rpm", 2.0),),
    ),
    RigDisturbance(
        "drive-droop",
        "drive speed-loop droop 500 rpm per N m of drive torque (motor side)",
        params=(("drive_droop_rpm_per_n_m", 500.0),),
    ),
    RigDisturbance(
        "ratio-ripple",
        "transmission ratio ripple +-0.2 % once per turntable revolution",
        params=(("ratio_ripple_fraction", 0.002), ("ratio_ripple_periods_per_rev", 1)),
    ),
    RigDisturbance(
        "belt-tension",
        "belt stiffness +-20 % and damping +-30 % with the turntable angle",
        params=(("belt_stiffness_variation", 0.2), ("belt_damping_variation", 0.3)),
    ),
    RigDisturbance(
        "encoder",
        "load encoder noise 3e-5 deg rms, interpolation error 5e-5 deg at 16384/rev",
        params=(
            ("position_noise_deg", 3e-5),
            ("encoder_cyclic_error_deg", 5e-5),
            ("encoder_cyclic_periods_per_rev", 16384),
        ),
    ),
)

RIG_DISTURBANCES: dict[str, RigDisturbance] = {
    d.name: d
    for d in (
        RigDisturbance("none", "no disturbance beyond the reference rig"),
        RigDisturbance("ideal", "the reference rig alone (the same as none): no article effects"),
        RigDisturbance(
            "tooth-meshing",
            "belt tooth meshing: ripple torque 0.5 N m, transmission error 0.03 deg, 30/rev",
            params=(("ripple_torque_n_m", 0.5), ("transmission_error_deg", 0.03)),
        ),
        RigDisturbance(
            "cogging",
            "motor cogging 0.005 N m (motor side), 12 per motor revolution",
            params=(("cogging_torque_n_m", 0.005), ("cogging_periods_per_rev", 12)),
        ),
        RigDisturbance(
            "load-steps",
            "load torque +1 N m at 1 s, -1 N m at 11 s, 0 at 21 s",
            torque=StepsTorque(times_s=(1.0, 11.0, 21.0), levels_n_m=(1.0, -1.0, 0.0)),
        ),
        RigDisturbance(
            "big-step", "load torque step 2 N m at 1 s",
            torque=StepTorque(amplitude_n_m=2.0, time_s=1.0),
        ),
        RigDisturbance(
            "friction-change",
            "Coulomb and static friction x1.6 at 5 s",
            friction_change=FrictionChange(time_s=5.0, factor=1.6),
        ),
        RigDisturbance(
            "stick-slip",
            "stronger stick-slip at reversals: static friction 0.8 N m, Stribeck 1 deg/s",
            params=(("static_torque_n_m", 0.8), ("stribeck_speed_deg_s", 1.0)),
        ),
        *_MOTOR_SIDE,
        RigDisturbance(
            "article-rig",
            "all of motor-friction, gearbox, drive-offset, drive-droop, ratio-ripple, "
            "belt-tension, encoder",
            params=tuple(kv for d in _MOTOR_SIDE for kv in d.params),
        ),
        *(
            RigDisturbance(name, f"load torque profile {name}", torque=d)
            for name, d in DISTURBANCES.items()
            if name != "none"
        ),
    )
}


#: The simulated rig every entry point runs unless told otherwise (`dobtune experiment`'s
#: time-domain tests, `autotune`, `tune`, `identify --plant sim`, the demo): the article's rig,
#: its rate disturbances at P's input and the belt varying with position. `--disturbance
#: ideal` (or `none`) names the reference rig without them.
DEFAULT_RIG_NAMES: tuple[str, ...] = ("article-rig",)
#: Names that add nothing (the reference rig alone).
NO_EFFECTS = ("none", "ideal")


def rig_names(names: tuple[str, ...] | list[str] | None) -> tuple[str, ...]:
    """`names` as given, or `DEFAULT_RIG_NAMES` when none are given."""
    return tuple(names) if names else DEFAULT_RIG_NAMES


@dataclass(frozen=True)
class RigSetup:
    """What a list of names amounts to: rig parameters, a torque profile, friction changes."""

    names: tuple[str, ...]
    params: RigParams
    torque: Disturbance | None
    friction_changes: tuple[FrictionChange, ...]

    @property
    def label(self) -> str:
        return "+".join(self.names) if self.names else "none"


def rig_setup(names: tuple[str, ...] | list[str], base: RigParams | None = None) -> RigSetup:
    """Combine named disturbances; ConfigError("disturbance", ...) for an unknown name or two
    names that set the same parameter."""
    base = base or RigParams()
    chosen: list[RigDisturbance] = []
    for name in names:
        if name not in RIG_DISTURBANCES:
            valid = ", ".join(sorted(RIG_DISTURBANCES))
            raise ConfigError("disturbance", f"unknown name {name!r}; valid: {valid}")
        if name not in NO_EFFECTS and name not in [d.name for d in chosen]:
            chosen.append(RIG_DISTURBANCES[name])
    overrides: dict[str, float] = {}
    torques: list[Disturbance] = []
    changes: list[FrictionChange] = []
    for d in chosen:
        for field, value in d.params:
            if field in overrides:
                raise ConfigError("disturbance", f"{d.name} and another name both set {field}")
            overrides[field] = value
        if d.torque is not None:
            torques.append(d.torque)
        if d.friction_change is not None:
            changes.append(d.friction_change)
    params = replace(base, **overrides) if overrides else base  # type: ignore[arg-type]
    torque: Disturbance | None
    torque = None if not torques else torques[0] if len(torques) == 1 else SumTorque(tuple(torques))
    return RigSetup(
        tuple(d.name for d in chosen),
        params,
        torque,
        tuple(sorted(changes, key=lambda c: c.time_s)),
    )


class ScheduledRig:
    """A SimRig whose friction changes at given times (the `Rig` protocol: read, step)."""

    __slots__ = ("_events", "_next", "rig", "tick")

    def __init__(self, rig: SimRig, changes: tuple[FrictionChange, ...]) -> None:
        self.rig = rig
        fc, fs = rig.friction_n_m
        self._events = [
            (round(c.time_s / rig.period_s), fc * c.factor, fs * c.factor) for c in changes
        ]
        self._next = 0
        self.tick = 0
        """Steps taken (the compiled offline loop advances it for the steps it makes)."""

    def read(self) -> tuple[float, float]:
        return self.rig.read()

    def step(self, command_deg_s: float) -> None:
        self.apply_due()
        self.rig.step(command_deg_s)
        self.tick += 1

    def apply_due(self) -> None:
        """Make the friction changes due at the present tick (before its step)."""
        ev = self._events
        while self._next < len(ev) and ev[self._next][0] <= self.tick:
            _, fc, fs = ev[self._next]
            self.rig.set_friction(fc, fs)
            self._next += 1

    def next_event_tick(self) -> int | None:
        """The tick of the next friction change not yet made (None: none left)."""
        return self._events[self._next][0] if self._next < len(self._events) else None


def build_rig(
    setup: RigSetup, *, rate_hz: float, seed: int, initial_position_deg: float
) -> SimRig | ScheduledRig:
    """The simulated rig for `setup` (a plain SimRig when no friction change is scheduled)."""
    if not math.isfinite(initial_position_deg):
        raise ConfigError("initial_position_deg", f"must be finite, got {initial_position_deg}")
    rig = SimRig(
        setup.params,
        rate_hz=rate_hz,
        seed=seed,
        disturbance=setup.torque,
        initial_position_deg=initial_position_deg,
    )
    return ScheduledRig(rig, setup.friction_changes) if setup.friction_changes else rig
