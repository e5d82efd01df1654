"""controller.auth and `dobtune auth`: files, modes, validation, generated Zenoh configuration.

(The rules themselves are checked on real sessions in tests/integration/test_zenoh_acl.py.)
"""

from __future__ import annotations

import io
import json
import stat
from pathlib import Path
from typing import Any

import pytest
import zenoh

from controller import protocol as proto
from controller.auth import (
    DICTIONARY_FILE,
    MIN_PASSWORD_LEN,
    USERS_FILE,
    AuthError,
    Users,
    acl_config,
    any_user_key,
    init_auth_dir,
    load_users,
    new_users,
    read_password_file,
    requester,
    user_key,
    user_of_key,
    users_toml,
    write_dictionary,
)
from controller.cli.auth import init_main, show_main
from controller.cli.commands import controller_commands
from controller.cli.common import build_parser
from controller.client.session import client_config, server_config


def mode_of(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def init(directory: Path, *args: str) -> tuple[int, str]:
    """`dobtune auth init DIR args...` through the real parser."""
    parser = build_parser("dobtune", None, controller_commands())
    ns = parser.parse_args(["auth", "init", str(directory), *args])
    out = io.StringIO()
    code = init_main(ns.directory, ns.rigs, ns.users, ns.force, ns.show_passwords, out)
    return code, out.getvalue()


@pytest.fixture
def auth_dir(tmp_path: Path) -> Path:
    users = new_users([("op_a", "operator"), ("view_a", "viewer")], ("a",))
    users += new_users([("everywhere", "viewer"), ("ctl", "controller")])
    init_auth_dir(tmp_path / "auth", users)
    return tmp_path / "auth"


# -- dobtune auth init / show ----------------------------------------------------------------


def test_init_writes_private_files_and_never_prints_passwords(tmp_path: Path) -> None:
    d = tmp_path / "sub" / "auth"
    code, out = init(d)
    assert code == 0
    assert mode_of(d) == 0o700
    assert mode_of(d / USERS_FILE) == 0o600
    assert mode_of(d / DICTIONARY_FILE) == 0o600
    users = load_users(d)
    assert [(u.name, u.role, u.rigs) for u in users] == [
        ("operator", "operator", ("*",)), ("viewer", "viewer", ("*",))
    ]
    pw = [u.password for u in users]
    assert len(set(pw)) == 2 and all(len(p) >= MIN_PASSWORD_LEN for p in pw)
    assert not any(p in out for p in pw)
    assert "operator" in out and "viewer" in out and str(d / USERS_FILE) in out
    assert (d / DICTIONARY_FILE).read_text() == "".join(f"{u.name}:{u.password}\n" for u in users)


def test_init_prints_passwords_only_when_asked(tmp_path: Path) -> None:
    code, out = init(tmp_path / "auth", "--show-passwords")
    assert code == 0
    assert all(u.password in out for u in load_users(tmp_path / "auth"))
    show = io.StringIO()
    assert show_main(tmp_path / "auth", False, show) == 0
    assert "viewer" in show.getvalue()
    assert not any(u.password in show.getvalue() for u in load_users(tmp_path / "auth"))


def test_init_refuses_to_overwrite_without_force(tmp_path: Path) -> None:
    d = tmp_path / "auth"
    assert init(d)[0] == 0
    before = (d / USERS_FILE).read_text()
    code, out = init(d, "--user", "x=viewer")
    assert code == 2
    assert "exists" in out and "--force" in out and str(d / USERS_FILE) in out
    assert (d / USERS_FILE).read_text() == before
    code, _ = init(d, "--force")
    assert code == 0
    assert (d / USERS_FILE).read_text() != before  # new passwords


def test_init_with_rigs_and_users(tmp_path: Path) -> None:
    code, _ = init(tmp_path / "auth", "--rig-name", "a", "--rig-name", "b",
                   "--user", "alice=operator", "--user", "ctl=controller")
    assert code == 0
    users = load_users(tmp_path / "auth")
    assert [(u.name, u.role, u.rigs) for u in users] == [
        ("alice", "operator", ("a", "b")), ("ctl", "controller", ("a", "b"))
    ]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--user", "alice=admin"), "unknown role 'admin'"),
        (("--user", "bad name=viewer"), "user name 'bad name'"),
        (("--user", "x=viewer", "--user", "x=operator"), "repeat"),
        (("--rig-name", "a/b"), "rig_name"),
        (("--rig-name", "*", "--rig-name", "a"), "only entry"),
    ],
)
def test_init_rejects_bad_options_and_writes_nothing(
    tmp_path: Path, args: tuple[str, ...], message: str
) -> None:
    code, out = init(tmp_path / "auth", *args)
    assert code == 2
    assert message in out
    assert not (tmp_path / "auth").exists()


