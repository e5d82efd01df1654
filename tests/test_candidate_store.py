"""The kept candidates on disk (server/candidate_store.py): one file per user per rig, read
when the store opens, rewritten atomically after each change; a failed write leaves the
previous file; an unreadable file is moved aside and its user told; no user or rig name can
point outside the store's directory; two dashboards on one directory keep each other's
candidates (issue 31 item 6), in one process and in two writing at once."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import msgspec
import pytest

from controller.core.config import LoopConfig, NominalModel
from server.candidate_store import (
    LOCK_FILE,
    PER_USER,
    CandidateStore,
    KeptCandidate,
    rig_dir_name,
    user_file_name,
)
from server.panels.tuning import kept_problem

RIG = "bench-1"
Q31 = "Q31 (3rd order, rel. deg 2)"


def _kept(cutoff_text: str = "0.8", version: int | None = 3, cv_kp: float = 1.2,
          nominal: NominalModel | None = None) -> KeptCandidate:
    base = LoopConfig(q_cutoff_hz=0.5)
    controls = (("q_type", Q31), ("cutoff_hz_input", cutoff_text), ("dob_on", True),
                ("ff_on", False), ("cv_kp", cv_kp), ("cv_ki", 10.0), ("pos_kp", 9.0),
                ("pos_ki", 3.5))
    return KeptCandidate(base, version, controls, nominal, against=base)


def _store(root: Path, **kw: object) -> CandidateStore:
    return CandidateStore(directory=root, rig=RIG, check=kept_problem, **kw)  # type: ignore[arg-type]


def _closed(store: CandidateStore) -> None:
    assert store.flush(30.0), "the writer did not finish"
    store.close()


def test_candidates_come_back_after_a_restart(tmp_path: Path) -> None:
    fitted = NominalModel(pn_den=(0.02, 1.1, 1.0))
    alice1, alice2 = _kept("0.8"), _kept("0.9x", nominal=fitted)  # an invalid text as typed
    anyone = _kept("1.25", version=None, cv_kp=0.7)
    store = _store(tmp_path)
    store.keep("alice", "tab-aaaaaaaa", _kept("0.6"))
    store.keep("alice", "tab-aaaaaaaa", alice1)  # the latest of a slot is kept
    store.keep("alice", "tab-bbbbbbbb", alice2)
    store.keep("", "tab-cccccccc", anyone)
    store.keep("alice", "", _kept("0.1"))  # no slot: nothing to come back to
    _closed(store)
    rig_dir = tmp_path / RIG
    assert sorted(p.name for p in rig_dir.iterdir()) == [LOCK_FILE, "_anyone.json", "alice.json"]

    again = _store(tmp_path)
    try:
        assert again.get("alice", "tab-aaaaaaaa") == alice1
        assert again.get("alice", "tab-bbbbbbbb") == alice2
        assert again.get("", "tab-cccccccc") == anyone
        assert len(again) == 3
        assert again.problem("alice") == again.problem("") == ""
        # Another rig's store does not see them.
        other = CandidateStore(directory=tmp_path, rig="bench-2")
        assert len(other) == 0
        other.close()
    finally:
        again.close()


def test_a_failed_write_leaves_the_previous_file_and_says_so(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    told: list[tuple[str, str]] = []
    store = _store(tmp_path, on_problem=lambda user, text: told.append((user, text)))
    try:
        store.keep("alice", "tab-aaaaaaaa", _kept("0.8"))
        assert store.flush(30.0)
        path = tmp_path / RIG / "alice.json"
        before = path.read_bytes()

        real_fsync = os.fsync

        def full_disk(fd: int) -> None:
            if os.path.isfile(f"/proc/self/fd/{fd}"):  # the file's fsync, not the directory's
                raise OSError(errno.ENOSPC, "No space left on device")
            real_fsync(fd)

        monkeypatch.setattr(os, "fsync", full_disk)
        store.keep("alice", "tab-aaaaaaaa", _kept("0.7"))
        assert store.flush(30.0)
        assert path.read_bytes() == before  # the previous file, whole
        # No temporary file left (the lock file stays: it is the directory's).
        assert sorted(p.name for p in path.parent.iterdir()) == [LOCK_FILE, "alice.json"]
        assert "not saved to disk" in store.problem("alice")
        assert "No space left on device" in store.problem("alice")
        assert told == [("alice", store.problem("alice"))]
        assert store.get("alice", "tab-aaaaaaaa") == _kept("0.7")  # memory has the change

        monkeypatch.setattr(os, "fsync", real_fsync)
        store.keep("alice", "tab-aaaaaaaa", _kept("0.75"))
        assert store.flush(30.0)
        assert store.problem("alice") == "" and told[-1] == ("alice", "")
        assert b'"0.75"' in path.read_bytes()
    finally:
        store.close()
    assert _store(tmp_path).get("alice", "tab-aaaaaaaa") == _kept("0.75")


def _valid_doc(user: str) -> dict[str, object]:
    k = _kept()
    return {"format": 1, "rig": RIG, "user": user, "saved_at_s": 1.0, "candidates": [
        {"slot": "tab-aaaaaaaa", "base": msgspec.to_builtins(k.base), "base_version": 3,
         "against": None, "controls": [list(c) for c in k.controls], "nominal": None}]}


def _bad_config(doc: dict[str, object]) -> None:
    doc["candidates"][0]["base"]["q_cutoff_hz"] = -1.0  # type: ignore[index]


def _unknown_control(doc: dict[str, object]) -> None:
    doc["candidates"][0]["controls"][0] = ["__class__", "x"]  # type: ignore[index]


def _gain_out_of_range(doc: dict[str, object]) -> None:
    doc["candidates"][0]["controls"][4] = ["cv_kp", 1e9]  # type: ignore[index]


def _other_rig(doc: dict[str, object]) -> None:
    doc["rig"] = "elsewhere"


def _other_user(doc: dict[str, object]) -> None:
    doc["user"] = "mallory"


@pytest.mark.parametrize("spoil, why", [
    (None, "is not a kept-candidates file"),
    (_bad_config, "q_cutoff_hz"),
    (_unknown_control, "controls"),
    (_gain_out_of_range, "controls.cv_kp"),
    (_other_rig, "rig 'elsewhere'"),
    (_other_user, "user 'mallory'"),
])
def test_an_unreadable_file_is_moved_aside_and_its_user_told(
        tmp_path: Path, spoil: object, why: str) -> None:
    rig_dir = tmp_path / RIG
    rig_dir.mkdir()
    if spoil is None:
        bad = b'{"format": 1, "rig": "bench-1", "candid'  # cut short
    else:
        doc = _valid_doc("alice")
        spoil(doc)  # type: ignore[operator]
        bad = msgspec.json.encode(doc)
    (rig_dir / "alice.json").write_bytes(bad)
    (rig_dir / "bob.json").write_bytes(msgspec.json.encode(_valid_doc("bob")))
    (rig_dir / ".bob.json.x1y2.tmp").write_bytes(b"half a wri")  # a crash's leftover

    store = _store(tmp_path)
    try:
        aside = [p for p in rig_dir.iterdir() if p.name.startswith("alice.json.unreadable-")]
        assert len(aside) == 1 and aside[0].read_bytes() == bad  # kept whole, not deleted
        assert not (rig_dir / "alice.json").exists()
        text = store.problem("alice")
        assert str(rig_dir / "alice.json") in text and why in text, text
        assert f"moved aside to {aside[0]}" in text
        assert store.get("alice", "tab-aaaaaaaa") is None
        assert store.get("bob", "tab-aaaaaaaa") is not None and store.problem("bob") == ""
        assert not (rig_dir / ".bob.json.x1y2.tmp").exists()
        # Alice's next change is saved anew; what was moved aside stays.
        store.keep("alice", "tab-aaaaaaaa", _kept("0.8"))
        assert store.flush(30.0)
        assert (rig_dir / "alice.json").exists() and aside[0].read_bytes() == bad
    finally:
        store.close()


def test_a_file_that_cannot_be_moved_aside_is_never_written_over(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rig_dir = tmp_path / RIG
    rig_dir.mkdir()
    (rig_dir / "alice.json").write_bytes(b"not json")

    def refused(self: Path, target: object) -> Path:
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(Path, "replace", refused)
    store = _store(tmp_path)
    monkeypatch.undo()
    try:
        assert "could not be moved aside" in store.problem("alice")
        store.keep("alice", "tab-aaaaaaaa", _kept())
        assert store.flush(30.0)
        assert (rig_dir / "alice.json").read_bytes() == b"not json"
        assert store.get("alice", "tab-aaaaaaaa") == _kept()  # kept in memory
    finally:
        store.close()


@pytest.mark.parametrize("user", ["../alice", "..", ".", "a/b", "/etc/passwd", "_anyone",
                                  ".hidden", "x" * 65, "al\x00ice", "alice\n"])
def test_no_user_name_makes_a_path_elsewhere(tmp_path: Path, user: str) -> None:
    with pytest.raises(ValueError, match="user"):
        user_file_name(user)
    store = _store(tmp_path)
    try:
        store.keep(user, "tab-aaaaaaaa", _kept())
        assert store.flush(30.0)
        assert "not saved to disk" in store.problem(user)
    finally:
        store.close()
    written = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert written == [], written


@pytest.mark.parametrize("rig", ["..", ".", "a/../../b", "rig 1", "rïg", "100%", ".hidden",
                                 "rig.1"])
def test_every_rig_name_is_one_directory_inside_the_store(tmp_path: Path, rig: str) -> None:
    name = rig_dir_name(rig)
    assert "/" not in name and not name.startswith(".") and name not in ("", ".", "..")
    assert (tmp_path / name).resolve().parent == tmp_path.resolve()
    assert rig_dir_name("rig.1") == "rig.1" and rig_dir_name("..") == "%2E."
    store = CandidateStore(directory=tmp_path, rig=rig, check=kept_problem)
    try:
        store.keep("alice", "tab-aaaaaaaa", _kept())
        assert store.flush(30.0) and store.problem("alice") == ""
    finally:
        store.close()
    assert [p.relative_to(tmp_path) for p in tmp_path.rglob("*.json")] == [
        Path(name) / "alice.json"]
    assert CandidateStore(directory=tmp_path, rig=rig).get("alice", "tab-aaaaaaaa") == _kept()


def test_distinct_rig_names_get_distinct_directories() -> None:
    names = ["a.b", "a%2Eb", "a b", "a%20b", "..", "%2E.", "%", "%25"]
    assert len({rig_dir_name(n) for n in names}) == len(names)


def test_two_dashboards_on_one_directory_keep_each_others_candidates(tmp_path: Path) -> None:
    """Issue 31: two dashboards on one candidates directory, both started before either wrote:
    each rewrote alice's file with its own memory, and the candidate kept by the other one
    vanished. Now a write changes only the slots its dashboard changed."""
    first, second = _store(tmp_path), _store(tmp_path)  # both read an empty directory
    try:
        first.keep("alice", "tab-first000", _kept("0.8"))
        assert first.flush(30.0)
        second.keep("alice", "tab-second00", _kept("0.9"))
        assert second.flush(30.0)
        first.keep("alice", "tab-first000", _kept("0.85"))  # its own slot changed again
        assert first.flush(30.0)
        assert first.problem("alice") == second.problem("alice") == ""
    finally:
        first.close()
        second.close()
    again = _store(tmp_path)
    try:
        assert again.get("alice", "tab-first000") == _kept("0.85")
        assert again.get("alice", "tab-second00") == _kept("0.9")
    finally:
        again.close()


def test_a_users_file_keeps_the_latest_slots_of_every_dashboard(tmp_path: Path) -> None:
    first, second = _store(tmp_path), _store(tmp_path)
    try:
        for i in range(PER_USER):
            first.keep("alice", f"tab-a{i:07d}", _kept(f"0.{i + 1}"))
        assert first.flush(30.0)
        second.keep("alice", "tab-b0000000", _kept("0.9"))
        assert second.flush(30.0)
    finally:
        first.close()
        second.close()
    again = _store(tmp_path)
    try:
        assert len(again) == PER_USER  # the oldest of the first's went
        assert again.get("alice", "tab-a0000000") is None
        assert again.get("alice", "tab-b0000000") == _kept("0.9")
        assert again.get("alice", f"tab-a{PER_USER - 1:07d}") is not None
    finally:
        again.close()


_WRITER = textwrap.dedent("""
    import sys
    from pathlib import Path
    from controller.core.config import LoopConfig
    from server.candidate_store import CandidateStore, KeptCandidate
    root, name, n = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
    store = CandidateStore(directory=root, rig="bench-1")
    print("ready", flush=True)
    sys.stdin.readline()  # both processes have read the directory: go
    base = LoopConfig(q_cutoff_hz=0.5)
    for i in range(n):
        store.keep("alice", f"tab-{name}{i:04d}",
                   KeptCandidate(base, 3, (("cutoff_hz_input", f"0.{i + 1}"),), None, base))
        assert store.flush(60.0)
    store.close()
    assert store.problem("alice") == "", store.problem("alice")
    print("done", flush=True)
