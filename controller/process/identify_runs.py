"""Identification runs inside the loop, as the controller process follows them.

The excitation program runs in the tick (`controller.ident.program`); here: planning it,
watching it from a thread, estimating the segments it finished (live results) and, at its
end, the estimate, fit and gate, all in the analysis worker process, never on the loop.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.gate.knowledge import MeasuredRecord
from controller.ident.program import ExcitationProgram
from controller.ident.result import position_uncertainty
from controller.process.analysis_worker import AnalysisWorker

__all__ = ["IdentifyJob", "IdentifyRuns", "identify_analysis", "identify_segments"]

log = logging.getLogger(__name__)


def _response_columns(est: Any) -> tuple[list[float], ...]:
    """(freq_hz, mag_db, phase_deg, coherence, mag_std_db, phase_std_deg) of an estimate."""
    import numpy as np

    return (
        est.freq_hz.tolist(),
        (20.0 * np.log10(np.abs(est.response))).tolist(),
        np.degrees(np.angle(est.response)).tolist(),
        est.coherence.tolist(),
        est.mag_std_db.tolist(),
        est.phase_std_deg.tolist(),
    )


def _position_response(
    index: int,
    center_deg: float,
    points_done: int,
    points_total: int,
    cols: tuple[list[float], ...],
    complete: bool | None = None,
) -> proto.PositionResponse:
    f, mag, ph, coh, mstd, pstd = cols
    return proto.PositionResponse(
        index=index,
        center_deg=center_deg,
        complete=points_done == points_total if complete is None else complete,
        points_done=points_done,
        points_total=points_total,
        freq_hz=f,
        mag_db=mag,
        phase_deg=ph,
        coherence=coh,
        mag_std_db=mstd,
        phase_std_deg=pstd,
    )


def identify_analysis(
    plan: Any,
    u: Sequence[float],
    w: Sequence[float],
    pos: Sequence[float],
    n_done: int,
    abort_reason: str | None,
    wall_s: float,
) -> dict[str, Any]:
    """Estimate (fit and gate when complete) from a program's records; the IdentifyStatus
    fields that carry results. Runs in the analysis worker process."""
    import json

    from controller.ident.engine import result_from_program
    from controller.ident.report import csv_name, summary_json

    result = result_from_program(plan, u, w, pos, n_done, abort_reason)
    positions = []
    files: dict[int, tuple[str | None, str]] = {}
    for p in result.positions:
        est = p.estimate
        files[p.index] = (None if est is None else csv_name(p), "")
        cols = tuple([] for _ in range(6)) if est is None else _response_columns(est)
        positions.append(
            _position_response(
                p.index, p.center_deg, p.points_done, p.points_total, cols, p.complete
            )
        )
    summary = summary_json(result, files, wall_s)
    summary["plant"] = "controller"

    def finite(v: float | None) -> float | None:
        return float(v) if v is not None and math.isfinite(v) else None

    fit = result.fit
    return {
        "positions": positions,
        "natural_freq_hz": None if fit is None else finite(fit.natural_freq_hz),
        "zeta": None if fit is None else finite(fit.zeta),
        "agreement_freq_hz": finite(summary["agreement_freq_hz"]),
        "recommended_cutoff_hz": {k: finite(v) for k, v in result.recommended_cutoff_hz.items()},
        "summary_json": json.dumps(summary, allow_nan=False),
    }


def identify_segments(segments: Sequence[Any]) -> list[tuple[list[float], ...]]:
    """Estimate finished segments (`controller.ident.engine.SegmentData`) of a running program:
    per segment (freq_hz, mag_db, phase_deg, coherence, mag_std_db, phase_std_deg) lists.
    Runs in the analysis worker process."""
    from controller.ident.engine import estimate_segment

    return [_response_columns(estimate_segment(seg)) for seg in segments]


class IdentifyJob:
    """The latest identification run as the controller sees it."""

    def __init__(
        self, run_id: int, plan: Any, program: ExcitationProgram, start_deg: float = math.nan
    ) -> None:
        self.run_id = run_id
        self.plan = plan
        self.program = program
        self.start_deg = start_deg
        """The position the plan was made from."""
        self.state = "running"
        self.t0 = time.monotonic()
        self.results: dict[str, Any] = {}
        self.abort_reason = ""
        self.text = ""
        #: live results: segments estimated so far, and per position the lists of
        #: PositionResponse fields (replaced, never mutated, once published in `partial`)
        self.segments_estimated = 0
        self.columns: dict[int, tuple[list[float], ...]] = {}
        self.partial: list[proto.PositionResponse] = []
        self.partial_failed = False

    def add_segments(self, first: int, estimates: list[tuple[list[float], ...]]) -> None:
        """Append the estimates of segments first, first + 1, ... and publish `partial`."""
        plan = self.plan
        n_seg = plan.n_segments
        for k, cols in enumerate(estimates, start=first):
            i = k // n_seg
            old = self.columns.get(i, ((),) * len(cols))
            self.columns[i] = tuple([*a, *b] for a, b in zip(old, cols, strict=True))
        self.segments_estimated = first + len(estimates)
        centers = plan.spec.centers_deg
        self.partial = [
            _position_response(
                i, float(centers[i]), min(n_seg, self.segments_estimated - i * n_seg), n_seg, cols
            )
            for i, cols in sorted(self.columns.items())
        ]


class IdentifyRuns:
    """The latest run: planning, the watch thread, its status. The caller submits the
    program to the loop (`plan`, then `begin` once the loop has taken it)."""

    def __init__(
        self,
        rig_name: str,
        worker: AnalysisWorker,
        stop_event: threading.Event,
        warn: Callable[[str], None],
    ) -> None:
        self.rig_name = rig_name
        self.worker = worker
        self.stop_event = stop_event
        self.warn = warn
        self.job: IdentifyJob | None = None

    def busy(self) -> bool:
        job = self.job
        return job is not None and job.state in ("running", "analysing")

    @staticmethod
    def plan(spec: Any, config: LoopConfig, pos_deg: float) -> tuple[Any, ExcitationProgram]:
        """The plan for `spec` (an `IdentifySpec`) from the present position, and its
        program. Raises ConfigError naming the spec's field."""
        from controller.ident.plan import plan_program, to_program

        plan = plan_program(spec, config, pos_deg)
        return plan, to_program(plan)

    def begin(
        self, plan: Any, program: ExcitationProgram, start_deg: float = math.nan
    ) -> IdentifyJob:
        """The loop has started `program` (planned from `start_deg`): a new run, watched from
        a thread."""
        run_id = (self.job.run_id if self.job is not None else 0) + 1
        job = self.job = IdentifyJob(run_id, plan, program, start_deg)
        log.info("identification %d started: %d ticks planned", run_id, plan.n_ticks)
        t = threading.Thread(target=self._watch, args=(job,), name="identify-watch", daemon=True)
        t.start()
        return job

    def status(self) -> proto.IdentifyStatus:
        job = self.job
        if job is None:
            return proto.IdentifyStatus(rig=self.rig_name, state="idle")
        prog = job.program
        state = job.state
        if state == "running":
            progress = prog.n_done / prog.n
            text = job.plan.label_at(prog.n_done)
        else:
            progress = 1.0 if state == "done" else prog.n_done / prog.n
            text = job.text
        fields = dict(job.results)
        fields.setdefault("positions", job.partial)  # live: the segments finished so far
        run = proto.IdentifyRun(
            spec=job.plan.spec,
            config=job.plan.config,
            start_deg=job.start_deg,
            start_seq=prog.start_seq,
            ticks_planned=prog.n,
            ticks_done=prog.n_done,
        )
        return proto.IdentifyStatus(
            rig=self.rig_name,
            state=state,
            run_id=job.run_id,
            progress=progress,
            text=text,
            abort_reason=job.abort_reason,
            run=run,
            **fields,
        )

    def adoptable(self, run_id: int | None) -> list[MeasuredRecord]:
        """The measured responses of finished run `run_id`, one per complete position, as
        plant knowledge (spread: the relative standard uncertainty per point, as `dobtune
        identify` states it; the position spread judges against twice that). Raises
        ValueError saying why there is nothing to adopt."""
        job = self.job
        if job is None or job.run_id != run_id:
            latest = job.run_id if job is not None else "none"
            raise ValueError(f"run {run_id} is not this controller's latest run ({latest})")
        if job.state != "done":
            raise ValueError(f"run {run_id} is {job.state}, not done")
        out = []
        for p in self.status().positions:
            if not p.complete or len(p.freq_hz) < 2:
                continue
            mag = 10.0 ** (np.asarray(p.mag_db) / 20.0)
            ph = np.radians(np.asarray(p.phase_deg))
            h = mag * np.exp(1j * ph)
            spread = position_uncertainty(p.freq_hz, p.coherence, p.mag_std_db, p.phase_std_deg)
            out.append(MeasuredRecord(
                name=f"run {run_id} position {p.index} ({p.center_deg:.4g} deg)",
                freq_hz=list(p.freq_hz), re=h.real.tolist(), im=h.imag.tolist(),
                sampled=False, spread=spread,
            ))
        if not out:
            raise ValueError(f"run {run_id} has no complete position")
        return out

    def _watch(self, job: IdentifyJob) -> None:
        prog = job.program
        while not prog.over:
            if self.stop_event.wait(0.05):
                prog._abort("controller shutting down", "shutdown")  # the loop has ended
                break
            self._estimate_finished_segments(job)
        if not self.stop_event.is_set():
            self._estimate_finished_segments(job)  # those that ended with the run
        aborted = prog.state == "aborted"
        job.abort_reason = prog.reason if aborted else ""
        job.text = "analysing"
        job.state = "analysing"
        if aborted:
            log.warning("identification %d aborted: %s", job.run_id, prog.reason)
        try:
            job.results = self.worker.call(
                identify_analysis,
                job.plan,
                prog.rec_u,
                prog.rec_w,
                prog.rec_pos,
                prog.n_done,
                prog.reason if aborted else None,
                time.monotonic() - job.t0,
            )
            job.text = f"aborted: {prog.reason}" if aborted else "done"
        except Exception as exc:
            self.warn(f"identification analysis failed: {type(exc).__name__}: {exc}")
            job.text = f"analysis failed: {type(exc).__name__}: {exc}"
        job.state = "aborted" if aborted else "done"
        log.info("identification %d: %s", job.run_id, job.text)

    def _estimate_finished_segments(self, job: IdentifyJob) -> None:
        """Live results: estimate the segments that finished since the last call (in the gate's
        worker; here only slices of their ticks are cut out). Nothing when none finished."""
        from controller.ident.engine import segment_data
        from controller.ident.plan import segments_done

        if job.partial_failed:
            return
        prog = job.program
        first = job.segments_estimated
        done = segments_done(job.plan, prog.n_done)
        if done <= first:
            return
        try:
            segs = [segment_data(job.plan, k, prog.rec_u, prog.rec_w) for k in range(first, done)]
            estimates = self.worker.call(identify_segments, segs, timeout_s=30.0)
            job.add_segments(first, estimates)
        except Exception as exc:  # the run goes on; the results come at its end
            job.partial_failed = True
            self.warn(f"identification live results failed: {type(exc).__name__}: {exc}")
