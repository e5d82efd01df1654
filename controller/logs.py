"""Logging for every process of the project: module loggers, the rig name in every record.

Nothing is logged per loop tick. Long-running commands call `setup_logging` once at start
with their `--log-level`; library code only does `log = logging.getLogger(__name__)`.
"""

from __future__ import annotations

import logging
import sys

_FORMAT = "%(asctime)s %(levelname)-7s %(name)s [rig=%(rig)s] %(message)s"


class _RigFilter(logging.Filter):
    """Stamps the process's rig name on every record that does not carry one."""

    def __init__(self, rig: str) -> None:
        super().__init__()
        self.rig = rig

    def filter(self, record: logging.LogRecord) -> bool:
        if not hasattr(record, "rig"):
            record.rig = self.rig
        return True


def setup_logging(level: str = "info", rig: str = "-") -> None:
    """Send the project's log records to stderr at `level`, each stamped with `rig`."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(_FORMAT))
    handler.addFilter(_RigFilter(rig))
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level.upper())
