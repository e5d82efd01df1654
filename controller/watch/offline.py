"""The watch on the compiled offline loop, faster than real time (pure, for the suite and the
bench): the simulated rig (its named disturbances, sensor noise and load torques on) runs the
loop through `controller.sim.offline.run_ticks` window by window, the plant changed at a
chosen simulated time, and each window goes through `controller.watch.step.watch_window`,
the code the live watch runs. Times are simulated seconds (the fit's own seconds are
reported beside them: live, an alarm comes that much later)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import UncertaintyBound
from controller.sim.offline import OfflineRun, run_ticks
from controller.sim.rig_disturbances import RigSetup, ScheduledRig, build_rig
from controller.sim.sim_rig import RigFaults, SimRig
from controller.watch.estimate import Window
from controller.watch.judge import DriftJudge, part_ranges
from controller.watch.step import WindowResult, watch_window

__all__ = ["OfflineWatch", "run_offline_watch"]


@dataclass
class OfflineWatch:
    """What the watch said over the run: each window's end (simulated s) and result, each
    alarm as (part, simulated s at the end of the window that raised it), and each window's
    part states as the judge left them ("ok", "note", "outside", "alarm", "not told")."""

    windows: list[tuple[float, WindowResult]] = field(default_factory=list)
    alarms: list[tuple[str, float]] = field(default_factory=list)
    states: list[dict[str, str]] = field(default_factory=list)

    def first_alarm(self, part: str) -> float | None:
        return next((t for p, t in self.alarms if p == part), None)


def run_offline_watch(setup: RigSetup, traj: Trajectory, seconds: float, *,
                      cfg: LoopConfig | None = None, rig_faults: RigFaults | None = None,
                      twin_faults: RigFaults | None = None, bound: UncertaintyBound | None,
                      window_s: float = 10.0, change_at_s: float | None = None,
                      change: Callable[[SimRig], None] | None = None, seed: int = 3,
                      on_window: Callable[[OfflineWatch], None] | None = None
                      ) -> OfflineWatch:
    """Run `seconds` of `traj` on the rig `setup` (with `rig_faults`, e.g. an extra mode),
    the watch comparing with the twin `setup.params` + `twin_faults` judged on `bound`;
    `change(rig)` at `change_at_s`. The first window starts after one window of running (the
    live watch too waits for a full window). `on_window(res)` after each judged window (a
    long run's progress)."""
    cfg = cfg or LoopConfig()
    rate = cfg.rate_hz
    twin_faults = twin_faults or RigFaults()
    built = build_rig(setup, rate_hz=rate, seed=seed, initial_position_deg=traj.at(0.0)[0])
    sim = built.rig if isinstance(built, ScheduledRig) else built
    if rig_faults is not None and rig_faults.active:
        sim.set_faults(rig_faults)
    loop = ServoLoop(LoopCoefficients.build(cfg, 0))
    judge = DriftJudge(part_ranges(setup.params, twin_faults, bound, rate))
    n_win = round(window_s * rate)
    total = round(seconds * rate)
    change_tick = None if change_at_s is None else round(change_at_s * rate)
    out = OfflineRun(np.empty((6, n_win)))
    res = OfflineWatch()
    tick, start = 0, None
    while tick + n_win <= total:
        done = 0
        while done < n_win:
            m = n_win - done
            if change_tick is not None and tick + done < change_tick < tick + n_win:
                m = min(m, change_tick - tick - done)
            run_ticks(loop, built, traj, m, traj_tick=tick + done, out=out, at=done)
            done += m
            if change is not None and tick + done == change_tick:
                change(sim)
        t0 = tick / rate
        tick += n_win
        if tick <= n_win:  # the first window: the loop settles, the watch waits
            continue
        win = Window(t0_s=t0, rate_hz=rate, pos_deg=out.pos_deg.copy(),
                     speed_deg_s=out.speed_deg_s.copy(), command_deg_s=out.command_deg_s.copy(),
                     ref_deg=out.ref_deg.copy(), error_deg=out.ref_deg - out.pos_deg)
        r = watch_window(setup.params, twin_faults, judge, win, cfg, start, t0)
        start = np.array(r.fit.x)
        res.windows.append((tick / rate, r))
        res.alarms.extend((p, tick / rate) for p in r.verdict.new_alarms)
        res.states.append({name: ps.state for name, ps in judge.parts.items()})
        if on_window is not None:
            on_window(res)
    return res
