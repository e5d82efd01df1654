"""The dashboard: a viser app that joins one controller's Zenoh session.

Built once at start: the live state, the identification, the history and the fleet are shared
GUI (every browser sees the same); the tuning candidate (its controls, verdict and charts) is
per browser, built into that browser's `client.gui` when it connects, so two engineers never
edit one candidate. Afterwards worker threads only assign new data to existing handles. The
HTTP server binds 127.0.0.1 unless told otherwise, and share tunnels are disabled.

Who acts. Without authentication, or with `--auth` and one `--user`, every browser acts as
the dashboard's one identity. With `--auth DIR` and no `--user`, each user of `DIR/users.toml`
who may reach the rig gets a URL of their own (a token per user): the dashboard knows which
user is behind each browser, refuses a viewer's changes itself (told to that browser only;
a raw websocket client can press any control, so the check is here, on the server, per
client) and sends an operator's changes through a Zenoh session logged in as that operator,
so the controller's access control, lease and audit see the real user, never the dashboard.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import secrets
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from controller import protocol as proto
from controller.client import ClientOptions, ControllerClient, ControllerUnavailable
from controller.client.recorder import RecordOptions
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import MeasuredResponse
from server.assets import web_asset
from server.engine import TuningEngine, measured_from_csv
from server.escape import esc
from server.fleet import FleetMonitor, FleetPanel
from server.gate import ESTOP_LINK_HTML, Gate, Refused, title_html
from server.measured import read_measured
from server.panels.identify import IdentifyPanel, NominalTuningPanel
from server.panels.live import LivePanel
from server.panels.recordings import RecordingsPanel
from server.panels.tuning import config_diff_html
from server.scene3d import TurntableScene
from server.workers import Requests, run_logged

__all__ = [
    "Dashboard",
    "DashboardOptions",
    "PortBusy",
    "check_port_free",
    "run_dashboard",
    "stop_requested",
]

log = logging.getLogger(__name__)

#: How long a lease the dashboard takes for its user's changes (renewed on the next change).
LEASE_S = 300.0
R = TypeVar("R")


def default_recordings_dir() -> Path:
    """Where recordings go unless told: a data directory of the user's, outside any working
    tree ($XDG_DATA_HOME/dobtune/recordings, else ~/.local/share/dobtune/recordings)."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "dobtune" / "recordings"


@dataclass(frozen=True)
class DashboardOptions:
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    rig_name: str = "demo"
    host: str = "127.0.0.1"
    port: int = 8080
    live_rate_hz: float = 25.0
    live_max_points: int = 600
    query_timeout_s: float = 3.0
    verbose: bool = True
    """Kept for callers; viser's own banner is never printed (its URL carries no token: it opens
    a 401 page). run_dashboard prints the URL with the token."""
    client_name: str = "dashboard"
    token: str | None = None
    """The browser access token (None: a random one, in the printed URL)."""
    auth: Path | None = None
    """With a controller that authenticates: the `dobtune auth init` directory or a password
    file, and `user`, whose role and lease the controller enforces. A directory without
    `user`: every user in it who may reach the rig, each in their own browser."""
    user: str = ""
    recordings_dir: Path = field(default_factory=lambda: default_recordings_dir())
    """The .mcap files the Recordings tab lists and compares (`dobtune record --out`, a
    controller's `<state-dir>/blackbox`)."""
    fleet: bool = False
    """Also the fleet overview: every rig reachable through `connect` (a router), each with an
    E-STOP and a full view of its own."""
    sim_disturbances: tuple[str, ...] = ()
    """The named disturbances of the simulated rig the previews and Suggest run on (the
    demo's: the same as its controller's simulated rig)."""


