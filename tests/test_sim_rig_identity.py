"""With every new rig effect off, the rig is bit-identical to the kernel before they were added.

The digests below were printed by `_digest` on the kernel of commit b037d28 (before the rate
disturbances at P's input, the position-dependent belt and the encoder errors were added), on
the same scenarios: open-loop command sequences with reversals through the full nonlinear rig,
with the load-torque profile, a friction change, the runtime faults and motor cogging.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np

from controller.sim.disturbance import SineTorque
from controller.sim.sim_rig import RigParams, SimRig

# sha256 of the read() positions and rates (float64, little endian) of each scenario, from the
# kernel of commit b037d28.
OLD_KERNEL_DIGESTS = {
    "plain": "3020ebcfb020b9f13be4dd4b0541341eb557189e4aca7726418740a5513f1f70",
    "torque+friction": "c5d429f964987c04bdf2a85406e4876bca1dd1aaf87e64e45469abcd55a038bf",
    "faults+cogging": "e21812e665e91e4d5079b63d1dd1b31f1b90a6e547d8cf5ec3e3a386c850dd9f",
}


def _commands(n: int) -> np.ndarray:
    t = np.arange(n) * 1e-3
    return 8.0 * np.sin(2 * math.pi * 0.7 * t) + 3.0 * np.sin(2 * math.pi * 6.0 * t)


def _run(rig: SimRig, n: int, at: dict[int, object] | None = None) -> bytes:
    out = np.empty((n, 2))
    for k, u in enumerate(_commands(n)):
        if at and k in at:
            at[k]()  # type: ignore[operator]
        out[k] = rig.read()
        rig.step(float(u))
    return out.astype("<f8").tobytes()


def _digest(name: str) -> str:
    n = 3000
    if name == "plain":
        data = _run(SimRig(seed=3, initial_position_deg=12.0), n)
    elif name == "torque+friction":
        rig = SimRig(seed=5, disturbance=SineTorque(0.4, 1.3))
        data = _run(rig, n, {1500: lambda: rig.set_friction(0.4, 0.6)})
    else:
        rig = SimRig(RigParams(cogging_torque_n_m=0.005), seed=7, initial_position_deg=-30.0)
        data = _run(
            rig,
            n,
            {
                500: lambda: rig.add_resonance(9.0, 0.05, 0.3),
                1500: lambda: rig.loosen_belt(0.05),
                2200: lambda: rig.set_plant_gain(0.8),
            },
        )
    return hashlib.sha256(data).hexdigest()


def test_all_new_effects_off_is_the_old_kernel_bit_for_bit() -> None:
    for name, digest in OLD_KERNEL_DIGESTS.items():
        assert _digest(name) == digest, name
