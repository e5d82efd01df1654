"""The one place that opens a Zenoh session: endpoints, mode, credentials, TLS.

Every process of the project opens its session here: the controller (serving its rig, with
`--auth` enforcing users and access control), a router, and every client (dashboard, `dobtune
ctl`, `record`, `identify --connect`, the fleet overview, tests). So "never listen on all
interfaces by default", "no multicast scouting" and "credentials and TLS when given" hold
everywhere. The default listen endpoint is loopback only; a peer that only connects (a client,
a test) listens nowhere.

`connect(SessionOptions(...))` opens; `session_config` builds the configuration alone. Errors
are those of the parts: ValueError / AuthError / OSError for bad options or credentials files,
`zenoh.ZError` when the session cannot open (a busy port; with `fail_after_s`, no connection).
"""

from __future__ import annotations

import ipaddress
import json
import socket
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from controller import protocol as proto
from controller.auth import (
    AuthError,
    User,
    Users,
    acl_config,
    check_name,
    load_users,
    password_problem,
    read_password_file,
    write_dictionary,
)
from controller.tls import client_tls, server_tls

__all__ = [
    "DEFAULT_LISTEN",
    "MAX_MESSAGE_BYTES",
    "SessionOptions",
    "check_endpoint",
    "client_config",
    "connect",
    "exposure_problem",
    "is_loopback",
    "put_estop",
    "server_config",
    "session_config",
    "zenoh_config",
]

#: The controller's default: loopback only, never all interfaces.
DEFAULT_LISTEN: tuple[str, ...] = ("tcp/127.0.0.1:7447",)

#: The largest Zenoh message any session of the project assembles (Zenoh's default: 1 GiB).
#: A longer one is dropped while its fragments arrive, before it is whole, so it never costs
#: more than this much memory (issue 31: four 200 MB queries from a viewer took a controller
#: to 1.34 GB before its 64 KiB request limit could refuse them). The largest legitimate
#: message is a 1000-entry history reply: about 0.4 MB, 8 MB with every entry's verdict
#: carrying 24 reasons of 300 characters (tests/test_session_limits.py).
MAX_MESSAGE_BYTES = 16 * 1024 * 1024

_PROTOCOLS = ("tcp/", "udp/", "tls/", "quic/", "unixsock-stream/", "ws/")


@dataclass(frozen=True)
class SessionOptions:
    """How to open one Zenoh session."""

    connect: tuple[str, ...] = ()
    """Endpoints to dial (a controller, a router)."""
    listen: tuple[str, ...] = ()
    """Endpoints to listen on (a controller, a router; clients listen nowhere)."""
    mode: str | None = None
    """"peer", "client" or "router"; None: peer, or with credentials `client_config`'s choice."""
    auth: Path | str | None = None
    """Credentials: an auth directory, a password file (a Path) or the password (a str)."""
    user: str = ""
    """With `auth` and no `serve`: the user to log in as."""
    serve: tuple[str, ...] = ()
    """With `auth` (a directory): accept logins of its users and enforce the access control for
    these rigs (a controller, a router)."""
    internal: tuple[User, ...] = ()
    """With `serve`: accounts of this process's own helpers (the controller's edge process),
    accepted beside the users file's; their dictionary goes to `internal_dir`, never to the
    auth directory."""
    internal_dir: Path | None = None
    fail_after_s: float | None = None
    """With `auth` as a client: opening raises when no connection is made within this long."""
    insecure: bool = False
    """Without `auth`: accept listening on (or, listening or as a router, linking to) an
    endpoint that is not loopback, where anyone who reaches it may act (`--insecure`)."""


def check_endpoint(endpoint: str) -> str:
    """A Zenoh endpoint `proto/address` (e.g. tcp/127.0.0.1:7447); ValueError naming it if not."""
    if not isinstance(endpoint, str) or not endpoint.startswith(_PROTOCOLS):
        raise ValueError(
            f"endpoint {endpoint!r}: expected <proto>/<address>, e.g. tcp/127.0.0.1:7447"
        )
    return endpoint


