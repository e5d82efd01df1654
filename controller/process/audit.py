"""The audit trail: every action the controller accepted or refused, as a hash chain on disk.

`<state-dir>/audit.jsonl` holds one JSON object per line in canonical form (msgspec, keys
sorted, no spaces), appended and fsynced one record at a time:

- `seq` (0, 1, 2 ... along the file), `time` (UTC ISO 8601), `rig`, `action`, `user`,
  `outcome`, `version_before` / `version_after` (active configuration versions, null when
  unknown), then the action's own fields (verdict, margins, reason ...);
- `prev`: hex SHA-256 of the previous line's bytes (the previous record's canonical bytes,
  its `hash` included); the first record's `prev` is `GENESIS`;
- `hash`: hex SHA-256 of this record's canonical bytes without `hash`.

What the chain shows: an edited field, a deleted, inserted or moved line, a truncated hash
breaks it at the first altered line. It holds no secret: whoever can write the file can
recompute the whole chain, and cutting lines off the end leaves a shorter valid chain. Both
are caught against an anchor kept elsewhere (a record's `hash` published or noted earlier:
`verify(path, anchor=...)`).

Crash policy, applied when the log is opened (only the end of the file is read):
- last line complete and consistent: the chain continues from it (a missing final newline is
  added: the record itself was complete);
- last line torn (no final newline, not a record) and the line before it fine (or no line
  before it): what a crash during a write leaves. The damaged bytes stay in the file,
  terminated by a newline, and an `audit.recovered` record follows that names them (length,
  SHA-256, the seq they follow) and chains from the last good record. The acknowledgement
  does not make the damage go away: a torn tail is also what erasing the last record leaves,
  so `verify` reports every torn line (acknowledged or not) as not intact unless the reader
  accepts torn tails explicitly (`accept_torn_tail`, `dobtune audit verify
  --accept-torn-tail`), and then lists what it accepted;
- anything else (a complete last line that is not a consistent record, or two bad lines: not
  what a crash leaves): the file is kept under a new name `audit.damaged-<UTC>.jsonl` and a
  new chain starts whose first record names it; `dobtune audit verify` fails while such a file
  sits next to the log.
Nothing is silently chained over. `AuditLog.recovered` says what was found (for the logs and
the Status notes).

A lost log (issue 31): the head (seq, hash, SHA-256 of the last line) is kept beside the log in
`audit.head.json`, rewritten after every record. A log deleted or replaced while the controller
runs is noticed at the next record or `check_file()` (the process calls it every second): a
replacement is kept as `audit.damaged-<UTC>.jsonl`, and a new file starts with an
`audit.continued` record that continues the chain (its seq and `prev` follow the lost head, so
the lost file and the new one, concatenated, verify) and says why. At start, a log that is
missing, behind the head file or different from it (truncated, deleted, replaced while the
controller was stopped) is treated the same way (a log deleted with its head file is not
told from a new state directory: anchor the log elsewhere, `verify --anchor`). `verify`
reports a file that begins with `audit.continued` as not intact (records before it are not in
the file) unless `accept_lost` (`--accept-lost`), which lists it.

Repeated e-stops (issue 31: ten seconds of a viewer's puts on the e-stop key made 155 000
records, 63 MB, each fsynced, 40 s of backlog in front of real actions): an accepted e-stop
opens a latch, in the log's view, that an accepted `reset` (or the controller's start or stop)
closes. The first e-stop is written at once, as is the first of each of up to
ESTOP_SENDERS_MAX distinct senders (user, key and claims: `ESTOP_SENDER_FIELDS`) while it is
latched; every other e-stop while latched is counted, and the count is written as one
`estop.repeated` record (`count`, `first_time`, `last_time`, `by_user`, `latched_seq`: the
e-stop it repeats) before the record that closes the latch, at close, and at most every
`repeat_interval_s` while they go on (with the e-stop that finds the interval over). A crash
loses the count since the last such record, never an e-stop that changed anything: the loop
was already stopped and latched by the recorded one.

Thread-safe (one lock). A record is a write plus an fsync: never call `record` on the loop's
tick; the process queues actions and records them from another thread.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

import msgspec

__all__ = [
    "ACTIONS",
    "AUDIT_FILE",
    "CONTINUED",
    "CORE_KEYS",
    "ESTOP_REPEATED",
    "ESTOP_SENDERS_MAX",
    "ESTOP_SENDER_FIELDS",
    "GENESIS",
    "HEAD_FILE",
    "OUTCOMES",
    "RECOVERED",
    "AuditError",
    "AuditLog",
    "VerifyResult",
    "audit_path",
    "iter_lines",
    "parse_anchor",
    "parse_record",
    "verify",
]

log = logging.getLogger(__name__)

AUDIT_FILE = "audit.jsonl"
#: The head of the chain, kept beside the log (see "A lost log" above).
HEAD_FILE = "audit.head.json"
#: The first record of a log that continues a lost one.
CONTINUED = "audit.continued"
#: `prev` of the first record of a chain.
GENESIS = "0" * 64
#: The record written after damage found on open.
RECOVERED = "audit.recovered"
#: The count of e-stops repeated while latched (see the module's docstring).
ESTOP_REPEATED = "estop.repeated"
#: While latched, the first e-stop of this many distinct senders is written in full.
ESTOP_SENDERS_MAX = 8
#: The fields (beside `user`) that tell one e-stop's sender from another's.
ESTOP_SENDER_FIELDS = ("source", "key", "claimed_client", "claimed_session", "command")
#: `by_user` of an `estop.repeated` record names at most this many users ("..." the rest).
_BY_USER_MAX = 32

#: What can be recorded (a typo is an error, not a new kind of record).
ACTIONS = frozenset({
    "apply",             # a configuration candidate: verdict, margins, versions
    "command",           # start / stop / trajectory ...
    "estop",
    "reset",
    "lease.acquire",
    "lease.renew",
    "lease.release",
    "lease.takeover",
    "lease.expire",
    "identify",          # identification started, finished, cancelled
    "knowledge",         # plant knowledge adopted or changed
    "rollback",          # watchdog or operator rollback to an earlier configuration
    "fault",
    "controller.start",
    "controller.stop",
    "request.budget",    # requests over a user's budget, refused by the edge (a count)
    ESTOP_REPEATED,      # e-stops repeated while latched (a count)
    CONTINUED,           # the log continues one that was lost (deleted, truncated, replaced)
    RECOVERED,
})
#: accepted / refused: a request's fate; failed: accepted but could not be carried out;
#: noted: something that happened without a request (fault, expiry, recovery).
OUTCOMES = ("accepted", "refused", "failed", "noted")
#: Keys every record has; `record(**fields)` may not use them.
CORE_KEYS = (
    "seq", "time", "rig", "action", "user", "outcome", "version_before", "version_after",
    "prev", "hash",
)



def _enc_hook(obj: Any) -> Any:
    """numpy scalars and arrays (margins, responses) as plain numbers and lists."""
    tolist = getattr(obj, "tolist", None)
    if callable(tolist):
        return tolist()
    raise TypeError(f"cannot record a {type(obj).__name__} in the audit log")


_encoder = msgspec.json.Encoder(order="sorted", enc_hook=_enc_hook)
_HEX64 = re.compile(r"[0-9a-f]{64}")
_TAIL_BLOCK = 8192


class AuditError(RuntimeError):
    """The audit log cannot be opened or written."""


def audit_path(state_dir: str | os.PathLike[str]) -> Path:
    """The audit log of a state directory."""
    return Path(state_dir) / AUDIT_FILE


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _record_hash(record: Mapping[str, Any]) -> str:
    return _sha256(_encoder.encode({k: v for k, v in record.items() if k != "hash"}))


def _utc_iso(time_s: float) -> str:
    return datetime.fromtimestamp(time_s, UTC).isoformat(timespec="microseconds")[:-6] + "Z"


_TYPES: dict[str, tuple[type, ...]] = {
    "seq": (int,), "time": (str,), "rig": (str,), "action": (str,), "user": (str,),
    "outcome": (str,), "version_before": (int, type(None)), "version_after": (int, type(None)),
    "prev": (str,), "hash": (str,),
}


def parse_record(line: bytes) -> tuple[dict[str, Any] | None, str]:
    """(record, "") when `line` (no newline) is a self-consistent record, else (None, why).

    Checks the form and the record's own hash, not its place in the chain."""
    try:
        rec = msgspec.json.decode(line)
    except msgspec.DecodeError:
        return None, "not JSON (torn or edited line)"
    if not isinstance(rec, dict):
        return None, "not a JSON object"
    for key, types in _TYPES.items():
        value = rec.get(key, ...)
        if value is ... or isinstance(value, bool) or not isinstance(value, types):
            return None, f"field {key!r} missing or of the wrong type"
    if _encoder.encode(rec) != line:
        return None, "not in canonical form (edited by hand?)"
    if not _HEX64.fullmatch(rec["hash"]):
        return None, "hash is not 64 hex digits (truncated or edited)"
    if _record_hash(rec) != rec["hash"]:
        return None, "hash does not match the record (a field was edited)"
    return rec, ""