def dashboard_users(opts: DashboardOptions) -> dict[str, Any]:
    """The users who each get their own URL ({} : one identity for every browser)."""
    if opts.auth is None or opts.user:
        return {}
    from controller.auth import load_users

    if not opts.auth.is_dir():
        raise ValueError(f"user: {opts.auth} is a password file: name its user with --user")
    users = {u.name: u for u in load_users(opts.auth)
             if u.role in ("operator", "viewer") and u.serves(opts.rig_name)}
    if not users:
        raise ValueError(f"auth: no operator or viewer in {opts.auth} may reach rig "
                         f"{opts.rig_name!r}")
    if opts.token is not None:
        raise ValueError("token: one token per user is made with several users")
    return users


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

    def _handler(signum: int, _frame: Any) -> None:
        stop.set()  # nothing else here: a signal handler must not take locks (logging does)

    old = {s: signal.signal(s, _handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)


class Dashboard:
    """Client + viser server + panels (context manager)."""

    def __init__(self, opts: DashboardOptions) -> None:
        self.opts = opts
        self.users = dashboard_users(opts)
        # The streams come through one session: a viewer's when the users are several.
        viewers = [n for n, u in self.users.items() if u.role == "viewer"]
        monitor = opts.user or (viewers or sorted(self.users) or [""])[0]
        self.client = ControllerClient(
            ClientOptions(
                connect=tuple(opts.connect),
                rig_name=opts.rig_name,
                query_timeout_s=opts.query_timeout_s,
                client_name=opts.client_name,
                auth=opts.auth,
                user=monitor,
            )
        )
        if self.users:
            self.gate = Gate(opts.host, users={n: secrets.token_urlsafe(24) for n in self.users})
        else:
            self.gate = Gate(opts.host) if opts.token is None else Gate(opts.host, opts.token)
        self._browser_users: dict[int, str] = {}
        self._acting: dict[str, ControllerClient] = {}
        self._acting_lock = threading.Lock()
        self.refusals = 0
        """Actions refused here (a viewer's change, an unknown browser)."""
        self.gate.on_estop = self._estop_from_link
        self.gate.page_extra = ESTOP_LINK_HTML + title_html(opts.rig_name)
        self.server: Any = None
        self.engine = TuningEngine(sim_disturbances=opts.sim_disturbances)
        self._knowledge_version = -1  # the plant knowledge fetched from the controller
        self._history_version = -1
        self._history: dict[int, LoopConfig] = {}
        self._requests = Requests(max_workers=2, name="ctl-request")
        self.panels: dict[int, NominalTuningPanel] = {}
        """The candidate panels, one per browser (viser client id; -1: built on the shared
        GUI by `panel_in` without a browser, as scripts and tests do)."""
        self._panels_lock = threading.Lock()
        self._build_lock = threading.Lock()
        """A viser tab takes one `with` at a time: browsers that connect at once build their
        panels one after the other."""
        self.active: LoopConfig | None = None
        self.active_version: int | None = None
        self.trajectory: Trajectory | None = None
        self.identify: IdentifyPanel | None = None
        self.recordings: RecordingsPanel | None = None
        self.live: LivePanel | None = None
        self.scene: TurntableScene | None = None
        self.fleet: FleetPanel | None = None
        self._fleet_monitor: FleetMonitor | None = None
        self._views: dict[str, Dashboard] = {}
        self._views_lock = threading.Lock()

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
                f"?token={self.gate.token_of(user)}")

    def __enter__(self) -> Dashboard:
        import viser

        check_port_free(self.opts.host, self.opts.port)
        with contextlib.ExitStack() as undo:
            self.client.__enter__()
            undo.push(self)  # a failure below closes what is open so far
            # viser's banner (printed whatever `verbose` says) shows a URL without the token,
            # which opens a 401 page: it goes nowhere; run_dashboard prints the URL.
            with self.gate.serving(), contextlib.redirect_stdout(io.StringIO()):
                server = viser.ViserServer(host=self.opts.host, port=self.opts.port,
                                           verbose=False)
            self.gate.port = server.get_port()
            # Never open a public share tunnel from this app.
            server.request_share_url = lambda *a, **k: None  # type: ignore[method-assign]
            self.server = server
            self._build(server)
            undo.pop_all()
        return self

    def __exit__(self, *exc: object) -> None:
        self._close()

    def _close(self) -> None:
        with self._panels_lock:
            panels, self.panels = list(self.panels.values()), {}
        for panel in (self.live, *panels, self.identify, self.fleet):
            if panel is not None:
                panel.stop()
        if self.recordings is not None and self.recordings.recording_to is not None:
            self.recordings.stop_recording()
        if self._fleet_monitor is not None:
            self._fleet_monitor.close()
        with self._views_lock:
            views, self._views = list(self._views.values()), {}
        for v in views:
            run_logged(v._close, what="closing a rig's full view")
        self._requests.shutdown()
        if self.server is not None:
            run_logged(self.server.stop, what="stopping the viser server")
            self.server = None
        with self._acting_lock:
            acting, self._acting = list(self._acting.values()), {}
        for c in acting:
            c.__exit__(None, None, None)
        self.client.__exit__(None, None, None)

    def open_view(self, rig: str, browser: Any = None) -> str:
        """The full view of `rig` (another dashboard in this process, on a free port of the
        same host, with the same endpoints and credentials); its URL for `browser`'s user
        (with several users, each their own token: a viewer never gets an operator's)."""
        proto.check_rig_name(rig)
        user = self.user_of(browser)
        if user is None:
            self._refuse(browser, "full view: this browser is not signed in")
        if rig == self.opts.rig_name:
            return self.url_for(user)
        with self._views_lock:
            view = self._views.get(rig)
            if view is None:
                import dataclasses
                import socket

                with socket.socket() as s:
                    s.bind((self.opts.host, 0))
                    port = int(s.getsockname()[1])
                view = Dashboard(dataclasses.replace(
                    self.opts, rig_name=rig, port=port, fleet=False, token=None))
                view.__enter__()
                self._views[rig] = view
        return view.url_for(user)

    # -- who acts ------------------------------------------------------------------------------

    def user_of(self, browser: Any) -> str | None:
        """The user behind a browser (viser client handle); "" with one identity; None:
        unknown (with several users, a browser must have come through its user's token)."""
        if not self.users:
            return ""
        return self._browser_users.get(getattr(browser, "client_id", -1))

    def client_for(self, browser: Any, action: str) -> ControllerClient:
        """The controller client that does `action` for this browser; `Refused` here (a
        viewer's change, an unknown browser), with the reason shown to that browser too."""
        if not self.users:
            return self.client
        user = self.user_of(browser)
        if user is None:
            self._refuse(browser, f"{action}: this browser is not signed in")
        if action == "e-stop":
            return self._estop_client(user)
        self.check_may_change(browser, action)
        with self._acting_lock:
            c = self._acting.get(user)
        return c if c is not None else self._open_acting(user)

    def check_may_change(self, browser: Any, action: str) -> None:
        """`Refused` (told to that browser alone) unless the user at `browser` may change the
        rig: an operator, or anyone without users (one identity for every browser)."""
        if not self.users:
            return
        user = self.user_of(browser)
        if user is None:
            self._refuse(browser, f"{action}: this browser is not signed in")
        if self.users[user].role != "operator":
            self._refuse(browser, f"{action}: {user} is a viewer: viewers watch and may E-STOP, "
                         f"not change the rig")

    def _estop_client(self, user: str) -> ControllerClient:
        """`user`'s own session when it is open; else, never waiting for a login, the
        streams' session (every role may e-stop)."""
        if not self.users:
            return self.client
        with self._acting_lock:
            c = self._acting.get(user)
        if c is None:
            self._requests.submit(self._open_acting, user)
            return self.client
        return c

    def _estop_from_link(self, user: str) -> str:
        """The always-visible E-STOP link (on viser's event loop: the put at once, the
        command for a reply in a worker)."""
        c = self._estop_client(user)
        try:
            c.put_estop()
        except Exception as exc:  # told to the page and logged; the command still follows
            log.exception("e-stop put from the E-STOP link failed")
            self._requests.submit(self._command, proto.EStop(), None, c)
            return f"E-STOP put failed ({exc}); the EStop command follows"
        self._requests.submit(self._command, proto.EStop(), None, c)
        log.warning("E-STOP from the page's E-STOP link (%s)", user or "dashboard")
        return "E-STOP sent"

    def _open_acting(self, user: str) -> ControllerClient:
        with self._acting_lock:
            c = self._acting.get(user)
            if c is None:
                o = self.opts
                c = ControllerClient(ClientOptions(
                    connect=tuple(o.connect), rig_name=o.rig_name,
                    query_timeout_s=o.query_timeout_s, client_name=f"{o.client_name}:{user}",
                    auth=o.auth, user=user, subscribe=False))
                c.__enter__()
                self._acting[user] = c
        return c

    def _refuse(self, browser: Any, why: str) -> NoReturn:
        self.refusals += 1
        log.warning("refused in the dashboard: %s", why)
        if browser is not None:
            run_logged(lambda: browser.add_notification(
                "Refused", why, color="red", auto_close_seconds=8.0), what="telling a browser")
        raise Refused(why)

    # -- building ------------------------------------------------------------------------------

    def _build(self, server: Any) -> None:
        gui = server.gui
        gui.configure_theme(control_width="large", show_share_button=False,
                            brand_color=(31, 119, 180))
        gui.set_panel_label("dobtune")
        self.scene = TurntableScene(server.scene)
        self.identify = IdentifyPanel(gui, self.panel_of,
                                      config_fn=lambda: self.active or LoopConfig(),
                                      add_measured=self._add_identified,
                                      client=self.client, client_for=self.client_for,
                                      leased=self.leased)
        live = LivePanel(
            gui, self.client, self._command_async, on_status=self._on_status,
            on_frame=self._on_frame, rate_hz=self.opts.live_rate_hz,
            max_points=self.opts.live_max_points,
        )
        self.live = live

        gui.add_html(_asset("header.html", "<b>dobtune</b>"))
        live.build_banner()
        live.build_estop()
        tabs = gui.add_tab_group()
        with tabs.add_tab("Tune") as self.tune_tab:
            # Shared, below each browser's own candidate controls (built when it connects).
            upload = gui.add_upload_button("Upload measured responses (CSV)",
                                           mime_type="text/csv,.csv", color="gray",
                                           order=_LAST)
            self.measured_text = gui.add_html(
                "<div class='dt-measured' style='font-size:12px;color:#555'>No measured "
                "responses: 1/|Delta| is the stated bound.</div>", order=_LAST + 1)
            upload.on_upload(self._on_upload)
        with tabs.add_tab("Live"):
            live.build_controls()
        with tabs.add_tab("Identify"):
            self.identify.build_controls()
        if self.opts.fleet:
            self._fleet_monitor = FleetMonitor(
                self.client.session,
                (lambda r: self.client.key(proto.key_estop(r)))).__enter__()
            self.fleet = FleetPanel(gui, self._fleet_monitor, self.open_view)
            with tabs.add_tab("Fleet"):
                self.fleet.build()
        with tabs.add_tab("History"):
            self.history_html = gui.add_html("<div class='dt-history'>No history yet.</div>")
            self.history_pick = gui.add_dropdown("Version", ("-",), initial_value="-")
            self.history_other = gui.add_dropdown(
                "Compare with", ("-",), initial_value="-",
                hint="the fields in which Version differs from this one")
            self.version_diff = gui.add_html("<div class='dt-version-diff'></div>")
            use = gui.add_button("Use as candidate", color="gray",
                                 hint="load that version into the controls; Apply sends it "
                                 "through the gate like any candidate")
            use.on_click(lambda e: self._use_version(e.client))
            self.history_pick.on_update(lambda _e: self._show_version_diff())
            self.history_other.on_update(lambda _e: self._show_version_diff())
        with tabs.add_tab("Recordings"):
            self.recordings = RecordingsPanel(gui, self.opts.recordings_dir,
                                              record=self._record_options(),
                                              rig_name=self.opts.rig_name,
                                              authorize=self.check_may_change)
            self.recordings.build()
        with tabs.add_tab("Help"):
            gui.add_markdown(_asset("help.md", "Help texts are missing (web_assets/help.md)."))

        plots = gui.add_panel()
        with plots.add_tab("Bode") as self.bode_tab:
            pass  # each browser's candidate charts, built when it connects
        with plots.add_tab("Live traces"):
            live.build_charts()
        with plots.add_tab("Identify"):
            self.identify.build_charts()
        plots.dock_right()
        run_logged(lambda: gui.main_panel.dock_left(), what="docking the controls left")
        run_logged(plots.set_width, 620, what="sizing the plots panel")
        self.plots = plots

        server.on_client_connect(self._on_client_connect)
        server.on_client_disconnect(self._on_client_disconnect)
        live.start()
        if self.fleet is not None:
            self.fleet.start()
        self._requests.submit(self._fetch_active)

    def _record_options(self) -> RecordOptions:
        """The recorder's way to this dashboard's rig (its `out` is set per recording)."""
        o = self.opts
        # With credentials: the streams' user (every role may record).
        user = self.client.opts.user if o.auth is not None else ""
        return RecordOptions(connect=tuple(o.connect), out=Path(o.recordings_dir),
                             rig_name=o.rig_name, auth=o.auth, user=user)

    # -- the candidates, one per browser --------------------------------------------------------

    def panel_in(self, gui: Any, browser: Any = None) -> NominalTuningPanel:
        """A candidate panel of its own in `gui` (a browser's `client.gui`; or the shared GUI
        without a browser): controls in the Tune tab, charts in the Bode tab, started on the
        active configuration when it is known."""
        t = NominalTuningPanel(gui, self.engine, self._apply_async)
        with self._build_lock:
            with self.tune_tab:
                t.build_controls()
            with self.bode_tab:
                t.build_charts()
        key = getattr(browser, "client_id", -1)
        with self._panels_lock:
            old = self.panels.pop(key, None)
            self.panels[key] = t
            if self.active is not None:
                t.set_active(self.active, self.active_version)
            if self.trajectory is not None:
                t.set_trajectory(self.trajectory)
        if old is not None:
            old.stop()
        t.start()
        return t

    def panel_of(self, browser: Any) -> NominalTuningPanel | None:
        """The candidate panel of `browser` (None: the one built without a browser)."""
        with self._panels_lock:
            return self.panels.get(getattr(browser, "client_id", -1))

    def _each_panel(self) -> list[NominalTuningPanel]:
        with self._panels_lock:
            return list(self.panels.values())

    def _set_active(self, cfg: LoopConfig, version: int,
                    trajectory: Trajectory | None = None) -> None:
        """The controller's active configuration (and trajectory), to every candidate panel."""
        with self._panels_lock:
            self.active, self.active_version = cfg, version
            if trajectory is not None:
                self.trajectory = trajectory
            panels = list(self.panels.values())
        for t in panels:
            t.set_active(cfg, version)
            if trajectory is not None:
                t.set_trajectory(trajectory)

    def _update_panels(self) -> None:
        for t in self._each_panel():
            t.request_update()

    # -- wiring ------------------------------------------------------------------------------

    def _on_client_connect(self, client: Any) -> None:
        """Note who is at the new browser (with several users) and point its camera at the
        turntable."""
        if self.users:
            # viser keeps each client's websocket; the gate noted whose token opened it.
            conn = self.server._websock_server._live_connections.get(client.client_id)
            user = self.gate.user_of_connection(conn) if conn is not None else None
            if user is None:
                log.error("browser %s: no user for its connection: it may only watch",
                          client.client_id)
            else:
                self._browser_users[client.client_id] = user
                role = self.users[user].role
                note = " (watch and E-STOP only)" if role == "viewer" else ""
                client.gui.add_html(
                    f"<div class='dt-whoami' style='font-size:12px'>Signed in as "
                    f"<b>{esc(user)}</b>, {esc(role)}{note}</div>")
                if role == "operator":
                    self._requests.submit(self._open_acting, user)
        self.panel_in(client.gui, client)
        client.camera.position = (0.75, -0.85, 0.75)
        client.camera.look_at = (0.15, 0.0, 0.05)

    def _on_client_disconnect(self, client: Any) -> None:
        self._browser_users.pop(client.client_id, None)
        with self._panels_lock:
            t = self.panels.pop(client.client_id, None)
        if t is not None:
            t.stop()

    def _fetch_active(self) -> None:
        try:
            reply = self.client.get_config()
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("active config not fetched (the first status will bring it): %s", exc)
            return
        self._set_active(reply.config, reply.version)

    def _fetch_history(self) -> None:
        try:
            reply = self.client.history(50)
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("history not fetched: %s", exc)
            self._history_version = -1
            return
        if not reply.ok:
            self.history_html.content = f"<div class='dt-history'>{esc(reply.message)}</div>"
            return
        self._history = {e.version: e.config for e in reply.entries}
        rows = []
        for e in reversed(reply.entries):
            m = e.margins
            pm = f"{m.phase_margin_deg:.1f}" if m is not None else "-"
            gm = f"{m.gain_margin_db:.1f}" if m is not None else "-"
            when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(e.time_s))
            rows.append(f"<tr><td>v{e.version}</td><td>{esc(when)}</td><td>{esc(e.client)}</td>"
                        f"<td>{esc(e.verdict or '-')}</td><td>{pm}</td><td>{gm}</td>"
                        f"<td>{esc(e.config.q_type)} {e.config.q_cutoff_hz:g} Hz</td></tr>")
        self.history_html.content = (
            "<div class='dt-history' style='font-size:12px'><table><tr><th>ver</th><th>when"
            "</th><th>who</th><th>verdict</th><th>PM</th><th>GM</th><th>Q</th></tr>"
            + "".join(rows) + "</table></div>")
        options = tuple(f"v{v}" for v in sorted(self._history, reverse=True)) or ("-",)
        self.history_pick.options = options
        self.history_pick.value = options[0]
        self.history_other.options = options
        self.history_other.value = options[min(1, len(options) - 1)]
        self._show_version_diff()

    def _show_version_diff(self) -> None:
        """The difference between the two versions chosen in the History tab."""
        a, b = str(self.history_other.value), str(self.history_pick.value)
        old = self._history.get(int(a[1:])) if a.startswith("v") else None
        new = self._history.get(int(b[1:])) if b.startswith("v") else None
        if old is None or new is None:
            self.version_diff.content = "<div class='dt-version-diff'></div>"
            return
        self.version_diff.content = config_diff_html(old, new, a, b, cls="dt-version-diff")

    def _use_version(self, browser: Any = None) -> None:
        """Load the chosen version into the candidate of the browser that asked."""
        t = self.panel_of(browser)
        value = str(self.history_pick.value)
        cfg = self._history.get(int(value[1:])) if value.startswith("v") else None
        if t is None or cfg is None:
            self._tell(browser, "Nothing loaded", "Choose a version first." if t is not None
                       else "This browser has no candidate panel.", "red")
            return
        t.load(cfg, self.active_version,
               say_text=f"Loaded {value} from the history as the candidate.")
        self._tell(browser, f"{value} is now your candidate",
                   "See the Tune tab: its verdict, then Apply sends it through the gate.", "blue")

    @staticmethod
    def _tell(browser: Any, title: str, body: str, color: str) -> None:
        """A notification in the browser that asked (nothing without one)."""
        if browser is not None:
            run_logged(lambda: browser.add_notification(title, body, color=color,
                                                        auto_close_seconds=8.0),
                       what="telling a browser")

    def _on_status(self, st: proto.Status) -> None:
        if st.config_version != self._history_version:
            self._history_version = st.config_version
            self._requests.submit(self._fetch_history)
        if st.knowledge_version != self._knowledge_version:
            self._knowledge_version = st.knowledge_version
            self._requests.submit(self._fetch_knowledge)
        self._set_active(st.config, st.config_version, st.trajectory)

    def _on_frame(self, latest: dict[str, float] | None) -> None:
        if latest is not None and self.scene is not None:
            self.scene.update(latest["pos_deg"], latest["ref_deg"])

    def _apply_async(self, panel: NominalTuningPanel, cand: LoopConfig, confirm: bool = False,
                     browser: Any = None) -> None:
        self._requests.submit(self._apply, panel, cand, confirm, browser)

    def _fetch_knowledge(self) -> None:
        """The controller's plant knowledge: the dashboard judges on nothing else."""
        try:
            reply = self.client.knowledge()
            self.engine.set_knowledge(reply.record)
        except (ControllerUnavailable, proto.ProtocolError, ValueError) as exc:
            log.warning("plant knowledge not fetched: %s", exc)
            self._knowledge_version = -1  # try again with the next status
            return
        log.info("plant knowledge v%d fetched (%s)", reply.record.version, reply.record.source)
        self._update_panels()

    @staticmethod
    def leased(client: ControllerClient, act: Callable[[], R]) -> R:
        """`act()`, under `client`'s user's operator lease when the controller authenticates:
        taken when that client holds none (the controller refuses it if someone else holds
        it: the reply says so), renewed once if the controller says the lease lapsed."""
        if not client.opts.user:
            return act()
        if not client.lease_token:
            client.lease("acquire", LEASE_S)
        reply = act()
        if getattr(reply, "field", "") == "lease":
            got = client.lease("renew" if client.lease_token else "acquire", LEASE_S)
            if not got.ok:
                got = client.lease("acquire", LEASE_S)
            if got.ok:
                reply = act()
        return reply

    def _apply(self, t: NominalTuningPanel, cand: LoopConfig, confirm: bool = False,
               browser: Any = None) -> None:
        """Send `t`'s candidate, made against `t.base_version` (the controller refuses it if
        the active version has moved on), and show the reply on `t`."""
        expect = t.base_version
        try:
            c = self.client_for(browser, "apply")
            reply = self.leased(c, lambda: c.apply(cand, confirm=confirm, expect_version=expect))
        except Refused:
            return  # logged, and told to the browser that asked (only)
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("apply failed: %s", exc)
            t.show_error(str(exc))
            return
        log.info("apply: %s, version %d", "accepted" if reply.accepted else "rejected",
                 reply.version)
        t.show_reply(reply.accepted, reply.version, list(reply.reasons))
        self._set_active(reply.config, reply.version)
        if reply.accepted:
            t.rebase(reply.config, reply.version)

    def _command_async(self, body: proto.CommandBody, browser: Any = None) -> None:
        if isinstance(body, proto.EStop):
            # The put goes out at once from the callback; the reply is shown when it comes.
            try:
                self.client_for(browser, "e-stop").put_estop()
            except Exception:
                log.exception("e-stop put failed; the EStop command follows")
        self._requests.submit(self._command, body, browser)

    def _command(self, body: proto.CommandBody, browser: Any = None,
                 via: ControllerClient | None = None) -> None:
        """Send `body` for `browser` (or through `via`) and show the reply."""
        live = self.live
        assert live is not None
        name = type(body).__name__
        try:
            if via is not None:
                reply = via.command(body)
            elif isinstance(body, proto.EStop):
                reply = self.client_for(browser, "e-stop").command(body)
            else:
                c = self.client_for(browser, name)
                reply = self.leased(c, lambda: c.command(body))
        except Refused:
            return  # logged, and told to the browser that asked (only)
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("command %s failed: %s", name, exc)
            live.command_result.content = _command_html(f"{name}: {esc(str(exc))}", False)
            return
        if not reply.ok:
            log.warning("command %s refused: %s", name, reply.message)
        live.command_result.content = _command_html(
            f"{name}: {'ok' if reply.ok else 'refused'} {esc(reply.message)} "
            f"(mode {reply.mode})", reply.ok)

    def _on_upload(self, event: Any) -> None:
        f = event.target.value
        self._requests.submit(self._load_measured, f.name, f.content, event.client)

    def _add_identified(self, m: MeasuredResponse, browser: Any = None) -> None:
        self._add_measured(m, "Identify", browser)

    def _load_measured(self, name: str, content: bytes, browser: Any = None) -> None:
        try:
            measured = measured_from_csv(name, read_measured(name, content))
        except ValueError as exc:
            log.warning("measured response %s not used: %s", name, exc)
            self.measured_text.content = (
                f"<div class='dt-measured' style='color:#d62728'>{esc(name)}: "
                f"{esc(str(exc))}</div>")
            return
        self._add_measured(measured, "CSV", browser)
        self._update_panels()

    def _add_measured(self, m: MeasuredResponse, source: str, browser: Any = None) -> None:
        """Send the response to the controller for adoption into its plant knowledge: the
        verdicts (the controller's and this dashboard's) use it once the controller has it."""
        try:
            c = self.client_for(browser, "plant knowledge")
            req = proto.KnowledgeRequest(record=self.engine.with_measured(m))
            reply = self.leased(c, lambda: c.knowledge(req))
        except Refused:
            return  # logged, and told to the browser that asked (only)
        except (ControllerUnavailable, proto.ProtocolError) as exc:
            log.warning("measured response %s not adopted: %s", m.name, exc)
            self.measured_text.content = (
                f"<div class='dt-measured' style='color:#d62728'>{esc(m.name)}: not adopted "
                f"by the controller: {esc(str(exc))}</div>")
            return
        if not reply.ok:
            self.measured_text.content = (
                f"<div class='dt-measured' style='color:#d62728'>{esc(m.name)}: refused by the "
                f"controller: {esc(reply.message)}</div>")
            return
        self.engine.set_knowledge(reply.record)
        self._knowledge_version = reply.record.version
        n = len(reply.record.measured)
        log.info("measured response %s adopted (%s); plant knowledge v%d has %d", m.name,
                 source, reply.record.version, n)
        self.measured_text.content = (
            f"<div class='dt-measured' style='font-size:12px'>plant knowledge "
            f"v{reply.record.version}: {n} measured response(s); last: {esc(m.name)} "
            f"({esc(source)}). The verdicts (here and in the controller) use them.</div>")


