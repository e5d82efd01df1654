"""The plant a tuning runs its candidates on (pure): a simulated rig's parameters, faults and
disturbances, and where they come from (the rig's twin, a true rig of a family, or the
built-in model when nothing was measured). Everything that predicts (`dobtune tune`,
`dobtune autotune`, Suggest) runs its candidates on one of these."""

from __future__ import annotations

from dataclasses import dataclass, field

from controller.core.trajectory import Trajectory
from controller.gate.knowledge import PlantKnowledge
from controller.sim.disturbance import Disturbance
from controller.sim.rig_disturbances import FrictionChange, RigSetup, ScheduledRig
from controller.sim.sim_rig import RigFaults, RigParams, SimRig
from controller.twin.fit import twin_from_knowledge

__all__ = ["BUILT_IN", "SimPlant", "plant_for"]

#: The source of a plant that was not measured: the built-in article rig.
BUILT_IN = "built-in model (nothing measured: the article rig, not yours)"


@dataclass(frozen=True)
class SimPlant:
    """A simulated plant: `SimRig(params)` with `faults` set, the load torque `torque` and the
    scheduled `friction_changes`; `source` says what it stands for (shown with every
    prediction)."""

    params: RigParams = field(default_factory=RigParams)
    faults: RigFaults = field(default_factory=RigFaults)
    torque: Disturbance | None = None
    friction_changes: tuple[FrictionChange, ...] = ()
    source: str = BUILT_IN
    label: str = "none"
    """The named disturbances (as `RigSetup.label`)."""

    @classmethod
    def of_setup(cls, setup: RigSetup, source: str = BUILT_IN,
                 faults: RigFaults | None = None) -> SimPlant:
        """The built-in rig (or `setup.params`' rig) with `setup`'s named disturbances."""
        return cls(setup.params, faults or RigFaults(), setup.torque, setup.friction_changes,
                   source, setup.label)

    @property
    def measured(self) -> bool:
        return self.source != BUILT_IN

    def rig(self, rate_hz: float, initial_position_deg: float,
            seed: int = 0) -> SimRig | ScheduledRig:
        """A fresh rig at rest at `initial_position_deg` (faults taken at its first step)."""
        rig = SimRig(self.params, rate_hz=rate_hz, seed=seed, disturbance=self.torque,
                     initial_position_deg=initial_position_deg)
        if self.faults.active:
            rig.set_faults(self.faults)
        return ScheduledRig(rig, self.friction_changes) if self.friction_changes else rig

    def rig_on(self, trajectory: Trajectory, rate_hz: float,
               seed: int = 0) -> SimRig | ScheduledRig:
        """A fresh rig starting on `trajectory`."""
        return self.rig(rate_hz, trajectory.at(0.0)[0], seed)


def plant_for(knowledge: PlantKnowledge, setup: RigSetup, rate_hz: float = 1000.0) -> SimPlant:
    """What predictions run on: the rig's twin (`controller.twin.fit.twin_from_knowledge`,
    fitted to the measured responses, with `setup`'s disturbances on top) when the knowledge
    holds measurements, else the built-in model (its `source` says so). Raises ValueError if
    the twin cannot be fitted (never a silent fall back to the built-in model)."""
    if not knowledge.measured:
        return SimPlant.of_setup(setup)
    tw = twin_from_knowledge(knowledge, rate_hz=rate_hz, base=setup.params)
    fitted = ", ".join(f"{k} {v:.3g}" for k, v in tw.fitted.items())
    worst = tw.worst_fit
    fit = f"; worst position fit {worst.rms_db:.2f} dB rms" if worst is not None else ""
    return SimPlant(tw.params, tw.faults, setup.torque, setup.friction_changes,
                    f"rig's twin of {knowledge.describe()} ({fitted}{fit})", setup.label)
