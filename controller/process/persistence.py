"""The controller's state on disk: the active configuration and the applied-changes log.

- `active_config.json`: {"version": N, "saved_at_s": UNIX time, "config": LoopConfig}, written
  atomically (temporary file in the same directory, fsync, os.replace, fsync of the
  directory) on every accepted change, so a crash leaves either the old or the new file.
- `applied_changes.jsonl`: one JSON object per accepted change, appended and fsynced:
  {"time_s", "version", "old_version", "old", "new", "client", "verdict"}, where "verdict" is
  the gate's `Verdict` (its wire form, as in `controller.protocol`) or null. JSON has no
  infinity nor NaN: an infinite figure (a gain margin with no phase crossover) is written as
  the string "inf" or "-inf" and read back as one; NaN ("not known") is written as null and
  read back as NaN, as is the null of lines written before infinity was kept. Lines of
  older versions (protocol 1) carry the verdict's kind as a string ("" or absent: not logged)
  and its "margins" beside it: `verdict_of_change` reads both forms. A change saved with its
  line (`save(..., change=)`) has it appended once the new file has replaced the old one, its
  fsync beside the directory's: both are on disk when `save` returns (one fsync's wait
  instead of two), and the log never names a configuration that was not saved.
- A watchdog rollback whose configuration cannot be saved (the directory takes no new file,
  the file's place is taken, ...) is recorded by a line of its own appended to the change
  log (an existing file, which such a directory still lets grow):
  {"time_s", "pending_rollback": {"version", "from_version", "config", "kind"}}. While the
  active file still holds the version rolled back from, `pending_rollback` returns it: a
  restart comes back on the configuration rolled back to, never on the one rolled back
  from. `read_changes` leaves these lines out (they name no saved configuration).
- `latch.json`: {"mode": "estop" | "fault", "reason", "fault", "saved_at_s"} while the loop is
  latched in e-stop or fault (written atomically, removed on reset): a restart comes back in
  that mode until an explicit reset.
- `running.json`: {"pid", "started_at_s"} while the loop runs (written atomically just before
  it starts, removed once it stopped cleanly and the latch was written): found at a start, the
  previous run ended without a clean stop (killed, crashed, power lost), and the new run
  starts latched in fault until a reset (`controller.process.main`).
- `plant_knowledge.json`: the plant knowledge every candidate is judged on (a
  `controller.gate.knowledge.KnowledgeRecord`: model, bound, measured responses, version,
  source), written atomically whenever an operator adopts new knowledge.

Versions are bounded by MAX_VERSION (2**53 - 1: exact in every JSON reader, a browser's
included, and far inside MessagePack's integers): a saved file above it is refused on load, and
a version above it is never saved, so the active version can never stop the publishing. Stale
temporary files (`.<name>.*.tmp`, left by a crash between write and rename) are removed when the
store opens.

Nothing here runs on the loop's thread.
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from controller.core.config import LoopConfig, config_from_builtins, config_to_builtins
from controller.core.errors import ConfigError
from controller.core.validate import split_msgspec_error
from controller.core.verdict import VERDICT_KINDS, Verdict, VerdictMargins
from controller.files import fsync_dir, write_atomically
from controller.gate.knowledge import KnowledgeRecord

__all__ = [
    "ACTIVE_FILE",
    "KNOWLEDGE_FILE",
    "LATCH_FILE",
    "LOG_FILE",
    "MAX_VERSION",
    "Change",
    "ChangeLogError",
    "Latch",
    "PendingRollback",
    "PersistenceError",
    "SavedConfig",
    "StateStore",
    "verdict_of_change",
]

ACTIVE_FILE = "active_config.json"
LOG_FILE = "applied_changes.jsonl"
LATCH_FILE = "latch.json"
RUN_FILE = "running.json"
KNOWLEDGE_FILE = "plant_knowledge.json"
MAX_VERSION = 2**53 - 1
#: The change-log key of a watchdog rollback not saved yet (`StateStore.record_pending_rollback`).
PENDING_KEY = "pending_rollback"
#: The temporary file `check_writable` writes.
_PROBE = ".write_probe"

_json = msgspec.json.Encoder()


class PersistenceError(RuntimeError):
    """The state directory cannot be read or written."""


class ChangeLogError(PersistenceError):
    """The configuration was saved; its line in the change log was not."""


@dataclass(frozen=True)
class Change:
    """What the change log records of a saved configuration besides it and its version
    (`StateStore.save`)."""

    old: LoopConfig | None
    old_version: int | None
    verdict: Verdict | None
    client: str = ""


@dataclass(frozen=True)
class Latch:
    """An e-stop or fault the loop is latched in (persisted until reset)."""

    mode: str
    """estop or fault."""
    reason: str
    """The e-stop's source, or the fault."""
    fault: str = ""
    """A fault reported while already in e-stop."""


