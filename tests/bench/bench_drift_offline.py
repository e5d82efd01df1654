"""Benchmark: the watch (issue 34) on the compiled offline loop, faster than real time: false
alarms per hour of normal running, and each plant change's detection time and size error.
Prints figures; not a test.

    nice -n 10 .venv/bin/python tests/bench/bench_drift_offline.py [--only normal,changes]
        [--seconds 900] [--trajectories sine,step,ramp,hold] [--window-s 10]
        [--changes stiffness,inertia,motor_friction,gain,resonance] [--change-run-s 60]

The article rig with all its disturbances and sensor noise on (`article-rig`, the demo's),
the default loop, the knowledge's commissioning bound; every window goes through
`controller.watch.step.watch_window`, the live watch's code (`controller.watch.offline`).
Times are simulated seconds; the fit's own seconds per window are printed beside them (live,
an alarm comes that much after its window ends).

- normal: `--seconds` of each trajectory, nothing changed: alarms (each one false), windows
  with a part outside its range, notes (a part moved but inside), and per part the windows
  that did not tell it. False alarms per hour over all the simulated time, and the 95 % upper
  bound when none was raised (3 / hours: the rule of three).
- changes: each of the issue's changes `--change-at-s` into a `--change-run-s` run of the sine
  (the demo's trajectory): the time from the change to the alarm (to the end of the window that
  raised it), the part named and any other, the estimate against the truth (its deviation and
  bias bound), and where the change falls in its window.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from controller.core.trajectory import default_trajectory
from controller.gate.knowledge import COMMISSIONING_BOUND
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import RigFaults, SimRig
from controller.watch.offline import OfflineWatch, run_offline_watch

SETUP = rig_setup(("article-rig",))
P0 = SETUP.params
#: The extra mode for the resonance's change (a 30 Hz payload mode; the twin has it too).
MODE = RigFaults(resonance_hz=30.0, resonance_damping=0.05)


@dataclass(frozen=True)
class Change:
    name: str
    part: str
    truth: float
    apply: Callable[[SimRig], None]
    mode: RigFaults | None = None


CHANGES = (
    Change("belt stiffness -40 %", "stiffness", 0.6, lambda rig: rig.set_params(
        replace(rig.params, belt_stiffness_n_m_rad=0.6 * P0.belt_stiffness_n_m_rad))),
    Change("load inertia +50 %", "inertia", 1.5, lambda rig: rig.set_params(
        replace(rig.params, load_inertia_kg_m2=1.5 * P0.load_inertia_kg_m2))),
    Change("motor friction x3", "motor_friction", 3.0, lambda rig: rig.set_params(
        replace(rig.params, motor_coulomb_n_m=3.0 * P0.motor_coulomb_n_m))),
    Change("drive gain -30 %", "gain", 0.7,
           lambda rig: rig.set_faults(RigFaults(plant_gain=0.7))),
    Change("resonance 30 -> 24 Hz", "resonance", 0.8,
           lambda rig: rig.set_faults(replace(MODE, resonance_hz=24.0)), MODE),
)


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _fit_s(run: OfflineWatch) -> str:
    f = [r.fit_s for _, r in run.windows]
    return f"fit per window median {np.median(f):.2f} s, max {np.max(f):.2f} s"


def _progress(kind: str, every: int, t: float) -> Callable[[OfflineWatch], None]:
    """A line per `every` judged windows (0: none): a long run's figures so far."""

    def show(run: OfflineWatch) -> None:
        n = len(run.windows)
        if every <= 0 or n % every:
            return
        outside = sum(any(v in ("outside", "alarm") for v in st.values()) for st in run.states)
        print(f"  {kind}: {n} windows ({run.windows[-1][0]:g} simulated s), alarms "
              f"{len(run.alarms)}, windows with a part outside {outside}, wall "
              f"{time.perf_counter() - t:.0f} s, load {os.getloadavg()[0]:.1f}", flush=True)

    return show


