"""The dashboard: a viser app that joins one controller's Zenoh session, composed of small parts.

- `server.options`: what it is started with, and the users who each get a URL;
- `server.session` (`BrowserSessions`): who is at each browser, the client acting for them,
  their lease; `server.dashboard.candidates` (`Candidates`): each browser's own tuning candidate;
- `server.commands` (`CommandRouter`): a browser's apply and commands to the controller;
- the shared views, one module each in `server/panels/`: live (banner, E-STOP, traces),
  identify, knowledge (measured responses), history, recordings, and `server.panels.fleet`.

Built once at start: the shared views (every browser sees the same); the tuning candidate (its
controls, verdict and charts) is per browser, built into that browser's `client.gui` when it
connects, so two engineers never edit one candidate. Afterwards worker threads only assign new
data to existing handles. The HTTP server binds 127.0.0.1 unless told otherwise, and share
tunnels are disabled.

Who acts: see `server.session` (one identity, or with `--auth DIR` and no `--user` one URL per
user, a viewer's changes refused here and an operator's sent as that operator).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import logging
import secrets
import signal
import socket
import threading
import types
from collections.abc import Callable, Iterator
from pathlib import Path

import viser

from controller import protocol as proto
from controller.auth import User
from controller.client import ClientOptions, ControllerClient, ControllerUnavailable
from controller.client.recorder import RecordOptions
from controller.core.config import LoopConfig
from controller.core.heap import freeze_startup_heap
from server.assets import web_asset
from server.commands import CommandRouter
from server.dashboard.browsers import Browsers
from server.dashboard.candidates import CandidatePlace, Candidates
from server.dashboard.page_views import PLOTS_WIDTH_PX, PageViews
from server.engine import TuningEngine
from server.http_access import GateOpen, HttpAccess, title_html
from server.message_gate import MessageGate
from server.options import DashboardOptions, dashboard_users
from server.panels.fleet import FleetMonitor, FleetPanel
from server.panels.history import HistoryPanel
from server.panels.identify import IdentifyPanel
from server.panels.knowledge import KnowledgePanel
from server.panels.live import LivePanel
from server.panels.nominal_tuning import NominalTuningPanel
from server.panels.recordings import RecordingsPanel
from server.panels.trends import TrendsPanel
from server.panels.widgets import EXPORT_LABEL
from server.scene3d import TurntableScene
from server.session import BrowserSessions, leased
from server.viser_adapter import (
    disable_share_url,
    filter_incoming,
)
from server.workers import Requests, run_logged

__all__ = [
    "PLOTS_WIDTH_PX",
    "Dashboard",
    "DashboardOptions",
    "PortBusy",
    "check_port_free",
    "run_dashboard",
    "stop_requested",
]

log = logging.getLogger(__name__)

def _asset(name: str, default: str = "") -> str:
    try:
        return web_asset(name).read_text(encoding="utf-8")
    except OSError as exc:
        log.warning("web asset %s unreadable (%s); showing a placeholder", name, exc)
        return default


@contextlib.contextmanager
def stop_requested() -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM while the block runs (the old handlers come back)."""
    stop = threading.Event()

    def _handler(signum: int, _frame: types.FrameType | None) -> None:
        stop.set()  # nothing else here: a signal handler must not take locks (logging does)

    old = {s: signal.signal(s, _handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def streams_client(opts: DashboardOptions, users: dict[str, User]) -> ControllerClient:
    """The client the streams come through: a viewer's when the users are several."""
    viewers = [n for n, u in users.items() if u.role == "viewer"]
    monitor = opts.user or (viewers or sorted(users) or [""])[0]
    return ControllerClient(ClientOptions(
        connect=tuple(opts.connect), rig_name=opts.rig_name,
        query_timeout_s=opts.query_timeout_s, client_name=opts.client_name, auth=opts.auth,
        user=monitor))


def access_gate(opts: DashboardOptions, users: dict[str, User]) -> HttpAccess:
    """Who may open the dashboard: a token per user, or the one token (given, or made)."""
    if users:
        return HttpAccess(opts.host, users={n: secrets.token_urlsafe(24) for n in users})
    return HttpAccess(opts.host) if opts.token is None else HttpAccess(opts.host, opts.token)


def record_options(opts: DashboardOptions, client: ControllerClient) -> RecordOptions:
    """The recorder's way to the dashboard's rig (its `out` is set per recording); with
    credentials, the streams' user (every role may record)."""
    user = client.opts.user if opts.auth is not None else ""
    return RecordOptions(connect=tuple(opts.connect), out=Path(opts.recordings_dir),
                         rig_name=opts.rig_name, auth=opts.auth, user=user)


def trends_tab(gui: viser.GuiApi, plots: viser.PanelHandle, opts: DashboardOptions,
               messages: MessageGate) -> TrendsPanel:
    """The plots panel's Trends tab (`server.panels.trends`), started; every role may choose
    its range and rig (what it reads and shows, for every browser)."""
    panel = TrendsPanel(gui, opts.trend_dirs, opts.rig_name, PLOTS_WIDTH_PX)
    with plots.add_tab("Trends"):
        panel.build()
    for handle in panel.controls:
        messages.open_to_all(handle)
    panel.start()
    return panel


def build_or_depart(server: viser.ViserServer | None, client: viser.ClientHandle,
                    build: Callable[[], None], depart: Callable[[], None]) -> None:
    """`build()` the new browser's own panels; if it left before or during the build, what
    was built for it is dropped (`depart()`: its disconnect callback may have run first, and
    its panel would live on unseen). viser removes a browser's containers and handles when
    it leaves, so a build racing the departure raises KeyError (a removed container) or
    RuntimeError (an assignment to a removed handle): taken as the departure; either from a
    browser still here is a fault and propagates."""

    def present() -> bool:
        return server is not None and client.client_id in server.get_clients()

    try:
        build()
    except (KeyError, RuntimeError):
        if present():
            raise
    if not present():
        log.info("browser %d left while its panels were built", client.client_id)
        depart()


class Dashboard:
    """Client + viser server + the parts above, wired together (context manager)."""

    def __init__(self, opts: DashboardOptions) -> None:
        self.opts = opts
        users = dashboard_users(opts)
        self.client = streams_client(opts, users)
        self.access = access_gate(opts, users)
        self._requests = Requests(max_workers=2, name="ctl-request")
        self.sessions = BrowserSessions(opts, users, self.client, self._requests)
        self.engine = TuningEngine(sim_disturbances=opts.sim_disturbances)
        self.candidates = Candidates(self.engine, self.sessions, self._requests, self.client,
                                     self._who, opts.candidates_dir, opts.rig_name)
        self.commands = CommandRouter(self.sessions, self._requests, self._show_command)
        self._place: CandidatePlace | None = None
        """Where each browser's candidate is built (the shared GUI's tabs, once built)."""
        self.access.on_estop = self.commands.estop_from_link
        self.access.page_extra = title_html(opts.rig_name)
        self.server: viser.ViserServer | None = None
        self.messages: MessageGate | None = None
        """The judge of every message a browser sends (built with the server)."""
        self.identify: IdentifyPanel | None = None
        self.recordings: RecordingsPanel | None = None
        self.live: LivePanel | None = None
        self.history: HistoryPanel | None = None
        self.knowledge: KnowledgePanel | None = None
        self.scene: TurntableScene | None = None
        self.fleet: FleetPanel | None = None
        self.trends: TrendsPanel | None = None
        self._fleet_monitor: FleetMonitor | None = None
        self._views: dict[str, Dashboard] = {}
        self._views_lock = threading.Lock()
        self.plots: viser.PanelHandle | None = None
        self.browsers: Browsers | None = None
        """The browsers of the server (built with it)."""
        self.pages: PageViews | None = None
        """What each page shows (built with the server)."""

    @property
    def users(self) -> dict[str, User]:
        return self.sessions.users

    @property
    def url(self) -> str:
        """The address to open: it carries the access token (keep it private). With several
        users: the first operator's (see `url_for`)."""
        operators = [n for n, u in self.users.items() if u.role == "operator"]
        return self.url_for((operators or sorted(self.users) or [""])[0])

    def url_for(self, user: str) -> str:
        """The address for `user` ("" with one identity): it carries that user's token."""
        assert self.server is not None
        return (f"http://{self.server.get_host()}:{self.server.get_port()}/"
                f"?token={self.access.token_of(user)}")

    def __enter__(self) -> Dashboard:
        check_port_free(self.opts.host, self.opts.port)
        with contextlib.ExitStack() as undo:
            self.client.__enter__()
            undo.push(self)  # a failure below closes what is open so far
            # viser's banner (printed whatever `verbose` says) shows a URL without the token,
            # which opens a 401 page: it goes nowhere; run_dashboard prints the URL.
            with self.access.serving(), contextlib.redirect_stdout(io.StringIO()):
                server = viser.ViserServer(host=self.opts.host, port=self.opts.port,
                                           verbose=False)
            self.access.port = server.get_port()
            disable_share_url(server)  # never a public share tunnel from this app
            self.server = server
            browsers = self.browsers = Browsers(server, self.access, self.sessions)
            self.pages = PageViews(browsers)
            self.access.on_view = self._on_view
            self.messages = MessageGate(role_of=browsers.role_of, shared_gui=server.gui,
                                        gui_of=browsers.gui_of, tell=browsers.tell,
                                        name_of=browsers.name_of, restore=browsers.restore,
                                        open_if=_is_export_row)
            filter_incoming(server, self.messages)
            self.access.prove(self.opts.host)  # GateOpen: nothing is served
            self._build(server, self.pages)
            undo.pop_all()
        return self

    def __exit__(self, *exc: object) -> None:
        self._close()

    def close(self) -> None:
        self._close()

    def _close(self) -> None:
        self.candidates.close()
        for panel in (self.live, self.identify, self.fleet, self.trends):
            if panel is not None:
                panel.stop()
        if self.recordings is not None and self.recordings.recording_to is not None:
            self.recordings.stop_recording()
        if self._fleet_monitor is not None:
            self._fleet_monitor.close()
        with self._views_lock:
            views, self._views = list(self._views.values()), {}
        for v in views:
            run_logged(v.close, what="closing a rig's full view")
        self._requests.shutdown()
        if self.server is not None:
            run_logged(self.server.stop, what="stopping the viser server")
            self.server = None
        self.sessions.close()
        self.client.__exit__(None, None, None)

    def open_view(self, rig: str, browser: viser.ClientHandle | None = None) -> str:
        """The full view of `rig` (another dashboard in this process, on a free port of the
        same host, with the same endpoints and credentials); its URL for `browser`'s user
        (with several users, each their own token: a viewer never gets an operator's)."""
        proto.check_rig_name(rig)
        user = self.sessions.signed_in_user(browser, "full view")
        if rig == self.opts.rig_name:
            return self.url_for(user)
        with self._views_lock:
            view = self._views.get(rig)
            if view is None:
                with socket.socket() as s:
                    s.bind((self.opts.host, 0))
                    port = int(s.getsockname()[1])
                view = Dashboard(dataclasses.replace(
                    self.opts, rig_name=rig, port=port, fleet=False, token=None))
                view.__enter__()
                self._views[rig] = view
        return view.url_for(user)

    # -- a browser's candidate (the public way in for scripts and tests) -------------------------

    def panel_in(self, gui: viser.GuiApi,
                 browser: viser.ClientHandle | None = None) -> NominalTuningPanel:
        """A candidate panel of its own in `gui` (`Candidates.panel_in`)."""
        assert self._place is not None, "the dashboard's GUI is not built yet"
        return self.candidates.panel_in(gui, self._place, browser)

    def panel_of(self, browser: viser.ClientHandle | None) -> NominalTuningPanel | None:
        """The candidate panel of `browser` (None: the one built without a browser)."""
        return self.candidates.panel_of(browser)

    @property
    def panels(self) -> dict[int, NominalTuningPanel]:
        """The candidate panels by browser (viser client id; -1: built without a browser)."""
        return self.candidates.panels

    # -- building ------------------------------------------------------------------------------

    def _build(self, server: viser.ViserServer, pages: PageViews) -> None:
        gui = server.gui
        gui.configure_theme(control_width="large", show_share_button=False,
                            brand_color=(31, 119, 180))
        gui.set_panel_label("dobtune")
        self.scene = TurntableScene(server.scene, server.get_event_loop())
        self.knowledge = KnowledgePanel(gui, self.client, self.engine, self.sessions,
                                        self._requests, self.candidates.update_all)
        self.identify = IdentifyPanel(gui, self.candidates.panel_of,
                                      config_fn=lambda: self.candidates.active or LoopConfig(),
                                      add_measured=self.knowledge.add_identified,
                                      client=self.client, client_for=self.sessions.client_for,
                                      leased=leased, authorize=self.sessions.check_may_change)
        live = LivePanel(
            gui, self.client, self.commands.command_async, on_status=self._on_status,
            on_frame=self._on_frame, rate_hz=self.opts.live_rate_hz,
            max_points=self.opts.live_max_points, audience=pages.live_audience,
            authorize=self.sessions.check_may_change, loop=server.get_event_loop(),
        )
        self.live = live
        self.history = HistoryPanel(gui, self.client, self._requests, self.candidates.panel_of)

        gui.add_html(_asset("header.html", "<b>dobtune</b>"))
        live.build_banner()
        live.build_estop()
        tabs = gui.add_tab_group()
        with tabs.add_tab("Tune") as tune_tab:
            self.knowledge.build()
        with tabs.add_tab("Live"):
            live.build_controls()
            view = gui.add_button("Hide / show the 3-D view", color="gray",
                                  hint="in this browser: the charts take the 3-D view's space, "
                                  "or give it back")
            view.on_click(lambda e: self._toggle_3d(e.client))
        assert self.messages is not None and live.estop_button is not None
        self.messages.open_to_all(live.estop_button)  # every role, each browser's own view
        self.messages.open_to_all(view)
        with tabs.add_tab("Identify"):
            self.identify.build_controls()
        if self.opts.fleet:
            self._fleet_monitor = FleetMonitor(
                self.client.session,
                (lambda r: self.client.key(proto.key_estop(r)))).__enter__()
            self.fleet = FleetPanel(gui, self._fleet_monitor, self.open_view)
            with tabs.add_tab("Fleet"):
                self.fleet.build()
            # Every role may E-STOP any rig (the rig picked, then the button) and open a
            # rig's full view (as its own user).
            for handle in (self.fleet.pick, self.fleet.estop_button, self.fleet.open_button):
                self.messages.open_to_all(handle)
        with tabs.add_tab("History"):
            self.history.build()
        with tabs.add_tab("Recordings"):
            recordings = RecordingsPanel(gui, self.opts.recordings_dir,
                                         record=record_options(self.opts, self.client),
                                         rig_name=self.opts.rig_name,
                                         authorize=self.sessions.check_may_change)
            self.recordings = recordings
            recordings.build()
        with tabs.add_tab("Help"):
            gui.add_markdown(_asset("help.md", "Help texts are missing (web_assets/help.md)."))

        plots = gui.add_panel()
        with plots.add_tab("Bode") as bode_tab:
            pass  # each browser's candidate charts, built when it connects
        with plots.add_tab("Live traces"):
            live.build_charts()
        with plots.add_tab("Identify"):
            self.identify.build_charts()
        recordings.build_compare(plots)  # each browser's comparison, built when it connects
        self.trends = trends_tab(gui, plots, self.opts, self.messages)
        plots.dock_right()
        run_logged(lambda: gui.main_panel.dock_left(), what="docking the controls left")
        run_logged(plots.set_width, PLOTS_WIDTH_PX, what="sizing the plots panel")
        self.plots = plots
        self._place = CandidatePlace(tune_tab, bode_tab, self.identify)

        server.on_client_connect(self._on_client_connect)
        server.on_client_disconnect(self._on_client_disconnect)
        live.start()
        if self.fleet is not None:
            self.fleet.start()
        self._requests.submit(self._fetch_active)

    # -- wiring ------------------------------------------------------------------------------

    def _show_command(self, html: str) -> None:
        if self.live is not None:
            self.live.command_result.content = html

    def _on_client_connect(self, client: viser.ClientHandle) -> None:
        build_or_depart(self.server, client, lambda: self._build_for(client),
                        lambda: self._on_client_disconnect(client))

    def _build_for(self, client: viser.ClientHandle) -> None:
        """Who is at the new browser; its own candidate; its camera on the turntable."""
        assert self.browsers is not None
        self.browsers.sign_in(client)
        self.panel_in(client.gui, client)
        if self.knowledge is not None:
            self.knowledge.offer_to(client, self.browsers.role_of(client.client_id) == "operator")
        if self.recordings is not None:
            self.recordings.compare_in(client.gui, client)
        client.camera.position = (0.75, -0.85, 0.75)
        client.camera.look_at = (0.15, 0.0, 0.05)

    def _toggle_3d(self, browser: viser.ClientHandle | None) -> None:
        if self.pages is not None and self.plots is not None:
            self.pages.toggle_3d(browser, self.plots)

    def _who(self, browser: viser.ClientHandle | None) -> tuple[str, str]:
        """(user, candidate slot) of a browser: whose candidate it edits, and which."""
        slot = self.browsers.slot_of(browser) if self.browsers is not None else ""
        return self.sessions.user_of(browser) or "", slot

    def _on_view(self, page: str, live_shown: bool) -> None:
        """A page says whether it shows the live traces; one that shows them again gets
        their present data at once (`PageViews.note_view`)."""
        if self.pages is None or self.live is None:
            return
        for browser in self.pages.note_view(page, live_shown):
            self.live.show_in(browser)

    def _on_client_disconnect(self, client: viser.ClientHandle) -> None:
        self.sessions.left(client.client_id)
        if self.messages is not None:
            self.messages.forget(client.client_id)
        self.candidates.drop(client.client_id)
        if self.recordings is not None:
            self.recordings.drop(client.client_id)
        if self.knowledge is not None:
            self.knowledge.drop(client.client_id)
        if self.pages is not None:
            self.pages.forget(client.client_id)

    def _fetch_active(self) -> None:
        try:
            reply = self.client.get_config()
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("active config not fetched (the first status will bring it): %s", exc)
            return
        self.candidates.set_active(reply.config, reply.version)

    def _on_status(self, st: proto.Status) -> None:
        if self.history is not None:
            self.history.follow.note(st.config_version)
        if self.knowledge is not None:
            self.knowledge.follow.note(st.knowledge_version)
        self.candidates.set_active(st.config, st.config_version, st.trajectory)

    def _on_frame(self, latest: dict[str, float] | None) -> None:
        if latest is not None and self.scene is not None and self.pages is not None and (
                self.pages.shows_3d()):  # while none shows it, not moved (moved after)
            self.scene.update(latest["pos_deg"], latest["ref_deg"])


def _is_export_row(handle: object) -> bool:
    """A chart's Export row (server/panels/widgets.py): its CSV goes to the browser that
    pressed it alone, so any role may press it."""
    return (isinstance(handle, viser.GuiButtonGroupHandle) and handle.label == EXPORT_LABEL
            and tuple(handle.options) == ("CSV",))


class PortBusy(RuntimeError):
    pass


def check_port_free(host: str, port: int, what: str = "--port") -> None:
    """viser moves to the next free port on its own; a dashboard must not silently appear
    elsewhere than asked: a busy port is an error that says so."""
    import socket

    if port == 0:
        return
    with socket.socket() as s:
        # As the server binds (asyncio's reuse_address on POSIX): the connections of a
        # dashboard just stopped, lingering in TIME_WAIT for a minute, do not make the port
        # busy (a restart on the same port failed without it); a listener still does.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            raise PortBusy(
                f"{what} {port}: {host}:{port} is in use ({exc.strerror}); choose another {what}"
            ) from None


def run_dashboard(opts: DashboardOptions) -> int:
    """Run until SIGINT/SIGTERM; returns the exit code (2: the port is busy, the users file is
    bad, or the access gate is not in front of every route: nothing is served)."""
    try:
        check_port_free(opts.host, opts.port)
    except PortBusy as exc:
        print(f"dobtune dashboard: {exc}", flush=True)
        return 2
    try:
        users = dashboard_users(opts)
    except ValueError as exc:  # AuthError included: it names the file and field
        print(f"dobtune dashboard: {exc}", flush=True)
        return 2
    with stop_requested() as stop:
        try:
            dash = Dashboard(opts).__enter__()
        except GateOpen as exc:  # nothing is served
            print(f"dobtune dashboard: {exc}", flush=True)
            return 2
        with contextlib.closing(dash):
            freeze_startup_heap()
            print(f"dobtune dashboard: {dash.url}  (rig '{opts.rig_name}' via "
                  f"{', '.join(opts.connect)})", flush=True)
            for name, user in sorted(users.items()):
                print(f"dobtune dashboard: {user.role} {name}: {dash.url_for(name)}", flush=True)
            while not stop.wait(0.5):
                pass
    return 0
