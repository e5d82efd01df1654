"""The watchdog in the runtime: a trip rolls back to the previous configuration at the next
tick (bumpless), a second trip soon after (or with nothing to go back to) is a fault with
command 0; fault injection reaches only the simulated rig. Runs the real loop on the
simulated rig against a fake clock (faster than real time)."""

from __future__ import annotations

import contextlib
import json
import math
import statistics
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from helpers import FakeClock, no_new_files, wait_until
from old_loop import OLD_LOOP

from controller.core.config import LoopConfig, NominalModel
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord, PlantKnowledge
from controller.process.access import Access
from controller.process.analysis_worker import AnalysisWorker
from controller.process.audit import AuditLog, audit_path
from controller.process.options import ControllerOptions
from controller.process.persistence import MAX_VERSION, Change, PendingRollback, StateStore
from controller.process.requests import ApplyCoefficients, InjectFault, ResetFault
from controller.process.runtime import FAULT, RUNNING, Runtime, RuntimeOptions
from controller.process.service import ControllerService
from controller.sim.sim_rig import RigFaults, SimRig

GOOD = LoopConfig()
# Chatters against stick-slip at standstill (watchdog tests): Q31 at 10 Hz on the earlier
# default loop, Cv = 0.5 (1 + 55/s).
BAD = OLD_LOOP.with_(q_cutoff_hz=10.0)
HOLD = Trajectory(kind="hold", offset_deg=10.0)


class Recorded(SimRig):
    """The simulated rig, recording the commands it receives."""

    def __init__(self) -> None:
        super().__init__(initial_position_deg=10.0)
        self.commands: list[float] = []

    def step(self, command_deg_s: float) -> None:
        self.commands.append(command_deg_s)
        super().step(command_deg_s)


def _runtime(
    first: LoopConfig = GOOD, trajectory: Trajectory = HOLD, **opts: float
) -> tuple[Runtime, Recorded]:
    c = FakeClock()
    rig = Recorded()
    rt = Runtime(
        ServoLoop(LoopCoefficients.build(first, 1)), rig, trajectory=trajectory,
        options=RuntimeOptions(**opts), clock=c.clock, sleep=c.sleep,  # type: ignore[arg-type]
    )
    return rt, rig


def _more(rt: Runtime, ticks: int) -> None:
    rt._stop = False
    rt.run(max_ticks=ticks)


def _apply(rt: Runtime, cfg: LoopConfig, fallback: LoopConfig | None) -> None:
    v = rt.loop.active.version + 1
    fb = None if fallback is None else LoopCoefficients.build(fallback, v + 1)
    t = rt.submit(ApplyCoefficients(LoopCoefficients.build(cfg, v), fb))
    _more(rt, 2)
    assert t.ok and rt.loop.active.version == v


def _roll_back(rt: Runtime, ticks_before: int = 500) -> None:
    """After `ticks_before` ticks of GOOD (v1), apply BAD (v2) with GOOD as its fallback and run
    until the watchdog trips: one rollback, to v3, and the loop still running."""
    _more(rt, ticks_before)
    _apply(rt, BAD, GOOD)
    for _ in range(20):  # until the trip (at most 10 s)
        _more(rt, 500)
        if rt.rollbacks:
            break
    assert rt.rollbacks == 1 and rt.mode == RUNNING and rt.loop.active.version == 3


def test_a_trip_rolls_back_at_the_next_tick_and_the_oscillation_dies() -> None:
    rt, rig = _runtime()
    _roll_back(rt, ticks_before=1000)
    seq, from_v, to_v, trip = rt.last_rollback  # type: ignore[misc]
    assert (from_v, to_v) == (2, 3) and trip.kind in ("oscillation", "growing oscillation")
    assert rt.loop.active.version == 3 and rt.loop.active.config == GOOD
    trip_seq = seq - 1  # the tick that tripped; the previous configuration ran from the next
    print(f"\n  trip-to-rollback: 1 tick; trip after {trip.duration_s:.2f} s of {trip.reason}")
    # Bumpless: no jump in the command at the swap beyond what the oscillation itself made.
    before = rig.commands[trip_seq - 200 : trip_seq + 1]
    jump = abs(rig.commands[seq] - rig.commands[seq - 1])
    assert jump <= max(abs(a - b) for a, b in zip(before[1:], before[:-1], strict=True))
    # The oscillation dies: the command's spread in the last second is a fraction of before.
    _more(rt, 4000)
    late = rig.commands[-1000:]
    assert statistics.pstdev(late) < 0.3 * statistics.pstdev(before)
    assert rt.rollbacks == 1 and rt.mode == RUNNING


