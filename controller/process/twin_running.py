"""The twin's friction, backlash and encoder noise from the controller's own running (issue 35
item 1): when the controller builds the twin after a knowledge change, the newest unbroken
stretch of normal running in the black box's state batches (`recent_running`, in the twin's
build thread, never on the tick) goes with it to the analysis worker, which estimates them
there (`twin_with_running`: `controller.twin.nonlinear.with_running`). A window that tells
nothing (too short, no reversal, too few slow samples: the pure functions' ValueError) leaves
the twin with the base rig's values and its notes say why; so does no window at all.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from controller.twin.model import RigTwin
from controller.twin.nonlinear import RunningWindow, with_running

__all__ = ["WINDOW_S", "RecentRunning", "recent_running", "twin_with_running"]

#: The newest this many seconds of running are the window (the article's sine, 0.5 rad/s,
#: reverses every 6.3 s: three or four reversals; the black box holds 30 s).
WINDOW_S = 25.0
#: The mode the loop runs a trajectory in (`controller.process.runtime.RUNNING`).
RUNNING = "running"
BASE_RIG = "friction, backlash and encoder noise: the base rig's, not estimated"


@dataclass(frozen=True)
class RecentRunning:
    """The state columns the window is made of (plain lists: they travel to the worker) and
    what it is (its time span in UTC, sequence numbers, configuration version)."""

    rate_hz: float
    pos_deg: list[float]
    speed_deg_s: list[float]
    command_deg_s: list[float]
    label: str


def _utc(epoch_s: float) -> str:
    return time.strftime("%H:%M:%S", time.gmtime(epoch_s)) + f".{int(epoch_s * 10) % 10}"


def recent_running(batches: Sequence[Any], seconds: float = WINDOW_S) -> RecentRunning | str:
    """The newest unbroken stretch (consecutive sequence numbers, one configuration version,
    mode running in every batch) of `batches` (StateBatch, oldest first), at most `seconds`
    long; or why there is none."""
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
    t0 = newest.epoch_s + newest.t_s[-1] - (len(pos) - 1) / rate
    t1 = newest.epoch_s + newest.t_s[-1]
    s1 = newest.seq0 + len(newest.t_s) - 1
    label = (f"the controller's running {_utc(t0)}-{_utc(t1)} UTC ({len(pos) / rate:.3g} s, "
             f"seq {s1 - len(pos) + 1}-{s1}, configuration v{newest.config_version})")
    return RecentRunning(rate, pos, col("speed_deg_s"), col("command_deg_s"), label)


def twin_with_running(twin: RigTwin, recent: RecentRunning | str) -> RigTwin:
    """`twin` (`build_twin`'s) with the friction, backlash and noise `recent` tells, said in
    its notes with the window and the deviations; with the base rig's and the reason in its
    notes where `recent` is a reason or tells nothing. For the analysis worker (runs there,
    a call of its own after the fit: a gate check waiting for the worker gets in between)."""
    if isinstance(recent, str):
        said = f"{BASE_RIG}: no window of normal running: {recent}"
    else:
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
