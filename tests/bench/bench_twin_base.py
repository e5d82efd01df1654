"""Why the controller's twin told friction and backlash worse live than offline (issue 35 item
1): the article rig's 25 s sine window (5-30 s of a 30 s run, the default loop, DOB on),
friction, backlash and noise estimated on a twin fitted to the rig's exact responses, built
on the built-in rig (what the controller used before b40d665: it lacks the article rig's motor
and gearbox friction, gearbox backlash, drive offset, ripple, belt variation) and on the
article rig's structure (what a --plant sim controller now uses), each without and with the
drive offset the twin lacks taken from d_hat first. Truth: Coulomb 0.25 N m, dead zone 0.05
deg, noise 3e-5 deg.

    nice -n 10 .venv/bin/python tests/bench/bench_twin_base.py

(About 30 s of CPU; over 10 min wall at load 26-28.) Printed at load 26-28: built-in rig
0.25 +- 0.307 N m, 0.08 +- 0.186 deg; offset (2.15 rpm) first 0.359 +- 0.12, 0.0145 +- 0.0885;
article rig 0.248 +- 0.00154, 0.0516 +- 0.00182 (offset first, a /tmp run of the same steps:
0.247 +- 0.0016).
"""

from __future__ import annotations

import time

from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.sim.experiment import run_experiment
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import RigFaults, SimRig
from controller.tune.family import true_knowledge
from controller.twin.fit import twin_from_knowledge
from controller.twin.nonlinear import RunningWindow, with_running
from controller.twin.replay import disturbance_lacking, with_disturbance


def main() -> None:
    setup = rig_setup(("article-rig",))
    true = setup.params
    cfg, sine = LoopConfig(), Trajectory()
    known = true_knowledge(true, RigFaults(), cfg.rate_hz)
    run = run_experiment(cfg, sine, 30.0, rig=SimRig(true, seed=3, disturbance=setup.torque))
    sl = slice(5000, 30000)
    win = RunningWindow(cfg.rate_hz, run.pos_deg[sl], run.speed_deg_s[sl],
                        run.command_deg_s[sl], "sine 5-30 s")
    for name, base in (("built-in rig", None), ("article rig", true)):
        tw = twin_from_knowledge(known, rate_hz=cfg.rate_hz, base=base)
        t0 = time.process_time()
        est = with_running(tw, win).nonlinear
        assert est is not None
        print(f"{name}: {est.describe()} ({time.process_time() - t0:.1f} s CPU)", flush=True)
        lack = disturbance_lacking(tw, cfg, sine, run.d_hat_deg_s, disturbance=setup.torque,
                                   seed=5)
        est = with_running(with_disturbance(tw, lack), win).nonlinear
        assert est is not None
        print(f"{name}, the offset it lacks ({lack.mean_deg_s * true.gear_ratio / 6:.3g} rpm) "
              f"first: {est.describe()}", flush=True)


if __name__ == "__main__":
    main()