def test_a_trip_with_nothing_to_roll_back_to_is_a_fault_with_command_0() -> None:
    rt, rig = _runtime(BAD)
    _more(rt, 10_000)
    assert rt.mode == FAULT and rt.fault is not None
    assert rt.fault.startswith("watchdog:") and "no previous configuration" in rt.fault
    n = len(rig.commands)
    _more(rt, 50)
    assert all(u == 0.0 for u in rig.commands[n:])


def test_a_second_trip_soon_after_a_rollback_is_a_fault() -> None:
    rt, _rig = _runtime()
    _more(rt, 500)
    _apply(rt, BAD, BAD)  # the "previous" configuration misbehaves too
    _more(rt, 12_000)
    assert rt.rollbacks == 1 and rt.mode == FAULT
    assert rt.last_rollback is not None
    assert rt.fault is not None and f"again after it rolled back to v{rt.last_rollback[2]}" in (
        rt.fault)


def test_fault_injection_reaches_only_the_simulated_rig() -> None:
    rt, rig = _runtime()
    t = rt.submit(InjectFault(RigFaults(plant_gain=0.5)))
    _more(rt, 2)
    assert t.ok and rig.faults.plant_gain == 0.5

    class Plain:
        def read(self) -> tuple[float, float]:
            return 0.0, 0.0

        def step(self, command_deg_s: float) -> None:
            pass

    c = FakeClock()
    plain = Runtime(ServoLoop(LoopCoefficients.build(GOOD)), Plain(), clock=c.clock,
                    sleep=c.sleep)
    t = plain.submit(InjectFault(RigFaults()))
    plain.run(max_ticks=2)
    assert not t.ok and "only the simulated rig" in t.message
    assert math.isfinite(rt.last_pos_deg)


# -- the service's side: what is active is what is persisted (issue 24, items 4 and 5) ---------


def _service(rt: Runtime, state: Path, version: int = 1) -> tuple[ControllerService, Access]:
    store = StateStore(state)
    store.save(rt.loop.active.config, version)
    audit = AuditLog(audit_path(state), rig="unit")
    access = Access(None, "unit", audit, lambda text: None)
    access.start()
    opts = ControllerOptions(rig_name="unit", state_dir=state, gate_in_subprocess=False)
    k = KnowledgeRecord.of(PlantKnowledge(bound=COMMISSIONING_BOUND, version=1))
    runner = AnalysisWorker(subprocess=False)
    verdict = runner.check(rt.loop.active.config, k)
    svc = ControllerService(opts, rt, store, runner, verdict, [], k, access)
    access.warn = svc.warn
    return svc, access


def _records(access: Access, state: Path) -> list[dict[str, Any]]:
    assert access.flush()
    return [json.loads(x) for x in audit_path(state).read_text().splitlines()]


def test_a_rollback_that_cannot_be_saved_is_recorded_so_a_restart_never_brings_back_the_bad(
    tmp_path: Path,
) -> None:
    """No new file can be made in the state directory (its permissions taken away): the
    rolled-back-to configuration cannot be saved, and the active file still holds v2, which
    the watchdog rolled back from. The change log (an existing file) records the rollback:
    what a restart reads (`pending_rollback`) is v3, so the loop runs on, says so, and the
    save is retried until it succeeds. Before, nothing recorded it: a restart came back on
    v2."""
    rt, _rig = _runtime()
    svc, access = _service(rt, tmp_path)
    _more(rt, 500)
    svc.store.save(BAD, 2, Change(old=GOOD, old_version=1, verdict=None))  # the apply's save
    _apply(rt, BAD, GOOD)
    with no_new_files(tmp_path):
        for _ in range(20):
            _more(rt, 500)
            if rt.rollbacks:
                break
        assert rt.rollbacks == 1 and rt.loop.active.version == 3
        svc.poll_rollback()
        _more(rt, 3)
        assert rt.mode == RUNNING, rt.fault
        saved = svc.store.load()
        assert saved is not None and (saved.version, saved.config) == (2, BAD)  # not saved
        pending = svc.store.pending_rollback(saved)
        assert pending is not None and (pending.version, pending.from_version) == (3, 2)
        assert pending.config == GOOD
        assert any("change log records it" in e and "comes back on v3" in e
                   for e in svc.errors), svc.errors
        assert [c["version"] for c in svc.store.read_changes()] == [2]  # not an entry
        svc.poll_rollback()  # retried, still failing: recorded once, the loop runs on
        _more(rt, 3)
        assert rt.mode == RUNNING
    recs = _records(access, tmp_path)
    rb = [r for r in recs if r["action"] == "rollback"]
    assert len(rb) == 1 and rb[0]["outcome"] == "failed" and rb[0]["recorded_unsaved"]
    # The directory takes new files again: the next poll saves the rollback.
    svc.poll_rollback()
    saved = svc.store.load()
    assert saved is not None and saved.version == 3 and saved.config == GOOD
    assert svc.store.pending_rollback(saved) is None
    assert [c["version"] for c in svc.store.read_changes()] == [2, 3]
    assert not any("could not be saved" in e for e in svc.errors), svc.errors
    assert rt.mode == RUNNING
    access.close()


