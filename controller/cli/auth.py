"""`dobtune auth`: the users of Zenoh authentication and access control (command bodies).

    dobtune auth init DIR [--rig-name R ...] [--user NAME=ROLE ...] [--force] [--show-passwords]
    dobtune auth show DIR [--passwords]

`init` creates DIR (0700) with `users.toml` and the Zenoh password dictionary (both 0600).
Passwords are printed only when asked. Exit codes: 0 done, 2 bad input (an existing users file
without --force, an invalid users file or option).
"""

from __future__ import annotations

import argparse
import stat
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from controller.auth import User

__all__ = ["DEFAULT_USERS", "init_main", "show_main"]

EXIT_OK, EXIT_BAD_INPUT = 0, 2
#: (name, role) of the users `init` creates unless --user is given.
DEFAULT_USERS: tuple[tuple[str, str], ...] = (("operator", "operator"), ("viewer", "viewer"))


def _user_lines(users: Sequence[User], passwords: bool) -> list[str]:
    width = max(len(u.name) for u in users)
    lines = []
    for u in users:
        line = f"  {u.name:<{width}}  {u.role:<10}  rigs: {', '.join(u.rigs)}"
        lines.append(f"{line}  password: {u.password}" if passwords else line)
    return lines


def init_main(
    directory: Path,
    rigs: Sequence[str],
    users: Sequence[tuple[str, str]],
    force: bool,
    show_passwords: bool,
    out: TextIO,
    tls_hosts: Sequence[str] = (),
) -> int:
    """`dobtune auth init`: write the users file and the dictionary; return the exit code."""
    from controller.auth import ALL_RIGS, DICTIONARY_FILE, init_auth_dir, new_users

    try:
        created = new_users(users or DEFAULT_USERS, rigs or (ALL_RIGS,))
        loaded = init_auth_dir(directory, created, force=force)
        if tls_hosts:
            from controller.tls import make_tls

            ca = make_tls(Path(directory), list(tls_hosts))
            out.write(f"wrote {ca} (give it to every client) and the server certificate for "
                      f"{', '.join(tls_hosts)}: listen on tls/ endpoints\n")
    except FileExistsError as exc:
        out.write(
            f"error: {exc.args[0]} exists; --force replaces it (new passwords for every user)\n"
        )
        return EXIT_BAD_INPUT
    except (ValueError, OSError) as exc:
        out.write(f"error: {exc}\n")
        return EXIT_BAD_INPUT
    path = loaded.path
    out.write(f"wrote {path} and {directory / DICTIONARY_FILE} (mode 0600)\n")
    out.write("\n".join(_user_lines(list(loaded), show_passwords)) + "\n")
    if not show_passwords:
        out.write(
            f"passwords: in {path} (`dobtune auth show {directory} --passwords` prints them)\n"
        )
    mode = stat.S_IMODE(Path(directory).stat().st_mode)
    if mode & 0o077:
        out.write(f"note: {directory} is open to others (mode {mode:04o}); the files are 0600\n")
    return EXIT_OK


def show_main(directory: Path, passwords: bool, out: TextIO) -> int:
    """`dobtune auth show`: validate the users file and list its users."""
    from controller.auth import AuthError, load_users

    try:
        users = load_users(directory)
    except AuthError as exc:
        out.write(f"error: {exc}\n")
        return EXIT_BAD_INPUT
    out.write(f"{users.path}\n")
    out.write("\n".join(_user_lines(list(users), passwords)) + "\n")
    return EXIT_OK


def _name_role(text: str) -> tuple[str, str]:
    name, sep, role = text.partition("=")
    if not sep or not name or not role:
        raise argparse.ArgumentTypeError(f"expected NAME=ROLE, got {text!r}")
    return name, role


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="auth_command", required=True)
    init = sub.add_parser("init", help="create DIR with users.toml and random passwords")
    init.add_argument("directory", type=Path, metavar="DIR")
    init.add_argument(
        "--rig-name",
        dest="rigs",
        action="append",
        default=[],
        metavar="R",
        help="a rig the users may reach (repeatable; default: every rig)",
    )
    init.add_argument(
        "--user",
        dest="users",
        type=_name_role,
        action="append",
        default=[],
        metavar="NAME=ROLE",
        help="a user to create, role operator|viewer|controller (repeatable; "
        "default: operator=operator viewer=viewer)",
    )
    init.add_argument("--force", action="store_true", help="replace an existing users file")
    init.add_argument("--tls", nargs="+", default=[], metavar="HOST",
                      help="also create a TLS authority and the controller's certificate for "
                      "these host names / addresses (then use tls/ endpoints)")
    init.add_argument("--show-passwords", action="store_true", help="print the passwords")
    show = sub.add_parser("show", help="check DIR/users.toml and list its users")
    show.add_argument("directory", type=Path, metavar="DIR")
    show.add_argument("--passwords", action="store_true", help="print the passwords")


def run(args: argparse.Namespace) -> int:
    if args.auth_command == "init":
        return init_main(
            args.directory, args.rigs, args.users, args.force, args.show_passwords, sys.stdout,
            args.tls,
        )
    return show_main(args.directory, args.passwords, sys.stdout)

