"""Authentication and access control with Zenoh's own mechanisms: user/password and ACL.

Findings (eclipse-zenoh 1.10.2; tests/integration/test_zenoh_acl.py checks them):
- usrpwd is one-way: the side that accepts a connection (controller, router) checks the opener's
  user name and an HMAC of its password against `dictionary_file` (plain `user:password` lines).
  The opener does not authenticate the acceptor and the traffic is not encrypted: on a network,
  use `tls/` endpoints as well. No or wrong credentials: the session "opens" with no peers and
  keeps retrying (`client_config(fail_after_s=...)` makes `zenoh.open` raise instead).
- The ACL (default deny) decides per remote user, flow (ingress/egress), message kind and key:
  a message passes only if an allowed key expression *includes* its key, so a wildcard get, put
  or subscription (`dobtune/**`) is denied unless one rule covers the whole wildcard. A denied
  message is dropped silently (a denied get gets no reply, only its timeout).
- zenoh-python does not tell who sent a query or sample: `source_info` is set by the sender
  (forgeable, None by default) and `Link.auth_identifier` is a TLS/QUIC certificate name only
  (None with usrpwd). So the key carries the user: a request on
  `dobtune/<rig>/@user/<name>/<what>` can only come from <name>, because the ACL lets no one
  else put or query there. `@user` is a verbatim chunk (`*` and `**` never match it), so the
  operator's `dobtune/<rig>/**` does not cover another user's scope.
- A session that dials out sees an unauthenticated remote, so its own ACL denies it everything:
  a server never dials out. Through a router (`server_config(mode="router")`), the controller
  and the clients connect in mode "client" (a router does not route between peers that listen
  nowhere) and the router enforces the rules.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import stat
import tempfile
import tomllib
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from controller import protocol as proto
from controller.protocol import USER_CHUNK, any_user_key, user_key, user_of_key

__all__ = [
    "ALL_RIGS",
    "DICTIONARY_FILE",
    "ROLES",
    "USERS_FILE",
    "USER_CHUNK",
    "AuthError",
    "User",
    "Users",
    "acl_config",
    "any_user_key",
    "check_name",
    "init_auth_dir",
    "load_users",
    "new_users",
    "password_problem",
    "read_password_file",
    "requester",
    "user_key",
    "user_of_key",
    "users_toml",
    "write_dictionary",
]

USERS_FILE = "users.toml"
#: The Zenoh user/password dictionary, generated from USERS_FILE (Zenoh reads only this form).
DICTIONARY_FILE = "zenoh-usrpwd.txt"
#: operator: changes its rigs; viewer: watches, reads, may e-stop; controller: the account a
#: controller uses to connect through a router (full access to its rigs' keys, every user's
#: scope included: trusted like the controller itself). Only a controller puts on a rig's
#: published keys (state, status, liveliness): a controller that listens itself (peer mode)
#: is the session enforcing the rules, so its own puts need no rule and no login; behind a
#: router it logs in with its `controller` account.
ROLES = ("operator", "viewer", "controller")
#: `rigs = ["*"]`: every rig the server serves.
ALL_RIGS = "*"
MIN_PASSWORD_LEN = 12

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
_USER_FIELDS = ("role", "rigs", "password")
_HEADER = """\
# dobtune users: Zenoh user/password authentication and access control.
# role: "operator" changes its rigs; "viewer" watches, reads and may e-stop;
#       "controller" is the account of a controller that connects through a router.
# rigs: the rig names this user may reach, or ["*"] for every rig.
# Keep this file private (mode 0600). After an edit, restart the controller or router: the
# Zenoh password dictionary next to this file is regenerated from it.
"""


class AuthError(ValueError):
    """A bad or missing users file, password file or user; the message names file and field."""


@dataclass(frozen=True)
class User:
    name: str
    role: str  #: one of ROLES
    rigs: tuple[str, ...]  #: rig names, or (ALL_RIGS,)
    password: str = field(repr=False)

    def serves(self, rig: str) -> bool:
        return ALL_RIGS in self.rigs or rig in self.rigs

    @property
    def may_change(self) -> bool:
        """Whether this user may apply configurations and send commands (given the lease)."""
        return self.role == "operator"


@dataclass(frozen=True)
class Users:
    """The validated users file of one auth directory."""

    directory: Path
    by_name: Mapping[str, User]

    def __getitem__(self, name: str) -> User:
        try:
            return self.by_name[name]
        except KeyError:
            raise AuthError(f"{self.path}: no user {name!r}") from None

    def __iter__(self) -> Iterator[User]:
        return iter(self.by_name.values())

    @property
    def path(self) -> Path:
        return self.directory / USERS_FILE


# -- keys: the user's own request scope ----------------------------------------------------------


def requester(users: Users, key_expr: object) -> User | None:
    """The authenticated user behind a request on a user-scoped key of its rig, else None.

    Trustworthy when every way into the session passes an ACL of `server_config`: its own
    (controller in peer mode) or its router's (controller in client mode behind a router). Only
    <name>, and "controller" accounts, can reach `dobtune/<rig>/@user/<name>/...`."""
    name = user_of_key(key_expr)
    user = users.by_name.get(name) if name is not None else None
    if user is None or not user.serves(str(key_expr).split("/")[1]):
        return None
    return user


# -- the users file ------------------------------------------------------------------------------


def check_name(name: str, what: str) -> str:
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(
            f"{what} {name!r}: 1-64 letters, digits, '_', '.', '-', starting with a letter or digit"
        )
    return name


def _check_private(path: Path) -> None:
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
    except OSError as exc:
        raise AuthError(f"{path}: cannot read: {exc.strerror}") from exc
    if mode & 0o077:
        raise AuthError(
            f"{path}: readable by others (mode {mode:04o}); refusing to use it: "
            f"`chmod 600 {path}` (and change the passwords if others may have read them)"
        )


def _user_from_toml(path: Path, name: str, table: Any) -> User:
    where = f"{path}: users.{name}"
    try:
        check_name(name, "user name")
    except ValueError as exc:
        raise AuthError(f"{where}: {exc}") from None
    if not isinstance(table, dict):
        raise AuthError(f"{where}: expected a table [users.{name}]")
    unknown = sorted(set(table) - set(_USER_FIELDS))
    if unknown:
        raise AuthError(f"{where}.{unknown[0]}: unknown field (expected {', '.join(_USER_FIELDS)})")
    for key in _USER_FIELDS:
        if key not in table:
            raise AuthError(f"{where}.{key}: missing")
    role, rigs, password = table["role"], table["rigs"], table["password"]
    if role not in ROLES:
        raise AuthError(f"{where}.role: unknown role {role!r} (expected {', '.join(ROLES)})")
    if not isinstance(rigs, list) or not rigs:
        raise AuthError(f'{where}.rigs: expected a non-empty list of rig names, or ["*"]')
    for rig in rigs:
        try:
            _check_rig(rig, alone=len(rigs) == 1)
        except ValueError as exc:
            raise AuthError(f"{where}.rigs: {exc}") from None
    why = password_problem(password)
    if why:
        raise AuthError(f"{where}.password: {why}")
    return User(name=name, role=role, rigs=tuple(rigs), password=password)


def _check_rig(rig: Any, alone: bool) -> None:
    if rig == ALL_RIGS:
        if not alone:
            raise ValueError('"*" (every rig) must be the only entry')
        return
    if not isinstance(rig, str):
        raise ValueError(f"{rig!r} is not a string")
    proto.check_rig_name(rig)


def password_problem(password: Any) -> str:
    """Why `password` cannot be used ("" if it can)."""
    if not isinstance(password, str) or not password:
        return "missing or not a string"
    if len(password) < MIN_PASSWORD_LEN:
        return f"shorter than {MIN_PASSWORD_LEN} characters"
    if not password.isprintable() or any(c.isspace() for c in password):
        return "contains spaces or control characters"
    return ""


def load_users(directory: Path) -> Users:
    """Read and validate `directory/users.toml` (private file, known roles, valid names)."""
    path = Path(directory) / USERS_FILE
    if not path.is_file():
        raise AuthError(f"{path}: no users file (create one with `dobtune auth init {directory}`)")
    _check_private(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise AuthError(f"{path}: cannot read: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise AuthError(f"{path}: invalid TOML: {exc}") from exc
    extra = sorted(set(data) - {"users"})
    if extra:
        raise AuthError(f"{path}: {extra[0]}: unknown top-level key (expected [users.<name>])")
    tables = data.get("users")
    if not isinstance(tables, dict) or not tables:
        raise AuthError(f"{path}: users: no [users.<name>] table")
    users = {name: _user_from_toml(path, name, t) for name, t in tables.items()}
    return Users(Path(directory), users)


def new_users(roles: Sequence[tuple[str, str]], rigs: Sequence[str] = (ALL_RIGS,)) -> list[User]:
    """Users (name, role) on these rigs, each with a random password."""
    names = [check_name(n, "user name") for n, _ in roles]
    if len(set(names)) != len(names):
        raise ValueError(f"user names repeat: {names}")
    for n, role in roles:
        if role not in ROLES:
            raise ValueError(f"user {n}: unknown role {role!r} (expected {', '.join(ROLES)})")
    if not rigs:
        raise ValueError("no rig names")
    for rig in rigs:
        _check_rig(rig, alone=len(rigs) == 1)
    return [User(n, role, tuple(rigs), secrets.token_urlsafe(24)) for n, role in roles]


def users_toml(users: Iterable[User]) -> str:
    out = [_HEADER]
    for u in users:
        out.append(
            f"\n[users.{json.dumps(u.name)}]\nrole = {json.dumps(u.role)}\n"
            f"rigs = {json.dumps(list(u.rigs))}\npassword = {json.dumps(u.password)}\n"
        )
    return "".join(out)


def _write_private(path: Path, text: str) -> None:
    """Write `text` to `path` with mode 0600, atomically (temporary file + rename)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o600)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _dictionary_text(users: Iterable[User]) -> str:
    return "".join(f"{u.name}:{u.password}\n" for u in users)


