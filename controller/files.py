"""Durable file writes: a file replaced whole or not at all.

`write_atomically` writes the new content to a temporary file beside the target
(`.<name>.<random>.tmp`, same directory: same file system), fsyncs it and renames it over the
target: a reader (or a restart after a crash) finds the old file or the new one, never a part
of one. A failed write leaves the old file as it was and removes its temporary file. The rename
itself is on disk once the directory is fsynced (`fsync_dir`), which the caller does (the
controller's state store overlaps it with its change log's fsync).

Used by the controller's state directory (controller/process/persistence.py) and the
dashboard's kept candidates (server/candidate_store.py).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

__all__ = ["fsync_dir", "write_atomically"]


def write_atomically(path: Path, data: bytes, mode: int = 0o644) -> None:
    """Replace `path` by a file holding `data` (permissions `mode`: mkstemp's 0600 would hide
    it from other tools), fsynced before the rename. Raises OSError (the old file untouched)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        try:
            os.fchmod(fd, mode)
            view = memoryview(data)
            while view:
                n = os.write(fd, view)
                view = view[n:]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def fsync_dir(directory: Path) -> None:
    """Put `directory`'s entries (a rename into it) on disk; a file system that cannot fsync a
    directory is left as it is (the file's own content was fsynced)."""
    try:
        dfd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(dfd)
    finally:
        os.close(dfd)