def test_an_apply_saved_before_the_retry_is_never_overwritten_by_the_older_rollback(
    tmp_path: Path,
) -> None:
    """The rollback to v3 waits for its retry; the directory takes files again and an apply
    (v4) is saved first: the retry must not write v3 over it (it did: a restart then came
    back on v3 while v4 ran)."""
    rt, _rig = _runtime()
    svc, access = _service(rt, tmp_path)
    svc.store.save(BAD, 2, Change(old=GOOD, old_version=1, verdict=None))  # the apply's save
    with no_new_files(tmp_path):
        _roll_back(rt)
        svc.poll_rollback()
        saved = svc.store.load()
        assert saved is not None and svc.store.pending_rollback(saved) is not None
    newer = GOOD.with_(q_cutoff_hz=0.8)
    with _ticking(rt):
        reply = svc.apply(newer, "test", confirm=True)
        assert reply.accepted and reply.version == 4, reply.reasons
        svc.poll_rollback()
    saved = svc.store.load()
    assert saved is not None and (saved.version, saved.config) == (4, newer)
    assert svc.store.pending_rollback(saved) is None
    assert not any("could not be saved" in e for e in svc.errors), svc.errors
    access.close()


def test_a_rollback_neither_saved_nor_recorded_stops_the_loop_and_is_audited(
    tmp_path: Path,
) -> None:
    """Nothing can be written: no new file in the state directory, and the change log's place
    is taken by a directory. The loop faults with command 0 and says why (a restart would
    bring back v2), the rollback and the fault are in the audit (user `watchdog` /
    `controller`), and the save is retried until it succeeds."""
    rt, rig = _runtime()
    svc, access = _service(rt, tmp_path)
    (tmp_path / "applied_changes.jsonl").mkdir()
    _roll_back(rt)
    with no_new_files(tmp_path):
        svc.poll_rollback()
        _more(rt, 3)
    assert rt.mode == FAULT and rt.fault is not None
    assert "rollback to v3 could not be saved" in rt.fault and "bring back v2" in rt.fault
    assert "nor recorded in the change log" in rt.fault
    n = len(rig.commands)
    _more(rt, 50)
    assert all(u == 0.0 for u in rig.commands[n:])
    svc.poll_faults()
    recs = _records(access, tmp_path)
    rb = [r for r in recs if r["action"] == "rollback"]
    assert len(rb) == 1 and rb[0]["user"] == "watchdog" and rb[0]["outcome"] == "failed"
    assert (rb[0]["version_before"], rb[0]["version_after"], rb[0]["persisted"]) == (2, 3, False)
    assert not rb[0]["recorded_unsaved"]
    faults = [r for r in recs if r["action"] == "fault"]
    assert len(faults) == 1 and faults[0]["user"] == "controller"
    assert "could not be saved" in faults[0]["reason"]
    assert any("could not be saved" in e for e in svc.errors)
    # The directory is writable again: the next poll saves the rollback (its line is not:
    # the log's place is still taken, which is reported).
    svc.poll_rollback()
    saved = svc.store.load()
    assert saved is not None and saved.version == 3 and saved.config == GOOD
    access.close()