def write_dictionary(users: Users) -> Path:
    """(Re)write the Zenoh dictionary next to the users file when it differs; its path."""
    path = users.directory / DICTIONARY_FILE
    text = _dictionary_text(users)
    try:
        same = path.read_text(encoding="utf-8") == text
        private = not stat.S_IMODE(path.stat().st_mode) & 0o077
    except (OSError, UnicodeDecodeError):
        same = private = False
    if not (same and private):
        _write_private(path, text)
    return path


def init_auth_dir(directory: Path, users: Sequence[User], force: bool = False) -> Users:
    """Create `directory` (0700) with the users file and the Zenoh dictionary (both 0600).

    FileExistsError when a users file is there and not `force`."""
    directory = Path(directory)
    path = directory / USERS_FILE
    if path.exists() and not force:
        raise FileExistsError(path)
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    _write_private(path, users_toml(users))
    loaded = load_users(directory)
    write_dictionary(loaded)
    return loaded


# -- Zenoh configurations ------------------------------------------------------------------------

_ALL_MESSAGES = (
    "put", "delete", "query", "reply", "declare_subscriber", "declare_queryable",
    "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
)


@dataclass(frozen=True)
class _Grant:
    flows: tuple[str, ...]
    messages: tuple[str, ...]
    keys: tuple[str, ...]


