"""The rig's twin on the demo rig (article-rig): identified offline at 3 positions (as
`dobtune identify --plant sim --positions 3`), the twin built from that knowledge, its fit per
position against the measurements and against the true rig's exact linear response (dB, deg),
and runs of the true rig replayed on the twin (measured against predicted position error).
Then the twin's friction, backlash and encoder noise estimated from a 20 s window of the true
rig's normal running (the default loop on the sine; `controller.twin.nonlinear`), against the
true rig's values, and the replays again with them; and the drive offset the twin lacks from
the DOB's d_hat (`--offset-rpm`: the true rig's drive offset, default the demo rig's own).

    .venv/bin/python tests/bench/bench_twin_fit.py [--coulomb-factor F] [--backlash-deg B]
        [--noise-deg S] [--offset-rpm R]

The options make the true rig differ from the demo rig the twin starts from (defaults: the
demo rig itself).
"""

from __future__ import annotations

import argparse
from dataclasses import replace

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
from controller.twin.model import RigTwin
from controller.twin.nonlinear import RunningWindow, with_running
from controller.twin.replay import disturbance_lacking, replay, with_disturbance


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


def main(coulomb_factor: float, backlash_deg: float | None, noise_deg: float | None,
         offset_rpm: float | None) -> None:
    demo = rig_setup(("article-rig",))
    p0 = demo.params
    true_p = replace(p0, coulomb_torque_n_m=p0.coulomb_torque_n_m * coulomb_factor,
                     static_torque_n_m=p0.static_torque_n_m * coulomb_factor,
                     backlash_deg=p0.backlash_deg if backlash_deg is None else backlash_deg,
                     position_noise_deg=(p0.position_noise_deg if noise_deg is None
                                         else noise_deg),
                     drive_offset_rpm=p0.drive_offset_rpm if offset_rpm is None else offset_rpm)
    setup = RigSetup(demo.names, true_p, demo.torque, demo.friction_changes)
    print(f"true rig: the demo rig with Coulomb {true_p.coulomb_torque_n_m:.3g} N m, backlash "
          f"{true_p.backlash_deg + true_p.gearbox_backlash_deg:.3g} deg (belt + gearbox), "
          f"encoder noise {true_p.position_noise_deg:.3g} deg, drive offset "
          f"{true_p.drive_offset_rpm:.3g} rpm")
    cfg = LoopConfig()
    k = demo_knowledge(setup, cfg)
    tw = twin_from_knowledge(k, rate_hz=cfg.rate_hz, base=p0)
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
    trues = [(label, c, run_experiment(c, traj, 30.0, rig=SimRig(setup.params,
                                                                    disturbance=setup.torque)))
             for label, c in runs]

    def replays(twin: RigTwin, what: str) -> None:
        for label, c, true in trues:
            r = replay(twin, c, traj, true.error_deg, label=label,
                       disturbance=setup.torque, seed=5)
            print(f"  replay 5 sin(0.5t) 30 s, {label}, {what}: measured RMSE "
                  f"{r.measured_rmse_deg:.5f} predicted {r.predicted_rmse_deg:.5f} "
                  f"({100 * (r.rmse_ratio - 1):+.1f} %); peak {r.measured_peak_deg:.4f} vs "
                  f"{r.predicted_peak_deg:.4f}")

    replays(tw, "the base rig's friction, backlash, noise")
    rec = run_experiment(cfg, traj, 20.0, rig=SimRig(setup.params, seed=3,
                                                     disturbance=setup.torque))
    win = RunningWindow(cfg.rate_hz, rec.pos_deg, rec.speed_deg_s, rec.command_deg_s,
                        label="20 s sine, default loop")
    # The speed offset the twin lacks first (the DOB's d_hat), then friction and backlash on
    # the twin with it: an offset changes when the load sticks at each reversal.
    lack = disturbance_lacking(tw, cfg, traj, rec.d_hat_deg_s, disturbance=setup.torque, seed=5)
    sd = lack.mean_std_deg_s or 0.0
    print(f"drive offset the twin lacks (d_hat less the twin's own): "
          f"{lack.mean_deg_s * p0.gear_ratio / 6:.3g} +- {sd * p0.gear_ratio / 6:.2g} rpm "
          f"(true: {true_p.drive_offset_rpm - tw.params.drive_offset_rpm:.3g} rpm)")
    td = with_disturbance(tw, lack)
    replays(td, "d_hat's offset")
    tn = with_running(td, win)
    est = tn.nonlinear
    assert est is not None
    print("estimated:", est.describe())
    replays(tn, "d_hat's offset + friction, backlash, noise estimated")

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--coulomb-factor", type=float, default=1.0)
    ap.add_argument("--backlash-deg", type=float, default=None,
                    help="the true rig's belt dead zone (the gearbox's 0.03 deg beside it)")
    ap.add_argument("--noise-deg", type=float, default=None)
    ap.add_argument("--offset-rpm", type=float, default=None)
    a = ap.parse_args()
    main(a.coulomb_factor, a.backlash_deg, a.noise_deg, a.offset_rpm)