def test_a_rollback_whose_log_line_cannot_be_written_is_saved_and_reported(
    tmp_path: Path,
) -> None:
    """The configuration and its change-log line are saved together now: a log that cannot
    be written (its place taken by a directory) leaves the rollback saved, the loop running
    and the failure reported, naming the log."""
    rt, _rig = _runtime()
    svc, access = _service(rt, tmp_path)
    log = tmp_path / "applied_changes.jsonl"
    log.mkdir()
    _roll_back(rt)
    svc.poll_rollback()
    saved = svc.store.load()
    assert saved is not None and saved.version == 3 and saved.config == GOOD
    assert rt.mode != FAULT
    assert any("applied_changes.jsonl: cannot append" in e for e in svc.errors), svc.errors
    access.close()


def test_a_watchdog_rollback_and_fault_are_audited_with_user_watchdog(tmp_path: Path) -> None:
    """Issue 24 item 4: 0 audit records for 4 rollbacks and a watchdog fault, before. The
    "previous" configuration is BAD too, swapped in by the runtime alone (the service never
    judged it): judged when the rollback is reported, it fails the gate (the nonlinear
    check's chatter), and the loop faults at once, by user `watchdog` too. (The trip again
    after a rollback: test_a_second_trip_soon_after_a_rollback_is_a_fault and the process
    test in tests/integration/test_watchdog_rollback.py.)"""
    rt, _rig = _runtime()
    svc, access = _service(rt, tmp_path)
    _more(rt, 500)
    _apply(rt, BAD, BAD)
    for _ in range(30):
        _more(rt, 500)
        svc.poll_rollback()
        svc.poll_faults()
        if rt.mode == FAULT:
            break
    assert rt.rollbacks == 1 and rt.mode == FAULT
    saved = svc.store.load()
    assert saved is not None and saved.version == 3  # persisted as soon as it was seen
    recs = _records(access, tmp_path)
    rb = [r for r in recs if r["action"] == "rollback"]
    assert [(r["user"], r["outcome"], r["version_before"], r["version_after"]) for r in rb] == [
        ("watchdog", "noted", 2, 3)]
    assert rb[0]["trip"] in ("oscillation", "growing oscillation", "saturation")
    faults = [r for r in recs if r["action"] == "fault"]
    assert len(faults) == 1 and faults[0]["user"] == "watchdog"
    assert faults[0]["reason"].startswith(
        "watchdog: rolled back to v3, which fails the gate on plant knowledge v1: nonlinear "
        "check: chatter"), faults[0]["reason"]
    access.close()


def test_no_version_beyond_the_limit_is_made_by_an_apply_or_its_rollback(tmp_path: Path) -> None:
    """Issue 24 item 5: at 2^53-2 an apply made 2^53-1 and the watchdog's rollback made 2^53
    active (unsaveable). The apply is refused now, naming `version`: the rollback target's
    version must fit too."""
    top = MAX_VERSION - 1  # 2**53 - 2
    c = FakeClock()
    rt = Runtime(ServoLoop(LoopCoefficients.build(GOOD, top)), Recorded(), trajectory=HOLD,
                 clock=c.clock, sleep=c.sleep)
    svc, access = _service(rt, tmp_path, version=top)
    reply = svc.apply(BAD, "op", confirm=True)
    assert not reply.accepted and reply.field == "version" and reply.version == top
    assert f"v{MAX_VERSION + 1}" in reply.reasons[0]
    _more(rt, 2)
    assert rt.loop.active.version == top
    saved = svc.store.load()
    assert saved is not None and saved.version == top
    access.close()


def test_a_status_never_carries_a_rollback_count_without_its_text(tmp_path: Path) -> None:
    """Status.rollbacks is the count the service has reported, with its `watchdog` text: it
    was the loop's count, which moves at the trip, while the text came when the service
    noticed the rollback (a Status between them had the new count and no text)."""
    rt, _rig = _runtime()
    svc, access = _service(rt, tmp_path)
    _roll_back(rt)
    before = svc.status()
    assert (before.rollbacks, before.watchdog) == (0, "")  # the loop rolled back, not reported
    svc.poll_rollback()
    after = svc.status()
    assert after.rollbacks == 1
    assert after.watchdog.startswith("watchdog: ") and "rolled back from v2" in after.watchdog
    access.close()


# -- at start: a rollback the change log records, a directory that takes no file ---------------


def _start(state: Path) -> Any:
    from controller.process.main import _initial_config

    opts = ControllerOptions(rig_name="unit", state_dir=state, gate_in_subprocess=False)
    k = KnowledgeRecord.of(PlantKnowledge(bound=COMMISSIONING_BOUND, version=1))
    runner = AnalysisWorker(subprocess=False)
    return _initial_config(opts, StateStore(state), lambda c: runner.check(c, k))


