"""The History tab (shared by every browser): the controller's change log, the difference
between two versions, and "Use as candidate" (into the candidate of the browser that asks)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import viser

from controller import protocol as proto
from controller.client import ControllerClient, ControllerUnavailable
from controller.core.config import LoopConfig
from controller.core.verdict import kind_of
from server.escape import esc
from server.gui import set_value
from server.panels.bode import fmt_value, gain_margin_items
from server.panels.nominal_tuning import NominalTuningPanel
from server.panels.tuning import config_diff_html
from server.prediction_view import prediction_html, state_of
from server.session import tell
from server.workers import Refetch, Requests

__all__ = ["HistoryPanel"]

log = logging.getLogger(__name__)


class HistoryPanel:
    """Fetched again whenever the controller's configuration version moves (`follow`)."""

    def __init__(self, gui: viser.GuiApi, client: ControllerClient, requests: Requests,
                 panel_of: Callable[[viser.ClientHandle | None], NominalTuningPanel | None],
                 ) -> None:
        """`panel_of(browser)`: that browser's candidate panel."""
        self.gui = gui
        self.client = client
        self._panel_of = panel_of
        self.follow = Refetch(requests, self.fetch)
        """`follow.note(version)`: the controller's configuration version (from a status);
        fetched again when it moves."""
        self.versions: dict[int, LoopConfig] = {}
        self.checks: list[proto.PredictionCheck] = []
        self._requests = requests

    def build(self) -> None:
        gui = self.gui
        self.prediction = gui.add_html(prediction_html([], None))
        self.table = gui.add_html("<div class='dt-history'>No history yet.</div>")
        # Each check the watch publishes (a prediction, then its verdict) refreshes the box.
        self.client.session.declare_subscriber(
            proto.key_prediction(self.client.opts.rig_name),
            lambda _s: self._requests.submit(self.fetch))
        self.pick = gui.add_dropdown("Version", ("-",), initial_value="-")
        self.other = gui.add_dropdown("Compare with", ("-",), initial_value="-",
                                      hint="the fields in which Version differs from this one")
        self.diff = gui.add_html("<div class='dt-version-diff'></div>")
        use = gui.add_button("Use as candidate", color="gray",
                             hint="load that version into the controls; Apply sends it "
                             "through the gate like any candidate")
        use.on_click(lambda e: self.use_version(e.client))
        self.pick.on_update(lambda _e: self.show_diff())
        self.other.on_update(lambda _e: self.show_diff())

    def fetch(self) -> None:
        try:
            reply = self.client.history(50)
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("history not fetched: %s", exc)
            self.follow.forget()
            return
        if not reply.ok:
            self.table.content = f"<div class='dt-history'>{esc(reply.message)}</div>"
            return
        self.versions = {e.version: e.config for e in reply.entries}
        if (reply.entries[-1].version if reply.entries else -1) < self.follow.version:
            # the history lagged the status that asked for it (at load ~12 the table stayed on
            # v2 under a v3 banner for a minute): the next status fetches again
            self.follow.forget()
        try:
            checks = self.client.prediction_checks(2.0)
        except proto.ProtocolError as exc:  # a watch of another version: said, not guessed
            log.warning("prediction checks not read: %s", exc)
            checks = []
        self.checks = checks
        running = reply.entries[-1].version if reply.entries else None
        self.prediction.content = prediction_html(checks, running)
        rows = []
        for e in reversed(reply.entries):
            v = e.verdict
            pm = fmt_value(v.margins.phase_margin_deg, 1) if v is not None else "-"
            gm = (" / ".join(f"{val} {unit}".strip() for _, val, unit in
                             gain_margin_items(v.margins)) if v is not None else "-")
            why = f" title='{esc('; '.join(v.reasons))}'" if v is not None and v.reasons else ""
            when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(e.time_s))
            rows.append(f"<tr><td>v{e.version}</td><td>{esc(when)}</td><td>{esc(e.client)}</td>"
                        f"<td{why}>{esc(kind_of(v))}</td><td>{pm}</td><td>{gm}</td>"
                        f"<td>{esc(e.config.q_type)} {e.config.q_cutoff_hz:g} Hz</td>"
                        f"<td>{esc(state_of(checks, e.version) or '-')}</td></tr>")
        note = (f"<div class='dt-history-note'>{esc(reply.message)}</div>"
                if reply.message else "")
        self.table.content = (
            "<div class='dt-history' style='font-size:12px'>" + note + "<table><tr><th>ver"
            "</th><th>when</th><th>who</th><th>verdict</th><th>PM</th><th>gain margins</th>"
            "<th>Q</th><th>prediction</th></tr>"
            + "".join(rows) + "</table></div>")
        options = tuple(f"v{v}" for v in sorted(self.versions, reverse=True)) or ("-",)
        self.pick.options = options
        k = next((c for c in checks if c.config_version == running), None)
        offered = k.rollback_to if k is not None and k.state == "failed badly" else None
        # a failed-badly prediction's rollback offer, ready for Use as candidate
        set_value(self.pick, f"v{offered}" if offered in self.versions else options[0])
        self.other.options = options
        # compared with the running version when a rollback is offered
        set_value(self.other, options[0 if offered in self.versions else
                                      min(1, len(options) - 1)])
        self.show_diff()

    def _chosen(self, value: str) -> LoopConfig | None:
        return self.versions.get(int(value[1:])) if value.startswith("v") else None

    def show_diff(self) -> None:
        """The difference between the two versions chosen."""
        a, b = str(self.other.value), str(self.pick.value)
        old, new = self._chosen(a), self._chosen(b)
        if old is None or new is None:
            self.diff.content = "<div class='dt-version-diff'></div>"
            return
        self.diff.content = config_diff_html(old, new, a, b, cls="dt-version-diff")

    def use_version(self, browser: viser.ClientHandle | None = None) -> None:
        """Load the chosen version into the candidate of the browser that asked."""
        t = self._panel_of(browser)
        value = str(self.pick.value)
        cfg = self._chosen(value)
        if t is None or cfg is None:
            tell(browser, "Nothing loaded", "Choose a version first." if t is not None
                 else "This browser has no candidate panel.", "red")
            return
        t.load(cfg, t.active_version,
               say_text=f"Loaded {value} from the history as the candidate.")
        tell(browser, f"{value} is now your candidate",
             "See the Tune tab: its verdict, then Apply sends it through the gate.", "blue")
