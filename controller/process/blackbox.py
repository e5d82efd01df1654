"""The controller's black box: the last `seconds` of loop samples in memory, written to
`<state-dir>/blackbox/<UTC time>-<reason>.mcap` on every e-stop, fault and watchdog rollback,
with the event that caused it; the oldest files go when the directory exceeds `max_bytes`.
A file is written as `<name>.mcap.tmp` and renamed when complete; unfinished ones (a crash
while writing) are removed when the black box opens.

The publisher thread hands every finished StateBatch to `add` (a deque append); `trigger`
snapshots the deque and writes the file in a thread of its own: never on the loop's thread,
never delaying the publisher or the status thread. A failed write is reported through `warn`.
"""

from __future__ import annotations

import collections
import logging
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["BlackBox"]

log = logging.getLogger(__name__)


class BlackBox:
    def __init__(
        self,
        directory: Path,
        rig: str,
        warn: Callable[[str], None],
        *,
        seconds: float = 30.0,
        batch_s: float = 0.02,
        max_bytes: int = 200 * 1024 * 1024,
    ) -> None:
        self.directory = Path(directory)
        self.rig = rig
        self.warn = warn
        self.max_bytes = max_bytes
        self._batches: collections.deque[Any] = collections.deque(
            maxlen=max(1, round(seconds / batch_s))
        )
        self._lock = threading.Lock()
        self._writers: list[threading.Thread] = []
        self.written: list[Path] = []
        self.removed_tmp = self._remove_unfinished()
        """Unfinished files (`*.mcap.tmp`, left by a crash while writing) removed at start."""

    def _remove_unfinished(self) -> list[str]:
        removed: list[str] = []
        try:
            unfinished = sorted(self.directory.glob("*.mcap.tmp"))
        except OSError as exc:
            self.warn(f"black box: {self.directory} cannot be listed: {exc}")
            return removed
        for p in unfinished:
            try:
                p.unlink()
            except OSError as exc:
                self.warn(f"black box: {p.name} (unfinished, left by a crash) not removed: {exc}")
                continue
            removed.append(p.name)
        if removed:
            log.info("black box: removed %d unfinished file(s) left by a crash: %s",
                     len(removed), ", ".join(removed))
        return removed

    def add(self, batch: Any) -> None:
        self._batches.append(batch)  # deque append: atomic, bounded

    def held(self) -> list[Any]:
        """The batches kept, oldest first (the state replay serves from them)."""
        return list(self._batches)

    def trigger(self, reason: str, text: str) -> None:
        """Write the last seconds with the event `reason` (`text` says what happened)."""
        batches = list(self._batches)
        if not batches:
            return
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        slug = re.sub(r"[^A-Za-z0-9_-]+", "-", reason)[:40].strip("-") or "event"
        path = self.directory / f"{stamp}-{slug}.mcap"
        t = threading.Thread(target=self._write, args=(path, batches, reason, text),
                             name="blackbox-writer", daemon=True)
        t.start()
        self._writers = [w for w in self._writers if w.is_alive()] + [t]

    def _write(self, path: Path, batches: list[Any], reason: str, text: str) -> None:
        from controller.recording.mcap_io import write_batches

        with self._lock:
            try:
                self.directory.mkdir(parents=True, exist_ok=True)
                n = 1
                while path.exists():
                    path = path.with_name(f"{path.stem}-{n}.mcap")
                    n += 1
                tmp = path.with_name(path.name + ".tmp")  # complete files only under *.mcap
                write_batches(tmp, batches, rig=self.rig, events=[(reason, text)])
                tmp.replace(path)
                self.written.append(path)
                self._prune()
            except Exception as exc:  # reported, never raised into the controller
                self.warn(f"black box: {path.name} not written: {type(exc).__name__}: {exc}")

    def _prune(self) -> None:
        files = sorted(self.directory.glob("*.mcap"), key=lambda p: p.stat().st_mtime)
        total = sum(p.stat().st_size for p in files)
        while files and total > self.max_bytes and len(files) > 1:
            old = files.pop(0)
            total -= old.stat().st_size
            old.unlink(missing_ok=True)

    def join(self, timeout_s: float = 10.0) -> None:
        for t in self._writers:
            t.join(timeout_s)