def iter_lines(path: Path) -> Iterator[tuple[int, bytes, bool]]:
    """(line number from 1, bytes without the newline, whether it ended with a newline)."""
    with open(path, "rb") as f:
        for n, raw in enumerate(f, start=1):
            complete = raw.endswith(b"\n")
            yield n, raw[:-1] if complete else raw, complete


# -- verification ----------------------------------------------------------------------------


@dataclass(frozen=True)
class VerifyResult:
    """What `verify` found."""

    ok: bool
    #: records that verified (before the first bad line, if any)
    records: int
    #: first bad line (from 1); None when ok, or when only the anchor is missing
    bad_line: int | None
    #: why the log is not intact ("" when ok)
    reason: str
    #: `hash` of the last verified record (GENESIS if none)
    head: str
    #: crash damage the controller found and acknowledged in the log, human-readable
    damaged: tuple[str, ...] = ()
    #: torn lines accepted (with `accept_torn_tail`), human-readable
    accepted_torn: tuple[str, ...] = ()
    #: records lost before an `audit.continued` record, accepted (with `accept_lost`)
    accepted_lost: tuple[str, ...] = ()


@dataclass
class _Chain:
    """Where the chain stands while reading a file."""

    prev: str = GENESIS
    seq: int = 0
    records: int = 0
    head: str = GENESIS

    def link_error(self, rec: Mapping[str, Any]) -> str:
        if rec["prev"] != self.prev:
            where = "the genesis value" if self.prev == GENESIS else "the line before"
            return f"prev does not chain to {where} (a line deleted, inserted or moved)"
        if rec["seq"] != self.seq:
            return f"seq {rec['seq']}, expected {self.seq} (a line deleted, inserted or moved)"
        return ""

    def advance(self, line: bytes, rec: Mapping[str, Any]) -> None:
        self.prev, self.seq, self.head = _sha256(line), rec["seq"] + 1, rec["hash"]
        self.records += 1


