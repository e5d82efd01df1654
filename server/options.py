"""What a dashboard is started with (`DashboardOptions`) and who may use it (`dashboard_users`)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from controller.auth import User

__all__ = ["DashboardOptions", "dashboard_users", "default_candidates_dir",
           "default_recordings_dir"]


def data_dir() -> Path:
    """The user's data directory for dobtune, outside any working tree ($XDG_DATA_HOME/dobtune,
    else ~/.local/share/dobtune)."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "dobtune"


def default_recordings_dir() -> Path:
    """Where recordings go unless told: <data>/recordings (`data_dir`)."""
    return data_dir() / "recordings"


def default_candidates_dir() -> Path:
    """Where `dobtune dashboard` keeps each user's candidates unless told: <data>/candidates
    (`data_dir`), one directory per rig."""
    return data_dir() / "candidates"


@dataclass(frozen=True)
class DashboardOptions:
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    rig_name: str = "demo"
    host: str = "127.0.0.1"
    port: int = 8080
    live_rate_hz: float = 10.0
    """The live traces' refresh (and the banner's). At 25 Hz a page in software rendering drew
    3 of them a second and decoded the rest (~60 kB each) for nothing."""
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
    candidates_dir: Path | None = None
    """Where each user's candidates are kept on disk, so that they survive a restart of the
    dashboard (`server.candidate_store`; None: in memory only, as scripts and tests run it;
    `dobtune dashboard` and `dobtune demo` default to `default_candidates_dir`)."""
    fleet: bool = False
    """Also the fleet overview: every rig reachable through `connect` (a router), each with an
    E-STOP and a full view of its own."""
    trend_dirs: tuple[Path, ...] = ()
    """Where the Trends tab finds the rigs' trends (`<state-dir>/trend` of their controllers:
    `<dir>/<rig>/<hour>.mcap`; () : the tab says there is none; `dobtune dashboard` defaults
    to `var/<rig>/trend`, the controller's default, and `dobtune demo` passes its own)."""
    sim_disturbances: tuple[str, ...] = ()
    """The named disturbances of the simulated rig the previews and Suggest run on (the
    demo's: the same as its controller's simulated rig)."""


def dashboard_users(opts: DashboardOptions) -> dict[str, User]:
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