def is_loopback(endpoint: str) -> bool:
    """Whether `endpoint` (proto/host:port, proto/[v6]:port, unixsock-stream/path) is local:
    every address its host resolves to is a loopback address (`tcp/127.example.com:P` is
    whatever DNS says, not loopback by its spelling). A host that does not resolve is not."""
    proto_, _, rest = check_endpoint(endpoint).partition("/")
    if proto_ == "unixsock-stream":
        return True
    address = rest.split("#", 1)[0].split("?", 1)[0]
    host, _, port = address.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not host:
        return False
    try:
        infos = socket.getaddrinfo(host, port or None, proto=socket.IPPROTO_TCP)
    except (OSError, UnicodeError):
        return False
    addresses = {str(info[4][0]).split("%", 1)[0] for info in infos}
    return bool(addresses) and all(ipaddress.ip_address(a).is_loopback for a in addresses)


def exposure_problem(listen: Iterable[str], connect: Iterable[str], insecure: bool,
                     serves: bool = True) -> str:
    """Why a session without authentication must not open this way ("" if it may).

    Without `--auth`, anyone who reaches a listening endpoint, or a router this session links
    to, may act (apply, start, reset, take the lease, impersonate streams). So a listen
    endpoint, and for a session that serves others (a controller, a router: `serves`) a
    connect endpoint, must be loopback unless `insecure`. The one check of the controller,
    the router and every client that listens."""
    if insecure:
        return ""
    for flag, endpoints in (("--listen", listen), ("--connect", connect if serves else ())):
        for e in endpoints:
            if not is_loopback(e):
                return (
                    f"{flag} {e}: not loopback (its host does not resolve to loopback "
                    "addresses only); without --auth DIR (see `dobtune auth init`) anyone who "
                    "reaches it could move the rig. Give --auth, or --insecure to accept that"
                )
    return ""


def zenoh_config(
    listen: Iterable[str] = DEFAULT_LISTEN, connect: Iterable[str] = ()
) -> zenoh.Config:
    """A peer configuration with exactly these endpoints, multicast scouting off and no
    message over MAX_MESSAGE_BYTES assembled (every other configuration builds on it)."""
    listen_l = [check_endpoint(e) for e in listen]
    connect_l = [check_endpoint(e) for e in connect]
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("listen/endpoints", json.dumps(listen_l))
    conf.insert_json5("connect/endpoints", json.dumps(connect_l))
    conf.insert_json5("scouting/multicast/enabled", "false")
    # A peer that connects to a controller not yet up keeps retrying instead of failing.
    conf.insert_json5("connect/exit_on_failure", "false")
    # ... and finds it within a second of it listening (Zenoh's default backs off to 4 s).
    conf.insert_json5(
        "connect/retry", "{period_init_ms: 250, period_max_ms: 1000, period_increase_factor: 2}"
    )
    conf.insert_json5("listen/exit_on_failure", "true")
    # Oversized messages refused before they are assembled (see MAX_MESSAGE_BYTES).
    conf.insert_json5("transport/link/rx/max_message_size", json.dumps(MAX_MESSAGE_BYTES))
    return conf


def session_config(o: SessionOptions) -> zenoh.Config:
    """The configuration `connect(o)` opens."""
    if o.auth is None:
        if o.user:
            raise ValueError("user: needs auth (the credentials of that user)")
        serves = bool(o.listen) or o.mode == "router"
        why = exposure_problem(o.listen, o.connect, o.insecure, serves)
        if why:
            raise ValueError(why)
        conf = zenoh_config(o.listen, o.connect)
        if o.mode is not None and o.mode != "peer":
            conf.insert_json5("mode", json.dumps(o.mode))
        return conf
    if o.serve:
        return server_config(Path(o.auth), o.serve, o.listen, o.connect, mode=o.mode or "peer",
                             internal=o.internal, internal_dir=o.internal_dir)
    if not o.user:
        raise ValueError("user: required with auth")
    return client_config(o.auth, o.user, o.connect, o.listen, fail_after_s=o.fail_after_s,
                         mode=o.mode)


def put_estop(session: zenoh.Session, key: str, sender: str) -> None:
    """An e-stop put on `key` (any payload stops the loop; no reply needed)."""
    msg = proto.Command(body=proto.EStop(), client=sender)
    session.put(key, proto.encode(msg))