def _own(keys: Iterable[str], user: str) -> tuple[str, ...]:
    """The public keys and the user's own scoped copies (what the user may send on)."""
    keys = tuple(keys)
    return keys + tuple(user_key(k, user) for k in keys)


def _declared(keys: Iterable[str]) -> tuple[str, ...]:
    """The public keys and the every-user copies (what the controller declares)."""
    keys = tuple(keys)
    return keys + tuple(any_user_key(k) for k in keys)


#: The fleet overview's subscriptions to every rig at once: the loop's streams and the
#: watch's drift state (its drift column).
_FLEET_STREAMS = tuple(f"{proto.KEY_PREFIX}/*/{what}" for what in ("state", "status", "drift"))


def _watched(rig: str) -> tuple[str, ...]:
    """What the watch publishes and answers for (its drift state, its alarms, the prediction
    checks): the rig's viewers read it as they read the loop's streams."""
    return proto.key_drift(rig), proto.key_drift_alarm(rig), proto.key_prediction(rig)


def _fleet(rig: str) -> list[_Grant]:
    """What the fleet overview and `ctl rigs` need: they subscribe to every rig at once
    (`dobtune/*/...`); the router then passes on the samples and liveliness of this rig only
    (the egress rules name it), so a user learns nothing of rigs it may not reach."""
    p = proto.KEY_PREFIX
    return [
        _Grant(("ingress",), ("declare_subscriber",), _FLEET_STREAMS),
        _Grant(("ingress",), ("declare_liveliness_subscriber", "liveliness_query"),
               (f"{p}/*/alive",)),
        _Grant(("egress",), ("liveliness_token",), (proto.key_alive(rig),)),
    ]


