"""The plant a tuning runs its candidates on (pure): a simulated rig's parameters, faults and
disturbances, and where they come from (the rig's twin, a true rig of a family, or the
built-in model when nothing was measured). Everything that predicts (`dobtune tune`,
`dobtune autotune`, Suggest) runs its candidates on one of these."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from controller.core.trajectory import Trajectory
from controller.gate.knowledge import PlantKnowledge
from controller.sim.disturbance import Disturbance
from controller.sim.rig_disturbances import FrictionChange, RigSetup, ScheduledRig
from controller.sim.sim_rig import RigFaults, RigParams, SimRig

__all__ = ["BUILT_IN", "SimPlant", "plant_for", "stand_in_twin"]

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


def stand_in_twin(knowledge: PlantKnowledge, setup: RigSetup) -> SimPlant:
    """A first twin from the measured responses, until the rig's own twin (fitted per position,
    friction and noise estimated) is built: the built-in rig with `setup`'s disturbances, its
    load inertia scaled so that the belt mode's natural frequency is the fitted model's
    (w_n^2 ~ k / J) and its drive gain the measured responses' low-frequency gain. Resonances
    and delay beyond the fit are not modelled."""
    if not knowledge.measured:
        return SimPlant.of_setup(setup)
    pn_den = knowledge.model.pn_den
    ref = RigParams()
    base = setup.params
    a2_ref = 0.0005169  # the built-in rig's Pn denominator (control.md eq. 34)
    scale = pn_den[0] / a2_ref if pn_den[0] > 0 else 1.0
    gain = float(np.median([abs(m.response[0]) for m in knowledge.measured]))
    params = replace(base, load_inertia_kg_m2=ref.load_inertia_kg_m2 * scale)
    faults = RigFaults(plant_gain=min(100.0, gain)) if math.isfinite(gain) else RigFaults()
    return SimPlant(params, faults, setup.torque, setup.friction_changes,
                    f"stand-in twin of {knowledge.describe()} (inertia x{scale:.2f}, gain "
                    f"x{gain:.2f})", setup.label)


def plant_for(knowledge: PlantKnowledge, setup: RigSetup) -> SimPlant:
    """What predictions run on: the twin when the knowledge holds measurements, else the
    built-in model (its `source` says so)."""
    return stand_in_twin(knowledge, setup)