def _acknowledges(rec: Mapping[str, Any], damaged: bytes, after_seq: int) -> bool:
    return (
        rec["action"] == RECOVERED
        and rec.get("damaged_after_seq") == after_seq
        and rec.get("damaged_bytes") == len(damaged)
        and rec.get("damaged_sha256") == _sha256(damaged)
    )


def parse_anchor(anchor: str) -> tuple[int | None, str]:
    """(seq or None, hash) of an anchor: `<seq>:<sha256>` (the form of `Status.audit_head`
    and `AuditLog.head`) or a bare `<sha256>`. ValueError naming the form if it is neither."""
    text = anchor.strip().lower()
    seq_text, sep, digest = text.rpartition(":")
    seq: int | None = None
    if sep:
        if not seq_text.isdigit():
            raise ValueError(f"anchor {anchor!r}: expected <seq>:<sha256> or <sha256> "
                             f"(seq a non-negative integer)")
        seq = int(seq_text)
    if not _HEX64.fullmatch(digest):
        raise ValueError(f"anchor {anchor!r}: expected <seq>:<sha256> or <sha256> "
                         f"(sha256 as 64 hex digits)")
    return seq, digest


def _lost(rec: Mapping[str, Any]) -> str:
    return (f"the log begins with {CONTINUED} at seq {rec['seq']} ({rec['time']}): the "
            f"{rec['seq']} record(s) before it are not in this file (lost head "
            f"{rec.get('lost_head') or 'unknown'}: {rec.get('why', '')})")


