"""The candidates kept for a reload and a restart: one per browser tab (and user).

A browser tab names its slot (web_assets/dashboard.js: an id in the tab's sessionStorage,
sent with the websocket's URL; `server.http_access.slot_of_path`); every change of that tab's
candidate is kept here under (user, slot), and a page that connects with a slot gets the
candidate kept for it. What is kept is what the controls showed (a typed cut-off as typed, an
invalid one too), the configuration the candidate was built on, the active version it was
made against and that version's configuration as the controller ran it: restored, a candidate
made against an older version is stale like before the reload (the panel says so, Apply is off
and the controller refuses it: its Apply carries that version), and so is one whose version
the controller now runs as another configuration (its state was reset since).

With a directory (the dashboard's data directory, `server.options.default_candidates_dir`),
each user's candidates are also on disk, one file per user per rig:
`<directory>/<rig>/<user>.json` (`rig_dir_name`, `user_file_name`: no name can point
elsewhere), read when the store opens and rewritten whole after each change (by a writer
thread: the GUI's callbacks never wait for a disk; a burst of changes is one write), atomically
(`controller.files.write_atomically`): a failed write leaves the previous file. A file that
cannot be read or makes no sense is moved aside (`<file>.unreadable-<time>`, never overwritten
nor deleted) and its user is told (`problem`); so is a write that fails (the candidate is then
in memory only).

Several dashboards may keep their candidates in one directory (two dashboards of one rig, a
restart beside the old one): a write is a read-modify-write of the user's file under an
exclusive lock of the rig's directory (`fcntl.flock` on `<directory>/<rig>/.lock`), and it
changes only the slots this dashboard changed since its last write: another dashboard's
candidates in the file stay (before, each dashboard rewrote the file with its own memory, and
a user's candidate kept by the other one vanished). The file keeps a user's `PER_USER` most
recently changed slots.

Nothing here is trusted: a file's values are checked (`check`) and go back into the controls
and through the same checks as typed ones.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from controller.auth import check_name
from controller.core.config import LoopConfig, NominalModel
from controller.files import fsync_dir, write_atomically

__all__ = ["FILE_FORMAT", "CandidateStore", "KeptCandidate", "rig_dir_name", "user_file_name"]

log = logging.getLogger(__name__)

#: The version of the files' form (a file of another form is not read: moved aside, said).
FILE_FORMAT = 1
#: The file of the one identity (a dashboard without users): a user name never starts with "_".
ANYONE_FILE = "_anyone.json"
#: Most tabs kept per user (the oldest go first).
PER_USER = 32
#: The lock file of a rig's directory (held while a user's file is read and rewritten).
LOCK_FILE = ".lock"


@contextlib.contextmanager
def _directory_locked(directory: Path) -> Iterator[None]:
    """An exclusive `flock` of `directory`'s lock file, held for the block: one dashboard at a
    time reads and rewrites the files in it (the lock goes with the process, so a crashed
    dashboard never leaves it taken). FileNotFoundError: no directory."""
    fd = os.open(directory / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


@dataclass(frozen=True)
class KeptCandidate:
    base: LoopConfig
    """The configuration the candidate's controls were last loaded from."""
    base_version: int | None
    """The active version the candidate was made against."""
    controls: tuple[tuple[str, Any], ...]
    """The controls as they showed: (panel attribute, value), the cut-off's text included."""
    nominal: NominalModel | None = None
    """A nominal model put in by Identify's "Use as nominal model" (None: the base's)."""
    against: LoopConfig | None = None
    """The controller's configuration at `base_version` when kept (None: not known)."""


