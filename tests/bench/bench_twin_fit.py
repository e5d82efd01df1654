"""The rig's twin on the demo rig (article-rig): identified offline at 3 positions (as
`dobtune identify --plant sim --positions 3`), the twin built from that knowledge, its fit per
position against the measurements and against the true rig's exact linear response (dB, deg),
and runs of the true rig replayed on the twin (measured against predicted position error).

    .venv/bin/python tests/bench/bench_twin_fit.py
"""

from __future__ import annotations

import numpy as np

from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
from controller.ident.offline import run_offline
from controller.ident.spec import IdentifySpec
from controller.sim.experiment import run_experiment
from controller.sim.rig_disturbances import RigSetup, rig_setup
from controller.sim.sim_rig import RigFaults, SimRig
from controller.twin.fit import position_fit, rig_response, twin_from_knowledge
from controller.twin.replay import replay


class Never:
    def is_set(self) -> bool:
        return False

    def wait(self, t: float | None = None) -> bool:
        return False


def demo_knowledge(setup: RigSetup, cfg: LoopConfig) -> PlantKnowledge:
    """The demo rig `setup` identified offline at 3 positions (as `dobtune identify --plant
    sim --positions 3`), as plant knowledge (also tests/bench/bench_prediction.py's)."""
    out = run_offline(IdentifySpec(positions=3), cfg.with_(dob_on=False), Never(),
                      rig_factory=lambda c, seed: SimRig(setup.params, rate_hz=c.rate_hz,
                                                         seed=seed, disturbance=setup.torque))
    res = out.result
    assert res is not None and out.complete, out.reason
    return PlantKnowledge(measured=res.measured_responses(), bound=COMMISSIONING_BOUND,
                          model=res.nominal or cfg.nominal, version=1, source="identified")


def main() -> None:
    setup = rig_setup(("article-rig",))
    cfg = LoopConfig()
    k = demo_knowledge(setup, cfg)
    tw = twin_from_knowledge(k, rate_hz=cfg.rate_hz)
    print(tw.describe())
    for p in tw.positions:
        print("  vs measured:", p.describe())
    f = np.geomspace(0.1, 20, 60)
    for pos in (0.0, 120.0, 240.0):
        true_h = rig_response(setup.params, RigFaults(), f, pos)
        twin_h = rig_response(tw.params, tw.faults, f, pos)
        print("  vs true rig:", position_fit(f"{pos:g} deg", pos, f, true_h, twin_h).describe())
    traj = Trajectory(kind="sine", amplitude_deg=5.0, omega_rad_s=0.5)
    runs = (("DOB off", cfg.with_(dob_on=False)), ("Q31 0.5 Hz", cfg.with_(dob_on=True)),
            ("Q20 3.85 Hz", cfg.with_(dob_on=True, q_type="q20", q_cutoff_hz=3.85)))
    for label, c in runs:
        true = run_experiment(c, traj, 30.0, rig=SimRig(setup.params, disturbance=setup.torque))
        r = replay(tw, c, traj, true.error_deg, label=label, disturbance=setup.torque)
        print(f"  replay 5 sin(0.5t) 30 s, {label}: measured RMSE {r.measured_rmse_deg:.5f} "
              f"predicted {r.predicted_rmse_deg:.5f} ({100 * (r.rmse_ratio - 1):+.1f} %); "
              f"peak {r.measured_peak_deg:.4f} vs {r.predicted_peak_deg:.4f}")


if __name__ == "__main__":
    main()
