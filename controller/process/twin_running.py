"""The twin's friction, backlash and encoder noise from the controller's own running (issue 35
item 1): when the controller builds the twin after a knowledge change, the newest unbroken
stretch of normal running in the black box's state batches (`recent_running`, in the twin's
build thread, never on the tick) goes with it to the twin's worker, which estimates them
there (`twin_with_running`: `controller.twin.nonlinear.with_running`). The stretch is only
where the loop followed its trajectory, bit for bit (`Runtime.following`): not the approach
onto it after a change of trajectory or a start, not an identification's excitation. The
drive's speed offset the twin lacks is taken from the DOB's d_hat over the window first
(`controller.twin.replay.disturbance_lacking`, the twin run on the same trajectory from the
window's trajectory time): an offset moves where the load sticks at each reversal. A window
that tells nothing (too short, no reversal, too few slow samples: the pure functions'
ValueError) leaves the twin with the base rig's values and its notes say why; so does no
window at all.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.twin.model import RigTwin
from controller.twin.nonlinear import RunningWindow, with_running
from controller.twin.replay import disturbance_lacking, with_disturbance

__all__ = ["BASE_RIG", "OFFSET_KEPT", "WINDOW_S", "RecentRunning", "recent_running",
           "twin_with_running"]

#: The newest this many seconds of running are the window (the article's sine, 0.5 rad/s,
#: reverses every 6.3 s: three or four reversals; the black box holds 30 s).
WINDOW_S = 25.0
#: The mode the loop runs a trajectory in (`controller.process.runtime.RUNNING`).
RUNNING = "running"
BASE_RIG = "friction, backlash and encoder noise: the base rig's, not estimated"
OFFSET_KEPT = "drive offset: the twin's, not estimated from d_hat"


@dataclass(frozen=True)
class RecentRunning:
    """The state columns the window is made of (plain lists: they travel to the worker) and
    what it is (its time span in UTC, sequence numbers, configuration version); where the
    loop followed a known trajectory all through it, that trajectory, the trajectory tick of
    the window's first sample, the DOB's d_hat and the configuration (the drive's offset the
    twin lacks is taken from them first: `twin_with_running`)."""

    rate_hz: float
    pos_deg: list[float]
    speed_deg_s: list[float]
    command_deg_s: list[float]
    label: str
    d_hat_deg_s: list[float] | None = None
    trajectory: Trajectory | None = None
    trajectory_tick: int = 0
    config: LoopConfig | None = None


def _utc(epoch_s: float) -> str:
    return time.strftime("%H:%M:%S", time.gmtime(epoch_s)) + f".{int(epoch_s * 10) % 10}"


def _following_from(ref: list[float], s_last: int,
                    following: tuple[Trajectory, int, float]) -> tuple[int, int] | str:
    """(how many of the newest samples of `ref` the loop's trajectory gave, bit for bit, the
    sequence number of the trajectory's time 0); or why none. The runtime's seq0 is read off
    its thread (a tick either way): the one that gives the newest sample exactly."""
    traj, guess, period = following
    at = traj.at
    for s0 in (guess, guess - 1, guess + 1, guess - 2, guess + 2):
        if s_last >= s0 and at((s_last - s0) * period)[0] == ref[-1]:
            break
    else:
        return ("the loop's newest sample is not its trajectory's (an identification runs, "
                "or the approach onto the trajectory)")
    n = 1
    while n < len(ref) and s_last - n >= s0 and at((s_last - n - s0) * period)[0] == ref[-1 - n]:
        n += 1
    return n, s0


def recent_running(batches: Sequence[Any], seconds: float = WINDOW_S,
                   following: tuple[Trajectory, int, float] | None = None,
                   config: tuple[LoopConfig, int] | None = None) -> RecentRunning | str:
    """The newest unbroken stretch (consecutive sequence numbers, one configuration version,
    mode running in every batch) of `batches` (StateBatch, oldest first), at most `seconds`
    long; or why there is none. `following` (`Runtime.following`): the stretch also only
    where the reference is that trajectory's (not the approach onto it, not an
    identification's excitation), and it comes with its trajectory time and d_hat; `config`:
    the loop's configuration and its version, kept if that is the window's."""
    if not batches:
        return "no state batches held (the loop has not published yet)"
    newest = batches[-1]
    if newest.mode != RUNNING:
        return f"the loop is {newest.mode or 'in an unknown mode'}, not running"
    rate = newest.rate_hz
    want = round(seconds * rate)
    taken: list[Any] = []
    n = 0
    for b in reversed(batches):
        if taken:
            nxt = taken[-1]
            if (b.mode != RUNNING or b.config_version != nxt.config_version
                    or b.rate_hz != rate or b.seq0 + len(b.t_s) != nxt.seq0):
                break
        taken.append(b)
        n += len(b.t_s)
        if n >= want:
            break
    taken.reverse()

    def col(name: str) -> list[float]:
        return [x for b in taken for x in getattr(b, name)][-want:]

    pos = col("pos_deg")
    if not pos:
        return "the newest state batch holds no sample"
    s1 = newest.seq0 + len(newest.t_s) - 1
    traj, tick0, keep = None, 0, len(pos)
    if following is not None:
        got = _following_from(col("ref_deg"), s1, following)
        if isinstance(got, str):
            return got
        keep, s0 = got
        traj, tick0 = following[0], s1 - keep + 1 - s0
    t0 = newest.epoch_s + newest.t_s[-1] - (keep - 1) / rate
    t1 = newest.epoch_s + newest.t_s[-1]
    label = (f"the controller's running {_utc(t0)}-{_utc(t1)} UTC ({keep / rate:.3g} s, "
             f"seq {s1 - keep + 1}-{s1}, configuration v{newest.config_version}"
             + (f", {traj.kind} from its {tick0 / rate:.4g} s" if traj is not None else "")
             + ")")
    cfg = config[0] if config is not None and config[1] == newest.config_version else None
    return RecentRunning(rate, pos[-keep:], col("speed_deg_s")[-keep:],
                         col("command_deg_s")[-keep:], label,
                         col("d_hat_deg_s")[-keep:] if traj is not None else None, traj, tick0,
                         cfg)


def _with_offset(twin: RigTwin, recent: RecentRunning) -> RigTwin:
    """`twin` with the drive's speed offset it lacks (the window's d_hat less the twin's own
    for the same run: `disturbance_lacking`) before friction and backlash are fitted (an
    offset moves where the load sticks at each reversal); said in its notes, and why not
    where the window cannot tell it."""
    cfg, traj = recent.config, recent.trajectory
    why = ""
    if recent.d_hat_deg_s is None or traj is None:
        why = "the window does not follow a known trajectory"
    elif cfg is None:
        why = "the window's configuration is no longer the active one"
    elif not cfg.dob_on:
        why = "the DOB is off (no d_hat)"
    else:
        try:
            lack = disturbance_lacking(twin, cfg, traj, np.asarray(recent.d_hat_deg_s),
                                       start_tick=recent.trajectory_tick)
        except ValueError as exc:
            why = str(exc)
        else:
            return with_disturbance(twin, lack)
    return msgspec.structs.replace(twin, notes=(
        *twin.notes, f"{OFFSET_KEPT}: {recent.label}: {why}"))


def twin_with_running(twin: RigTwin, recent: RecentRunning | str) -> RigTwin:
    """`twin` (`build_twin`'s) with the friction, backlash and noise `recent` tells, said in
    its notes with the window and the deviations; with the base rig's and the reason in its
    notes where `recent` is a reason or tells nothing. For the twin's worker (a process of its
    own, after the fit there: no gate check waits behind either)."""
    if isinstance(recent, str):
        said = f"{BASE_RIG}: no window of normal running: {recent}"
    else:
        twin = _with_offset(twin, recent)
        try:
            win = RunningWindow(recent.rate_hz, np.asarray(recent.pos_deg),
                                np.asarray(recent.speed_deg_s),
                                np.asarray(recent.command_deg_s), recent.label)
            twin = with_running(twin, win)
        except ValueError as exc:
            said = f"{BASE_RIG}: {recent.label} tells nothing: {exc}"
        else:
            est = twin.nonlinear
            assert est is not None
            said = f"estimated from {recent.label}: {est.describe()}"
    return msgspec.structs.replace(twin, notes=(*twin.notes, said))