def _pending_state(state: Path) -> StateStore:
    """v2 (BAD) saved, its rollback to v3 (GOOD) only recorded."""
    store = StateStore(state)
    store.save(GOOD, 1, Change(old=None, old_version=None, verdict=None))
    store.save(BAD, 2, Change(old=GOOD, old_version=1, verdict=None))
    store.record_pending_rollback(PendingRollback(GOOD, 3, 2, "oscillation"))
    return store


def test_a_start_saves_the_recorded_rollback_and_runs_it(tmp_path: Path) -> None:
    store = _pending_state(tmp_path)
    start = _start(tmp_path)
    assert (start.config, start.version, start.fault, start.unsaved) == (GOOD, 3, "", None)
    assert "rollback from v2 to v3, not saved before the restart, was saved" in start.note
    assert start.verdict.applicable and start.verdict.knowledge_version == 1
    saved = store.load()
    assert saved is not None and (saved.config, saved.version) == (GOOD, 3)
    last = store.read_changes()[-1]
    assert last["version"] == 3 and last["old_version"] == 2
    assert last["client"] == "watchdog rollback: oscillation (saved at start)"
    assert store.pending_rollback(saved) is None
    again = _start(tmp_path)  # and the next start just runs it
    assert (again.config, again.version, again.fault) == (GOOD, 3, "")


def test_a_start_that_cannot_save_the_recorded_rollback_starts_it_faulted(
    tmp_path: Path,
) -> None:
    _pending_state(tmp_path)
    with no_new_files(tmp_path):
        start = _start(tmp_path)
    assert (start.config, start.version) == (GOOD, 3)  # never BAD, v2
    assert "rollback to v3" in start.fault and "never on v2" in start.fault
    assert start.unsaved is not None and start.rolled_back_from == BAD


def test_a_start_with_a_directory_that_takes_no_file_is_faulted(tmp_path: Path) -> None:
    """Nothing recorded (a rollback or an e-stop of the run before may have been lost): the
    loop starts stopped, saying why."""
    store = StateStore(tmp_path)
    store.save(GOOD, 1, Change(old=None, old_version=None, verdict=None))
    assert _start(tmp_path).fault == ""
    with no_new_files(tmp_path):
        start = _start(tmp_path)
    assert (start.config, start.version) == (GOOD, 1)
    assert start.fault.startswith("state_dir: cannot be written") and "reset" in start.fault


def test_a_recorded_rollback_is_ignored_once_a_newer_configuration_is_saved(
    tmp_path: Path,
) -> None:
    store = _pending_state(tmp_path)
    store.save(GOOD.with_(cv_kp=0.6), 3, Change(old=BAD, old_version=2, verdict=None))
    saved = store.load()
    assert store.pending_rollback(saved) is None
    start = _start(tmp_path)
    assert (start.version, start.config.cv_kp, start.fault) == (3, 0.6, "")


# -- a rollback after new plant knowledge (the controller owns it) ------------------------------

STIFF = OLD_LOOP.with_(cv_kp=1.0)  # a caution on the model, unstable with the drive gain x5


def _knowledge(gain: float) -> KnowledgeRecord:
    """The commissioning knowledge with the plant model's gain times `gain`."""
    model = NominalModel(pn_num=tuple(x * gain for x in NominalModel().pn_num))  # type: ignore[arg-type]
    return KnowledgeRecord.of(PlantKnowledge(bound=COMMISSIONING_BOUND, model=model))


@contextlib.contextmanager
def _ticking(rt: Runtime) -> Iterator[None]:
    """The loop runs in a thread of its own (on its fake clock: faster than real time), so
    that the service's requests, which wait for a tick, are served."""
    rt._stop = False
    th = threading.Thread(target=rt.run, daemon=True)
    th.start()
    try:
        yield
    finally:
        rt.stop()
        th.join(60.0)


def _trip(rt: Runtime) -> None:
    """The drive gain x5: STIFF oscillates (on a sine: at a hold it creeps without
    tripping); until the watchdog acts (within 10 s of the loop's time)."""
    rt.submit(InjectFault(RigFaults(plant_gain=5.0)))
    assert wait_until(lambda: rt.rollbacks or rt.mode == FAULT, 120.0)