# -- load_users ----------------------------------------------------------------------------------

GOOD = {"role": "operator", "rigs": ["a"], "password": "p" * MIN_PASSWORD_LEN}


def write_users_file(d: Path, text: str) -> Path:
    d.mkdir(mode=0o700, exist_ok=True)
    path = d / USERS_FILE
    path.write_text(text)
    path.chmod(0o600)
    return path


def table(name: str, **fields: object) -> str:
    body = "".join(f"{k} = {json.dumps(v)}\n" for k, v in fields.items())
    return f"[users.{json.dumps(name)}]\n{body}"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (table("u", **{**GOOD, "role": "admin"}), "users.u.role: unknown role 'admin'"),
        (table("u", role="viewer", rigs=["a"]), "users.u.password: missing"),
        (table("u", **{**GOOD, "password": "short"}), "users.u.password: shorter than"),
        (table("u", **{**GOOD, "password": "has space in it"}), "users.u.password: contains"),
        (table("u", **{**GOOD, "password": 12345678901234}), "users.u.password: missing or not"),
        (table("bad name", **GOOD), "users.bad name: user name 'bad name'"),
        (table("a:b", **GOOD), "users.a:b: user name"),
        (table("u", role="viewer", password=GOOD["password"]), "users.u.rigs: missing"),
        (table("u", **{**GOOD, "rigs": []}), "users.u.rigs: expected a non-empty list"),
        (table("u", **{**GOOD, "rigs": ["a/b"]}), "users.u.rigs: rig_name"),
        (table("u", **{**GOOD, "rigs": ["*", "a"]}), "users.u.rigs: \"*\""),
        (table("u", **GOOD, admin=True), "users.u.admin: unknown field"),
        ("[other]\nx = 1\n", "other: unknown top-level key"),
        ("users = 3\n", "users: no [users.<name>] table"),
        ("[users\n", "invalid TOML"),
    ],
)
def test_load_users_names_the_file_and_field(tmp_path: Path, text: str, message: str) -> None:
    path = write_users_file(tmp_path / "auth", text)
    with pytest.raises(AuthError) as err:
        load_users(tmp_path / "auth")
    assert str(path) in str(err.value)
    assert message in str(err.value)


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660])
def test_load_users_refuses_a_file_others_can_read(auth_dir: Path, mode: int) -> None:
    (auth_dir / USERS_FILE).chmod(mode)
    with pytest.raises(AuthError, match=rf"readable by others \(mode {mode:04o}\).*chmod 600"):
        load_users(auth_dir)


def test_load_users_without_a_file_says_how_to_make_one(tmp_path: Path) -> None:
    with pytest.raises(AuthError, match="dobtune auth init"):
        load_users(tmp_path)


def test_users_toml_round_trips(tmp_path: Path) -> None:
    users = new_users([("a.b-c_d", "viewer")], ("r1", "r2"))
    write_users_file(tmp_path / "auth", users_toml(users))
    assert list(load_users(tmp_path / "auth")) == users


def test_dictionary_follows_the_users_file(auth_dir: Path) -> None:
    dictionary = auth_dir / DICTIONARY_FILE
    dictionary.write_text("stale:entry-entry\n")
    dictionary.chmod(0o644)
    users = load_users(auth_dir)
    assert write_dictionary(users) == dictionary
    assert dictionary.read_text().splitlines() == [f"{u.name}:{u.password}" for u in users]
    assert mode_of(dictionary) == 0o600


# -- keys and attribution ------------------------------------------------------------------------


def test_user_scoped_keys() -> None:
    cmd = proto.key_command("rig1")
    assert user_key(cmd, "alice") == "dobtune/rig1/@user/alice/cmd"
    assert any_user_key(cmd) == "dobtune/rig1/@user/*/cmd"
    assert user_of_key(user_key(cmd, "alice")) == "alice"
    for not_attributed in (cmd, any_user_key(cmd), "dobtune/rig1/@user/**/cmd",
                           "dobtune/rig1/@user/$*/cmd", "dobtune/rig1/@user/alice",
                           "x/r/@user/a/b"):
        assert user_of_key(not_attributed) is None, not_attributed
    with pytest.raises(ValueError):
        user_key(cmd, "*")
    with pytest.raises(ValueError):
        user_key("other/rig1/cmd", "alice")