def connect(o: SessionOptions) -> zenoh.Session:
    """Open the session `o` describes (use it as a context manager: `with connect(o) as s:`).

    A session that declared a queryable must be closed, or the interpreter can hang at exit.
    """
    return zenoh.open(session_config(o))


def server_config(
    directory: Path,
    rig_names: Sequence[str],
    listen: Iterable[str] = DEFAULT_LISTEN,
    connect: Iterable[str] = (),
    mode: str = "peer",
    internal: Sequence[User] = (),
    internal_dir: Path | None = None,
) -> zenoh.Config:
    """The configuration of a controller (mode "peer") or router serving `rig_names`.

    Every session that connects must authenticate with a user of `directory/users.toml`; the
    ACL (default deny) gives each user the rules of its role on its rigs. Rewrites the Zenoh
    dictionary from the users file when they differ.

    `connect` must be empty: user/password authenticates only the side that dials, so the ACL
    of a session that dials out denies everything to the remote. A controller behind a router
    uses `client_config(directory, <its "controller" user>, [router], mode="client")` and the
    router (this function, mode "router") enforces the rules."""
    if mode not in ("peer", "router"):
        raise ValueError(f"mode {mode!r}: expected peer or router")
    if list(connect):
        raise ValueError(
            "connect: a server with access control cannot dial out (the remote would be "
            "unauthenticated and denied everything); behind a router, open the controller "
            'with client_config(..., mode="client")'
        )
    for rig in rig_names:
        proto.check_rig_name(rig)
    users = load_users(directory)
    try:
        acl = acl_config([*users, *internal], rig_names)
    except ValueError as exc:
        raise AuthError(f"{users.path}: {exc}") from None
    if internal:
        if internal_dir is None:
            raise ValueError("internal: needs internal_dir (where its dictionary is written)")
        users = Users(internal_dir, {**users.by_name, **{u.name: u for u in internal}})
    dictionary = write_dictionary(users)
    conf = zenoh_config(listen, ())
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5(
        "transport/auth/usrpwd/dictionary_file", json.dumps(str(dictionary.resolve()))
    )
    conf.insert_json5("access_control", json.dumps(acl))
    server_tls(conf, Path(directory))
    return conf


def client_config(
    credentials: Path | str,
    user: str,
    connect: Iterable[str],
    listen: Iterable[str] = (),
    fail_after_s: float | None = None,
    mode: str | None = None,
) -> zenoh.Config:
    """A client's configuration: explicit endpoints, no multicast, logging in as `user`.

    `credentials`: an auth directory (its users file has the password), a password file (a
    Path), or the password itself (a str). `mode`: "client" (the default without `listen`)
    reaches a controller directly or through a router (a router does not route between peers
    that listen nowhere, and an authenticated controller behind a router listens nowhere);
    "peer" (the default with `listen`) to be reachable itself.
    `fail_after_s`: `zenoh.open` raises when no connection succeeded within that time
    (unreachable or refused credentials look the same); by default it opens anyway and keeps
    retrying."""
    listen = tuple(listen)
    if mode is None:
        mode = "peer" if listen else "client"
    if mode not in ("peer", "client"):
        raise ValueError(f"mode {mode!r}: expected peer or client")
    if isinstance(credentials, Path):
        if credentials.is_dir():
            password = load_users(credentials)[user].password
        else:
            password = read_password_file(credentials)
    else:
        password = credentials
        why = password_problem(password)
        if why:
            raise AuthError(f"password of {user}: {why}")
    conf = zenoh_config(listen, connect)
    conf.insert_json5("mode", json.dumps(mode))
    login = {"user": check_name(user, "user"), "password": password}
    conf.insert_json5("transport/auth/usrpwd", json.dumps(login))
    if isinstance(credentials, Path):
        # The authority of the auth directory (or of the password file's directory): on tls/
        # endpoints the client then accepts only the controller it certified.
        client_tls(conf, credentials if credentials.is_dir() else credentials.parent)
    if fail_after_s is not None:
        conf.insert_json5("connect/exit_on_failure", "true")
        conf.insert_json5("connect/timeout_ms", json.dumps(max(1, round(fail_after_s * 1000))))
    return conf