@dataclass(frozen=True)
class PendingRollback:
    """A watchdog rollback the change log records as not saved: what a restart must come
    back on instead of the active file's configuration (the one rolled back from)."""

    config: LoopConfig
    """The configuration rolled back to."""
    version: int
    from_version: int
    kind: str
    """The watchdog trip's kind."""


@dataclass(frozen=True)
class SavedConfig:
    config: LoopConfig
    version: int
    saved_at_s: float


#: How the change log writes the infinities JSON has not (read back by `_float_of_json`).
_INF_JSON = {math.inf: "inf", -math.inf: "-inf"}


def _json_floats(value: Any) -> Any:
    """JSON has no inf/nan: +-inf as "inf"/"-inf", NaN as None, recursively."""
    if isinstance(value, float):
        if value != value:
            return None
        return _INF_JSON.get(value, value)
    if isinstance(value, dict):
        return {k: _json_floats(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_floats(v) for v in value]
    return value


def _read_or_none(path: Path) -> bytes | None:
    """The file's bytes; None if it does not exist; PersistenceError if it cannot be read."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise PersistenceError(f"{path}: cannot read: {exc}") from exc


def _decode_json(path: Path, raw: bytes) -> Any:
    """The JSON value of a file's bytes; PersistenceError naming the file if it is not JSON."""
    try:
        return msgspec.json.decode(raw)
    except msgspec.DecodeError as exc:
        raise PersistenceError(f"{path}: not valid JSON: {exc}") from exc


class StateStore:
    """Active configuration + change log in one directory (created if missing)."""

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = Path(directory)
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise PersistenceError(f"state_dir: cannot create {self.directory}: {exc}") from exc
        self.removed_tmp = self._remove_stale_tmp()
        """Names of the stale temporary files removed when the store opened."""

    def _remove_stale_tmp(self) -> list[str]:
        removed: list[str] = []
        names = (ACTIVE_FILE, LATCH_FILE, KNOWLEDGE_FILE, _PROBE)
        try:
            entries = list(self.directory.iterdir())
        except OSError:
            return removed
        for p in entries:
            n = p.name
            if n.endswith(".tmp") and any(n.startswith(f".{name}.") for name in names):
                with contextlib.suppress(OSError):
                    p.unlink()
                    removed.append(n)
        return removed

    @property
    def active_path(self) -> Path:
        return self.directory / ACTIVE_FILE

    @property
    def log_path(self) -> Path:
        return self.directory / LOG_FILE

    # -- active configuration ----------------------------------------------------------------

    def load(self) -> SavedConfig | None:
        """The saved active configuration; None if there is none; PersistenceError if the file
        is unreadable or invalid (the caller decides; it is never silently replaced)."""
        path = self.active_path
        raw = _read_or_none(path)
        if raw is None:
            return None
        data = _decode_json(path, raw)
        try:
            if not isinstance(data, dict):
                raise PersistenceError(f"{path}: expected a JSON object")
            version = data.get("version")
            if isinstance(version, bool) or not isinstance(version, int) or version < 0:
                raise PersistenceError(f"{path}: version: expected an int >= 0, got {version!r}")
            if version > MAX_VERSION:
                raise PersistenceError(
                    f"{path}: version: {version} is above the limit {MAX_VERSION}; "
                    "restart with --config FILE (or edit the version) to start a new count"
                )
            saved_at = data.get("saved_at_s", 0.0)
            if isinstance(saved_at, bool) or not isinstance(saved_at, (int, float)):
                raise PersistenceError(f"{path}: saved_at_s: expected a number")
            cfg = config_from_builtins(data.get("config"))
        except ConfigError as exc:
            raise PersistenceError(f"{path}: config.{exc}") from exc
        return SavedConfig(config=cfg, version=version, saved_at_s=float(saved_at))

    def save(self, config: LoopConfig, version: int, change: Change | None = None) -> None:
        """Atomically replace the active configuration file; with `change`, append its line
        to the change log too, once the new file is in place, the two fsyncs overlapped.
        When this returns, both are on disk. PersistenceError: the configuration is not
        saved (the old file stays, the log is untouched); ChangeLogError: it is saved, its
        line is not."""
        if isinstance(version, bool) or not 0 <= version <= MAX_VERSION:
            raise PersistenceError(f"version: {version} is outside [0, {MAX_VERSION}]")
        now = time.time()
        doc = {"version": version, "saved_at_s": now, "config": config_to_builtins(config)}
        data = msgspec.json.format(_json.encode(doc), indent=2) + b"\n"
        if change is None:
            self._atomic_write(self.active_path, data)
            return
        line = self._change_line(old=change.old, old_version=change.old_version, new=config,
                                 version=version, client=change.client, time_s=now,
                                 verdict=change.verdict)
        failed: list[ChangeLogError] = []

        def log() -> None:
            try:
                self._append_line(line)
            except PersistenceError as exc:
                failed.append(ChangeLogError(str(exc)))

        self._atomic_write(self.active_path, data, beside_dir_fsync=log)
        if failed:
            raise failed[0]

    def _atomic_write(self, path: Path, data: bytes,
                      beside_dir_fsync: Callable[[], None] | None = None) -> None:
        """Replace `path` by `data` (`controller.files.write_atomically`), fsync the
        directory; `beside_dir_fsync` (which must not raise) runs on a thread of its own
        during the directory's fsync, and has ended when this returns."""
        try:
            try:
                write_atomically(path, data)
            except FileNotFoundError:  # the directory vanished: make it again, once
                self.directory.mkdir(parents=True, exist_ok=True)
                write_atomically(path, data)
        except OSError as exc:
            raise PersistenceError(f"{path}: cannot write: {exc}") from exc
        if beside_dir_fsync is None:
            self._fsync_dir()
            return
        beside = threading.Thread(target=beside_dir_fsync, name="state-log", daemon=True)
        beside.start()
        try:
            self._fsync_dir()
        finally:
            beside.join()

    def check_writable(self) -> None:
        """PersistenceError if a new file cannot be written, synced and removed in the
        directory (what every save needs)."""
        self._atomic_write(self.directory / _PROBE, b"probe\n")
        try:
            (self.directory / _PROBE).unlink()
        except OSError as exc:
            raise PersistenceError(f"{self.directory}: cannot remove a file: {exc}") from exc

    def _fsync_dir(self) -> None:
        # The rename itself is durable only once the directory entry is on disk.
        fsync_dir(self.directory)

    # -- the e-stop / fault latch -------------------------------------------------------------

    @property
    def latch_path(self) -> Path:
        return self.directory / LATCH_FILE

    def save_latch(self, latch: Latch | None) -> None:
        """Write the latch atomically, or remove it (None: not latched)."""
        if latch is None:
            self._remove(self.latch_path)
            return
        doc = {
            "mode": latch.mode,
            "reason": latch.reason,
            "fault": latch.fault,
            "saved_at_s": time.time(),
        }
        self._atomic_write(self.latch_path, _json.encode(doc) + b"\n")

    def load_latch(self) -> Latch | None:
        """The persisted latch; None if there is none. A file that cannot be read or makes no
        sense counts as a fault (never as "not latched"): PersistenceError is for the caller
        to turn into one."""
        path = self.latch_path
        raw = _read_or_none(path)
        if raw is None:
            return None
        data = _decode_json(path, raw)
        if not isinstance(data, dict) or data.get("mode") not in ("estop", "fault"):
            raise PersistenceError(f"{path}: mode: expected estop or fault")
        reason, fault = data.get("reason", ""), data.get("fault", "")
        if not isinstance(reason, str) or not isinstance(fault, str):
            raise PersistenceError(f"{path}: reason/fault: expected strings")
        return Latch(str(data["mode"]), reason[:500], fault[:500])

    # -- the run marker ---------------------------------------------------------------------

    @property
    def run_path(self) -> Path:
        return self.directory / RUN_FILE

    def mark_running(self, pid: int, started_at_s: float) -> None:
        """The loop is about to run (atomic): until `clear_running`, a start finds it."""
        self._atomic_write(self.run_path, _json.encode(
            {"pid": pid, "started_at_s": started_at_s}) + b"\n")

    def clear_running(self) -> None:
        """The loop stopped cleanly: remove the marker (durably)."""
        self._remove(self.run_path)

    def _remove(self, path: Path) -> None:
        """Remove `path` if it is there, durably (the directory fsynced)."""
        try:
            path.unlink()
        except FileNotFoundError:
            return
        except OSError as exc:
            raise PersistenceError(f"{path}: cannot remove: {exc}") from exc
        self._fsync_dir()

    def unclean_stop(self) -> str:
        """"" if the last run stopped cleanly (no marker); else what the marker says of the run
        that did not ("pid 123, started 2026-11-29 20:31:02 UTC"; an unreadable marker still
        counts as an unclean stop, named so)."""
        path = self.run_path
        try:
            raw = _read_or_none(path)
        except PersistenceError as exc:
            return f"{RUN_FILE} unreadable ({exc})"
        if raw is None:
            return ""
        try:
            data = _decode_json(path, raw)
            pid, t = data["pid"], data["started_at_s"]
            if not isinstance(pid, int) or not isinstance(t, (int, float)):
                raise ValueError("pid/started_at_s: expected numbers")
            when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t))
        except (PersistenceError, KeyError, TypeError, ValueError, OverflowError, OSError) as exc:
            return f"{RUN_FILE} unreadable ({exc})"
        return f"pid {pid}, started {when}"

    @property
    def knowledge_path(self) -> Path:
        return self.directory / KNOWLEDGE_FILE

    def save_knowledge(self, record: KnowledgeRecord) -> None:
        if not 0 <= record.version <= MAX_VERSION:
            raise PersistenceError(f"knowledge version: {record.version} is outside the range")
        data = msgspec.json.format(msgspec.json.encode(record), indent=1) + b"\n"
        self._atomic_write(self.knowledge_path, data)

    def load_knowledge(self) -> KnowledgeRecord | None:
        """The saved plant knowledge (None if there is none). A file that cannot be read or
        validated raises PersistenceError naming the field: the controller never judges on
        knowledge it cannot read (nor silently on a default)."""
        path = self.knowledge_path
        raw = _read_or_none(path)
        if raw is None:
            return None
        try:
            rec = msgspec.json.decode(raw, type=KnowledgeRecord)
            if not 0 <= rec.version <= MAX_VERSION:
                raise ValueError(f"version: {rec.version} is outside [0, {MAX_VERSION}]")
            rec.to_knowledge()
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError) as exc:
            raise PersistenceError(f"{path}: {exc}") from exc
        return rec

    def load_latch_or_none(self) -> Latch | None:
        """`load_latch`, with an unreadable file as None (the writer then rewrites it)."""
        try:
            return self.load_latch()
        except PersistenceError:
            return None

    # -- applied-changes log -----------------------------------------------------------------

    def append_change(
        self,
        *,
        old: LoopConfig | None,
        old_version: int | None,
        new: LoopConfig,
        version: int,
        verdict: Verdict | None,
        client: str = "",
        time_s: float | None = None,
    ) -> None:
        """Append one line to the applied-changes log (fsynced)."""
        self._append_line(self._change_line(
            old=old, old_version=old_version, new=new, version=version, client=client,
            time_s=time_s, verdict=verdict))

    @staticmethod
    def _change_line(
        *, old: LoopConfig | None, old_version: int | None, new: LoopConfig, version: int,
        client: str, time_s: float | None, verdict: Verdict | None,
    ) -> bytes:
        entry = {
            "time_s": time.time() if time_s is None else time_s,
            "version": version,
            "old_version": old_version,
            "old": None if old is None else config_to_builtins(old),
            "new": config_to_builtins(new),
            "client": client,
            "verdict": None if verdict is None else msgspec.to_builtins(verdict),
        }
        return _json.encode(_json_floats(entry)) + b"\n"

    def _append_line(self, line: bytes) -> None:
        try:
            with open(self.log_path, "ab") as f:
                f.write(line)
                f.flush()
                os.fsync(f.fileno())
        except OSError as exc:
            raise PersistenceError(f"{self.log_path}: cannot append: {exc}") from exc

    def _log_items(self) -> list[dict[str, Any]]:
        """Every JSON object of the log, oldest first (a torn last line is skipped)."""
        try:
            lines = self.log_path.read_bytes().splitlines()
        except FileNotFoundError:
            return []
        out: list[dict[str, Any]] = []
        for line in lines:
            if not line.strip():
                continue
            try:
                item = msgspec.json.decode(line)
            except msgspec.DecodeError:
                continue
            if isinstance(item, dict):
                out.append(item)
        return out

    def read_changes(self) -> list[dict[str, Any]]:
        """Every entry of the log, oldest first (a torn last line is skipped; the lines of
        rollbacks not saved then are not entries)."""
        return [item for item in self._log_items() if PENDING_KEY not in item]

    def record_pending_rollback(self, pending: PendingRollback) -> None:
        """Append (fsynced) the line that makes a restart come back on `pending.config` while
        the active file still holds `pending.from_version` (`pending_rollback`)."""
        doc = {"time_s": time.time(), PENDING_KEY: {
            "version": pending.version, "from_version": pending.from_version,
            "config": config_to_builtins(pending.config), "kind": pending.kind}}
        self._append_line(_json.encode(doc) + b"\n")

    def pending_rollback(self, saved: SavedConfig | None) -> PendingRollback | None:
        """The newest rollback the log records as not saved, if the active file (`saved`)
        still holds the version it rolled back from; None otherwise (saved since, or
        superseded by a later save). PersistenceError for a line that cannot be read: the
        controller never guesses which configuration is safe to start."""
        if saved is None:
            return None
        try:
            items = self._log_items()
        except OSError as exc:
            raise PersistenceError(f"{self.log_path}: cannot read: {exc}") from exc
        for item in reversed(items):
            value = item.get(PENDING_KEY)
            if value is None:
                continue
            try:
                if not isinstance(value, dict):
                    raise ValueError("expected an object")
                version, from_version = value["version"], value["from_version"]
                kind = value.get("kind", "")
                for name, v in (("version", version), ("from_version", from_version)):
                    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= MAX_VERSION:
                        raise ValueError(f"{name}: expected an int in [0, {MAX_VERSION}]")
                if not isinstance(kind, str):
                    raise ValueError("kind: expected a string")
                config = config_from_builtins(value["config"])
            except KeyError as exc:
                raise PersistenceError(
                    f"{self.log_path}: {PENDING_KEY}.{exc.args[0]}: missing") from exc
            except (ValueError, ConfigError) as exc:
                raise PersistenceError(f"{self.log_path}: {PENDING_KEY}: {exc}") from exc
            if from_version != saved.version:
                return None  # saved since (or an older one): the active file is newer
            return PendingRollback(config, version, from_version, kind[:100])
        return None