def verify(
    path: str | os.PathLike[str],
    anchor: str | None = None,
    *,
    accept_torn_tail: bool = False,
    accept_lost: bool = False,
) -> VerifyResult:
    """Check the whole chain of the audit log at `path` (a file).

    `anchor`: a record known from elsewhere that must be in the chain (detects lines cut off
    the end, or a rewritten chain): `<seq>:<sha256>` (`Status.audit_head`: the record with that
    seq must have that hash) or a bare record `hash` (see `parse_anchor`; ValueError if it is
    neither). A torn line (acknowledged by the controller or the
    unterminated last line) is evidence, not intact: it fails the check unless
    `accept_torn_tail`, and is then listed in `accepted_torn`. A file that begins with
    `audit.continued` (the records before it lost) fails unless `accept_lost` (then listed in
    `accepted_lost`). OSError if the file cannot be read."""
    chain = _Chain()
    notes: list[str] = []
    accepted: list[str] = []
    pending: tuple[int, bytes, str, bool] | None = None  # a bad line: acknowledged next?
    anchor_seq, anchor_hash = parse_anchor(anchor) if anchor is not None else (None, "")
    anchor_seen = anchor is None
    lost: list[str] = []

    def bad(line_no: int, why: str) -> VerifyResult:
        return VerifyResult(False, chain.records, line_no, why, chain.head, tuple(notes),
                            tuple(accepted), tuple(lost))

    for n, line, complete in iter_lines(Path(path)):
        rec, why = parse_record(line)
        if pending is not None:
            bad_no, bad_bytes, bad_why, _ = pending
            if rec is None or not _acknowledges(rec, bad_bytes, chain.seq - 1):
                return bad(bad_no, bad_why)
            torn = (
                f"line {bad_no}: {len(bad_bytes)} damaged bytes after seq {chain.seq - 1}, "
                f"acknowledged by the controller at {rec['time']}"
            )
            if not accept_torn_tail:
                return bad(bad_no, f"torn tail: {len(bad_bytes)} damaged bytes after seq "
                           f"{chain.seq - 1} (acknowledged by the controller at {rec['time']}): "
                           "a crash while writing, or the last record erased; check against "
                           "an anchor, then accept it explicitly (--accept-torn-tail)")
            notes.append(torn)
            accepted.append(torn)
            pending = None
        elif rec is None:
            pending = (n, line, why, complete)
            continue
        elif rec["action"] == RECOVERED and "damaged_after_seq" in rec:
            return bad(n, "acknowledges a damaged line that is not there")
        if rec["action"] == CONTINUED and n == 1:
            if not accept_lost:
                return bad(1, _lost(rec) + "; accept it explicitly (--accept-lost)")
            lost.append(f"line 1: {_lost(rec)}")
            chain.prev, chain.seq = rec["prev"], rec["seq"]
        link = chain.link_error(rec)
        if link:
            return bad(n, link)
        if rec["action"] == RECOVERED and "moved_to" in rec:
            notes.append(f"line {n}: the earlier log was damaged, kept as {rec['moved_to']}")
        if not complete:
            notes.append(f"line {n}: last record complete but without its final newline")
        chain.advance(line, rec)
        anchor_seen = anchor_seen or (
            rec["hash"] == anchor_hash and anchor_seq in (None, rec["seq"])
        )
    if pending is not None:
        bad_no, bad_bytes, bad_why, complete = pending
        if complete or not accept_torn_tail:
            return bad(bad_no, bad_why + "; unacknowledged (a crash while writing, or the "
                       "last record erased; the controller notes a torn last line when it next "
                       "starts)")
        accepted.append(f"line {bad_no}: torn last line, {len(bad_bytes)} bytes after seq "
                        f"{chain.seq - 1}, unacknowledged")
    if not anchor_seen:
        return VerifyResult(
            False, chain.records, None,
            f"anchor {anchor} is not in the chain (lines cut off the end, or a rewritten log)",
            chain.head, tuple(notes), tuple(accepted), tuple(lost),
        )
    return VerifyResult(True, chain.records, None, "", chain.head, tuple(notes), tuple(accepted),
                        tuple(lost))