def test_requester_is_a_known_user_of_that_rig(auth_dir: Path) -> None:
    users = load_users(auth_dir)
    op = requester(users, user_key(proto.key_command("a"), "op_a"))
    assert op is not None and op.name == "op_a" and op.may_change
    viewer = requester(users, user_key(proto.key_config("a"), "view_a"))
    assert viewer is not None and not viewer.may_change
    assert requester(users, proto.key_command("a")) is None  # public key: nobody in particular
    assert requester(users, user_key(proto.key_command("a"), "nobody")) is None
    assert requester(users, user_key(proto.key_command("b"), "op_a")) is None  # not its rig
    everywhere = requester(users, user_key(proto.key_config("b"), "everywhere"))
    assert everywhere is not None and everywhere.name == "everywhere"


# -- the access-control section ------------------------------------------------------------------


def rules_of(acl: dict[str, Any], user: str) -> list[dict[str, Any]]:
    policies = [p for p in acl["policies"] if p["id"] == user]
    ids = set(policies[0]["rules"]) if policies else set()
    return [r for r in acl["rules"] if r["id"] in ids]


def keys_for(rules: list[dict[str, Any]], flow: str, message: str) -> set[str]:
    return {k for r in rules if flow in r["flows"] and message in r["messages"]
            for k in r["key_exprs"]}


def test_acl_is_default_deny_with_consistent_ids(auth_dir: Path) -> None:
    acl = acl_config(load_users(auth_dir), ["a", "b"])
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rule_ids = [r["id"] for r in acl["rules"]]
    subject_ids = [s["id"] for s in acl["subjects"]]
    assert len(set(rule_ids)) == len(rule_ids) and len(set(subject_ids)) == len(subject_ids)
    for p in acl["policies"]:
        assert set(p["rules"]) <= set(rule_ids) and set(p["subjects"]) <= set(subject_ids)
    assert all(r["permission"] == "allow" for r in acl["rules"])


def test_viewer_rules(auth_dir: Path) -> None:
    rules = rules_of(acl_config(load_users(auth_dir), ["a", "b"]), "view_a")
    everything = {k for r in rules for k in r["key_exprs"]}
    # rig a only, but for the fleet overview's subscriptions to every rig at once (whose
    # samples and liveliness the egress rules limit to rig a)
    fleet = {"dobtune/*/state", "dobtune/*/status", "dobtune/*/drift", "dobtune/*/alive"}
    assert all(k.startswith("dobtune/a/") or k in fleet for k in everything)
    assert fleet <= everything
    assert keys_for(rules, "egress", "liveliness_token") == {"dobtune/a/alive"}
    assert not any(k.endswith("/cmd") or "**" in k for k in everything)
    assert keys_for(rules, "ingress", "query") == {
        "dobtune/a/config", "dobtune/a/identify", "dobtune/a/knowledge", "dobtune/a/lease",
        "dobtune/a/history", "dobtune/a/state/replay",
        "dobtune/a/@user/view_a/config", "dobtune/a/@user/view_a/identify",
        "dobtune/a/@user/view_a/knowledge", "dobtune/a/@user/view_a/lease",
        "dobtune/a/@user/view_a/history", "dobtune/a/@user/view_a/state/replay",
        # the watch's (public keys only: it serves no user's scope)
        "dobtune/a/drift", "dobtune/a/drift/alarm", "dobtune/a/prediction",
    }
    assert keys_for(rules, "ingress", "put") == {"dobtune/a/estop", "dobtune/a/@user/view_a/estop"}
    assert keys_for(rules, "egress", "put") == {"dobtune/a/state", "dobtune/a/status",
                                                "dobtune/a/drift", "dobtune/a/drift/alarm",
                                                "dobtune/a/prediction"}
    assert keys_for(rules, "ingress", "declare_queryable") == set()


def test_operator_rules_cover_its_rig_and_only_its_own_scope(auth_dir: Path) -> None:
    rules = rules_of(acl_config(load_users(auth_dir), ["a", "b"]), "op_a")
    assert keys_for(rules, "ingress", "query") == {"dobtune/a/**", "dobtune/a/@user/op_a/**"}
    # Puts on the e-stop only: the published keys (state, status) are the controller's.
    assert keys_for(rules, "ingress", "put") == {"dobtune/a/estop", "dobtune/a/@user/op_a/estop"}
    assert keys_for(rules, "ingress", "delete") == set()
    assert keys_for(rules, "ingress", "liveliness_token") == set()  # it cannot fake the rig alive
    assert keys_for(rules, "ingress", "declare_queryable") == set()  # it cannot serve the rig


