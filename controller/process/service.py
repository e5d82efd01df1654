"""What each request to the controller does: apply a candidate, run a command, start an
identification, report the status; and the log records of what happened in the loop.

The controller is the single authority: nothing but an accepted candidate changes what runs.
Requests arrive here already decoded and converted to domain types (`controller.process.node`
is the Zenoh edge); the replies are the wire's reply messages. Everything here runs in worker
threads, never on the loop's thread: the loop only exchanges prepared objects.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import msgspec

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.core.verdict import Verdict
from controller.gate.knowledge import KnowledgeRecord
from controller.process.access import Access
from controller.process.analysis_worker import AnalysisWorker, WorkerStopped
from controller.process.history import history_reply
from controller.process.identify_runs import IdentifyRuns
from controller.process.options import ControllerOptions
from controller.process.persistence import (
    MAX_VERSION,
    Change,
    ChangeLogError,
    PendingRollback,
    PersistenceError,
    StateStore,
)
from controller.process.requests import (
    ApplyCoefficients,
    DropFallback,
    RequestBody,
    ResetFault,
    RunProgram,
)
from controller.process.runtime import ESTOP, FAULT, Runtime, Ticket
from controller.process.twin_running import recent_running, twin_with_running
from controller.sim.sim_rig import RigParams
from controller.twin.fit import build_twin
from controller.twin.model import RigTwin, knowledge_digest
from controller.twin.model import encode as encode_twin

__all__ = ["TWIN_TIMEOUT_S", "ControllerService", "RuntimeEvents", "config_changes"]

log = logging.getLogger(__name__)

NOT_IN_TIME = "loop did not reach a tick boundary in time"
#: Identical rejections within this time are counted, not logged one by one.
REPEAT_LOG_S = 10.0
#: Distinct warnings kept for Status.notes.
MAX_WARNINGS = 8
#: Status.notes key of the verdict on the running configuration under new plant knowledge.
KNOWLEDGE_NOTE = "knowledge"
#: Status.notes key of a watchdog rollback not saved yet.
UNSAVED_NOTE = "unsaved rollback"


def config_changes(old: LoopConfig, new: LoopConfig) -> str:
    """The fields that differ, `name old -> new`, for the log."""
    a, b = msgspec.structs.asdict(old), msgspec.structs.asdict(new)
    diff = [f"{k} {a[k]} -> {b[k]}" for k in a if a[k] != b[k]]
    return ", ".join(diff) or "no change"



#: The rig's twin gets this long in the twin's worker: a hung worker's bound, not a fit's
#: budget (a fit with a measured mode took 20-57 s at load 22-25 and over 120 s at load 30-37;
#: the twin is built in the background, in a worker process of its own: nothing waits on it
#: but the twin's own readers; in the analysis worker an adoption's gate check waited behind
#: it, past the edge's 30 s).
TWIN_TIMEOUT_S = 600.0


class ControllerService:
    """The request handlers of one controller (any worker thread; applies one at a time)."""

    def __init__(
        self,
        opts: ControllerOptions,
        runtime: Runtime,
        store: StateStore,
        worker: AnalysisWorker,
        verdict: Verdict,
        notes: list[str],
        knowledge: KnowledgeRecord | None = None,
        access: Access | None = None,
        twin_worker: AnalysisWorker | None = None,
    ) -> None:
        self.opts = opts
        self.rt = runtime
        self.store = store
        self.worker = worker
        #: The twin's fit and its friction/backlash/noise estimate from running (seconds to
        #: minutes of CPU): their own worker process, so no request served by `worker` (an
        #: apply's or an adoption's gate check, an identification's estimate) waits behind them.
        self.twin_worker = twin_worker if twin_worker is not None else worker
        self.notes = notes
        self._warnings: dict[str, tuple[str, int]] = {}  # key -> (text, count)
        self._warn_lock = threading.Lock()
        #: Roles, the operator lease and the audit trail (no users, no audit: local use).
        self.access = access if access is not None else Access(None, opts.rig_name, None, self.warn)
        self.stop_event = threading.Event()
        self.identify = IdentifyRuns(opts.rig_name, worker, self.stop_event, self.warn)
        self._apply_lock = threading.Lock()
        #: The plant knowledge every candidate is judged on (the controller owns it; replaced
        #: whole under the apply lock, so an apply and a change of knowledge never interleave).
        self.knowledge = knowledge if knowledge is not None else KnowledgeRecord()
        #: The rig's twin of the knowledge's content (digest, twin or None, why none).
        self._twin: tuple[str, RigTwin | None, str] | None = None
        self._twin_lock = threading.Lock()
        #: The content whose twin is wanted and not built yet (the latest asked for wins: a
        #: fit of older content finishing after it was asked is dropped, never kept over it).
        self._twin_building: str | None = None
        #: What the builder thread fits next (digest, record), and whether it runs.
        self._twin_next: tuple[str, KnowledgeRecord] | None = None
        self._twin_builder = False
        #: The state batches held (oldest first; the node sets it to the black box's): the
        #: twin's window of normal running comes from them. None: no window, said in the twin.
        self.recent_state: Callable[[], list[Any]] | None = None
        #: The gate's verdict on the running configuration (re-judged on new knowledge).
        self.running_verdict = verdict
        #: The configuration the watchdog would roll back to, its verdict (judged on the
        #: knowledge now: adopting knowledge judges it again), and the configuration it would
        #: roll back from.
        self._fallback_state: tuple[LoopConfig, Verdict, LoopConfig] | None = None
        self._rollbacks_seen = 0
        self._rollback_lock = threading.Lock()
        #: A rollback not saved yet: (config, version, from version, bad config, trip kind).
        self._unsaved: tuple[LoopConfig, int, int, LoopConfig | None, str] | None = None
        #: The change log records `_unsaved` (a restart comes back on it).
        self._unsaved_recorded = False
        self._fault_seen: str | None = None
        #: Why a reset is refused ("": it is not): the watchdog rolled back to a configuration
        #: that fails the gate now; an apply (or knowledge on which it passes) lifts it.
        self._reset_refused = ""
        self.watchdog_text = ""
        self._identify_lock = threading.Lock()
        # The last rejection logged, when, and how many identical ones followed unlogged.
        self._last_rejection: tuple[str, tuple[str, ...]] | None = None
        self._last_rejection_s = 0.0
        self._unlogged_rejections = 0

    def warn(self, text: str, key: str | None = None) -> None:
        """A problem worth a WARNING record and a line in Status.notes. One line per `key`
        (default: the text): a repeat replaces it and is counted, so a failure retried every
        second never pushes the other lines out; the latest MAX_WARNINGS keys are kept."""
        k = text if key is None else key
        with self._warn_lock:
            previous = self._warnings.pop(k, None)
            self._warnings[k] = (text, 1 if previous is None else previous[1] + 1)
            while len(self._warnings) > MAX_WARNINGS:
                del self._warnings[next(iter(self._warnings))]
        n = 1 if previous is None else previous[1] + 1
        if n == 1 or n % 100 == 0:  # a repeat is logged again every 100th time
            log.warning("%s%s", text, f" ({n} times)" if n > 1 else "")

    def clear_warning(self, key: str) -> None:
        """Drop the Status.notes line of `key` (what it said is no longer so)."""
        with self._warn_lock:
            self._warnings.pop(key, None)

    @property
    def errors(self) -> list[str]:
        """The warnings for Status.notes, oldest first, repeats counted."""
        with self._warn_lock:
            items = list(self._warnings.values())
        return [t if n == 1 else f"{t} ({n} times)" for t, n in items]

    # -- configuration ---------------------------------------------------------------------------

    def config_reply(self, **kw: Any) -> proto.ConfigReply:
        """A ConfigReply; version and config default to the active ones."""
        active = self.rt.loop.active
        kw.setdefault("version", active.version)
        kw.setdefault("config", active.config)
        return proto.ConfigReply(**kw)

    def active_config(self) -> proto.ConfigReply:
        return self.config_reply(accepted=True, verdict=self.running_verdict)

    def _rejected(self, client: str, reasons: list[str], **kw: Any) -> proto.ConfigReply:
        """A rejection (under the apply lock). A client that repeats the same rejected
        candidate (a flood) gets one record per REPEAT_LOG_S, with the count in between."""
        key = (client, tuple(reasons))
        now = time.monotonic()
        if key == self._last_rejection and now - self._last_rejection_s < REPEAT_LOG_S:
            self._unlogged_rejections += 1
        else:
            n, self._unlogged_rejections = self._unlogged_rejections, 0
            self._last_rejection, self._last_rejection_s = key, now
            log.info(
                "candidate from %s rejected: %s%s",
                client or "a client",
                "; ".join(reasons),
                f" ({n} identical rejections before this one not logged)" if n else "",
            )
        return self.config_reply(accepted=False, reasons=reasons, **kw)

    def apply(
        self,
        candidate: LoopConfig,
        client: str,
        *,
        confirm: bool = False,
        expect_version: int | None = None,
    ) -> proto.ConfigReply:
        """Gate, persist, swap at a tick boundary, log; one candidate at a time. A `caution`
        verdict is applied only with `confirm`; with `expect_version`, only if that is still
        the active version (compare-and-set, checked under the apply lock)."""
        with self._apply_lock:
            active = self.rt.loop.active
            if expect_version is not None and expect_version != active.version:
                reason = (
                    f"expect_version: the candidate is based on version {expect_version}, the "
                    f"active version is {active.version} (changed meanwhile): fetch it, review, "
                    "send again"
                )
                return self._rejected(client, [reason], field="expect_version")
            if candidate.rate_hz != active.config.rate_hz:
                reason = (
                    f"candidate.rate_hz: {candidate.rate_hz} Hz differs from the running loop's "
                    f"{active.config.rate_hz} Hz; the rate changes only on restart (--rate-hz)"
                )
                return self._rejected(client, [reason], field="candidate.rate_hz")
            version = active.version + 1
            if version + 1 > MAX_VERSION:
                # The watchdog's rollback target takes the version after the candidate's.
                reason = (
                    f"version: the active version {active.version} is at the limit: the "
                    f"candidate (v{version}) and its rollback target (v{version + 1}) must not "
                    f"exceed {MAX_VERSION}; restart with --config FILE to start a new count"
                )
                return self._rejected(client, [reason], field="version")
            same = candidate == active.config
            # The analysis and the filter design run in the analysis worker process.
            record = self.knowledge
            verdict, coefficients = self.worker.check_and_build(
                candidate, version, record, build=not same)
            if not verdict.applicable:
                return self._rejected(client, list(verdict.reasons), verdict=verdict)
            if verdict.verdict == "caution" and not confirm:
                reasons = [*verdict.reasons, "confirm: the verdict is caution; send the request "
                           "again with confirm true to apply it anyway"]
                return self._rejected(client, reasons, verdict=verdict, field="confirm")
            if same or coefficients is None:
                return self.config_reply(accepted=True, verdict=verdict)
            try:
                # Saved with its change-log line (both on disk before the swap: the log
                # names what a restart comes back on).
                self.store.save(candidate, version, Change(
                    old=active.config, old_version=active.version, verdict=verdict,
                    client=client))
            except ChangeLogError as exc:
                self.warn(str(exc))
            except PersistenceError as exc:
                reason = f"state_dir: not applied, the configuration could not be saved: {exc}"
                self.warn(reason)
                return self.config_reply(
                    accepted=False, reasons=[reason], verdict=verdict, field="state_dir"
                )
            # A rollback still unsaved is superseded: the active file holds this candidate
            # now (a retry must never write the older configuration over it).
            self._forget_unsaved()
            # The filters are built here (this thread); the tick only swaps them in. The
            # configuration running now goes with them, under the next version, as the
            # watchdog's rollback target (its filters are designed already: no design work),
            # unless it fails the gate on the knowledge now (new knowledge judged it so).
            armed = self.running_verdict.applicable
            fallback = dataclasses.replace(active, version=version + 1) if armed else None
            ticket = self.rt.submit(ApplyCoefficients(coefficients, fallback))
            if not armed:
                self.rt.submit(DropFallback(
                    f"not rolled back: v{active.version} before it "
                    f"{_fails_gate(self.running_verdict)}"))
            if not ticket.wait(self.opts.apply_timeout_s) or not ticket.ok:
                # Saved but not (yet) swapped: only while shutting down. Report it.
                reason = f"loop: not applied at a tick boundary ({ticket.message or 'timeout'})"
                self.warn(reason)
                return self.config_reply(accepted=False, reasons=[reason], verdict=verdict)
            self._wait_version(version)
            self._reset_refused = ""  # what runs now passed the gate
            self.clear_warning(KNOWLEDGE_NOTE)  # it judged the configuration replaced now
            self._fallback_state = (
                (active.config, self.running_verdict, candidate) if armed else None)
            self.running_verdict = verdict
            log.info(
                "config v%d applied at seq %d (from %s): %s",
                version,
                ticket.seq,
                client or "a client",
                config_changes(active.config, candidate),
            )
            return self.config_reply(
                accepted=True, version=version, config=candidate, verdict=verdict,
                reasons=list(verdict.reasons),
            )

    # -- history -------------------------------------------------------------------------------

    def history(self, last: int) -> proto.HistoryReply:
        """The newest `last` applied configurations from the change log (oldest first)."""
        return history_reply(self.store.read_changes, last)

    # -- watchdog ------------------------------------------------------------------------------

    def poll_rollback(self) -> None:
        """Persist, audit and report what the watchdog did (status and latch threads; the
        tick only counts). What is active is what a restart comes back on: a rollback that
        cannot be saved is recorded in the change log, or else faults the loop (command 0),
        and is retried here until it is saved."""
        rt = self.rt
        trip = rt.last_trip
        if trip is not None and rt.mode == FAULT and rt.fault and rt.fault.startswith("watchdog"):
            self.watchdog_text = rt.fault
        if not self._rollback_lock.acquire(blocking=False):
            return  # another thread is at it
        try:
            # The retry and an apply's save never interleave (skipped while one runs).
            if self._unsaved is not None and self._apply_lock.acquire(blocking=False):
                try:
                    if self._unsaved is not None:
                        self._save_rollback(*self._unsaved)
                finally:
                    self._apply_lock.release()
            if rt.rollbacks == self._rollbacks_seen or rt.last_rollback is None:
                return
            with self._apply_lock:
                self._rolled_back(rt.rollbacks - self._rollbacks_seen)
        finally:
            self._rollback_lock.release()

    @property
    def rollbacks_reported(self) -> int:
        """The rollbacks reported with their `watchdog_text` (the count Status publishes; the
        loop's own count moves first, at the trip)."""
        return self._rollbacks_seen

    def _rolled_back(self, count: int) -> None:
        rt = self.rt
        seen = rt.rollbacks
        seq, from_v, to_v, trip = rt.last_rollback  # type: ignore[misc]
        self._wait_version(to_v)
        active = rt.loop.active
        text = (
            f"watchdog: {trip.reason}; rolled back from v{from_v} to the previous "
            f"configuration as v{to_v} at seq {seq}"
        )
        bad: LoopConfig | None = None
        judged: Verdict | None = None
        if self._fallback_state is not None:
            _, judged, bad = self._fallback_state
            self._fallback_state = None
        superseded = active.version != to_v  # another change came first; logged on its own
        if not superseded:
            self._judge_restored(active.config, to_v, judged)
        saved = superseded or self._save_rollback(active.config, to_v, from_v, bad, trip.kind)
        # Reported once the save was tried: a client that sees the rollback in a Status finds
        # its line in the change log (or the loop faulted because it could not be saved).
        self.watchdog_text = text
        # The count Status publishes, set after its text: a Status never carries a rollback
        # count without the text that reports it (`status` reads the count first).
        self._rollbacks_seen = seen
        self.warn(text)
        self.access.record(
            "rollback", "watchdog", "noted" if saved else "failed",
            version_before=from_v, version_after=to_v, trip=trip.kind, reason=trip.reason,
            loop_seq=seq, persisted=saved and not superseded, superseded=superseded,
            rollbacks=count, recorded_unsaved=not saved and self._unsaved_recorded,
        )

    def _judge_restored(self, config: LoopConfig, version: int, judged: Verdict | None) -> None:
        """The verdict the configuration rolled back to runs under: the one it was judged with,
        if on the knowledge now, else judged again now (off the tick). If it fails the gate,
        the loop faults (command 0): never run what fails the gate."""
        k = self.knowledge
        if judged is None or judged.knowledge_version != k.version:
            judged = self.worker.check(config, k)
        self.running_verdict = judged
        if not judged.applicable:
            self._reset_refused = (
                f"watchdog: rolled back to v{version}, which {_fails_gate(judged)}; stopped "
                "(command 0): apply a configuration that passes, then reset")
            self.rt.request_fault(self._reset_refused)

    def rollback_not_saved(self, pending: PendingRollback, bad: LoopConfig | None) -> None:
        """At start: the configuration running is the rollback the change log records as not
        saved (it could not be saved at start either); retried like any unsaved rollback."""
        self._unsaved = (pending.config, pending.version, pending.from_version, bad,
                         pending.kind)
        self._unsaved_recorded = True

    def _save_rollback(
        self, config: LoopConfig, version: int, from_v: int, bad: LoopConfig | None, kind: str
    ) -> bool:
        """Save the configuration rolled back to. If it cannot be saved, keep it for a retry
        and record the rollback in the change log (a line of its own, appended: a restart
        then comes back on v`version`); if that cannot be written either, fault the loop
        (command 0): a restart would bring back v`from_v`, which the watchdog rolled back."""
        try:
            self.store.save(config, version, Change(
                old=bad, old_version=from_v, verdict=self.running_verdict,
                client=f"watchdog rollback: {kind}"))
        except ChangeLogError as exc:
            self.warn(str(exc))
        except PersistenceError as exc:
            first = self._unsaved is None
            self._unsaved = (config, version, from_v, bad, kind)
            unrecorded = ""
            if not self._unsaved_recorded:
                try:
                    self.store.record_pending_rollback(
                        PendingRollback(config, version, from_v, kind))
                    self._unsaved_recorded = True
                except PersistenceError as log_exc:
                    unrecorded = str(log_exc)
            if self._unsaved_recorded:
                # The loop runs on: a restart comes back on what it runs.
                self.warn(
                    f"state_dir: the rollback to v{version} could not be saved ({exc}); the "
                    f"change log records it, so a restart comes back on v{version}, not "
                    f"v{from_v}; retried until saved", key=UNSAVED_NOTE)
                return False
            reason = (
                f"state_dir: the rollback to v{version} could not be saved ({exc}) nor recorded "
                f"in the change log ({unrecorded}): stopped (command 0), since a restart would "
                f"bring back v{from_v}; retried until saved"
            )
            if first or self.rt.mode != FAULT:
                self.rt.request_fault(reason)
            self.warn(reason, key=UNSAVED_NOTE)
            return False
        if self._unsaved is not None:
            log.info("the rollback to v%d is saved now", version)
        self._forget_unsaved()
        return True

    def _forget_unsaved(self) -> None:
        """No rollback waits for its save (saved, or superseded by a later save)."""
        if self._unsaved is not None:
            self.clear_warning(UNSAVED_NOTE)
        self._unsaved = None
        self._unsaved_recorded = False

    def poll_faults(self) -> None:
        """Audit every fault the loop entered (status thread): user `watchdog` for the
        watchdog's, `controller` for the state directory's, `rig` for lost I/O."""
        rt = self.rt
        fault, mode = rt.fault, rt.mode
        if fault and fault != self._fault_seen:
            user = ("watchdog" if fault.startswith("watchdog") else
                    "controller" if fault.startswith("state_dir") else "rig")
            self.access.record(
                "fault", user, "noted", version_before=rt.loop.active.version,
                reason=fault[:500], mode=mode, loop_seq=rt.seq,
            )
        self._fault_seen = fault

    # -- plant knowledge -------------------------------------------------------------------------

    def knowledge_reply(self, ok: bool, message: str = "", field: str = "") -> proto.KnowledgeReply:
        twin, note = self.twin_of(self.knowledge)
        return proto.KnowledgeReply(ok=ok, record=self.knowledge, message=message, field=field,
                                    twin=twin, twin_note=note)

    def twin_of(self, rec: KnowledgeRecord) -> tuple[str, str]:
        """(the rig's twin of `rec` as JSON, "" or why there is none). Built once per content
        (the last one kept) in the twin's worker, by a builder thread that this starts: never
        on the tick nor in a request's time; until it is done the note says so."""
        try:
            knowledge = rec.to_knowledge()
        except ValueError as exc:
            return "", f"no twin: {exc}"
        if not knowledge.measured:
            return "", "no twin: nothing measured (predictions run on the built-in model)"
        digest = knowledge_digest(knowledge)
        with self._twin_lock:
            got = self._twin if self._twin is not None and self._twin[0] == digest else None
            if got is None:
                if self._twin_building != digest:
                    self._twin_building = digest
                    self._twin_next = (digest, rec)
                    if not self._twin_builder:
                        self._twin_builder = True
                        threading.Thread(target=self._build_twins, name="twin-build",
                                         daemon=True).start()
                return "", f"no twin yet: being built for plant knowledge v{rec.version}"
        _, built, note = got
        if built is None:
            return "", note
        return encode_twin(msgspec.structs.replace(
            built, knowledge_version=rec.version, source=rec.source)).decode(), ""

    @property
    def twin_built(self) -> object:
        """The last twin built (a new object after each build: what the edge's snapshot
        compares)."""
        return self._twin

    def _twin_base(self) -> tuple[RigParams | None, str]:
        """The rig the twin starts from: the simulated rig this controller drives, with its
        named disturbances (the structure a fit to responses cannot see: motor and gearbox
        friction, the drive's offset, ...; `dobtune tune` and the watch take the same), else
        the built-in rig."""
        from controller.sim.rig_disturbances import rig_setup

        names = list(self.opts.sim_disturbances) if self.opts.plant == "sim" else []
        if not names:
            return None, ""
        setup = rig_setup(names)
        return setup.params, f"the simulated rig {setup.label} (this controller's plant)"

    def _build_twins(self) -> None:
        """The builder thread: fits the twin of the content asked for last, one at a time,
        until nothing more is asked; a fit finished after newer content was asked for is
        dropped (the newer one is built next), never kept over it."""
        while True:
            with self._twin_lock:
                job, self._twin_next = self._twin_next, None
                if job is None:
                    self._twin_builder = False
                    return
            digest, rec = job
            try:
                twin, note = self._build_twin(rec)
            except Exception as exc:  # said in every knowledge reply, never lost
                twin, note = None, f"no twin: its build failed: {type(exc).__name__}: {exc}"
                log.warning("twin of plant knowledge v%d: %s", rec.version, note)
            with self._twin_lock:
                if self._twin_building != digest:
                    log.info("twin of plant knowledge v%d: dropped (newer knowledge since)",
                             rec.version)
                    continue
                self._twin = (digest, twin, note)
                self._twin_building = None

    def _build_twin(self, rec: KnowledgeRecord) -> tuple[RigTwin | None, str]:
        """The twin of `rec` and why there is none, fitted in the twin's worker."""
        # The window of normal running is taken now (after the change, before the fit), here.
        active = self.rt.loop.active
        recent = (recent_running(self.recent_state(), following=self.rt.following,
                                 config=(active.config, active.version))
                  if self.recent_state is not None else "the controller holds no state batches")
        try:
            rate_hz = active.config.rate_hz
            base, label = self._twin_base()
            twin, note = self.twin_worker.call(build_twin, rec, rate_hz, base, label,
                                               timeout_s=TWIN_TIMEOUT_S)
        except WorkerStopped:  # the controller stops: the fit is of no use now
            twin, note = None, "no twin: the controller stopped during its fit"
            log.info("twin of plant knowledge v%d: %s", rec.version, note)
        except Exception as exc:  # a dead or late worker: said in every knowledge reply
            twin, note = None, f"no twin: the twin's worker failed: {type(exc).__name__}: {exc}"
            log.warning("twin of plant knowledge v%d: %s", rec.version, note)
        if twin is not None:
            try:
                twin = self.twin_worker.call(twin_with_running, twin, recent,
                                             timeout_s=TWIN_TIMEOUT_S)
            except WorkerStopped:
                twin, note = None, "no twin: the controller stopped during its fit"
                log.info("twin of plant knowledge v%d: %s", rec.version, note)
            except Exception as exc:  # the fitted twin kept, with the base rig's nonlinear parts
                why = (f"friction, backlash and encoder noise: the base rig's: their estimate "
                       f"failed in the twin's worker: {type(exc).__name__}: {exc}")
                twin = msgspec.structs.replace(twin, notes=(*twin.notes, why))
                log.warning("twin of plant knowledge v%d: %s", rec.version, why)
        return twin, note

    def handle_knowledge(self, req: proto.KnowledgeRequest) -> proto.KnowledgeReply:
        """Return the plant knowledge, or adopt new knowledge (a record, or the measured
        responses of an identification run of this controller)."""
        if req.record is None and req.adopt_run is None:
            return self.knowledge_reply(True)
        if req.record is not None and req.adopt_run is not None:
            return self.knowledge_reply(False, "adopt_run: give a record or a run, not both",
                                        field="adopt_run")
        if req.record is not None:
            rec, source = req.record, req.record.source or "uploaded"
        else:
            try:
                measured = self.identify.adoptable(req.adopt_run)
            except ValueError as exc:
                return self.knowledge_reply(False, f"adopt_run: {exc}", field="adopt_run")
            cur = self.knowledge
            rec = KnowledgeRecord(model=cur.model, bound=cur.bound, measured=measured)
            source = f"identification run {req.adopt_run}"
        try:
            rec.to_knowledge()  # validate: every field, every response
        except ValueError as exc:
            return self.knowledge_reply(False, f"record: {exc}", field="record")
        return self.adopt_knowledge(rec, source, req.client)

    def adopt_knowledge(
        self, rec: KnowledgeRecord, source: str, client: str
    ) -> proto.KnowledgeReply:
        """Number, persist and use `rec`; re-judge the running configuration on it."""
        with self._apply_lock:
            version = self.knowledge.version + 1
            if version > MAX_VERSION:
                return self.knowledge_reply(
                    False, f"version: the knowledge version {version - 1} is at the limit "
                    f"{MAX_VERSION}", field="version")
            new = msgspec.structs.replace(rec, version=version, source=source[:200])
            try:
                self.store.save_knowledge(new)
            except PersistenceError as exc:
                reason = f"state_dir: not adopted, the plant knowledge could not be saved: {exc}"
                self.warn(reason)
                return self.knowledge_reply(False, reason, field="state_dir")
            self.knowledge = new
            log.info("plant knowledge v%d adopted (%s) from %s", version, source,
                     client or "a client")
            active = self.rt.loop.active
            verdict = self.worker.check(active.config, new)
            self.running_verdict = verdict
            if verdict.applicable:
                self._reset_refused = ""
            message = f"plant knowledge v{version} adopted"
            self.clear_warning(KNOWLEDGE_NOTE)  # about older knowledge: no longer so
            if verdict.verdict != "accept":
                message += (
                    f"; the running configuration v{active.version} is now judged "
                    f"{verdict.verdict}: " + "; ".join(verdict.reasons)
                )
            dropped = False
            if self._fallback_state is not None:
                # What the watchdog would roll back to is judged on it too: a rollback never
                # restores what fails the gate now, nor shows an older verdict.
                fb_config, _, bad = self._fallback_state
                fb_verdict = self.worker.check(fb_config, new)
                self._fallback_state = (fb_config, fb_verdict, bad)
                if not fb_verdict.applicable:
                    why = f"v{active.version - 1} before it {_fails_gate(fb_verdict)}"
                    self.rt.submit(DropFallback(f"not rolled back: {why}"))
                    message += f"; a watchdog trip faults (not rolled back: {why})"
                    dropped = True
            if verdict.verdict != "accept" or dropped:
                self.warn(message, key=KNOWLEDGE_NOTE)
            return self.knowledge_reply(True, message)

    def _wait_version(self, version: int) -> None:
        # The loop swaps at the start of the tick that served the ticket; this returns at
        # once unless that tick is still running.
        deadline = time.monotonic() + self.opts.apply_timeout_s
        while self.rt.loop.active.version < version and time.monotonic() < deadline:
            time.sleep(0.0005)

    # -- commands ----------------------------------------------------------------------------------

    def refused(self, message: str, **kw: Any) -> proto.CommandReply:
        return proto.CommandReply(ok=False, message=message, mode=self.rt.mode, **kw)

    def command(self, request: RequestBody, client: str) -> proto.CommandReply:
        """Hand `request` to the tick and wait for its answer (an EStop engages in `submit`).
        A reset is refused while the configuration loaded fails the gate after a rollback."""
        refused = self._reset_refused
        if refused and isinstance(request, ResetFault):
            log.warning("command ResetFault from %s: refused (%s)", client or "a client", refused)
            return self.refused(f"reset: refused: {refused}")
        ticket = self.rt.submit(request)
        reply = self._ticket_reply(ticket, self.opts.command_timeout_s)
        name = type(request).__name__
        level = logging.INFO if reply.ok else logging.WARNING
        log.log(
            level,
            "command %s from %s: %s%s (mode %s, seq %d)",
            name,
            client or "a client",
            "ok" if reply.ok else "refused",
            f": {reply.message}" if reply.message else "",
            reply.mode,
            reply.seq,
        )
        return reply

    def _ticket_reply(self, ticket: Ticket, timeout_s: float) -> proto.CommandReply:
        if not ticket.wait(timeout_s):
            return self.refused(NOT_IN_TIME, received_seq=ticket.received_seq)
        return proto.CommandReply(
            ok=ticket.ok,
            message=ticket.message,
            mode=ticket.mode,
            field=f"body.{ticket.field}" if ticket.field else "",
            seq=ticket.seq,
            received_seq=ticket.received_seq,
        )

    # -- identification --------------------------------------------------------------------------

    def start_identify(self, spec: Any, client: str) -> proto.CommandReply:
        """Plan `spec` (an IdentifySpec) here, off the loop, hand the program to the tick,
        watch it in a thread. Raises ConfigError (naming the spec's field) for a bad plan."""
        rt = self.rt
        with self._identify_lock:
            if self.identify.busy():
                return self.refused("an identification is already running")
            start_deg = rt.last_pos_deg
            plan, program = self.identify.plan(spec, rt.loop.active.config, start_deg)
            ticket = rt.submit(RunProgram(program))
            if not ticket.wait(self.opts.command_timeout_s) or not ticket.ok:
                reply = self.refused(
                    ticket.message or NOT_IN_TIME, received_seq=ticket.received_seq
                )
                log.warning("identification from %s refused: %s", client, reply.message)
                return reply
            job = self.identify.begin(plan, program, start_deg)
        return proto.CommandReply(
            ok=True,
            message=f"identification {job.run_id}: {plan.n_ticks / plan.config.rate_hz:.1f} s "
            "planned",
            mode=ticket.mode,
            seq=ticket.seq,
            received_seq=ticket.received_seq,
        )

    # -- status ------------------------------------------------------------------------------------

    def status(self, extra_notes: tuple[str, ...] = ()) -> proto.Status:
        rt = self.rt
        timing = rt.timing_snapshot()
        faults = [rt.fault] if rt.fault else []
        if rt.mode == ESTOP:
            faults.append(f"e-stop ({rt.estop_source}) at seq {rt.estop_seq}")
        active = rt.loop.active
        # The rollbacks this service has reported (with their `watchdog` text), not the loop's
        # count, which moves first. Read before the text (which is set before it).
        rollbacks = self._rollbacks_seen
        return proto.Status(
            rig=self.opts.rig_name,
            plant=self.opts.plant,
            mode=rt.mode,
            t_s=time.perf_counter() - rt.t0,
            seq=rt.seq,
            trajectory=rt.trajectory,
            run_trajectory=rt.run_trajectory,
            config_version=active.version,
            config=active.config,
            timing=timing,
            faults=faults,
            estop_seq=rt.estop_seq,
            notes=[*self.notes, *self.errors, *extra_notes],
            knowledge_version=self.knowledge.version,
            knowledge=self.knowledge_description(),
            verdict=self.running_verdict,
            watchdog=self.watchdog_text,
            rollbacks=rollbacks,
            operator=self.access.holder,
            audit_head=self.access.head,
            auth=self.access.auth,
        )

    def knowledge_description(self) -> str:
        k = self.knowledge
        n = len(k.measured)
        band = ""
        if n:
            band = (f", {n} measured response(s) {min(m.freq_hz[0] for m in k.measured):.3g}-"
                    f"{max(m.freq_hz[-1] for m in k.measured):.3g} Hz")
        return f"v{k.version} {k.source}{band}"


def _fails_gate(verdict: Verdict) -> str:
    """'fails the gate on plant knowledge vK: reasons' (for a fault or a note)."""
    return (f"fails the gate on plant knowledge v{verdict.knowledge_version}: "
            + "; ".join(verdict.reasons))


class RuntimeEvents:
    """Log records of what the tick did (it logs nothing itself): mode changes, e-stops,
    faults, and a summary of lost ticks. `poll()` from any thread but the loop's."""

    def __init__(self, runtime: Runtime, summary_period_s: float = 60.0) -> None:
        self.rt = runtime
        self.summary_period_s = summary_period_s
        self._mode = runtime.mode
        self._fault = runtime.fault
        self._estop_seq = runtime.estop_seq
        self._lost = self._lost_now()
        self._next_summary = time.monotonic() + summary_period_s

    def _lost_now(self) -> tuple[int, int, int]:
        rt = self.rt
        return rt.overruns, rt.skipped_ticks, rt.dropped_samples

    def poll(self) -> None:
        rt = self.rt
        mode, fault, estop_seq = rt.mode, rt.fault, rt.estop_seq
        if estop_seq != self._estop_seq:
            log.warning("e-stop (%s) at seq %d", rt.estop_source, estop_seq)
        if fault and (fault != self._fault or (mode == FAULT and self._mode != FAULT)):
            log.warning("fault: %s (mode %s)", fault, mode)
        if mode != self._mode and mode not in (ESTOP, FAULT):
            log.info("mode %s -> %s", self._mode, mode)
        self._mode, self._fault, self._estop_seq = mode, fault, estop_seq
        if time.monotonic() >= self._next_summary:
            self._next_summary += self.summary_period_s
            self.summary(only_if_lost=True)

    def summary(self, *, only_if_lost: bool = False) -> None:
        """Log the ticks lost since the previous summary (WARNING if any, else INFO)."""
        now = self._lost_now()
        d_over, d_skip, d_drop = (b - a for a, b in zip(self._lost, now, strict=True))
        self._lost = now
        lost = d_over or d_skip or d_drop
        if only_if_lost and not lost:
            return
        log.log(
            logging.WARNING if lost else logging.INFO,
            "loop: %d overruns, %d skipped ticks, %d dropped samples since the last summary "
            "(%d ticks in all)",
            d_over,
            d_skip,
            d_drop,
            self.rt.ticks,
        )