# -- writing ---------------------------------------------------------------------------------


def _read_tail(f: BinaryIO, size: int) -> tuple[list[bytes], bool]:
    """The file's last two lines (fewer if it has fewer), newest last, without newlines, and
    whether the file ends with a newline."""
    data = b""
    pos = size
    while pos > 0:
        step = min(_TAIL_BLOCK, pos)
        pos -= step
        f.seek(pos)
        data = f.read(step) + data
        if data.count(b"\n") >= 3:  # two complete lines after a (maybe partial) first piece
            break
    ends_nl = data.endswith(b"\n")
    parts = (data[:-1] if ends_nl else data).split(b"\n")
    if pos > 0:
        parts = parts[1:]
    return parts[-2:], ends_nl


@dataclass
class _Repeats:
    """E-stops counted while latched, not yet written."""

    count: int = 0
    first_s: float = 0.0
    last_s: float = 0.0
    by_user: dict[str, int] = field(default_factory=dict)

    def add(self, user: str, now_s: float, n: int = 1) -> None:
        if not self.count:
            self.first_s = now_s
        self.count += n
        self.last_s = now_s
        if user in self.by_user or len(self.by_user) < _BY_USER_MAX:
            self.by_user[user] = self.by_user.get(user, 0) + n
        else:
            self.by_user["..."] = self.by_user.get("...", 0) + n


def _sender(user: str, fields: Mapping[str, Any]) -> tuple[str, ...]:
    return (user, *(str(fields.get(k, "")) for k in ESTOP_SENDER_FIELDS))