class _Kept(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A kept candidate in a user's file."""

    slot: str
    base: LoopConfig
    base_version: int | None
    against: LoopConfig | None
    controls: list[tuple[str, bool | float | str]]
    nominal: NominalModel | None


class _UserFile(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    format: int
    rig: str
    user: str
    saved_at_s: float
    candidates: list[_Kept]
    """Least recently changed first."""


_encoder = msgspec.json.Encoder()


def rig_dir_name(rig: str) -> str:
    """The directory of a rig's files: letters, digits, '_', '-' and (not first) '.' as they
    are, every other character as %XX of its UTF-8 bytes ('%' too: one name per rig; '/' or a
    leading '.' can never name another directory)."""
    if not rig:
        raise ValueError("rig_name: empty")
    return "".join(
        c if (c.isascii() and (c.isalnum() or c in "_-")) or (c == "." and i > 0)
        else "".join(f"%{b:02X}" for b in c.encode()) for i, c in enumerate(rig))


def user_file_name(user: str) -> str:
    """The file of `user`'s candidates: a user name as the users file allows it (letters,
    digits, '_', '.', '-', starting with a letter or digit: no separator, never '.' or '..'),
    checked again here; "" (one identity) is `ANYONE_FILE`. ValueError otherwise."""
    return ANYONE_FILE if user == "" else check_name(user, "user") + ".json"


def _user_of_file(name: str) -> str | None:
    """The user whose file this is (None: not a user's file)."""
    if name == ANYONE_FILE:
        return ""
    if not name.endswith(".json"):
        return None
    try:
        return check_name(name[: -len(".json")], "user")
    except ValueError:
        return None


class CandidateStore:
    """(user, slot) -> the latest `KeptCandidate`; the `capacity` most recently changed only,
    at most `PER_USER` per user (a client cannot grow it without bound by naming new slots);
    with `directory`, on disk too (see the module)."""

    def __init__(self, capacity: int = 256, directory: Path | None = None, rig: str = "",
                 check: Callable[[KeptCandidate], str] | None = None,
                 on_problem: Callable[[str, str], None] | None = None) -> None:
        """`check(kept)`: why a candidate read from a file cannot be restored ("" : it can).
        `on_problem(user, text)`: `problem(user)` changed (from the writer thread)."""
        self.capacity = capacity
        self._kept: OrderedDict[tuple[str, str], KeptCandidate] = OrderedDict()
        self._lock = threading.Lock()
        self.directory = None if directory is None else Path(directory) / rig_dir_name(rig)
        self.rig = rig
        self._check = check
        self.on_problem = on_problem
        self._read_problems: dict[str, str] = {}
        self._write_problems: dict[str, str] = {}
        self._no_write: set[str] = set()
        """Users whose unreadable file could not be moved aside: never overwritten."""
        self._dir_problem = ""
        """The rig's directory cannot be listed: no file is read, none is written."""
        self._dirty: dict[str, set[str]] = {}
        """user -> the slots changed here and not yet written."""
        self._writing = False
        self._cond = threading.Condition(self._lock)
        self._stop = False
        self._writer: threading.Thread | None = None
        if self.directory is not None:
            self._read_all()
            self._writer = threading.Thread(target=self._write_loop, name="candidate-files",
                                            daemon=True)
            self._writer.start()

    # -- memory ------------------------------------------------------------------------------

    def keep(self, user: str, slot: str, kept: KeptCandidate) -> None:
        if not slot:
            return
        with self._lock:
            self._put(user, slot, kept)
            if self.directory is not None:
                self._dirty.setdefault(user, set()).add(slot)
                self._cond.notify_all()

    def _put(self, user: str, slot: str, kept: KeptCandidate) -> None:
        """(Lock held.) Keep, then drop the least recently changed beyond the limits (from
        memory: a user's file keeps their `PER_USER` most recently changed slots)."""
        self._kept[(user, slot)] = kept
        self._kept.move_to_end((user, slot))
        mine = [k for k in self._kept if k[0] == user]
        for key in mine[: max(0, len(mine) - PER_USER)]:
            del self._kept[key]
        while len(self._kept) > self.capacity:
            self._kept.popitem(last=False)

    def get(self, user: str, slot: str) -> KeptCandidate | None:
        if not slot:
            return None
        with self._lock:
            return self._kept.get((user, slot))

    def __len__(self) -> int:
        with self._lock:
            return len(self._kept)

    def problem(self, user: str) -> str:
        """What `user` should know about their kept candidates on disk ("" : nothing)."""
        with self._lock:
            return " ".join(p for p in (self._dir_problem, self._read_problems.get(user, ""),
                                        self._write_problems.get(user, "")) if p)

    # -- files -------------------------------------------------------------------------------

    def path_of(self, user: str) -> Path:
        assert self.directory is not None, "a store without a directory has no files"
        return self.directory / user_file_name(user)

    def _read_all(self) -> None:
        """Every user's file of this rig into memory (the most recently saved files last),
        under the directory's lock (another dashboard's write in progress is not cut short)."""
        assert self.directory is not None
        try:
            with _directory_locked(self.directory):
                self._read_all_locked()
        except FileNotFoundError:
            return
        except OSError as exc:  # no lock file here (a read-only directory): nobody writes
            log.warning("kept candidates: %s cannot be locked (%s): read without the lock",
                        self.directory, exc)
            self._read_all_locked()

    def _read_all_locked(self) -> None:
        assert self.directory is not None
        try:
            names = sorted(p.name for p in self.directory.iterdir())
        except OSError as exc:  # every user is told; nothing is written over what is there
            log.error("kept candidates: %s cannot be listed: %s", self.directory, exc)
            self._dir_problem = (f"The kept candidates in {self.directory} cannot be read "
                                 f"({exc}): none is restored, and none is saved to disk.")
            return
        files: list[tuple[float, str, _UserFile]] = []
        for name in names:
            if name.startswith(".") and name.endswith(".tmp"):  # a write a crash cut short
                try:
                    (self.directory / name).unlink()
                except OSError as exc:
                    log.warning("kept candidates: %s not removed: %s", name, exc)
                continue
            user = _user_of_file(name)
            if user is None:
                continue  # a file moved aside, or not ours
            read = self._read_file(user)
            if read is not None:
                files.append((read.saved_at_s, user, read))
        for _saved, user, read in sorted(files, key=lambda f: f[0]):
            for k in read.candidates:
                self._put(user, k.slot, KeptCandidate(
                    k.base, k.base_version, tuple((n, v) for n, v in k.controls),
                    k.nominal, k.against))
            log.info("kept candidates: %d of user %r read from %s", len(read.candidates),
                     user, self.path_of(user))
        self._dirty.clear()

    def _read_file(self, user: str) -> _UserFile | None:
        """One user's file (None: there is none, or it was unreadable: moved aside, said)."""
        path = self.path_of(user)
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as exc:
            self._unreadable(user, path, f"cannot be read: {exc}")
            return None
        try:
            doc = msgspec.json.decode(raw, type=_UserFile)
        except (msgspec.DecodeError, msgspec.ValidationError) as exc:
            self._unreadable(user, path, f"is not a kept-candidates file: {exc}")
            return None
        why = (f"format {doc.format}, this dashboard reads {FILE_FORMAT}"
               if doc.format != FILE_FORMAT
               else f"it is rig {doc.rig!r}'s, not {self.rig!r}'s" if doc.rig != self.rig
               else f"it is user {doc.user!r}'s" if doc.user != user else "")
        for k in doc.candidates if not why else ():
            problem = self._check(self._as_kept(k)) if self._check is not None else ""
            if problem:
                why = f"slot {k.slot!r}: {problem}"
                break
        if why:
            self._unreadable(user, path, f"makes no sense here: {why}")
            return None
        return doc

    @staticmethod
    def _as_kept(k: _Kept) -> KeptCandidate:
        return KeptCandidate(k.base, k.base_version, tuple((n, v) for n, v in k.controls),
                             k.nominal, k.against)

    def _unreadable(self, user: str, path: Path, why: str) -> None:
        """Move the file aside (kept, never overwritten) and tell its user."""
        aside = path.with_name(f"{path.name}.unreadable-{time.strftime('%Y%m%dT%H%M%S')}")
        n = 1
        while aside.exists():
            aside = aside.with_name(f"{path.name}.unreadable-{time.strftime('%Y%m%dT%H%M%S')}-{n}")
            n += 1
        try:
            path.replace(aside)
            where = f"it was moved aside to {aside}"
        except OSError as exc:
            self._no_write.add(user)
            where = (f"it could not be moved aside ({exc}), so it is left as it is and your "
                     "candidates are not saved to disk")
        text = (f"Your kept candidates could not be restored: {path} {why}; {where}. "
                "Your candidate starts from the active configuration.")
        log.error("kept candidates of user %r: %s", user, text)
        self._read_problems[user] = text

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Wait until every change is written (or failed: see `problem`); False on timeout."""
        end = time.monotonic() + timeout_s
        with self._lock:
            while self._dirty or self._writing:
                left = end - time.monotonic()
                if left <= 0 or self._writer is None or not self._writer.is_alive():
                    return False
                self._cond.wait(left)
        return True

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what is pending, then stop the writer."""
        if self._writer is None:
            return
        if not self.flush(timeout_s):
            log.error("kept candidates: not all written within %.0f s at close", timeout_s)
        with self._lock:
            self._stop = True
            self._cond.notify_all()
        self._writer.join(timeout_s)

    def _write_loop(self) -> None:
        while True:
            with self._lock:
                while not self._dirty and not self._stop:
                    self._cond.wait()
                if self._stop and not self._dirty:
                    return
                user, slots = self._dirty.popitem()
                self._writing = True
                # Least recently changed first; a slot dropped from memory meanwhile is not
                # written (the file keeps what it had).
                mine = [_Kept(slot=slot, base=k.base, base_version=k.base_version,
                              against=k.against, controls=list(k.controls), nominal=k.nominal)
                        for (u, slot), k in self._kept.items() if u == user and slot in slots]
                skip = user in self._no_write or bool(self._dir_problem)
            try:
                if not skip:
                    self._write(user, mine)
            finally:
                with self._lock:
                    self._writing = False
                    self._cond.notify_all()

    def _write(self, user: str, mine: list[_Kept]) -> None:
        """`user`'s file with the slots `mine` changed here, under the directory's lock: the
        file as it is now (another dashboard's slots in it stay), `mine` put in as the most
        recently changed."""
        assert self.directory is not None
        try:
            path = self.path_of(user)
            self.directory.mkdir(parents=True, exist_ok=True)
            with _directory_locked(self.directory):
                now = self._read_file(user)  # an unreadable one is moved aside, as at start
                ours = {k.slot for k in mine}
                merged = [k for k in (now.candidates if now is not None else ())
                          if k.slot not in ours] + mine
                doc = _UserFile(format=FILE_FORMAT, rig=self.rig, user=user,
                                saved_at_s=time.time(), candidates=merged[-PER_USER:])
                data = msgspec.json.format(_encoder.encode(doc), indent=1) + b"\n"
                write_atomically(path, data)
                fsync_dir(self.directory)
            text = ""
        except (OSError, ValueError) as exc:  # ValueError: a user name no file can have
            log.error("kept candidates of user %r not written: %s", user, exc)
            text = (f"Your candidate is not saved to disk ({exc}): it is kept in this "
                    "dashboard's memory only, and a restart of the dashboard loses it.")
        with self._lock:
            changed = self._write_problems.get(user, "") != text
            if text:
                self._write_problems[user] = text
            else:
                self._write_problems.pop(user, None)
        if changed and self.on_problem is not None:
            self.on_problem(user, self.problem(user))
