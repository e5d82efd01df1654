"""`dobtune identify --from FILE.mcap`: an identification run analysed again from its recording.

A recording made by `dobtune record` while the controller ran an identification holds every
tick of it on `/state` (speed command, load rate and position, one message per tick) and, on
`/events`, `identify` events carrying what the run executed (`protocol.IdentifyRun`: the spec,
the configuration and the position the plan was made from, the sequence number of its first
tick, the ticks planned and done). The excitation itself is not a state column: it is
recovered by planning again (`controller.ident.plan.plan_program`, deterministic), and the
plan is checked against the recording (the tick count, and the speed offset, which the state
stream carries as `speed_ref_deg_s` on every excitation tick). The analysis is then the
controller's own (`controller.process.identify_runs.identify_analysis`) on the recorded ticks,
so the estimates, fit and recommendations are those of the live run, and the output (files,
table, `--json`) is that of `dobtune identify --connect`.

Every problem is a `RecordingProblem` (a ValueError) whose message names the file and what is
wrong: no identification in the recording, a run not finished when the recording ended,
samples lost inside the run, a recording that starts after the run began, a plan that no
longer matches (the planning code changed since the recording was made).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from controller import protocol as proto
from controller.core.errors import ConfigError
from controller.ident.plan import ProgramPlan, plan_program
from controller.ident.result import PHASE_EXCITE
from controller.recording.mcap_io import Recording, read_recording

__all__ = ["RecordedRun", "RecordingProblem", "recorded_run", "status_from_recording"]

#: States in which the run's ticks are final (the program has ended).
_OVER = ("analysing", "done", "aborted")
#: Relative tolerance of the recorded speed offset against the rebuilt plan. The values travel
#: as float64 through MessagePack and JSON (shortest round-trip repr): they come back exact.
OFFSET_RTOL = 1e-9


class RecordingProblem(ValueError):
    """The recording cannot be analysed as an identification run (the message says why)."""


@dataclass(frozen=True)
class RecordedRun:
    """One identification run found in a recording, its plan rebuilt and its ticks cut out."""

    run_id: int
    state: str
    """analysing | done | aborted (as the controller last reported it to the recorder)."""
    abort_reason: str | None
    """None: the run completed."""
    run: proto.IdentifyRun
    plan: ProgramPlan
    u: np.ndarray
    """Speed command of each executed tick (deg/s)."""
    w: np.ndarray
    """Load rate of each executed tick (deg/s)."""
    pos: np.ndarray
    """Load position of each executed tick (deg)."""


def _identify_events(rec: Recording) -> list[dict[str, Any]]:
    return [ev for ev in rec.events if ev.get("kind") == "identify" and "run" in ev]


def _seq_ranges(seqs: np.ndarray) -> str:
    """'a-b, c' of a sorted array of integers (at most 5 ranges, then '...')."""
    if seqs.size == 0:
        return ""
    breaks = np.nonzero(np.diff(seqs) != 1)[0]
    starts = np.concatenate([[seqs[0]], seqs[breaks + 1]])
    ends = np.concatenate([seqs[breaks], [seqs[-1]]])
    parts = [f"{a}" if a == b else f"{a}-{b}" for a, b in zip(starts, ends, strict=True)]
    return ", ".join(parts[:5]) + (", ..." if len(parts) > 5 else "")


def recorded_run(path: str | Path, rec: Recording | None = None) -> RecordedRun:
    """The latest identification run of the recording at `path`, checked and cut out.

    Raises `RecordingProblem` naming the file and the problem (see the module docstring),
    also when the file cannot be read.
    """
    path = Path(path)
    if rec is None:
        try:
            rec = read_recording(path)
        except (OSError, ValueError) as exc:  # ValueError names the file already
            raise RecordingProblem(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from exc
    events = _identify_events(rec)
    if not events:
        raise RecordingProblem(
            f"{path}: no identification run in this recording (no 'identify' event: record "
            "with `dobtune record` while the controller runs `identify_start`)"
        )
    run_id = int(events[-1]["run_id"])
    last = [ev for ev in events if int(ev["run_id"]) == run_id][-1]
    state = str(last["state"])
    if state not in _OVER:
        raise RecordingProblem(
            f"{path}: identification {run_id} had not ended when the recording stopped "
            f"(last reported {state!r}): record until the run is done"
        )
    try:
        run = msgspec.convert(last["run"], proto.IdentifyRun)
    except (msgspec.ValidationError, ConfigError, ValueError, TypeError) as exc:
        raise RecordingProblem(
            f"{path}: identification {run_id}: its recorded spec or configuration is invalid: "
            f"{exc}"
        ) from exc
    if not math.isfinite(run.start_deg) or run.start_seq < 0:
        raise RecordingProblem(
            f"{path}: identification {run_id}: the recorded run has no start position or first "
            f"tick (start_deg {run.start_deg}, start_seq {run.start_seq}): the controller that "
            "ran it is too old to be analysed again"
        )
    try:
        plan = plan_program(run.spec, run.config, run.start_deg)
    except ConfigError as exc:
        raise RecordingProblem(
            f"{path}: identification {run_id}: its spec cannot be planned any more: {exc}"
        ) from exc
    if plan.n_ticks != run.ticks_planned:
        raise RecordingProblem(
            f"{path}: identification {run_id}: the plan rebuilt from its spec has "
            f"{plan.n_ticks} ticks, the controller planned {run.ticks_planned} (the planning "
            "code changed since the recording was made): cannot recover the excitation"
        )
    n_done = run.ticks_done
    if not 0 < n_done <= plan.n_ticks:
        raise RecordingProblem(
            f"{path}: identification {run_id}: {n_done} ticks done of {plan.n_ticks} planned: "
            "nothing to analyse"
        )
    abort_reason = str(last.get("abort_reason") or "") or None
    if abort_reason is None and (state == "aborted" or n_done < plan.n_ticks):
        abort_reason = f"aborted after {n_done} of {plan.n_ticks} ticks"
    u, w, pos, ref_speed = _cut(path, rec, run_id, run.start_seq, n_done)
    _check_plan(path, run_id, plan, run.start_seq, n_done, ref_speed)
    return RecordedRun(
        run_id=run_id,
        state=state,
        abort_reason=abort_reason,
        run=run,
        plan=plan,
        u=u,
        w=w,
        pos=pos,
    )


def _cut(
    path: Path, rec: Recording, run_id: int, start_seq: int, n_done: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(u, w, pos, speed_ref) of ticks start_seq .. start_seq + n_done - 1, all present."""
    seq = rec.state["seq"]
    end_seq = start_seq + n_done - 1
    what = f"{path}: identification {run_id} (seq {start_seq}-{end_seq})"
    if seq.size == 0:
        raise RecordingProblem(f"{what}: the recording has no state samples")
    if seq[0] > start_seq:
        raise RecordingProblem(
            f"{what}: the recording starts at seq {seq[0]}, {seq[0] - start_seq} tick(s) after "
            "the run began: start recording before the identification"
        )
    if seq[-1] < end_seq:
        raise RecordingProblem(
            f"{what}: the recording ends at seq {seq[-1]}, {end_seq - seq[-1]} tick(s) before "
            "the run ended"
        )
    lo, hi = np.searchsorted(seq, [start_seq, end_seq + 1])
    got = seq[lo:hi]
    if got.size != n_done or (got.size and np.any(np.diff(got) != 1)):
        missing = np.setdiff1d(np.arange(start_seq, end_seq + 1), got)
        raise RecordingProblem(
            f"{what}: a gap inside the run: {missing.size} sample(s) lost "
            f"(seq {_seq_ranges(missing)}); the estimates need every tick"
        )
    cols = [rec.state[c][lo:hi] for c in ("command_deg_s", "speed_deg_s", "pos_deg",
                                         "speed_ref_deg_s")]
    for name, col in zip(("command_deg_s", "speed_deg_s", "pos_deg"), cols, strict=False):
        bad = np.nonzero(~np.isfinite(col))[0]
        if bad.size:
            raise RecordingProblem(
                f"{what}: {name} is not finite at seq {_seq_ranges(got[bad])}"
            )
    return cols[0], cols[1], cols[2], cols[3]