def test_a_rollback_after_new_knowledge_runs_under_the_verdict_judged_on_it(
    tmp_path: Path,
) -> None:
    """OLD_LOOP (v1) was accepted on knowledge v1; STIFF applied (v2); knowledge v2 (the
    model's gain x2) adopted, on which OLD_LOOP is a caution. The watchdog rolls back to it:
    the Status and the History show the verdict on knowledge v2 (it showed v1's accept)."""
    rt, _rig = _runtime(OLD_LOOP, Trajectory())
    svc, access = _service(rt, tmp_path)
    _more(rt, 500)
    assert svc.running_verdict.verdict == "accept"
    with _ticking(rt):
        assert svc.apply(STIFF, "test", confirm=True).accepted
        reply = svc.adopt_knowledge(_knowledge(2.0), "test x2", "op")
        assert reply.ok and "trip faults" not in reply.message, reply.message
        _trip(rt)
    assert rt.rollbacks == 1 and rt.loop.active.version == 3
    svc.poll_rollback()
    _more(rt, 3)
    st = svc.status()
    assert st.mode == RUNNING and st.config == OLD_LOOP and st.config_version == 3
    assert st.verdict is not None and st.knowledge_version == 2
    assert (st.verdict.verdict, st.verdict.knowledge_version) == ("caution", 2), st.verdict
    last = svc.history(5).entries[-1]
    assert last.version == 3 and last.verdict == st.verdict
    access.close()


def test_new_knowledge_on_which_the_fallback_fails_makes_a_trip_fault(tmp_path: Path) -> None:
    """Knowledge v2 (gain x3) rejects OLD_LOOP, the watchdog's fallback: a trip faults with
    command 0 and says why, instead of rolling back to what fails the gate (it rolled back)."""
    rt, rig = _runtime(OLD_LOOP, Trajectory())
    svc, access = _service(rt, tmp_path)
    _more(rt, 500)
    with _ticking(rt):
        assert svc.apply(STIFF, "test", confirm=True).accepted
        reply = svc.adopt_knowledge(_knowledge(3.0), "test x3", "op")
        assert reply.ok and "a watchdog trip faults (not rolled back: v1 before it fails the " \
            "gate on plant knowledge v2" in reply.message, reply.message
        _trip(rt)
    assert rt.rollbacks == 0 and rt.mode == FAULT and rt.loop.active.version == 2
    assert rt.fault is not None and "not rolled back: v1 before it fails the gate" in rt.fault
    n = len(rig.commands)
    _more(rt, 50)
    assert all(u == 0.0 for u in rig.commands[n:])
    access.close()


def test_a_restored_configuration_that_fails_the_gate_now_faults_the_loop(
    tmp_path: Path,
) -> None:
    """The service did not judge the fallback (swapped in by the runtime alone) and knowledge
    v2 rejects it: the rollback's verdict is judged when it is seen (off the tick), and
    since it fails the gate the loop faults (command 0) with the reason; Status and History
    show that verdict."""
    rt, rig = _runtime(OLD_LOOP, Trajectory())
    svc, access = _service(rt, tmp_path)
    _more(rt, 500)
    _apply(rt, STIFF, OLD_LOOP)
    with _ticking(rt):
        assert svc.adopt_knowledge(_knowledge(3.0), "test x3", "op").ok
        _trip(rt)
    assert rt.rollbacks == 1 and rt.loop.active.version == 3
    svc.poll_rollback()
    _more(rt, 3)
    assert rt.mode == FAULT and rt.fault is not None
    assert rt.fault.startswith("watchdog: rolled back to v3, which fails the gate on plant "
                               "knowledge v2"), rt.fault
    n = len(rig.commands)
    _more(rt, 50)
    assert all(u == 0.0 for u in rig.commands[n:])
    st = svc.status()
    assert st.verdict is not None and (st.verdict.verdict, st.verdict.knowledge_version) == (
        "reject", 2)
    assert svc.history(5).entries[-1].verdict == st.verdict
    # A reset would run it: refused until a configuration that passes is applied.
    with _ticking(rt):
        reply = svc.command(ResetFault(rt.estop_seq), "op")
        assert not reply.ok and reply.message.startswith("reset: refused: watchdog: rolled back "
                                                         "to v3, which fails the gate"), reply
        assert rt.mode == FAULT
        passing = OLD_LOOP.with_(cv_kp=0.17)  # accepted on the gain x3
        applied = svc.apply(passing, "op")
        assert applied.accepted and applied.verdict.knowledge_version == 2, applied.reasons
        assert svc.command(ResetFault(rt.estop_seq), "op").ok
        assert rt.mode != FAULT and rt.loop.active.config == passing
    access.close()