""")


def test_two_dashboard_processes_writing_at_once_lose_nothing(tmp_path: Path) -> None:
    """Two processes (two dashboards) each keep alice's candidates as fast as they can, on one
    directory: every slot of both is in her file at the end (the lock makes each
    read-modify-write whole)."""
    n = PER_USER // 2
    procs = [subprocess.Popen([sys.executable, "-c", _WRITER, str(tmp_path), name, str(n)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
             for name in ("aaaa", "bbbb")]
    try:
        for p in procs:
            assert p.stdout is not None and p.stdout.readline().strip() == "ready"
        for p in procs:
            assert p.stdin is not None
            p.stdin.write("go\n")
            p.stdin.flush()
        for p in procs:
            out, _ = p.communicate(timeout=120)
            assert p.returncode == 0 and "done" in out, out
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    store = CandidateStore(directory=tmp_path, rig="bench-1")
    try:
        assert len(store) == 2 * n
        assert all(store.get("alice", f"tab-{name}{i:04d}") is not None
                   for name in ("aaaa", "bbbb") for i in range(n))
    finally:
        store.close()


def test_the_speed_command_filters_controls_are_kept_and_checked(tmp_path: Path) -> None:
    """A candidate kept with the filter's controls (issue 35 item 3) comes back with them; one
    kept before they existed is still taken; a filter control with a value of another kind is
    refused naming it."""
    filt = (("filter_kind", "notch"), ("notch_hz_input", "31.5"),
            ("notch_depth_db_input", "20.0"), ("notch_width_input", "0.3x"),  # as typed
            ("lowpass_hz_input", "200.0"), ("lowpass_damping_input", "0.707"))
    old = _kept("0.8")
    with_filter = KeptCandidate(old.base, old.base_version, old.controls + filt, None,
                                old.against)
    assert kept_problem(old) == "" and kept_problem(with_filter) == ""
    store = _store(tmp_path)
    store.keep("alice", "tab-aaaaaaaa", with_filter)
    _closed(store)
    again = _store(tmp_path)
    back = again.get("alice", "tab-aaaaaaaa")
    again.close()
    assert back is not None and dict(back.controls)["notch_hz_input"] == "31.5"
    bad = KeptCandidate(old.base, old.base_version,
                        (*old.controls, ("filter_kind", "band-stop"), *filt[1:]), None,
                        old.against)
    assert kept_problem(bad).startswith("controls.filter_kind:")
    partial = KeptCandidate(old.base, old.base_version, old.controls + filt[:2], None,
                            old.against)
    assert kept_problem(partial).startswith("controls: expected")