#: viser's order of the shared elements that follow each browser's own ones in a tab.
_LAST = 1e9


def _command_html(text: str, ok: bool) -> str:
    color = "#2e7d32" if ok else "#d62728"
    return f"<div class='dt-cmd' style='color:{color};font-size:12px'>{text}</div>"


class PortBusy(RuntimeError):
    pass



def check_port_free(host: str, port: int, what: str = "--port") -> None:
    """viser moves to the next free port on its own; a dashboard must not silently appear
    elsewhere than asked: a busy port is an error that says so."""
    import socket

    if port == 0:
        return
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise PortBusy(
                f"{what} {port}: {host}:{port} is in use ({exc.strerror}); choose another {what}"
            ) from None


def run_dashboard(opts: DashboardOptions) -> int:
    """Run until SIGINT/SIGTERM; returns the exit code (2: the port is busy)."""
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
    with stop_requested() as stop, Dashboard(opts) as dash:
        print(f"dobtune dashboard: {dash.url}  (rig '{opts.rig_name}' via "
              f"{', '.join(opts.connect)})", flush=True)
        for name, user in sorted(users.items()):
            print(f"dobtune dashboard: {user.role} {name}: {dash.url_for(name)}", flush=True)
        while not stop.wait(0.5):
            pass
    return 0
