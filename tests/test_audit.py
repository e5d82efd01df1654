"""The audit trail: record format, hash chain, crash recovery, and every alteration caught.

The chain is re-derived here independently (sorted compact JSON, SHA-256), so the format on
disk is the documented one and not just whatever the module happens to write.
"""

from __future__ import annotations

import hashlib
import io
import itertools
import json
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from controller.cli.audit import show_main, verify_main
from controller.cli.commands import controller_commands
from controller.process import audit as audit_mod
from controller.process.audit import (
    AUDIT_FILE,
    GENESIS,
    RECOVERED,
    AuditError,
    AuditLog,
    audit_path,
    verify,
)

T0 = 1_750_000_000.0


def clock() -> Callable[[], float]:
    ticks = itertools.count()
    return lambda: T0 + next(ticks)


def canonical(obj: dict[str, Any]) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def make_log(directory: Path, extra: int = 0) -> Path:
    """Six varied records (plus `extra`: e-stop, reset, e-stop ...) in `directory/audit.jsonl`."""
    with AuditLog(audit_path(directory), rig="bench", clock=clock()) as log:
        log.record("controller.start", "controller", "noted", version_before=3, version_after=3)
        log.record("lease.acquire", "alice", "accepted", holder="alice", token_id="ab12")
        log.record("apply", "alice", "accepted", version_before=3, version_after=4,
                   verdict="accept", margins={"phase_margin_deg": 48.2, "gain_margin_db": 12.5})
        log.record("apply", "bob", "refused", version_before=4, version_after=4,
                   reason="not the lease holder")
        log.record("estop", "bob", "accepted", version_before=4, version_after=4)
        log.record("reset", "alice", "accepted", version_before=4, version_after=4)
        for i in range(extra):  # each e-stop written: a reset between (repeats are counted)
            log.record("estop" if i % 2 == 0 else "reset", "carol", "accepted",
                       version_before=4, version_after=4)
    return directory / AUDIT_FILE


def lines_of(path: Path) -> list[bytes]:
    return path.read_bytes().splitlines(keepends=True)


def cli_verify(
    path: Path, anchor: str | None = None, as_json: bool = False, accept_torn: bool = False,
    accept_lost: bool = False,
) -> tuple[int, str]:
    out = io.StringIO()
    return verify_main(path, anchor, as_json, out, accept_torn, accept_lost), out.getvalue()


def cli_show(path: Path, as_json: bool = False, tail: int | None = None) -> tuple[int, str]:
    out = io.StringIO()
    return show_main(path, as_json, tail, out), out.getvalue()


# -- format ----------------------------------------------------------------------------------


