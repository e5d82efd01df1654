"""One window of the watch (pure): the same code for the live watch process
(`controller.process.watch`) and for the watch run on the compiled offline loop faster than
real time (`controller.watch.offline`): fit the twin's parts to the window, run the active
configuration on the twin over its reference, judge the parts."""

from __future__ import annotations

import time
from dataclasses import dataclass

from controller.core.arrays import FloatArray
from controller.core.config import LoopConfig
from controller.sim.sim_rig import RigFaults, RigParams
from controller.watch.estimate import DriftFit, LoopResidual, Window, fit_window, loop_residual
from controller.watch.judge import DriftJudge, WindowVerdict

__all__ = ["WindowResult", "watch_window"]


@dataclass(frozen=True)
class WindowResult:
    """A window's fit, the loop's residual, the judge's verdict, and the seconds the fit and
    the loop's run on the twin took."""

    fit: DriftFit
    loop: LoopResidual
    verdict: WindowVerdict
    fit_s: float


def watch_window(params: RigParams, faults: RigFaults, judge: DriftJudge, win: Window,
                 cfg: LoopConfig, start: FloatArray | None, t0_s: float) -> WindowResult:
    """Fit `win` from `start` (the previous window's `DriftFit.x`; None: the twin's), the
    loop's residual under `cfg`, and `judge` updated (its states change); `t0_s`: the window's
    start as the alarms state it (UNIX time live, simulated seconds offline)."""
    t = time.perf_counter()
    fit = fit_window(params, faults, win, start=start)
    lr = loop_residual(cfg, params, faults, win)
    fit_s = time.perf_counter() - t
    return WindowResult(fit, lr, judge.update(fit, t0_s), fit_s)
