"""What other threads may ask of the loop: the runtime's own request types (domain, not wire).

The Zenoh edge (`controller.process.node`) converts the wire messages of `controller.protocol`
into these; the runtime never sees a wire message. Each request is served by the tick at the
next tick boundary (see `Runtime.submit`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from controller.core.loop import LoopCoefficients, PreparedCoefficients
from controller.core.trajectory import Trajectory
from controller.ident.program import ExcitationProgram

__all__ = [
    "AbortProgram",
    "ApplyCoefficients",
    "DriftRig",
    "DropFallback",
    "EStop",
    "InjectFault",
    "RequestBody",
    "ResetFault",
    "RunProgram",
    "SetTrajectory",
    "Start",
    "Stop",
]


@dataclass(frozen=True, slots=True)
class SetTrajectory:
    """Follow `trajectory` (at once when running; otherwise it is what Start resumes)."""

    trajectory: Trajectory


@dataclass(frozen=True, slots=True)
class Start:
    """Run the trajectory (from stopped; refused in e-stop or fault until reset)."""


@dataclass(frozen=True, slots=True)
class Stop:
    """Controlled stop: hold the present position."""


@dataclass(frozen=True, slots=True)
class EStop:
    """Speed command 0 from the next tick, drive disabled, until ResetFault + Start."""


@dataclass(frozen=True, slots=True)
class ResetFault:
    """Leave e-stop or fault: re-enable the drive, hold the present position (stopped).
    Refused unless `estop_seq` is the latest e-stop's (`Runtime.estop_seq`): a reset clears
    only the e-stop its sender saw."""

    estop_seq: int


class ApplyCoefficients:
    """Swap in these coefficients at the next tick boundary.

    The filters are built here, in the thread that makes the request, so the tick that swaps
    only takes prepared objects over (`PreparedCoefficients`). Single use.
    """

    __slots__ = ("fallback", "prepared")

    def __init__(
        self, coefficients: LoopCoefficients, fallback: LoopCoefficients | None = None
    ) -> None:
        self.prepared = PreparedCoefficients(coefficients)
        #: The configuration the watchdog rolls back to if these coefficients misbehave
        #: (the one running before, under the next version number), prepared here too.
        self.fallback = PreparedCoefficients(fallback) if fallback is not None else None

    @property
    def coefficients(self) -> LoopCoefficients:
        return self.prepared.coefficients


@dataclass(frozen=True, slots=True)
class DropFallback:
    """The watchdog must not roll back to the configuration it would (it fails the gate on
    the plant knowledge now): a trip faults instead, saying `reason`. The next apply arms a
    fallback again."""

    reason: str


@dataclass(frozen=True, slots=True)
class RunProgram:
    """Start an ExcitationProgram at the next tick (mode running or stopped)."""

    program: ExcitationProgram


@dataclass(frozen=True, slots=True)
class InjectFault:
    """Simulated rig only: replace its injected faults (`RigFaults`; all defaults clear)."""

    faults: Any


@dataclass(frozen=True, slots=True)
class DriftRig:
    """Simulated rig only (tests, the demo): factors on the rig's starting stiffness, inertia
    and motor friction, and on its extra mode's frequency (`controller.protocol.SimDrift`)."""

    belt_stiffness_factor: float = 1.0
    load_inertia_factor: float = 1.0
    motor_friction_factor: float = 1.0
    resonance_factor: float = 1.0


@dataclass(frozen=True, slots=True)
class AbortProgram:
    """Abort the running program; the loop holds the present position."""

    reason: str = "aborted by request"


RequestBody = (
    SetTrajectory
    | Start
    | Stop
    | EStop
    | ResetFault
    | ApplyCoefficients
    | DropFallback
    | RunProgram
    | AbortProgram
    | InjectFault
    | DriftRig
)