def test_records_carry_the_documented_fields_and_chain(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    raw = [line.rstrip(b"\n") for line in lines_of(path)]
    recs = [json.loads(line) for line in raw]
    assert [r["seq"] for r in recs] == list(range(6))
    assert recs[0]["time"] == "2025-06-15T15:06:40.000000Z"  # T0, UTC
    assert recs[1]["time"] == "2025-06-15T15:06:41.000000Z"
    assert {r["rig"] for r in recs} == {"bench"}
    assert (recs[2]["action"], recs[2]["user"], recs[2]["outcome"]) == ("apply", "alice",
                                                                         "accepted")
    assert (recs[2]["version_before"], recs[2]["version_after"]) == (3, 4)
    assert recs[2]["margins"]["phase_margin_deg"] == 48.2
    assert recs[1]["version_before"] is None and recs[1]["version_after"] is None
    prev = GENESIS
    for line, rec in zip(raw, recs, strict=True):
        assert line == canonical(rec)  # canonical bytes: sorted keys, no spaces
        assert rec["prev"] == prev
        assert rec["hash"] == sha(canonical({k: v for k, v in rec.items() if k != "hash"}))
        prev = sha(line)


def test_record_returns_what_is_stored_and_nonfinite_becomes_null(tmp_path: Path) -> None:
    with AuditLog(tmp_path / AUDIT_FILE, rig="r") as log:
        got = log.record("apply", "alice", "accepted", margins={"gain_margin_db": float("inf")},
                         sources=("nominal", "pos0"))
        assert log.head == (0, got["hash"])
    stored = json.loads((tmp_path / AUDIT_FILE).read_bytes())
    assert got == stored
    assert got["margins"] == {"gain_margin_db": None} and got["sources"] == ["nominal", "pos0"]
    assert verify(tmp_path / AUDIT_FILE).ok


def test_numpy_values_are_recorded_as_plain_numbers(tmp_path: Path) -> None:
    with AuditLog(tmp_path / AUDIT_FILE) as log:
        got = log.record("knowledge", "alice", "accepted", spread_db=np.float64(1.5),
                         positions=np.arange(3), count=np.int64(4))
        assert (got["spread_db"], got["positions"], got["count"]) == (1.5, [0, 1, 2], 4)
        with pytest.raises(TypeError, match="cannot record a object"):
            log.record("knowledge", "alice", "accepted", thing=object())
    result = verify(tmp_path / AUDIT_FILE)
    assert result.ok and result.records == 1


@pytest.mark.parametrize(
    ("args", "kwargs", "match"),
    [
        (("aply", "alice", "accepted"), {}, "unknown audit action"),
        (("apply", "alice", "ok"), {}, "outcome"),
        (("apply", "alice", "accepted"), {"seq": 7}, "reserved"),
        (("apply", "alice", "accepted"), {"hash": "0"}, "reserved"),
        (("apply", "alice", "accepted"), {"prev": "0", "rig": "x"}, "reserved"),
        (("apply", None, "accepted"), {}, "user"),
        (("apply", "alice", "accepted"), {"version_before": True}, "versions"),
    ],
)
def test_bad_records_are_refused_before_writing(
    tmp_path: Path, args: tuple[Any, ...], kwargs: dict[str, Any], match: str
) -> None:
    with AuditLog(tmp_path / AUDIT_FILE) as log, pytest.raises(ValueError, match=match):
        log.record(*args, **kwargs)
    assert (tmp_path / AUDIT_FILE).read_bytes() == b""


def test_every_record_is_fsynced(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[int] = []
    real = os.fsync

    def counting_fsync(fd: int) -> None:
        calls.append(fd)
        real(fd)

    monkeypatch.setattr(os, "fsync", counting_fsync)
    with AuditLog(tmp_path / AUDIT_FILE) as log:
        for _ in range(3):
            log.record("command", "a", "accepted")
    assert len(calls) == 3


def test_reopening_continues_the_chain(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    head = verify(path).head
    with AuditLog(path, rig="bench") as log:
        assert log.recovered is None
        assert log.head == (5, head)
        rec = log.record("estop", "carol", "accepted")
    assert rec["seq"] == 6 and rec["prev"] == sha(lines_of(path)[5].rstrip(b"\n"))
    result = verify(path)
    assert result.ok and result.records == 7 and result.damaged == ()


def test_concurrent_writers_keep_one_chain(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_FILE
    with AuditLog(path) as log:
        def work(user: str) -> None:
            for _ in range(40):
                log.record("command", user, "accepted")

        threads = [threading.Thread(target=work, args=(f"u{i}",)) for i in range(6)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    result = verify(path)
    assert result.ok and result.records == 240
    assert [json.loads(line)["seq"] for line in lines_of(path)] == list(range(240))


def test_closed_log_refuses(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / AUDIT_FILE)
    log.close()
    with pytest.raises(AuditError, match="closed"):
        log.record("estop", "a", "accepted")


# -- alterations: each one is caught, at the right line --------------------------------------


def _replace_in(i: int, old: bytes, new: bytes) -> Callable[[list[bytes]], list[bytes]]:
    def alter(lines: list[bytes]) -> list[bytes]:
        assert old in lines[i]
        return [*lines[:i], lines[i].replace(old, new), *lines[i + 1:]]
    return alter


def _rehash(line: bytes, **changes: Any) -> bytes:
    rec = {**json.loads(line), **changes}
    rec["hash"] = sha(canonical({k: v for k, v in rec.items() if k != "hash"}))
    return canonical(rec) + b"\n"


def _edit_and_rehash(lines: list[bytes]) -> list[bytes]:
    """A smarter edit: the record's own hash is recomputed; the next line's prev breaks."""
    return [*lines[:2], _rehash(lines[2], user="mallory"), *lines[3:]]


def _forged_insert(lines: list[bytes]) -> list[bytes]:
    """A self-consistent record that chains to line 2: the original line 3 no longer does."""
    forged = _rehash(lines[1], prev=sha(lines[1].rstrip(b"\n")), seq=2, user="mallory",
                     time="2025-06-15T15:06:41.500000Z")
    return [*lines[:2], forged, *lines[2:]]


def _swap(i: int) -> Callable[[list[bytes]], list[bytes]]:
    def alter(lines: list[bytes]) -> list[bytes]:
        out = list(lines)
        out[i], out[i + 1] = out[i + 1], out[i]
        return out
    return alter


def _reencode_unsorted(lines: list[bytes]) -> list[bytes]:
    rec = json.loads(lines[1])
    reordered = dict(reversed(list(rec.items())))
    return [lines[0], json.dumps(reordered, separators=(",", ":")).encode() + b"\n", *lines[2:]]


def _truncate_hash(i: int) -> Callable[[list[bytes]], list[bytes]]:
    def alter(lines: list[bytes]) -> list[bytes]:
        h = json.loads(lines[i])["hash"].encode()
        return _replace_in(i, h, h[:-1])(lines)
    return alter


ALTERATIONS: dict[str, tuple[Callable[[list[bytes]], list[bytes]], int, str]] = {
    # name: (alteration, first bad line, words in the reason)
    "edited user": (_replace_in(3, b'"user":"bob"', b'"user":"eve"'), 4, "hash does not match"),
    "edited margin": (_replace_in(2, b"48.2", b"58.2"), 3, "hash does not match"),
    "edited version": (_replace_in(2, b'"version_after":4', b'"version_after":5'), 3,
                       "hash does not match"),
    "edited outcome": (_replace_in(3, b'"refused"', b'"accepted"'), 4, "hash does not match"),
    "edited and rehashed": (_edit_and_rehash, 4, "prev does not chain"),
    "deleted middle line": (lambda ls: [*ls[:2], *ls[3:]], 3, "prev does not chain"),
    "deleted first line": (lambda ls: ls[1:], 1, "genesis"),
    "reordered lines": (_swap(2), 3, "prev does not chain"),
    "last two reordered": (_swap(4), 5, "prev does not chain"),
    "inserted duplicate": (lambda ls: [*ls[:2], ls[1], *ls[2:]], 3, "prev does not chain"),
    "inserted blank line": (lambda ls: [*ls[:2], b"\n", *ls[2:]], 3, "not JSON"),
    "inserted text": (lambda ls: [*ls[:2], b"hello\n", *ls[2:]], 3, "not JSON"),
    "inserted forged record": (_forged_insert, 4, "prev does not chain"),
    "seq rewritten and rehashed": (lambda ls: [*ls[:5], _rehash(ls[5], seq=9)], 6,
                                   "seq 9, expected 5"),
    "truncated hash": (_truncate_hash(1), 2, "64 hex"),
    "truncated last hash": (_truncate_hash(5), 6, "64 hex"),
    "hash replaced": (_replace_in(0, b'"hash":"', b'"hash":"f'), 1, "hash"),
    "extra space": (_replace_in(1, b'"user":"alice"', b'"user": "alice"'), 2, "canonical"),
    "keys reordered": (_reencode_unsorted, 2, "canonical"),
    "field added": (_replace_in(1, b'"user":"alice"', b'"user":"alice","x":1'), 2, "canonical"),
    "file cut mid-line": (lambda ls: [*ls[:5], ls[5][:40]], 6, "unacknowledged"),
    "prev edited": (_replace_in(3, b'"prev":"', b'"prev":"0'), 4, "64 hex|hash"),
}


@pytest.mark.parametrize("name", sorted(ALTERATIONS))
def test_every_alteration_is_caught(tmp_path: Path, name: str) -> None:
    alter, bad_line, words = ALTERATIONS[name]
    path = make_log(tmp_path)
    assert cli_verify(tmp_path)[0] == 0
    path.write_bytes(b"".join(alter(lines_of(path))))
    result = verify(path)
    assert not result.ok
    assert result.bad_line == bad_line, result
    assert any(w in result.reason for w in words.split("|")), result.reason
    assert result.records == bad_line - 1
    code, text = cli_verify(tmp_path)
    assert code == 1
    assert f"line {bad_line}:" in text
    code, text = cli_verify(tmp_path, as_json=True)
    assert code == 1 and json.loads(text)["bad_line"] == bad_line


def test_lines_cut_off_the_end_are_caught_against_an_anchor(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    anchor = verify(path).head
    path.write_bytes(b"".join(lines_of(path)[:-1]))
    # A shorter chain is still a valid chain: the chain alone cannot tell ...
    assert verify(path).ok
    # ... the anchor can.
    result = verify(path, anchor=anchor)
    assert not result.ok and result.bad_line is None and "anchor" in result.reason
    code, text = cli_verify(tmp_path, anchor=anchor)
    assert code == 1 and "anchor" in text
    assert cli_verify(tmp_path, anchor=verify(path).head)[0] == 0


def test_an_edited_and_rehashed_last_record_is_caught_against_an_anchor(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    anchor = verify(path).head
    lines = lines_of(path)
    path.write_bytes(b"".join([*lines[:5], _rehash(lines[5], user="mallory")]))
    assert verify(path).ok  # nothing chains from the last record yet
    result = verify(path, anchor=anchor)
    assert not result.ok and "anchor" in result.reason


def test_a_rewritten_chain_is_caught_against_an_anchor(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    lines = lines_of(path)
    before_edit, after_edit = (json.loads(lines[i])["hash"] for i in (2, 4))
    # The attacker edits line 4 and recomputes every hash after it: a valid chain again.
    prev = sha(lines[2].rstrip(b"\n"))
    for i in range(3, 6):
        changes: dict[str, Any] = {"prev": prev}
        if i == 3:
            changes["user"] = "mallory"
        lines[i] = _rehash(lines[i], **changes)
        prev = sha(lines[i].rstrip(b"\n"))
    path.write_bytes(b"".join(lines))
    assert verify(path).ok
    assert verify(path, anchor=before_edit).ok  # the records before the edit are untouched
    result = verify(path, anchor=after_edit)
    assert not result.ok and "anchor" in result.reason


def test_the_status_anchor_form_seq_hash_is_accepted(tmp_path: Path) -> None:
    """Issue 31 item 5: `--anchor <seq>:<sha256>`, the form Status.audit_head carries, said
    "not in the chain" on an intact log. Now it is checked as what it says: the record with
    that seq has that hash."""
    from controller.process.access import Access

    path = make_log(tmp_path)
    access = Access(None, "r", AuditLog(path, rig="r"), lambda *a, **k: None)
    head = access.head  # what the controller publishes as Status.audit_head
    access.close()
    seq, digest = head.split(":")
    assert int(seq) == 5 and len(digest) == 64
    assert verify(path, anchor=head).ok
    code, text = cli_verify(tmp_path, anchor=head)
    assert code == 0 and "chain intact" in text, text
    # The hash alone still works; the same hash under another seq is not that record.
    assert verify(path, anchor=digest).ok
    wrong = verify(path, anchor=f"4:{digest}")
    assert not wrong.ok and "anchor" in wrong.reason
    # The attack the anchor exists for: the last record cut off.
    path.write_bytes(b"".join(lines_of(path)[:-1]))
    assert verify(path).ok
    code, text = cli_verify(tmp_path, anchor=head)
    assert code == 1 and "not in the chain" in text
    # An earlier head still verifies against the shortened log.
    earlier = json.loads(lines_of(path)[-1])
    assert cli_verify(tmp_path, anchor=f"{earlier['seq']}:{earlier['hash']}")[0] == 0


@pytest.mark.parametrize("bad", ["", "5:", ":abc", "x:" + "a" * 64, "-1:" + "a" * 64,
                                 "5:" + "a" * 63, "g" * 64])
def test_a_malformed_anchor_is_bad_input_naming_the_form(tmp_path: Path, bad: str) -> None:
    make_log(tmp_path)
    code, text = cli_verify(tmp_path, anchor=bad)
    assert code == 2 and "<seq>:<sha256>" in text, text
    with pytest.raises(ValueError, match="anchor"):
        verify(tmp_path / AUDIT_FILE, anchor=bad)


# -- crash recovery --------------------------------------------------------------------------


def test_a_torn_last_line_is_kept_and_acknowledged_not_chained_over(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    torn = lines_of(path)[5][:57]  # as if the controller died inside a write
    with open(path, "ab") as f:
        f.write(torn)
    result = verify(path)
    assert not result.ok and result.bad_line == 7 and "unacknowledged" in result.reason
    assert cli_verify(tmp_path)[0] == 1

    with AuditLog(path, rig="bench") as log:
        assert log.recovered is not None and "torn" in log.recovered
        rec = log.record("estop", "carol", "accepted")
    lines = lines_of(path)
    assert lines[6] == torn + b"\n"  # the damaged bytes are still there
    ack = json.loads(lines[7])
    assert ack["action"] == RECOVERED and ack["outcome"] == "noted"
    assert (ack["seq"], ack["damaged_after_seq"]) == (6, 5)
    assert ack["damaged_bytes"] == len(torn) and ack["damaged_sha256"] == sha(torn)
    assert ack["prev"] == sha(lines[5].rstrip(b"\n"))  # chains from the last good record
    assert rec["seq"] == 7
    # Acknowledged is not intact: a torn tail is also what erasing the last record leaves.
    result = verify(path)
    assert not result.ok and result.bad_line == 7 and "torn tail" in result.reason
    assert "--accept-torn-tail" in result.reason
    code, text = cli_verify(tmp_path)
    assert code == 1 and "line 7: torn tail" in text
    result = verify(path, accept_torn_tail=True)
    assert result.ok and result.records == 8
    assert len(result.accepted_torn) == 1 and "line 7" in result.accepted_torn[0]
    code, text = cli_verify(tmp_path, accept_torn=True)
    assert code == 0 and "ACCEPTED torn tail (--accept-torn-tail): line 7" in text
    code, text = cli_verify(tmp_path, as_json=True, accept_torn=True)
    assert code == 0 and len(json.loads(text)["accepted_torn"]) == 1
    _, shown = cli_show(tmp_path)
    assert "line 7: damaged" in shown


def test_an_erased_last_record_is_not_acknowledged_away_by_a_restart(tmp_path: Path) -> None:
    """Issue 24 item 6: cut the last record (an e-stop) to a torn tail, restart the controller
    (it notes the torn tail), and the log still verified. Now `verify` fails at that line
    until told to accept torn tails, and then says what it accepted. (Here the head file is
    gone too, as with a log from before it existed: with it, the restart also sees that the
    log does not reach its head, test_a_log_behind_its_head_file_...)"""
    path = make_log(tmp_path, extra=1)
    lines = lines_of(path)
    assert json.loads(lines[-1])["action"] == "estop"
    path.write_bytes(b"".join(lines[:-1]) + lines[-1][:40])  # the e-stop record erased
    (tmp_path / audit_mod.HEAD_FILE).unlink()
    with AuditLog(path, rig="bench") as log:  # the controller restarts
        assert log.recovered is not None and "torn" in log.recovered
        log.record("controller.start", "controller", "noted")
    code, text = cli_verify(tmp_path)
    assert code == 1 and "line 7: torn tail: 40 damaged bytes after seq 5" in text
    code, text = cli_verify(tmp_path, as_json=True)
    assert code == 1 and json.loads(text)["bad_line"] == 7
    code, text = cli_verify(tmp_path, accept_torn=True)
    assert code == 0 and "ACCEPTED torn tail" in text and "40 damaged bytes" in text
    # Before any restart (no acknowledgement) the same: fails, unless accepted.
    (tmp_path / "b").mkdir()
    other = make_log(tmp_path / "b", extra=1)
    other.write_bytes(other.read_bytes()[:-30])
    assert cli_verify(tmp_path / "b")[0] == 1
    code, text = cli_verify(tmp_path / "b", accept_torn=True)
    assert code == 0 and "torn last line" in text and "unacknowledged" in text


def test_accepting_torn_tails_accepts_nothing_else(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    path.write_bytes(path.read_bytes() + b"garbage\n")  # complete, not torn: not a crash
    assert cli_verify(tmp_path, accept_torn=True)[0] == 1
    path.write_bytes(b"".join(_replace_in(3, b'"bob"', b'"eve"')(lines_of(path)[:6])))
    result = verify(path, accept_torn_tail=True)
    assert not result.ok and result.bad_line == 4


def test_tampering_with_the_acknowledgement_is_caught(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    with open(path, "ab") as f:
        f.write(b'{"action":"est')
    AuditLog(path).close()
    lines = lines_of(path)
    # the damaged bytes changed after the acknowledgement
    path.write_bytes(b"".join([*lines[:6], b'{"action":"esx\n', lines[7]]))
    result = verify(path)
    assert not result.ok and result.bad_line == 7
    # an acknowledgement of a damaged line that is not there
    path.write_bytes(b"".join([*lines[:6], lines[7]]))
    result = verify(path)
    assert not result.ok and result.bad_line == 7 and "not there" in result.reason


def test_a_complete_last_record_without_its_newline_is_continued(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    path.write_bytes(path.read_bytes()[:-1])
    assert verify(path).ok
    with AuditLog(path) as log:
        assert log.recovered is None
        log.record("estop", "a", "accepted")
    result = verify(path)
    assert result.ok and result.records == 7 and result.damaged == ()


def test_a_failed_write_is_acknowledged_by_the_next_record(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = make_log(tmp_path)
    real_write = os.write
    with AuditLog(path) as log:
        def half_then_fail(fd: int, data: Any) -> int:
            real_write(fd, bytes(data[: len(data) // 2]))
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(os, "write", half_then_fail)
        with pytest.raises(AuditError, match="cannot append"):
            log.record("estop", "a", "accepted")
        monkeypatch.setattr(os, "write", real_write)
        assert not verify(path).ok
        log.record("estop", "a", "accepted")
        assert log.recovered is not None
    assert not verify(path).ok  # the half-written record stays evidence ...
    result = verify(path, accept_torn_tail=True)  # ... accepted only when asked
    assert result.ok and len(result.damaged) == 1 and len(result.accepted_torn) == 1


@pytest.mark.parametrize(
    "damage",
    [
        pytest.param(lambda ls: [*ls[:5], b"garbage\n"], id="complete bad last line"),
        pytest.param(lambda ls: [*ls[:4], b"garbage\n", b"torn"], id="two bad lines"),
        pytest.param(_replace_in(5, b'"user":"alice"', b'"user":"eve"'), id="edited last record"),
    ],
)
def test_damage_a_crash_cannot_leave_sets_the_log_aside(
    tmp_path: Path, damage: Callable[[list[bytes]], list[bytes]]
) -> None:
    path = make_log(tmp_path)
    damaged = b"".join(damage(lines_of(path)))
    path.write_bytes(damaged)
    with AuditLog(path, rig="bench", clock=clock()) as log:
        assert log.recovered is not None and "audit.damaged-" in log.recovered
        log.record("controller.start", "controller", "noted")
    kept = list(tmp_path.glob("audit.damaged-*.jsonl"))
    assert len(kept) == 1 and kept[0].read_bytes() == damaged
    first = json.loads(lines_of(path)[0])
    assert first["action"] == RECOVERED and first["prev"] == GENESIS and first["seq"] == 0
    assert first["moved_to"] == kept[0].name and first["moved_sha256"] == sha(damaged)
    result = verify(path)
    assert result.ok and result.records == 2 and kept[0].name in result.damaged[0]
    # The chain is fine, the directory is not: the set-aside log must be looked at.
    code, text = cli_verify(tmp_path)
    assert code == 1 and "NOT INTACT" in text and kept[0].name in text
    assert cli_verify(kept[0].parent / kept[0].name)[0] == 1


def test_an_empty_or_missing_log_starts_at_genesis(tmp_path: Path) -> None:
    path = tmp_path / "sub" / AUDIT_FILE
    with AuditLog(path) as log:
        assert log.head == (-1, GENESIS) and log.recovered is None
    assert verify(path) == audit_mod.VerifyResult(True, 0, None, "", GENESIS)


def test_tail_recovery_reads_long_files_from_the_end(tmp_path: Path) -> None:
    path = make_log(tmp_path, extra=300)  # longer than one tail block
    with open(path, "ab") as f:
        f.write(b'{"act')
    with AuditLog(path) as log:
        assert log.recovered is not None
        assert log.record("estop", "a", "accepted")["seq"] == 307
    assert verify(path, accept_torn_tail=True).ok


# -- the command -----------------------------------------------------------------------------


def test_show_prints_records_oldest_first(tmp_path: Path) -> None:
    make_log(tmp_path)
    code, text = cli_show(tmp_path)
    rows = text.splitlines()
    assert code == 0 and len(rows) == 6
    assert "alice" in rows[2] and "apply" in rows[2] and "accepted" in rows[2]
    assert "v3->v4" in rows[2] and 'verdict="accept"' in rows[2]
    assert 'reason="not the lease holder"' in rows[3]
    code, text = cli_show(tmp_path / AUDIT_FILE, tail=2)
    assert code == 0 and [r.split()[0] for r in text.splitlines()] == ["4", "5"]


def test_show_json_prints_the_stored_records(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    code, text = cli_show(tmp_path, as_json=True, tail=3)
    assert code == 0
    assert [json.loads(r) for r in text.splitlines()] == [json.loads(r)
                                                          for r in lines_of(path)[3:]]


@pytest.mark.parametrize("as_json", [False, True])
def test_missing_log_is_bad_input(tmp_path: Path, as_json: bool) -> None:
    for run in (cli_show, cli_verify):
        code, text = run(tmp_path / "nowhere", as_json=as_json)
        assert code == 2 and "no audit log" in text
    code, _ = cli_verify(tmp_path)  # a directory without a log
    assert code == 2


def test_command_is_registered_with_its_subcommands() -> None:
    cmd = controller_commands()["audit"]
    import argparse

    p = argparse.ArgumentParser()
    cmd.add_arguments(p)
    args = p.parse_args(["verify", "d", "--anchor", "ab"])
    assert (args.audit_command, args.dir, args.anchor) == ("verify", Path("d"), "ab")
    assert not args.accept_torn_tail
    assert p.parse_args(["verify", "d", "--accept-torn-tail"]).accept_torn_tail
    args = p.parse_args(["show", "d", "--json", "--tail", "5"])
    assert (args.audit_command, args.json, args.tail) == ("show", True, 5)
    with pytest.raises(SystemExit):
        p.parse_args(["show", "d", "--tail", "0"])


# -- the controller's writer: nothing dropped while the file cannot be written ---------------


def test_records_held_while_the_log_cannot_be_written_are_written_later_in_order(
    tmp_path: Path,
) -> None:
    """Issue 24 item 9: records dropped while the file could not be written were lost. Now
    they are held in order and retried; Status.notes (warn) says so, and when they are in."""
    from controller.process.access import Access

    path = tmp_path / AUDIT_FILE
    audit = AuditLog(path, rig="r")
    warnings: list[str] = []
    access = Access(None, "r", audit, lambda text, key=None: warnings.append(text))
    access.start()
    access.record("command", "a", "accepted", n=0)
    assert access.flush()
    # The log's descriptor now refuses writes (what a full or failing disk does): the records
    # pile up instead of being dropped.
    good = os.dup(audit._fd)
    bad = os.open(os.devnull, os.O_RDONLY)
    os.dup2(bad, audit._fd)
    for n in range(1, 6):
        access.record("command", "a", "accepted", n=n)
    assert not access.flush(0.5) and access.pending >= 5
    assert any("cannot be written" in w and "held in order" in w for w in warnings)
    assert len(lines_of(path)) == 1
    os.dup2(good, audit._fd)  # writable again
    os.close(bad)
    os.close(good)
    access.record("reset", "a", "accepted", n=6)
    assert access.flush(10.0)
    assert any("writable again" in w for w in warnings)
    access.close()
    recs = [json.loads(x) for x in lines_of(path)]
    assert [r["n"] for r in recs] == list(range(7))  # none lost, in order
    assert verify(path).ok


# -- e-stops repeated while latched: counted, not written one by one (issue 31 item 2) -------


def _ms_clock() -> Callable[[], float]:
    ticks = itertools.count()
    return lambda: T0 + next(ticks) * 0.001


def _key_estop(log: AuditLog, user: str = "public", client: str = "viewer-flood",
               session: str = "abc:1") -> dict[str, Any] | None:
    """An e-stop as the controller's e-stop subscriber records it (controller/process/node.py)."""
    return log.record("estop", user, "accepted", source="estop key", key="dobtune/r/estop",
                      claimed_client=client, claimed_session=session)


def test_an_estop_flood_while_latched_is_one_record_with_its_count(tmp_path: Path) -> None:
    """Before: every put on the e-stop key was a record of its own, fsynced (a viewer's 10 s
    flood: 155 000 records, 63 MB). Now: the first at once, the rest one count, written
    before the reset that ends the latch; the chain verifies."""
    path = tmp_path / AUDIT_FILE
    with AuditLog(path, rig="r", clock=_ms_clock()) as log:
        first = _key_estop(log)
        assert first is not None and first["action"] == "estop"
        assert len(lines_of(path)) == 1  # the real e-stop is on disk at once
        assert all(_key_estop(log) is None for _ in range(20_000))
        assert len(lines_of(path)) == 1
        log.record("reset", "op", "accepted", estop_seq=7)
        after = _key_estop(log)  # a new latch: written at once
        assert after is not None
    recs = [json.loads(x) for x in lines_of(path)]
    assert [r["action"] for r in recs] == ["estop", "estop.repeated", "reset", "estop"]
    rep = recs[1]
    assert (rep["count"], rep["latched_seq"], rep["by_user"]) == (20_000, 0, {"public": 20_000})
    assert rep["first_time"] < rep["last_time"] <= recs[2]["time"]
    assert len(path.read_bytes()) < 2_000
    assert verify(path).ok
    code, text = cli_verify(tmp_path)
    assert code == 0 and "chain intact, 4 records" in text


def test_repeated_estops_are_written_at_a_bounded_rate_while_they_go_on(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_FILE
    with AuditLog(path, rig="r", clock=_ms_clock(), repeat_interval_s=1.0) as log:
        _key_estop(log)
        for _ in range(10_000):  # 10 s of the log's clock
            _key_estop(log)
        written = [json.loads(x) for x in lines_of(path)]
    recs = [json.loads(x) for x in lines_of(path)]
    counts = [r["count"] for r in recs if r["action"] == "estop.repeated"]
    # One count a second while they go on (each with the e-stop that found the second over),
    # the rest at close: none lost, none counted twice.
    assert 9 <= len(counts) <= 11 and sum(counts) == 10_000
    assert len(written) == len(recs) - 1  # the last count was written by close
    assert verify(path).ok


def test_distinct_senders_are_written_up_to_a_bound_then_counted(tmp_path: Path) -> None:
    """While latched, the first e-stop of each sender (user, key, claims) is still written in
    full, up to ESTOP_SENDERS_MAX of them: a flood varying its claims stays bounded."""
    path = tmp_path / AUDIT_FILE
    with AuditLog(path, rig="r", clock=_ms_clock()) as log:
        _key_estop(log, "op", "dashboard")
        assert _key_estop(log, "view", "cli") is not None  # another user's: in full
        assert _key_estop(log, "view", "cli") is None  # the same again: counted
        for n in range(1000):
            _key_estop(log, "public", f"forged-{n}", session=f"s{n}")
        log.record("controller.stop", "controller", "noted")
    recs = [json.loads(x) for x in lines_of(path)]
    full = [r for r in recs if r["action"] == "estop"]
    assert len(full) == audit_mod.ESTOP_SENDERS_MAX
    assert [r["claimed_client"] for r in full[:3]] == ["dashboard", "cli", "forged-0"]
    (rep,) = [r for r in recs if r["action"] == "estop.repeated"]
    assert rep["count"] == 1 + 1000 - (audit_mod.ESTOP_SENDERS_MAX - 2)
    assert rep["by_user"] == {"view": 1, "public": 1000 - (audit_mod.ESTOP_SENDERS_MAX - 2)}
    assert recs[-1]["action"] == "controller.stop" and recs[-2] is rep
    assert verify(path).ok


def test_a_refused_reset_does_not_end_the_latch(tmp_path: Path) -> None:
    path = tmp_path / AUDIT_FILE
    with AuditLog(path, rig="r", clock=_ms_clock()) as log:
        _key_estop(log)
        log.record("reset", "view", "refused", reason="lease: view is a viewer")
        assert _key_estop(log) is None
    assert [json.loads(x)["action"] for x in lines_of(path)] == [
        "estop", "reset", "estop.repeated"]


def test_a_count_that_cannot_be_written_is_kept_and_written_later(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / AUDIT_FILE
    real_write = os.write
    with AuditLog(path, rig="r", clock=_ms_clock()) as log:
        _key_estop(log)
        for _ in range(5):
            _key_estop(log)

        def fail(fd: int, data: Any) -> int:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(os, "write", fail)
        with pytest.raises(AuditError):
            log.record("reset", "op", "accepted")
        monkeypatch.setattr(os, "write", real_write)
        log.record("reset", "op", "accepted")  # what the writer thread retries
    recs = [json.loads(x) for x in lines_of(path)]
    assert [r["action"] for r in recs] == ["estop", "estop.repeated", "reset"]
    assert recs[1]["count"] == 5
    assert verify(path).ok


def test_an_estop_flood_through_the_writer_thread_is_o1_records(tmp_path: Path) -> None:
    """The controller's path: the e-stop callback queues a record (Access.record) and the
    writer thread writes it. 50 000 e-stops, then the operator's reset: three records."""
    from controller.process.access import Access

    path = tmp_path / AUDIT_FILE
    access = Access(None, "r", AuditLog(path, rig="r"), lambda *a, **k: None)
    access.start()
    for _ in range(50_000):
        access.record("estop", "local", "accepted", source="estop key", key="dobtune/r/estop",
                      claimed_client="flood")
    access.record("reset", "local", "accepted", estop_seq=1)
    assert access.flush(60.0)
    access.close()
    recs = [json.loads(x) for x in lines_of(path)]
    assert [r["action"] for r in recs] == ["estop", "estop.repeated", "reset"]
    assert recs[1]["count"] == 49_999
    assert cli_verify(tmp_path)[0] == 0


# -- a lost log: deleted or replaced while running, missing or cut at restart (issue 31) -----


def test_a_log_deleted_while_running_is_noticed_and_continued(tmp_path: Path) -> None:
    """Before: the controller kept writing to the deleted file (its open descriptor) and
    nothing said so. Now `check_file` (the writer thread calls it every second) and every
    record notice it: a new file whose first record continues the chain and says why."""
    path = make_log(tmp_path)
    with AuditLog(path, rig="r", clock=clock()) as log:
        assert log.check_file() == ""
        old = path.read_bytes()
        path.unlink()
        found = log.check_file()
        assert "deleted while the controller ran" in found
        assert log.check_file() == ""  # once
        log.record("command", "op", "accepted")
    first, second = (json.loads(x) for x in lines_of(path))
    assert first["action"] == audit_mod.CONTINUED and first["outcome"] == "noted"
    assert first["seq"] == 6 and first["prev"] == sha(lines_of_bytes(old)[-1])
    assert first["lost_head"] == f"5:{json.loads(lines_of_bytes(old)[-1])['hash']}"
    assert second["seq"] == 7
    # Not intact on its own: the records before it are not in the file ...
    code, text = cli_verify(tmp_path)
    assert code == 1 and "line 1:" in text and "audit.continued" in text
    assert "--accept-lost" in text
    code, text = cli_verify(tmp_path, accept_lost=True)
    assert code == 0 and "ACCEPTED lost records" in text
    # ... and the lost file (had someone kept it) and the continuation are one chain.
    whole = tmp_path / "whole"
    whole.mkdir()
    (whole / AUDIT_FILE).write_bytes(old + path.read_bytes())
    assert verify(whole / AUDIT_FILE).ok


def test_a_log_deleted_while_running_is_noticed_by_the_idle_writer(tmp_path: Path) -> None:
    """Through the controller's writer thread, with no record coming: a Status note."""
    from controller.process.access import Access

    path = make_log(tmp_path)
    notes: list[str] = []
    access = Access(None, "r", AuditLog(path, rig="r"), lambda t, key=None: notes.append(t))
    access.start()
    try:
        path.unlink()
        deadline = threading.Event()
        for _ in range(200):
            if any("deleted while the controller ran" in n for n in notes):
                break
            deadline.wait(0.05)
        assert any("deleted while the controller ran" in n for n in notes), notes
        assert json.loads(lines_of(path)[0])["action"] == audit_mod.CONTINUED
    finally:
        access.close()


def test_a_log_replaced_while_running_is_kept_aside_and_continued(tmp_path: Path) -> None:
    path = make_log(tmp_path)
    forged_dir = tmp_path / "forged"
    forged_dir.mkdir()
    forged = make_log(forged_dir)  # a valid chain of someone else's
    with AuditLog(path, rig="r", clock=clock()) as log:
        os.replace(forged, path)
        rec = log.record("apply", "op", "accepted")
        assert rec is not None and rec["seq"] == 7
        assert log.recovered is not None and "replaced" in log.recovered
    aside = list(tmp_path.glob("audit.damaged-*.jsonl"))
    assert len(aside) == 1 and verify(aside[0]).ok  # the replacement, kept
    assert json.loads(lines_of(path)[0])["moved_to"] == aside[0].name
    code, text = cli_verify(tmp_path, accept_lost=True)
    assert code == 1 and "NOT INTACT" in text and aside[0].name in text


def lines_of_bytes(data: bytes) -> list[bytes]:
    return data.splitlines()


def test_a_log_deleted_while_stopped_is_not_a_new_intact_chain(tmp_path: Path) -> None:
    """Before: after a restart the controller started a new chain that `verify` called intact.
    Now the head file says there was history: the new log continues it and says so."""
    path = make_log(tmp_path)
    head = verify(path).head
    path.unlink()
    with AuditLog(path, rig="r") as log:
        assert log.recovered is not None and "missing" in log.recovered
        log.record("controller.start", "controller", "noted")
    first = json.loads(lines_of(path)[0])
    assert first["action"] == audit_mod.CONTINUED and first["lost_head"] == f"5:{head}"
    code, text = cli_verify(tmp_path)
    assert code == 1 and "6 record(s) before it are not in this file" in text


@pytest.mark.parametrize("cut", [1, 3])
def test_a_log_behind_its_head_file_is_kept_aside_and_continued(tmp_path: Path, cut: int) -> None:
    """Records cut off the end while stopped (a shorter chain still verifies on its own)."""
    path = make_log(tmp_path)
    path.write_bytes(b"".join(lines_of(path)[:-cut]))
    assert verify(path).ok
    with AuditLog(path, rig="r") as log:
        assert log.recovered is not None
        assert "does not reach the head file's record" in log.recovered
    assert len(list(tmp_path.glob("audit.damaged-*.jsonl"))) == 1
    assert cli_verify(tmp_path)[0] == 1


def test_a_head_file_older_than_the_log_is_a_crash_not_a_loss(tmp_path: Path) -> None:
    """The head file is written after the record: a crash between leaves it one behind."""
    path = make_log(tmp_path)
    lines = lines_of(path)
    rec4 = json.loads(lines[4])
    (tmp_path / audit_mod.HEAD_FILE).write_text(json.dumps(
        {"seq": 4, "hash": rec4["hash"], "line_sha256": sha(lines[4].rstrip(b"\n"))}))
    with AuditLog(path, rig="r") as log:
        assert log.recovered is None
        assert log.record("command", "op", "accepted")["seq"] == 6  # type: ignore[index]
    assert cli_verify(tmp_path)[0] == 0
    assert json.loads((tmp_path / audit_mod.HEAD_FILE).read_text())["seq"] == 6


def test_a_continuation_that_cannot_be_opened_is_retried(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = make_log(tmp_path)
    real_open = os.open
    with AuditLog(path, rig="r") as log:
        path.unlink()

        def refuse(*args: Any, **kwargs: Any) -> int:
            raise OSError(24, "Too many open files")

        monkeypatch.setattr(os, "open", refuse)
        with pytest.raises(AuditError, match="cannot open"):
            log.record("command", "op", "accepted", n=1)
        monkeypatch.setattr(os, "open", real_open)
        log.record("command", "op", "accepted", n=2)
    recs = [json.loads(x) for x in lines_of(path)]
    assert [(r["action"], r["seq"]) for r in recs] == [(audit_mod.CONTINUED, 6), ("command", 7)]
    assert recs[1]["n"] == 2
    assert verify(path, accept_lost=True).ok
