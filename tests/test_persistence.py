"""Active configuration saved atomically and restored; the applied-changes log."""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import msgspec
import numpy as np
import pytest
from helpers import spawn

from controller.core.config import LoopConfig, config_from_builtins
from controller.core.verdict import Verdict, VerdictMargins
from controller.process.persistence import (
    ACTIVE_FILE,
    LATCH_FILE,
    LOG_FILE,
    MAX_VERSION,
    Change,
    ChangeLogError,
    Latch,
    PersistenceError,
    StateStore,
    verdict_of_change,
)


def test_nothing_saved_yet(tmp_path: Path) -> None:
    store = StateStore(tmp_path / "new" / "dir")
    assert store.directory.is_dir()
    assert store.load() is None
    assert store.read_changes() == []


def test_save_then_load_round_trips(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    cfg = LoopConfig(q_cutoff_hz=0.8, ff_on=True, q_type="q20")
    store.save(cfg, 7)
    got = StateStore(tmp_path).load()
    assert got is not None
    assert got.config == cfg and got.version == 7 and got.saved_at_s > 0
    doc = json.loads((tmp_path / ACTIVE_FILE).read_text())
    assert doc["version"] == 7 and doc["config"]["q_type"] == "q20"


def test_save_replaces_atomically_and_leaves_no_temporary_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = StateStore(tmp_path)
    store.save(LoopConfig(), 1)
    calls: list[tuple[str, str]] = []
    real_replace = os.replace

    def spy(src: str, dst: str) -> None:
        calls.append((str(src), str(dst)))
        # The new content is complete in the temporary file before the rename.
        assert json.loads(Path(src).read_text())["version"] == 2
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", spy)
    store.save(LoopConfig(cv_kp=0.6), 2)
    assert len(calls) == 1 and calls[0][1] == str(tmp_path / ACTIVE_FILE)
    assert Path(calls[0][0]).parent == tmp_path
    assert sorted(p.name for p in tmp_path.iterdir()) == [ACTIVE_FILE]


def test_a_failed_write_keeps_the_old_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    store = StateStore(tmp_path)
    store.save(LoopConfig(), 1)
    before = (tmp_path / ACTIVE_FILE).read_bytes()

    def broken_fsync(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", broken_fsync)
    with pytest.raises(PersistenceError, match="cannot write"):
        store.save(LoopConfig(cv_kp=0.7), 2)
    assert (tmp_path / ACTIVE_FILE).read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [ACTIVE_FILE]


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"{not json", "not valid JSON"),
        (b"[1, 2]", "JSON object"),
        (b'{"version": -1, "config": {}}', "version"),
        (b'{"version": 3, "config": {"cv_kp": "x"}}', "config.cv_kp"),
        (b'{"version": 3, "config": {"q_cutoff_hz": 900.0}}', "q_cutoff_hz"),
    ],
)
def test_an_invalid_saved_file_is_an_error_not_a_silent_default(
    tmp_path: Path, content: bytes, match: str
) -> None:
    (tmp_path / ACTIVE_FILE).write_bytes(content)
    with pytest.raises(PersistenceError, match=match):
        StateStore(tmp_path).load()


