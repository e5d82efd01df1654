"""`dobtune router`: a Zenoh router (Zenoh's own router mode) for a lab or a site (command body).

    dobtune router [--listen EP ...] [--connect EP ...] [--auth DIR --rig-name R ... | --insecure]

Controllers connect to it (`dobtune controller --connect ROUTER_EP`, each still listening on its
own endpoint), clients too (`dobtune ctl --connect ROUTER_EP rigs`, the dashboard); routers link
sites with `--connect` to each other. With `--auth`, the router enforces the users and access
control of DIR for the rigs named (then it cannot dial out: the sites' routers connect to it).
Without `--auth`, a --listen or --connect endpoint that is not loopback (by what its host
resolves to) is refused unless `--insecure`: anyone who reaches the router may act on every rig.
Exit codes: 0 stopped (Ctrl-C / SIGTERM), 2 bad input or the endpoint is busy.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from controller.cli.common import add_parent_pid, end_with_parent

__all__ = ["router_options"]

DEFAULT_ROUTER_LISTEN = ("tcp/127.0.0.1:7446",)


def router_options(listen: list[str], connect: list[str], auth: Path | None,
                   rigs: list[str], insecure: bool = False) -> Any:
    """The router's session: mode router; with `auth`, serving `rigs` with their access
    control (ValueError when no rig is named)."""
    from controller.client.session import SessionOptions

    if auth is not None and not rigs:
        raise ValueError("--rig-name: name the rigs the router serves (with --auth)")
    return SessionOptions(listen=tuple(listen), connect=tuple(connect), mode="router",
                          auth=auth, serve=tuple(rigs) if auth is not None else (),
                          insecure=insecure)


def run(args: argparse.Namespace) -> int:
    import zenoh

    from controller.client.session import connect
    from controller.logs import setup_logging

    def say(text: str) -> None:
        print(f"dobtune router: {text}", file=sys.stderr, flush=True)

    end_with_parent(args.parent_pid, say)
    setup_logging(args.log_level, "router")
    listen = args.listen or list(DEFAULT_ROUTER_LISTEN)
    try:
        session = connect(router_options(listen, args.connect, args.auth, args.rig_name,
                                                 args.insecure))
    except (ValueError, OSError) as exc:
        print(f"dobtune router: {exc}", file=sys.stderr, flush=True)
        return 2
    except zenoh.ZError as exc:
        print(f"dobtune router: --listen {', '.join(listen)}: cannot open (port in use?): {exc}",
              file=sys.stderr, flush=True)
        return 2
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT,
                                                                      signal.SIGTERM)}
    try:
        with session:
            print(f"dobtune router: listening on {', '.join(listen)}"
                  + (f", linked to {', '.join(args.connect)}" if args.connect else ""),
                  file=sys.stderr, flush=True)
            while not stop.wait(0.5):
                pass
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    print("dobtune router: stopped", file=sys.stderr, flush=True)
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"default {DEFAULT_ROUTER_LISTEN[0]}")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="another site's router")
    p.add_argument("--auth", type=Path, default=None, metavar="DIR")
    p.add_argument("--insecure", action="store_true",
                   help="allow a non-loopback --listen or --connect without --auth (anyone "
                   "who reaches the router may act on every rig behind it)")
    p.add_argument("--rig-name", action="append", default=[], metavar="R",
                   help="with --auth: a rig the router serves (repeatable)")
    add_parent_pid(p, "router")

