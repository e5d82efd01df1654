"""The demo's Measure at 3 positions, offline: `dobtune identify --plant sim --positions 3`
on article-rig (friction and backlash at small amplitude: its 0.1 Hz point is the uncertain
one), DOB off, as the identification runs it."""

from __future__ import annotations

from controller.core.config import LoopConfig
from controller.ident.offline import run_offline
from controller.ident.result import IdentifyResult
from controller.ident.spec import IdentifySpec
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import SimRig

DEMO_CONFIG = LoopConfig().with_(dob_on=False)


class _Never:
    def is_set(self) -> bool:
        return False

    def wait(self, timeout: float | None = None) -> bool:
        return False


def demo_identification() -> IdentifyResult:
    """The complete run's result (AssertionError if it did not complete)."""
    setup = rig_setup(("article-rig",))
    out = run_offline(IdentifySpec(positions=3), DEMO_CONFIG, _Never(),
                      rig_factory=lambda c, seed: SimRig(setup.params, rate_hz=c.rate_hz,
                                                         seed=seed, disturbance=setup.torque))
    assert out.complete and out.result is not None
    return out.result
