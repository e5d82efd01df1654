"""The candidates kept for a reload: one per browser tab (and user), in the dashboard process.

A browser tab names its slot (web_assets/dashboard.js: an id in the tab's sessionStorage,
sent with the websocket's URL; `server.http_access.slot_of_path`); every change of that tab's
candidate is kept here under (user, slot), and a page that connects with a slot gets the
candidate kept for it. What is kept is what the controls showed (a typed cut-off as typed, an
invalid one too), the configuration the candidate was built on and the active version it was
made against: restored, a candidate made against an older version is stale like before the
reload (the panel says so, Apply is off and the controller refuses it: its Apply carries that
version).
Nothing here is trusted: the values go back into the controls and through the same checks.
Kept in memory: a restart of the dashboard starts every tab on the active configuration.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

from controller.core.config import LoopConfig, NominalModel

__all__ = ["CandidateStore", "KeptCandidate"]


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


class CandidateStore:
    """(user, slot) -> the latest `KeptCandidate`; the `capacity` most recently used only (a
    client cannot grow it without bound by naming new slots)."""

    def __init__(self, capacity: int = 256) -> None:
        self.capacity = capacity
        self._kept: OrderedDict[tuple[str, str], KeptCandidate] = OrderedDict()
        self._lock = threading.Lock()

    def keep(self, user: str, slot: str, kept: KeptCandidate) -> None:
        if not slot:
            return
        with self._lock:
            self._kept[(user, slot)] = kept
            self._kept.move_to_end((user, slot))
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