def _float_of_json(value: object) -> object:
    """A figure as a change-log line holds it: null is NaN (not known; in lines written before
    infinity was kept, also an infinity), "inf"/"-inf" an infinity; anything else as it is
    (msgspec then says what is wrong with it)."""
    if value is None:
        return math.nan
    if value == "inf":
        return math.inf
    if value == "-inf":
        return -math.inf
    return value


def _margins_of_json(margins: object) -> object:
    """Margins as a change-log line holds them, as floats (`_float_of_json`)."""
    if not isinstance(margins, dict):
        return margins
    return {k: _float_of_json(v) for k, v in margins.items()}


def _convert(value: object, kind: type[Any], where: str) -> Any:
    """msgspec.convert; ValueError naming the field from `where` ("verdict.margins.x: ...")."""
    try:
        return msgspec.convert(value, kind)
    except msgspec.ValidationError as exc:
        field, why = split_msgspec_error(str(exc))
        raise ValueError(f"{where}.{field}: {why}" if field != "payload" else
                         f"{where}: {why}") from exc


def verdict_of_change(item: dict[str, Any]) -> Verdict | None:
    """The gate's verdict a change-log line records (None: none was logged). Reads this
    version's lines ("verdict": a `Verdict`) and older ones ("verdict": its kind, "" when not
    logged, with "margins" beside it: no reasons, knowledge version 0, unknown then).
    ValueError names what is wrong ("verdict.margins.gain_margin_db: ...")."""
    value = item.get("verdict")
    if value is None or value == "":
        return None
    if isinstance(value, str):  # an older line: the kind, and the margins beside it
        if value not in VERDICT_KINDS:
            raise ValueError(f"verdict: {value!r} is not one of {', '.join(VERDICT_KINDS)}")
        old = item.get("margins")
        if old is not None and not isinstance(old, dict):
            raise ValueError(f"margins: expected an object, got {type(old).__name__}")
        margins = (VerdictMargins.unknown() if old is None else
                   _convert(_margins_of_json(old), VerdictMargins, "margins"))
        return _convert({"verdict": value, "margins": margins}, Verdict, "verdict")
    if not isinstance(value, dict):
        raise ValueError(f"verdict: expected an object or a string, got {type(value).__name__}")
    if "margins" in value:
        value = {**value, "margins": _margins_of_json(value["margins"])}
    cutoff = value.get("recommended_max_cutoff_hz")
    if cutoff in _INF_JSON.values():  # (null stays None there: no recommendation)
        value = {**value, "recommended_max_cutoff_hz": _float_of_json(cutoff)}
    return _convert(value, Verdict, "verdict")
