"""The tuning candidates, one per browser: each browser edits its own candidate (controls in
the Tune tab, charts in the Bode tab, built into that browser's `client.gui`), so two engineers
never edit one candidate. Every candidate follows the controller's active configuration.

Each candidate comes with its guided tuning path (server/panels/guide.py) above its controls,
and is kept for a reload of its browser tab (server/candidate_store.py): a page that connects
naming a slot gets the candidate kept for it; with a directory, also after a restart of the
dashboard (what went wrong with its files is shown to the user in the candidate's panel)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import viser

from controller.client import ControllerClient
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from server.candidate_apply import CandidateApply
from server.candidate_store import CandidateStore
from server.engine import TuningEngine
from server.panels.guide import GuidePanel
from server.panels.identify import IdentifyPanel
from server.panels.nominal_tuning import NominalTuningPanel
from server.panels.tuning import kept_problem
from server.session import BrowserSessions
from server.workers import Requests

__all__ = ["CandidatePlace", "Candidates"]


@dataclass(frozen=True)
class CandidatePlace:
    """Where a browser's candidate is built in the dashboard's GUI: its controls (with its
    guided path) in the Tune tab, its charts in the Bode tab; the identification panel its
    guide reads."""

    tune_tab: viser.GuiTabHandle
    bode_tab: viser.GuiTabHandle
    identify: IdentifyPanel | None


class Candidates:
    """The candidate panels by browser (viser client id; -1: built on the shared GUI by
    `panel_in` without a browser, as scripts and tests do) and the active configuration they
    start from."""

    def __init__(self, engine: TuningEngine, sessions: BrowserSessions, requests: Requests,
                 client: ControllerClient,
                 who: Callable[[viser.ClientHandle | None], tuple[str, str]],
                 directory: Path | None = None, rig: str = "") -> None:
        """`sessions`, `requests`: how a candidate's Apply reaches the controller (its
        `CandidateApply`); `client`: the controller client the guides read; `who(browser)`:
        the (user, candidate slot) of a browser; `directory`: where rig `rig`'s candidates are
        kept on disk (None: in memory only)."""
        self.engine = engine
        self._sessions = sessions
        self.applier = CandidateApply(sessions, requests, self.set_active)
        """Every candidate panel's Apply (the reply's active configuration comes back here)."""
        self.client = client
        self.who = who
        self.panels: dict[int, NominalTuningPanel] = {}
        self._lock = threading.Lock()
        self._build_lock = threading.Lock()
        """A viser tab takes one `with` at a time: browsers that connect at once build their
        panels one after the other."""
        self.active: LoopConfig | None = None
        self.active_version: int | None = None
        self.trajectory: Trajectory | None = None
        self.guides: dict[int, GuidePanel] = {}
        """The guided tuning path of each browser (keyed as `panels`)."""
        self._users: dict[int, str] = {}
        """The user of each panel (keyed as `panels`)."""
        self.kept = CandidateStore(directory=directory, rig=rig, check=kept_problem,
                                   on_problem=self._show_problem)
        """Each browser tab's candidate, kept for a reload of that tab (and a restart)."""

    def panel_in(self, gui: viser.GuiApi, place: CandidatePlace,
                 browser: viser.ClientHandle | None = None
                 ) -> NominalTuningPanel:
        """A candidate panel of its own in `gui` (a browser's `client.gui`; or the shared GUI
        without a browser), built at `place`: controls in the Tune tab, charts in the Bode
        tab, started on the active configuration when it is known."""
        user, slot = self.who(browser)
        t = NominalTuningPanel(gui, self.engine, self.applier,
                               on_change=lambda p: self.kept.keep(user, slot, p.kept()))
        kept = self.kept.get(user, slot)
        guide = GuidePanel(gui, t, place.identify, self.client,
                           authorize=self._sessions.check_may_change,
                           may_change=self._may_change(browser))
        with self._build_lock:
            with place.tune_tab:
                guide.build()
                t.build_controls()
            with place.bode_tab:
                t.build_charts()
        key = getattr(browser, "client_id", -1)
        with self._lock:
            old = self.panels.pop(key, None)
            self.panels[key] = t
            self._users[key] = user
            old_guide = self.guides.pop(key, None)
            self.guides[key] = guide
            if self.active is not None:
                t.set_active(self.active, self.active_version)
            if self.trajectory is not None:
                t.set_trajectory(self.trajectory)
        for stale in (old, old_guide):
            if stale is not None:
                stale.stop()
        t.show_kept_problem(self.kept.problem(user))
        if kept is not None:
            t.restore(kept)
        t.start()
        guide.start()
        return t

    def _may_change(self, browser: viser.ClientHandle | None) -> bool:
        """Whether the user at `browser` may change the rig (an operator; anyone with one
        identity): a viewer's page gets the operators' guided-path controls disabled."""
        users = self._sessions.users
        if not users:
            return True
        user = self._sessions.user_of(browser)
        return user is not None and users[user].role == "operator"

    def panel_of(self, browser: viser.ClientHandle | None) -> NominalTuningPanel | None:
        """The candidate panel of `browser` (None: the one built without a browser)."""
        with self._lock:
            return self.panels.get(getattr(browser, "client_id", -1))

    def drop(self, browser_id: int) -> None:
        """The browser left: its panel stops."""
        with self._lock:
            t = self.panels.pop(browser_id, None)
            self._users.pop(browser_id, None)
            guide = self.guides.pop(browser_id, None)
        for stale in (guide, t):
            if stale is not None:
                stale.stop()

    def _show_problem(self, user: str, text: str) -> None:
        """`user`'s kept candidates: `text` (from the store's writer) in each of their panels."""
        with self._lock:
            panels = [t for key, t in self.panels.items() if self._users.get(key) == user]
        for t in panels:
            t.show_kept_problem(text)

    def close(self) -> None:
        """Every panel stopped, the kept candidates written."""
        self.stop_all()
        self.kept.close()

    def stop_all(self) -> None:
        with self._lock:
            panels, self.panels = list(self.panels.values()), {}
            guides, self.guides = list(self.guides.values()), {}
        for g in guides:
            g.stop()
        for t in panels:
            t.stop()

    def set_active(self, cfg: LoopConfig, version: int,
                   trajectory: Trajectory | None = None) -> None:
        """The controller's active configuration (and trajectory), to every candidate panel."""
        with self._lock:
            self.active, self.active_version = cfg, version
            if trajectory is not None:
                self.trajectory = trajectory
            panels = list(self.panels.values())
        for t in panels:
            t.set_active(cfg, version)
            if trajectory is not None:
                t.set_trajectory(trajectory)

    def update_all(self) -> None:
        """Every candidate re-evaluated (the plant knowledge changed)."""
        with self._lock:
            panels = list(self.panels.values())
        for t in panels:
            t.request_update()