def _viewer(rig: str, user: str) -> list[_Grant]:
    """Receive state and status and the watch's drift, read config and identification, put
    e-stop."""
    streams = (proto.key_state(rig), proto.key_status(rig), *_watched(rig))
    reads = (
        proto.key_config(rig), proto.key_identify(rig), proto.key_knowledge(rig),
        proto.key_lease(rig), proto.key_history(rig),
        proto.key_state_replay(rig),  # the stream's lost samples again: readable as it is
    )
    estop = (proto.key_estop(rig),)
    return [
        *_fleet(rig),
        _Grant(("ingress",), ("declare_subscriber",), streams),
        _Grant(("egress",), ("put",), streams),
        _Grant(("ingress",), ("query",), _own(reads, user)),
        _Grant(("egress",), ("reply",), _own(reads, user)),
        _Grant(("egress",), ("declare_queryable",), _declared(reads)),
        # The watch answers on the public keys only (it is no user's request handler).
        _Grant(("ingress",), ("query",), _watched(rig)),
        _Grant(("egress",), ("reply", "declare_queryable"), _watched(rig)),
        _Grant(("ingress",), ("put",), _own(estop, user)),
        _Grant(("egress",), ("declare_subscriber",), _declared(estop)),
    ]


def _operator(rig: str, user: str) -> list[_Grant]:
    """Every request on the rig, in the user's own scope (and the public keys); puts on the
    e-stop only. The rig's published keys (state, status, its liveliness) are the controller's:
    no user may put on them (or declare the rig alive), so a subscriber of them receives the
    controller's samples and no one else's."""
    rig_all = f"{proto.KEY_PREFIX}/{rig}/**"
    mine = (rig_all, f"{proto.KEY_PREFIX}/{rig}/{USER_CHUNK}/{user}/**")
    seen = (rig_all, f"{proto.KEY_PREFIX}/{rig}/{USER_CHUNK}/*/**")
    asks = ("query", "declare_subscriber", "declare_liveliness_subscriber", "liveliness_query")
    return [
        *_fleet(rig),
        _Grant(("ingress",), asks, mine),
        _Grant(("ingress",), ("put",), _own((proto.key_estop(rig),), user)),
        _Grant(("egress",), ("put", "delete", "reply"), mine),
        _Grant(("egress",), ("declare_subscriber", "declare_queryable", "liveliness_token"), seen),
    ]


def _controller(rig: str, user: str) -> list[_Grant]:
    """Serves the rig through a router: every message on every key of the rig."""
    keys = (f"{proto.KEY_PREFIX}/{rig}/**", f"{proto.KEY_PREFIX}/{rig}/{USER_CHUNK}/*/**")
    p = proto.KEY_PREFIX
    return [
        _Grant(("ingress", "egress"), _ALL_MESSAGES, keys),
        # The fleet overview's interest in every rig at once reaches the controller (and the
        # watch, which logs in with this account), which then sends its streams and liveliness
        # to the router (that passes them on by rule).
        _Grant(("egress",), ("declare_subscriber",), _FLEET_STREAMS),
        _Grant(("egress",), ("declare_liveliness_subscriber", "liveliness_query"),
               (f"{p}/*/alive",)),
    ]


_ROLE_GRANTS = {"viewer": _viewer, "operator": _operator, "controller": _controller}


def acl_config(users: Iterable[User], rig_names: Sequence[str]) -> dict[str, Any]:
    """The Zenoh `access_control` section: default deny, one subject and policy per user.

    A user gets the rules of its role on each rig it may reach among `rig_names`."""
    rig_names = [proto.check_rig_name(r) for r in rig_names]
    if not rig_names:
        raise ValueError("no rig names to serve")
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for u in users:
        ids = []
        for rig in (r for r in rig_names if u.serves(r)):
            for i, g in enumerate(_ROLE_GRANTS[u.role](rig, u.name)):
                ids.append(f"{u.name}/{rig}/{i}")
                rules.append({
                    "id": ids[-1], "permission": "allow", "flows": list(g.flows),
                    "messages": list(g.messages), "key_exprs": list(g.keys),
                })
        if ids:
            subjects.append({"id": f"user {u.name}", "usernames": [u.name]})
            policies.append({"id": u.name, "rules": ids, "subjects": [f"user {u.name}"]})
    if not policies:
        raise ValueError(f"no user may reach any of the rigs {rig_names}")
    return {
        "enabled": True, "default_permission": "deny",
        "rules": rules, "subjects": subjects, "policies": policies,
    }


def read_password_file(path: Path) -> str:
    """The password in a private file (the whole file, without its final newline)."""
    path = Path(path)
    _check_private(path)
    try:
        password = path.read_text(encoding="utf-8").rstrip("\r\n")
    except (OSError, UnicodeDecodeError) as exc:
        raise AuthError(f"{path}: cannot read: {exc}") from exc
    why = password_problem(password)
    if why:
        raise AuthError(f"{path}: password: {why}")
    return password