class AuditLog:
    """The controller's audit log (append-only, fsynced, hash-chained, thread-safe)."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        rig: str = "",
        clock: Callable[[], float] | None = None,
        repeat_interval_s: float = 60.0,
    ) -> None:
        """Open (or create) the log at `path` and recover the chain's tail (see the module's
        crash policy); `clock` returns UNIX seconds (default `time.time`);
        `repeat_interval_s`: the longest time e-stops repeated while latched go unwritten
        while they go on."""
        self.path = Path(path)
        self.rig = rig
        self._clock = clock if clock is not None else time.time
        self.repeat_interval_s = repeat_interval_s
        #: seq of the e-stop record that latched (None: not latched in the log's view)
        self._latched_seq: int | None = None
        self._senders: set[tuple[str, ...]] = set()
        self._repeats = _Repeats()
        self._lock = threading.Lock()
        self._fd = -1
        self._prev = GENESIS
        self._seq = 0
        self._head = GENESIS
        #: what the open (or a failed write) found and did; None when the tail was intact
        self.recovered: str | None = None
        self._suspect = False
        self._head_path = self.path.with_name(HEAD_FILE)
        self._inode = (0, 0)
        self._new_segment = False
        #: a continuation not yet written (why, lost head): retried by the next call
        self._reopen: tuple[str, tuple[int, str, str] | None] | None = None
        with self._lock:
            head = self._read_head()  # before the open writes it
            self._open()
            self._check_head(head)

    # -- public ------------------------------------------------------------------------------

    @property
    def head(self) -> tuple[int, str]:
        """(seq, hash) of the newest record; (-1, GENESIS) for an empty log. Publish it to
        anchor the log (see `verify`)."""
        with self._lock:
            return self._seq - 1, self._head

    def record(
        self,
        action: str,
        user: str,
        outcome: str,
        *,
        version_before: int | None = None,
        version_after: int | None = None,
        **fields: Any,
    ) -> dict[str, Any] | None:
        """Append one record and fsync it; return it as stored (non-finite floats are null),
        or None for an e-stop repeated while latched, counted instead (module docstring).

        ValueError for an unknown action or outcome or a reserved field name; AuditError if the
        file cannot be written (the next call checks the tail again before writing; nothing
        of this call was recorded or counted)."""
        if action not in ACTIONS:
            raise ValueError(f"unknown audit action {action!r}")
        if outcome not in OUTCOMES:
            raise ValueError(f"outcome must be one of {OUTCOMES}, got {outcome!r}")
        reserved = sorted(set(fields) & set(CORE_KEYS))
        if reserved:
            raise ValueError(f"reserved audit field names: {reserved}")
        if not isinstance(user, str):
            raise ValueError(f"user must be a str, got {user!r}")
        for v in (version_before, version_after):
            if v is not None and (isinstance(v, bool) or not isinstance(v, int)):
                raise ValueError(f"config versions are ints or None, got {v!r}")
        with self._lock:
            if self._reopen is not None:
                self._continue(*self._reopen)
            if self._fd < 0:
                raise AuditError(f"{self.path}: closed")
            self._check_file()
            if self._suspect:
                self._recover_tail()
            body = {
                **fields,
                "action": action,
                "user": user,
                "outcome": outcome,
                "version_before": version_before,
                "version_after": version_after,
            }
            if action == "estop" and outcome == "accepted":
                return self._estop(body, _sender(user, fields))
            if (action == "reset" and outcome == "accepted") or action in (
                "controller.start", "controller.stop"
            ):
                self._write_repeats()
                rec = self._append(body)
                self._latched_seq, self._senders = None, set()
                return rec
            return self._append(body)

    def check_file(self) -> str:
        """Whether the log on disk is still the file being written: "" if so; else it was
        deleted or replaced, and the log is reopened as a continuation (module docstring);
        returns what was found and done. AuditError if that cannot be written."""
        with self._lock:
            if self._reopen is not None:
                self._continue(*self._reopen)
                assert self.recovered is not None
                return self.recovered
            if self._fd < 0:
                return ""
            return self._check_file()

    def close(self) -> None:
        """Write the count of repeated e-stops if any (AuditError if it cannot), then close."""
        with self._lock:
            self._reopen = None
            try:
                if self._fd >= 0 and self._repeats.count:
                    self._write_repeats()
            finally:
                if self._fd >= 0:
                    os.close(self._fd)
                    self._fd = -1

    def __enter__(self) -> AuditLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals (called with the lock held) -----------------------------------------------

    def _write_head(self) -> None:
        """Keep the head beside the log (rename, no fsync: after a crash it may be older than
        the log, never newer). A failure is logged, not raised: the record is written."""
        data = _encoder.encode(
            {"seq": self._seq - 1, "hash": self._head, "line_sha256": self._prev}
        )
        tmp = self._head_path.with_name(f".{HEAD_FILE}.tmp")
        try:
            tmp.write_bytes(data)
            os.replace(tmp, self._head_path)
        except OSError as exc:
            log.warning("audit log: the head file %s cannot be written: %s", self._head_path, exc)

    def _read_head(self) -> tuple[int, str, str] | None:
        """(seq, hash, line_sha256) of the head file; None if there is none. An unreadable one
        is logged and taken as none."""
        try:
            data = msgspec.json.decode(self._head_path.read_bytes())
            seq, digest, line_sha = data["seq"], data["hash"], data["line_sha256"]
            if not (isinstance(seq, int) and isinstance(digest, str)
                    and isinstance(line_sha, str)):
                raise ValueError("fields of the wrong type")
            return seq, digest, line_sha
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("audit log: the head file %s is unreadable (%s): ignored",
                        self._head_path, exc)
            return None

    def _check_head(self, head: tuple[int, str, str] | None) -> None:
        """At open: the log against the head file as it was."""
        if self._new_segment:
            return  # damage found: the log was set aside and a new chain starts, saying so
        last = self._seq - 1
        if head is None:  # a new state directory, or a log from before the head file
            self._write_head()
            return
        seq, digest, line_sha = head
        if last > seq or (last == seq and self._head == digest):
            self._write_head()  # intact (a head older than the log: a crash between the two)
            return
        if last < 0:
            why = (f"the audit log is missing (deleted while the controller was stopped?); "
                   f"the head file says seq {seq}")
        else:
            why = (f"the audit log does not reach the head file's record (seq {seq}); it ends "
                   f"at seq {last} (truncated, its last record erased, or replaced while the "
                   f"controller was stopped?)")
        self._continue(why, lost=(seq, digest, line_sha))

    def _check_file(self) -> str:
        """The log on disk is the file being written ("") or it was deleted or replaced: then
        continue in a new file (and say what was done)."""
        try:
            st = os.stat(self.path)
            if (st.st_dev, st.st_ino) == self._inode:
                return ""
            why = "the audit log was replaced while the controller ran"
        except FileNotFoundError:
            why = "the audit log was deleted while the controller ran"
        except OSError as exc:
            raise AuditError(f"{self.path}: cannot stat: {exc}") from exc
        self._continue(why, lost=(self._seq - 1, self._head, self._prev))
        assert self.recovered is not None
        return self.recovered

    def _continue(self, why: str, lost: tuple[int, str, str] | None) -> None:
        """A new log file whose first record continues the lost head `lost` (seq, hash, last
        line's SHA-256; None: unknown, the chain restarts at seq 0) and says `why`. A file
        found at the path is kept aside first."""
        moved = ""
        self._reopen = (why, lost)
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        if self.path.exists():
            stamp = datetime.fromtimestamp(self._clock(), UTC).strftime("%Y%m%dT%H%M%SZ")
            aside = self.path.with_name(f"audit.damaged-{stamp}.jsonl")
            k = 1
            while aside.exists():
                k += 1
                aside = self.path.with_name(f"audit.damaged-{stamp}-{k}.jsonl")
            try:
                os.replace(self.path, aside)
            except OSError as exc:
                raise AuditError(f"{self.path}: cannot set the log found aside: {exc}") from exc
            moved = aside.name
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_EXCL,
                               0o644)
            st = os.fstat(self._fd)
        except OSError as exc:
            raise AuditError(f"{self.path}: cannot open: {exc}") from exc
        self._inode = (st.st_dev, st.st_ino)
        if lost is None:
            self._prev, self._seq, self._head = GENESIS, 0, GENESIS
        else:
            self._prev, self._seq, self._head = lost[2], lost[0] + 1, lost[1]
        lost_head = "" if lost is None else f"{lost[0]}:{lost[1]}"
        self.recovered = (f"{why}; the log continues in a new file from "
                          f"{lost_head or 'an unknown head'}"
                          + (f", the file found there kept as {moved}" if moved else ""))
        log.warning("audit log: %s", self.recovered)
        fields: dict[str, Any] = {"why": why, "lost_head": lost_head}
        if moved:
            fields["moved_to"] = moved
        self._append({
            **fields, "action": CONTINUED, "user": "controller", "outcome": "noted",
            "version_before": None, "version_after": None,
        })
        self._reopen = None

    def _estop(self, body: dict[str, Any], sender: tuple[str, ...]) -> dict[str, Any] | None:
        """An accepted e-stop: written when it latches or is a new sender's (of the first
        ESTOP_SENDERS_MAX), else counted; the count written when it is repeat_interval_s old.
        `repeats` (a field, from the controller's own code): that many more e-stops of the
        same sender, coalesced before they reached the log, counted as repeats."""
        repeats = body.pop("repeats", 0)
        rec = self._estop_one(body, sender)
        if isinstance(repeats, int) and repeats > 0:
            self._repeats.add(body["user"], self._clock(), repeats)
        return rec

    def _estop_one(self, body: dict[str, Any], sender: tuple[str, ...]) -> dict[str, Any] | None:
        if self._latched_seq is None or (
            sender not in self._senders and len(self._senders) < ESTOP_SENDERS_MAX
        ):
            rec = self._append(body)
            if self._latched_seq is None:
                self._latched_seq = rec["seq"]
            self._senders.add(sender)
            return rec
        now = self._clock()
        if self._repeats.count and now - self._repeats.first_s >= self.repeat_interval_s:
            self._write_repeats((body["user"], now))  # this one included; raises: not counted
        else:
            self._repeats.add(body["user"], now)
        return None

    def _write_repeats(self, extra: tuple[str, float] | None = None) -> None:
        """Write the counted e-stops (and `extra`) as one record; the count restarts only once
        it is written."""
        counted = _Repeats(self._repeats.count, self._repeats.first_s, self._repeats.last_s,
                           dict(self._repeats.by_user))
        if extra is not None:
            counted.add(*extra)
        if not counted.count:
            return
        self._append({
            "action": ESTOP_REPEATED, "user": "controller", "outcome": "noted",
            "version_before": None, "version_after": None,
            "count": counted.count, "first_time": _utc_iso(counted.first_s),
            "last_time": _utc_iso(counted.last_s), "by_user": counted.by_user,
            "latched_seq": self._latched_seq,
            "note": f"{counted.count} e-stop(s) while latched by the e-stop at seq "
                    f"{self._latched_seq}, counted, not written one by one",
        })
        self._repeats = _Repeats()

    def _open(self) -> None:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            st = os.fstat(self._fd)
        except OSError as exc:
            raise AuditError(f"{self.path}: cannot open: {exc}") from exc
        self._inode = (st.st_dev, st.st_ino)
        self._recover_tail()

    def _recover_tail(self) -> None:
        self._suspect = False
        try:
            with open(self.path, "rb") as f:
                size = os.fstat(f.fileno()).st_size
                lines, ends_nl = _read_tail(f, size) if size else ([], True)
        except OSError as exc:
            raise AuditError(f"{self.path}: cannot read: {exc}") from exc
        self._prev, self._seq, self._head = GENESIS, 0, GENESIS
        if not lines:
            return
        last = lines[-1]
        rec, why = parse_record(last)
        if rec is not None:
            if not ends_nl:
                self._write(b"\n")
            self._prev, self._seq, self._head = _sha256(last), rec["seq"] + 1, rec["hash"]
            return
        before = parse_record(lines[0])[0] if len(lines) == 2 else None
        if ends_nl or (len(lines) == 2 and before is None):
            # Not what a crash leaves: it tears the final write, whose last byte is the newline.
            self._start_new_segment(why)
            return
        if before is not None:
            self._prev, self._seq, self._head = _sha256(lines[0]), before["seq"] + 1, before["hash"]
        self._write(b"\n")
        self.recovered = (
            f"{self.path}: the last line ({len(last)} bytes) is torn ({why}); kept and "
            f"acknowledged, the chain continues from seq {self._seq - 1}"
        )
        log.warning("audit log: %s", self.recovered)
        self._append_recovered(
            damaged_after_seq=self._seq - 1,
            damaged_bytes=len(last),
            damaged_sha256=_sha256(last),
            note=why,
        )

    def _start_new_segment(self, why: str) -> None:
        stamp = datetime.fromtimestamp(self._clock(), UTC).strftime("%Y%m%dT%H%M%SZ")
        moved = self.path.with_name(f"audit.damaged-{stamp}.jsonl")
        k = 1
        while moved.exists():
            k += 1
            moved = self.path.with_name(f"audit.damaged-{stamp}-{k}.jsonl")
        os.close(self._fd)
        self._fd = -1
        try:
            digest = _sha256(self.path.read_bytes())
            os.replace(self.path, moved)
        except OSError as exc:
            raise AuditError(f"{self.path}: cannot set the damaged log aside: {exc}") from exc
        self._open()  # a new, empty file: the chain starts at GENESIS
        self._new_segment = True
        self.recovered = (
            f"{self.path}: the end of the log is not what a crash leaves ({why}); the log is "
            f"kept as {moved.name} and a new chain starts"
        )
        log.warning("audit log: %s", self.recovered)
        self._append_recovered(moved_to=moved.name, moved_sha256=digest, note=why)

    def _append_recovered(self, **fields: Any) -> None:
        self._append({
            **fields, "action": RECOVERED, "user": "controller", "outcome": "noted",
            "version_before": None, "version_after": None,
        })

    def _append(self, body: dict[str, Any]) -> dict[str, Any]:
        body.update(
            seq=self._seq, time=_utc_iso(self._clock()), rig=self.rig, prev=self._prev
        )
        # Round trip first, so the hash covers exactly what a reader decodes (inf -> null,
        # tuples -> lists, structs -> objects).
        rec: dict[str, Any] = msgspec.json.decode(_encoder.encode(body))
        rec["hash"] = _record_hash(rec)
        line = _encoder.encode(rec)
        self._write(line + b"\n")
        self._prev, self._seq, self._head = _sha256(line), self._seq + 1, rec["hash"]
        self._write_head()
        return rec

    def _write(self, data: bytes) -> None:
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(self._fd, view):]
            os.fsync(self._fd)
        except OSError as exc:
            self._suspect = True  # maybe a partial line: check the tail before the next write
            raise AuditError(f"{self.path}: cannot append: {exc}") from exc
