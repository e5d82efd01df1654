"""The applied configurations as a HistoryReply, read from the change log: one function for
the controller's service and its edge process (which answers history requests itself, so a
flood of them never reaches the loop's process)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from controller import protocol as proto
from controller.core.config import config_from_builtins
from controller.core.errors import ConfigError
from controller.process.persistence import verdict_of_change

__all__ = ["MAX_LAST", "history_reply"]

#: The most entries one request may ask for.
MAX_LAST = 1000


def _entry_name(item: dict[str, Any]) -> str:
    """How a change-log line is named in a message: by its version if it has one."""
    v = item.get("version")
    return f"v{v}" if isinstance(v, int) and not isinstance(v, bool) else "an entry"


def history_reply(read_changes: Callable[[], list[dict[str, Any]]], last: int,
                  ) -> proto.HistoryReply:
    """The newest `last` applied configurations of the change log `read_changes` returns
    (oldest first)."""
    if isinstance(last, bool) or not 1 <= last <= MAX_LAST:
        return proto.HistoryReply(
            ok=False, field="last", message=f"last: {last} not in 1..{MAX_LAST}"
        )
    try:
        items = read_changes()[-last:]
    except OSError as exc:
        return proto.HistoryReply(ok=False, field="state_dir",
                                  message=f"state_dir: the change log cannot be read: {exc}")
    entries = []
    unread: list[str] = []
    for item in items:
        try:
            entries.append(proto.HistoryEntry(
                version=int(item["version"]), time_s=float(item.get("time_s") or 0.0),
                client=str(item.get("client", ""))[:200],
                config=config_from_builtins(item["new"]),
                verdict=verdict_of_change(item),
            ))
        except KeyError as exc:
            unread.append(f"{_entry_name(item)}: {exc.args[0]}: missing")
        except (TypeError, ValueError, ConfigError) as exc:
            unread.append(f"{_entry_name(item)}: {exc}")
    # A line this version cannot read is left out, and the reply says which and why.
    message = "" if not unread else (
        f"{len(unread)} entr{'y' if len(unread) == 1 else 'ies'} of the change log not "
        f"shown ({'; '.join(unread[:3])[:600]})")
    return proto.HistoryReply(ok=True, entries=entries, message=message)