def _check_plan(
    path: Path, run_id: int, plan: ProgramPlan, start_seq: int, n_done: int,
    ref_speed: np.ndarray,
) -> None:
    """The recorded speed offset on every excitation tick is the rebuilt plan's."""
    kind = plan.column("kind", n_done)
    a = plan.column("a", n_done)
    exc = np.nonzero(kind == PHASE_EXCITE)[0]
    if exc.size == 0:
        return
    diff = np.abs(ref_speed[exc] - a[exc])
    bad = np.nonzero(~(diff <= OFFSET_RTOL * (1.0 + np.abs(a[exc]))))[0]
    if bad.size:
        i = int(exc[bad[0]])
        raise RecordingProblem(
            f"{path}: identification {run_id}: the recording does not follow the plan rebuilt "
            f"from its spec: at tick {i} (seq {start_seq + i}) the speed offset is "
            f"{ref_speed[i]!r} deg/s, the plan's {a[i]!r} deg/s ({bad.size} excitation ticks "
            "differ): the planning code changed since the recording was made"
        )


def status_from_recording(path: str | Path, rig: str = "") -> proto.IdentifyStatus:
    """The IdentifyStatus the controller would give for the recorded run, computed again by
    the controller's own analysis. RecordingProblem as `recorded_run`."""
    from controller.process.identify_runs import identify_analysis

    got = recorded_run(path)
    t0 = time.perf_counter()
    fields = identify_analysis(  # the controller's records are sequences of floats too
        got.plan, got.u.tolist(), got.w.tolist(), got.pos.tolist(), got.run.ticks_done,
        got.abort_reason, 0.0,
    )
    aborted = got.abort_reason is not None
    return proto.IdentifyStatus(
        rig=rig,
        state="aborted" if aborted else "done",
        run_id=got.run_id,
        progress=got.run.ticks_done / got.plan.n_ticks,
        text=(f"aborted: {got.abort_reason}" if aborted else "done")
        + f" (analysed again from {Path(path).name} in {time.perf_counter() - t0:.1f} s)",
        abort_reason=got.abort_reason or "",
        run=got.run,
        **fields,
    )