def _normal(args: argparse.Namespace) -> None:
    total_s, total_alarms = 0.0, 0
    for kind in args.trajectories.split(","):
        t = time.perf_counter()
        run = run_offline_watch(SETUP, default_trajectory(kind), args.seconds,
                                bound=COMMISSIONING_BOUND, window_s=args.window_s,
                                on_window=_progress(kind, args.progress, t))
        wall = time.perf_counter() - t
        judged_s = len(run.windows) * args.window_s
        total_s += judged_s
        total_alarms += len(run.alarms)
        names = list(run.states[0]) if run.states else []
        outside = sum(any(v in ("outside", "alarm") for v in st.values()) for st in run.states)
        notes = {n: sum(st[n] == "note" for st in run.states) for n in names}
        not_told = {n: sum(st[n] == "not told" for st in run.states) for n in names}
        print(f"normal {kind:5s}: {judged_s:g} s judged ({len(run.windows)} windows of "
              f"{args.window_s:g} s after one settling), alarms {len(run.alarms)} "
              f"{run.alarms}, windows with a part outside {outside}; notes per part {notes}; "
              f"not told per part {not_told}; wall {wall:.0f} s ({judged_s / wall:.1f}x real "
              f"time), {_fit_s(run)}; load {os.getloadavg()[0]:.1f}", flush=True)
    hours = total_s / 3600.0
    bound = f" (95 % upper bound {3.0 / hours:.2g} per hour)" if total_alarms == 0 else ""
    print(f"false alarms: {total_alarms} in {hours:.2f} h of judged normal running on "
          f"{args.trajectories}: {total_alarms / hours:.2g} per hour{bound}", flush=True)


def _changes(args: argparse.Namespace) -> None:
    wanted = set(args.changes.split(",")) if args.changes else None
    at = args.change_at_s
    w = args.window_s
    k = int(at // w)
    print(f"each change at {at:g} s of a {args.change_run_s:g} s sine run, windows of {w:g} s "
          f"(the change {at - k * w:g} s into the window {k * w:g}-{(k + 1) * w:g} s)")
    print("| change | alarm after (simulated s) | part named | other alarms | estimate vs "
          "truth | error | +-std / bias bound |")
    print("|---|---|---|---|---|---|---|")
    for c in CHANGES:
        if wanted is not None and c.part not in wanted:
            continue
        t = time.perf_counter()
        run = run_offline_watch(SETUP, default_trajectory("sine"), args.change_run_s,
                                bound=COMMISSIONING_BOUND, rig_faults=c.mode,
                                twin_faults=c.mode, window_s=w, change_at_s=at,
                                change=c.apply)
        wall = time.perf_counter() - t
        t_alarm = run.first_alarm(c.part)
        others = sorted({p for p, _ in run.alarms if p != c.part})
        early = [(p, ta) for p, ta in run.alarms if ta <= at]
        # The estimate in the window that raised the alarm (else the last window).
        at_alarm = next((r for te, r in run.windows if te == t_alarm), run.windows[-1][1])
        est = at_alarm.fit.part(c.part)
        err = 100.0 * (est.value - c.truth) / c.truth
        after = f"{t_alarm - at:.0f} s" if t_alarm is not None else "NO ALARM"
        print(f"| {c.name} | {after} | {c.part if t_alarm is not None else '-'} | "
              f"{', '.join(others) or 'none'}{' BEFORE THE CHANGE ' + str(early) if early else ''}"
              f" | x{est.value:.3f} vs x{c.truth:g} | {err:+.1f} % | +-{est.std:.2g} / "
              f"{est.bias:.2g} |", flush=True)
        print(f"    ({wall:.0f} s wall, {_fit_s(run)}; load {os.getloadavg()[0]:.1f})",
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", default="normal,changes")
    ap.add_argument("--seconds", type=float, default=900.0,
                    help="normal: simulated seconds per trajectory")
    ap.add_argument("--trajectories", default="sine,step,ramp,hold")
    ap.add_argument("--window-s", type=float, default=10.0)
    ap.add_argument("--progress", type=int, default=10,
                    help="normal: a line every N judged windows (0: none)")
    ap.add_argument("--changes", default="", help="changes: only these parts, comma-separated")
    ap.add_argument("--change-at-s", type=float, default=25.0)
    ap.add_argument("--change-run-s", type=float, default=60.0)
    args = ap.parse_args()
    print(f"start: {_uptime()}", flush=True)
    t = time.perf_counter()
    for what in args.only.split(","):
        {"normal": _normal, "changes": _changes}[what](args)
    print(f"wall {time.perf_counter() - t:.0f} s; end: {_uptime()}", flush=True)


if __name__ == "__main__":
    main()