def test_rules_follow_the_served_rigs(auth_dir: Path) -> None:
    users = load_users(auth_dir)
    only_b = acl_config(users, ["b"])
    assert rules_of(only_b, "op_a") == [] and rules_of(only_b, "view_a") == []
    assert {s["id"] for s in only_b["subjects"]} == {"user everywhere", "user ctl"}
    both = acl_config(users, ["a", "b"])
    ctl = {k for r in rules_of(both, "ctl") for k in r["key_exprs"]}
    fleet = {"dobtune/*/state", "dobtune/*/status", "dobtune/*/drift",  # interest, egress only
             "dobtune/*/alive"}
    assert ctl == {"dobtune/a/**", "dobtune/a/@user/*/**", "dobtune/b/**", "dobtune/b/@user/*/**",
                   *fleet}
    assert all(r["flows"] == ["egress"] for r in rules_of(both, "ctl")
               if set(r["key_exprs"]) <= fleet)
    with pytest.raises(ValueError, match="no user may reach"):
        acl_config([u for u in users if u.name == "op_a"], ["b"])
    with pytest.raises(ValueError, match="no rig names"):
        acl_config(users, [])


# -- zenoh.Config ------------------------------------------------------------------------------


def test_server_config(auth_dir: Path) -> None:
    conf = server_config(auth_dir, ["a"], listen=["tcp/127.0.0.1:7999"])
    acl = json.loads(conf.get_json("access_control"))
    acl["subjects"] = [{k: v for k, v in s.items() if v is not None} for s in acl["subjects"]]
    assert acl == acl_config(load_users(auth_dir), ["a"])  # Zenoh fills the absent with null
    usrpwd = json.loads(conf.get_json("transport/auth/usrpwd"))
    assert usrpwd["dictionary_file"] == str((auth_dir / DICTIONARY_FILE).resolve())
    assert usrpwd["user"] is None and usrpwd["password"] is None
    assert json.loads(conf.get_json("mode")) == "peer"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7999"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    router = server_config(auth_dir, ["a", "b"], listen=["tcp/127.0.0.1:7999"], mode="router")
    assert json.loads(router.get_json("mode")) == "router"


def test_server_config_refuses(auth_dir: Path) -> None:
    with pytest.raises(ValueError, match="cannot dial out"):
        server_config(auth_dir, ["a"], connect=["tcp/127.0.0.1:7447"])
    with pytest.raises(ValueError, match="mode"):
        server_config(auth_dir, ["a"], mode="client")
    with pytest.raises(ValueError, match="rig_name"):
        server_config(auth_dir, ["a/*"])
    (auth_dir / USERS_FILE).chmod(0o644)
    with pytest.raises(AuthError, match="readable by others"):
        server_config(auth_dir, ["a"])


def login_of(conf: zenoh.Config) -> dict[str, Any]:
    login: dict[str, Any] = json.loads(conf.get_json("transport/auth/usrpwd"))
    return login


def test_client_config_credentials(auth_dir: Path, tmp_path: Path) -> None:
    users = load_users(auth_dir)
    conf = client_config(auth_dir, "view_a", ["tcp/127.0.0.1:7447"])
    assert login_of(conf)["user"] == "view_a"
    assert login_of(conf)["password"] == users["view_a"].password
    assert json.loads(conf.get_json("listen/endpoints")) == []
    assert json.loads(conf.get_json("mode")) == "client"  # listening nowhere: a client
    listening = client_config(auth_dir, "view_a", ["tcp/127.0.0.1:7447"],
                              ["tcp/127.0.0.1:7448"])
    assert json.loads(listening.get_json("mode")) == "peer"

    pw_file = tmp_path / "pw"
    pw_file.write_text(users["op_a"].password + "\n")
    pw_file.chmod(0o600)
    assert read_password_file(pw_file) == users["op_a"].password
    conf = client_config(pw_file, "op_a", ["tcp/127.0.0.1:7447"], mode="client")
    assert login_of(conf)["password"] == users["op_a"].password
    assert json.loads(conf.get_json("mode")) == "client"

    conf = client_config("typed-password-1", "op_a", [], fail_after_s=1.5)
    assert login_of(conf)["password"] == "typed-password-1"
    assert json.loads(conf.get_json("connect/exit_on_failure")) is True
    assert json.loads(conf.get_json("connect/timeout_ms")) == 1500


def test_client_config_refuses(auth_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(AuthError, match="no user 'mallory'"):
        client_config(auth_dir, "mallory", [])
    pw_file = tmp_path / "pw"
    pw_file.write_text("a-long-enough-password")
    pw_file.chmod(0o644)
    with pytest.raises(AuthError, match="readable by others"):
        client_config(pw_file, "op_a", [])
    with pytest.raises(AuthError, match="shorter than"):
        client_config("short", "op_a", [])
    with pytest.raises(ValueError, match="mode"):
        client_config(auth_dir, "op_a", [], mode="router")


def test_users_lookup_error_names_the_file(auth_dir: Path) -> None:
    users: Users = load_users(auth_dir)
    with pytest.raises(AuthError, match=str(auth_dir / USERS_FILE)):
        users["nobody"]