def test_change_log_appends_one_line_per_change(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    a, b = LoopConfig(), LoopConfig(q_cutoff_hz=1.0)
    store.append_change(old=None, old_version=None, new=a, version=1, verdict=None, time_s=10.0)
    margins = VerdictMargins(gain_margin_db=float("inf"), phase_margin_deg=55.0,
                             peak_sensitivity_db=4.0, small_gain_peak=float("nan"),
                             max_pole_radius=0.99, noise_to_command_peak_db=14.0)
    verdict = Verdict(verdict="caution", cautions=("phase margin 25 deg",), margins=margins,
                      recommended_max_cutoff_hz=2.5, knowledge="plant knowledge v3 (x)",
                      knowledge_version=3)
    store.append_change(old=a, old_version=1, new=b, version=2, verdict=verdict, client="dash")
    lines = (tmp_path / "applied_changes.jsonl").read_text().splitlines()
    assert len(lines) == 2
    entries = [json.loads(x) for x in lines]  # strict JSON: inf as "inf", nan as null
    assert entries[0]["time_s"] == 10.0 and entries[0]["old"] is None
    assert entries[0]["verdict"] is None and verdict_of_change(entries[0]) is None
    assert entries[1]["old"]["q_cutoff_hz"] == 0.5 and entries[1]["new"]["q_cutoff_hz"] == 1.0
    assert entries[1]["verdict"]["margins"]["gain_margin_db"] == "inf"
    assert entries[1]["verdict"]["margins"]["small_gain_peak"] is None
    assert "margins" not in entries[1]  # the margins are the verdict's, nowhere else
    assert entries[1]["client"] == "dash" and entries[1]["old_version"] == 1
    assert store.read_changes() == entries
    back = verdict_of_change(entries[1])
    assert back is not None and back.margins.gain_margin_db == math.inf  # kept
    assert math.isnan(back.margins.small_gain_peak)  # null: not known
    def known(v: Verdict) -> Verdict:  # NaN != NaN
        return msgspec.structs.replace(v, margins=msgspec.structs.replace(
            v.margins, small_gain_peak=0.0))

    assert known(back) == known(verdict)


@pytest.mark.parametrize("gm_db", [math.inf, -math.inf, 12.5])
def test_an_infinite_margin_round_trips_through_the_log_and_history(
    tmp_path: Path, gm_db: float
) -> None:
    """An infinite gain margin (no phase crossover) was written as null and came back as NaN
    ("n/a" in History): it is written as "inf"/"-inf" now, and the History reply carries it
    (over the wire too: MessagePack has infinity) as the History tab shows it."""
    from controller import protocol as proto
    from server.panels.bode import fmt_value

    store = StateStore(tmp_path)
    margins = VerdictMargins(gain_margin_db=gm_db, phase_margin_deg=60.0,
                             peak_sensitivity_db=3.0, small_gain_peak=0.3,
                             max_pole_radius=0.99, noise_to_command_peak_db=math.inf)
    verdict = Verdict(verdict="accept", margins=margins, recommended_max_cutoff_hz=math.inf,
                      knowledge_version=2)
    store.save(LoopConfig(), 1, Change(old=None, old_version=None, verdict=verdict))
    line = (tmp_path / LOG_FILE).read_bytes()
    json.loads(line, parse_constant=lambda c: pytest.fail(f"not strict JSON: {c}"))
    [item] = store.read_changes()
    back = verdict_of_change(item)
    assert back == verdict
    reply = proto.decode(proto.encode(proto.HistoryReply(ok=True, entries=[proto.HistoryEntry(
        version=1, time_s=1.0, client="", config=LoopConfig(), verdict=back)])),
        proto.HistoryReply)
    got = reply.entries[0].verdict
    assert got is not None and got.margins.gain_margin_db == gm_db
    assert fmt_value(got.margins.gain_margin_db, 1) == (
        "inf" if gm_db == math.inf else "-inf" if gm_db == -math.inf else "12.5")


def test_a_null_margin_of_an_older_line_still_reads_as_not_known() -> None:
    """Lines written before infinity was kept have null for it (and for NaN): not known."""
    line = {"version": 3, "verdict": {"verdict": "accept", "margins": {
        "gain_margin_db": None, "phase_margin_deg": 60.0, "peak_sensitivity_db": 3.0,
        "small_gain_peak": None, "max_pole_radius": 0.99}, "recommended_max_cutoff_hz": None}}
    back = verdict_of_change(line)
    assert back is not None and math.isnan(back.margins.gain_margin_db)
    assert back.recommended_max_cutoff_hz is None
    with pytest.raises(ValueError, match="gain_margin_db"):
        verdict_of_change({"verdict": {**line["verdict"], "margins": {  # type: ignore[dict-item]
            **line["verdict"]["margins"], "gain_margin_db": "infinite"}}})  # type: ignore[index]


#: Lines as the version before protocol 2 wrote them (the verdict's kind and its margins side by
#: side; "" or absent when no verdict was logged: start-up and watchdog rollback lines).
OLD_LINES = [
    '{"time_s":1.0,"version":1,"old_version":null,"old":null,"new":{},"margins":{"gain_margin_'
    'db":12.0,"phase_margin_deg":48.0,"peak_sensitivity_db":3.5,"small_gain_peak":null,"max_po'
    'le_radius":0.99},"client":"startup (defaults)"}',
    '{"time_s":2.0,"version":2,"old_version":1,"old":{},"new":{"q_cutoff_hz":0.8},"margins":{"g'
    'ain_margin_db":null,"phase_margin_deg":40.0,"peak_sensitivity_db":4.0,"small_gain_peak":0.'
    '5,"max_pole_radius":0.99,"noise_to_command_peak_db":12.0},"client":"dash","verdict":"acce'
    'pt"}',
    '{"time_s":3.0,"version":3,"old_version":2,"old":{},"new":{},"margins":null,"client":"watchd'
    'og rollback: oscillation","verdict":""}',
]


def test_lines_of_an_older_version_still_load(tmp_path: Path) -> None:
    (tmp_path / "applied_changes.jsonl").write_text("\n".join(OLD_LINES) + "\n")
    items = StateStore(tmp_path).read_changes()
    assert [verdict_of_change(i) for i in items][0::2] == [None, None]  # no kind logged
    v = verdict_of_change(items[1])
    assert v is not None and v.verdict == "accept" and v.reasons == ()
    assert v.margins.phase_margin_deg == 40.0 and math.isnan(v.margins.gain_margin_db)
    assert v.margins.noise_to_command_peak_db == 12.0 and v.knowledge_version == 0


FULL = {"gain_margin_db": 1.0, "phase_margin_deg": 1.0, "peak_sensitivity_db": 1.0,
        "small_gain_peak": 1.0, "max_pole_radius": 1.0}


@pytest.mark.parametrize(
    ("line", "named"),
    [
        ({"verdict": "maybe"}, "verdict: 'maybe' is not one of accept, caution, reject"),
        ({"verdict": "accept", "margins": {"gain_margin_db": "big"}}, "margins.gain_margin_db"),
        ({"verdict": "accept", "margins": [1.0]}, "margins: expected an object"),
        ({"verdict": 7}, "verdict: expected an object or a string"),
        ({"verdict": {"verdict": "accept"}}, "verdict.margins: missing"),
        ({"verdict": {"verdict": "accept", "margins": {}}}, "verdict.margins.gain_margin_db"),
        ({"verdict": {"verdict": "maybe", "margins": FULL}}, "verdict.verdict"),
        ({"verdict": {"verdict": "reject", "margins": FULL, "rejections": [3]}},
         "verdict.rejections[0]"),
        ({"verdict": {"verdict": "reject", "margins": FULL, "knowledge_version": "3"}},
         "verdict.knowledge_version"),
    ],
)
def test_a_line_that_cannot_be_read_names_the_field(line: dict[str, object], named: str) -> None:
    with pytest.raises(ValueError) as info:
        verdict_of_change(line)
    assert str(info.value).startswith(named), str(info.value)


def test_a_torn_last_log_line_is_skipped(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.append_change(old=None, old_version=None, new=LoopConfig(), version=1, verdict=None)
    with open(tmp_path / "applied_changes.jsonl", "ab") as f:
        f.write(b'{"time_s": 1.0, "vers')
    assert [e["version"] for e in store.read_changes()] == [1]


def test_unwritable_directory_is_reported(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(PersistenceError, match="state_dir"):
        StateStore(blocker / "sub")


# -- the e-stop / fault latch, bounds, stale files, a directory that fails -----------------------


def test_latch_round_trips_and_is_removed_on_reset(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    assert store.load_latch() is None
    store.save_latch(Latch("estop", "estop key"))
    assert StateStore(tmp_path).load_latch() == Latch("estop", "estop key")
    store.save_latch(Latch("fault", "heartbeat lost", ""))
    assert store.load_latch() == Latch("fault", "heartbeat lost", "")
    store.save_latch(None)
    assert store.load_latch() is None and not (tmp_path / LATCH_FILE).exists()
    store.save_latch(None)  # idempotent


def test_an_unreadable_latch_is_an_error_never_not_latched(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    (tmp_path / LATCH_FILE).write_bytes(b"\xff{garbage")
    with pytest.raises(PersistenceError, match="latch"):
        store.load_latch()
    (tmp_path / LATCH_FILE).write_text('{"mode": "running"}')
    with pytest.raises(PersistenceError, match="mode"):
        store.load_latch()


def test_stale_temporary_files_are_removed_at_start(tmp_path: Path) -> None:
    (tmp_path / f".{ACTIVE_FILE}.abc123.tmp").write_text("{")
    (tmp_path / f".{LATCH_FILE}.zz.tmp").write_text("{")
    keep = tmp_path / "notes.tmp"
    keep.write_text("someone else's")
    store = StateStore(tmp_path)
    assert sorted(store.removed_tmp) == sorted(
        [f".{ACTIVE_FILE}.abc123.tmp", f".{LATCH_FILE}.zz.tmp"]
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.tmp"]


def test_versions_are_bounded(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.save(LoopConfig(), MAX_VERSION)
    assert store.load() is not None
    with pytest.raises(PersistenceError, match="version"):
        store.save(LoopConfig(), MAX_VERSION + 1)
    doc = json.loads((tmp_path / ACTIVE_FILE).read_text())
    doc["version"] = 2**64 - 2
    (tmp_path / ACTIVE_FILE).write_text(json.dumps(doc))
    with pytest.raises(PersistenceError, match=r"version: .* above the limit"):
        store.load()


def test_a_read_only_directory_is_a_persistence_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = StateStore(tmp_path)

    def read_only(*_a: object, **_k: object) -> None:
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    with pytest.raises(PersistenceError, match="cannot write"):
        store.save(LoopConfig(), 2)
    with pytest.raises(PersistenceError, match="cannot write"):
        store.save_latch(Latch("estop", "x"))


def test_a_vanished_directory_is_made_again(tmp_path: Path) -> None:
    store = StateStore(tmp_path / "state")
    shutil.rmtree(tmp_path / "state")
    store.save(LoopConfig(), 3)
    loaded = store.load()
    assert loaded is not None and loaded.version == 3


def test_unfinished_black_box_files_left_by_a_crash_are_removed_at_start(tmp_path: Path) -> None:
    """Issue 24 item 9: `blackbox/*.mcap.tmp` (a crash while a black box file was written)
    stayed forever. Complete files stay; unfinished ones go when the black box opens."""
    from controller.process.blackbox import BlackBox

    box = tmp_path / "blackbox"
    box.mkdir()
    done = box / "20260101T000000Z-estop.mcap"
    done.write_bytes(b"\x89MCAP0\r\n complete")
    torn = box / "20260101T000001Z-fault.mcap.tmp"
    torn.write_bytes(b"\x89MCAP0\r\n half")
    warnings: list[str] = []
    bb = BlackBox(box, "r", warnings.append)
    assert bb.removed_tmp == [torn.name] and not torn.exists()
    assert done.exists() and warnings == []
    assert BlackBox(box, "r", warnings.append).removed_tmp == []  # nothing left the next time


# -- a configuration saved with its change-log line: durable in order, never torn -------------


def _fd_path(fd: int) -> str:
    return os.readlink(f"/proc/self/fd/{fd}")


def test_a_change_is_saved_then_logged_with_both_fsyncs_before_save_returns(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The order that keeps a crash from coming back on an older configuration than one
    reported applied, and the log from naming one that was not saved: the new file's data
    fsynced, then renamed over the old, then the directory fsynced and the log line appended
    and fsynced (on a thread beside it), all before `save` returns."""
    store = StateStore(tmp_path)
    store.save(LoopConfig(), 1)
    events: list[str] = []
    lock = threading.Lock()
    real_fsync, real_replace = os.fsync, os.replace

    def note(what: str) -> None:
        with lock:
            events.append(what)

    def fsync(fd: int) -> None:
        path = _fd_path(fd)
        name = ("dir" if path == str(tmp_path) else "log" if path.endswith(LOG_FILE)
                else "tmp" if path.endswith(".tmp") else path)
        if name == "log":  # the log's line is written before its fsync: check what it says
            assert json.loads((tmp_path / LOG_FILE).read_text().splitlines()[-1])["version"] == 2
            assert json.loads((tmp_path / ACTIVE_FILE).read_text())["version"] == 2
        real_fsync(fd)
        note(f"fsync {name}")

    def replace(src: str, dst: str) -> None:
        note("rename")
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    new = LoopConfig(cv_kp=0.6)
    judged = Verdict(verdict="caution", margins=VerdictMargins.unknown(), cautions=("thin",))
    store.save(new, 2, Change(old=LoopConfig(), old_version=1, verdict=judged, client="dash"))
    events_at_return = list(events)
    assert events_at_return[:2] == ["fsync tmp", "rename"]
    assert sorted(events_at_return[2:]) == ["fsync dir", "fsync log"]
    loaded = store.load()
    assert loaded is not None and (loaded.config, loaded.version) == (new, 2)
    (entry,) = store.read_changes()
    assert entry["version"] == 2 and entry["old_version"] == 1 and entry["client"] == "dash"
    back = verdict_of_change(entry)  # the whole verdict; NaN written as null, read as NaN
    assert back is not None and (back.verdict, back.cautions) == ("caution", ("thin",))
    assert entry["verdict"]["margins"]["gain_margin_db"] is None
    assert math.isnan(back.margins.gain_margin_db)
    assert config_from_builtins(entry["new"]) == new and entry["time_s"] == loaded.saved_at_s


@pytest.mark.parametrize("fails", ["tmp", "rename", "log"])
def test_a_failing_write_leaves_the_old_or_the_new_state_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fails: str
) -> None:
    """A write that fails at each step: before the rename the old configuration stays and
    the log is untouched (PersistenceError: not saved); a log that cannot be written leaves
    the new configuration saved (ChangeLogError, for the caller to report)."""
    store = StateStore(tmp_path)
    old = LoopConfig()
    store.save(old, 1, Change(old=None, old_version=None, verdict=None))
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        path = _fd_path(fd)
        if (fails == "tmp" and path.endswith(".tmp")) or (fails == "log"
                                                         and path.endswith(LOG_FILE)):
            raise OSError(errno.EIO, "I/O error")
        real_fsync(fd)

    def replace(src: str, dst: str) -> None:
        if fails == "rename":
            raise OSError(errno.ENOSPC, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    new = LoopConfig(cv_kp=0.7)
    with pytest.raises(PersistenceError) as err:
        store.save(new, 2, Change(old=old, old_version=1, verdict=None))
    loaded = store.load()
    assert loaded is not None
    if fails == "log":
        assert isinstance(err.value, ChangeLogError) and "cannot append" in str(err.value)
        assert (loaded.config, loaded.version) == (new, 2)
    else:
        assert not isinstance(err.value, ChangeLogError) and "cannot write" in str(err.value)
        assert (loaded.config, loaded.version) == (old, 1)
        assert [e["version"] for e in store.read_changes()] == [1]
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


_SAVER = """
import sys
from controller.core.config import LoopConfig
from controller.process.persistence import Change, StateStore
store = StateStore(sys.argv[1])
prev = LoopConfig()
for v in range(2, 100000):
    cfg = LoopConfig(cv_kp=0.3 + (v % 50) / 100.0, q_cutoff_hz=0.2 + (v % 7) / 10.0)
    store.save(cfg, v, Change(old=prev, old_version=v - 1, verdict=None, client="kill test"))
    print(v, flush=True)  # the reply: saved and logged
    prev = cfg
"""


def test_a_process_killed_anywhere_comes_back_on_what_it_reported_or_newer(
    tmp_path: Path,
) -> None:
    """SIGKILL at arbitrary points of a stream of saves (each reported once `save` returned):
    the state directory always loads, on the last reported version or the one after it, and
    the log's last line is that version or the one before (a rename can precede its line)."""
    rng = np.random.default_rng(5)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    for _ in range(5):
        state = tmp_path / f"state{_}"
        StateStore(state).save(LoopConfig(), 1)
        proc = spawn([sys.executable, "-c", _SAVER, str(state)],
                     stdout=subprocess.PIPE, text=True, env=env)
        assert proc.stdout is not None
        reported = 1
        for _line in range(int(rng.integers(1, 40))):
            line = proc.stdout.readline()
            assert line, "the saver ended early"
            reported = int(line)
        proc.kill()
        rest = proc.stdout.read()
        proc.wait()
        if rest.split():
            reported = int(rest.split()[-1])  # replies printed before the kill landed
        loaded = StateStore(state).load()
        assert loaded is not None and loaded.version in (reported, reported + 1)
        logged = [e["version"] for e in StateStore(state).read_changes()]
        assert logged == list(range(2, logged[-1] + 1)) if logged else reported == 1
        assert (logged[-1] if logged else 1) in (loaded.version, loaded.version - 1)
        assert (logged[-1] if logged else 1) >= reported


@pytest.mark.parametrize(
    ("pending", "named"),
    [
        ({"version": 3, "from_version": 2}, "pending_rollback.config: missing"),
        ({"version": "3", "from_version": 2, "config": {}}, "pending_rollback: version"),
        ({"version": 3, "from_version": -1, "config": {}}, "pending_rollback: from_version"),
        ({"version": 3, "from_version": 2, "config": {"cv_kp": "x"}}, "cv_kp"),
        ([3, 2], "pending_rollback: expected an object"),
    ],
)
def test_a_recorded_rollback_that_cannot_be_read_is_an_error_naming_it(
    tmp_path: Path, pending: object, named: str
) -> None:
    """The controller never guesses which configuration is safe to start on."""
    store = StateStore(tmp_path)
    store.save(LoopConfig(), 2, Change(old=None, old_version=None, verdict=None))
    with open(tmp_path / LOG_FILE, "ab") as f:
        f.write(json.dumps({"time_s": 1.0, "pending_rollback": pending}).encode() + b"\n")
    with pytest.raises(PersistenceError, match=named):
        store.pending_rollback(store.load())
    assert [e["version"] for e in store.read_changes()] == [2]  # not an entry of History


def test_check_writable_leaves_nothing_behind(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.check_writable()
    assert list(tmp_path.iterdir()) == []


def test_the_run_marker_tells_an_unclean_stop_from_a_clean_one(tmp_path: Path) -> None:
    """No marker: the last run stopped cleanly (or there was none). A marker left behind names
    the run that did not stop cleanly; an unreadable one still counts as an unclean stop."""
    store = StateStore(tmp_path)
    assert store.unclean_stop() == ""
    t = 1796070662.0  # 2026-11-30 20:31:02 UTC
    store.mark_running(4321, t)
    assert StateStore(tmp_path).unclean_stop() == "pid 4321, started 2026-11-30 20:31:02 UTC"
    store.clear_running()
    assert StateStore(tmp_path).unclean_stop() == ""
    store.clear_running()  # twice: nothing to remove, no error
    for bad in (b"{", b"[]", b'{"pid": "x", "started_at_s": 1}', b'{"pid": 1}'):
        store.run_path.write_bytes(bad)
        said = store.unclean_stop()
        assert said.startswith("running.json unreadable ("), (bad, said)
