"""The one place that builds a Zenoh configuration: peer mode, explicit endpoints, no multicast.

Both the controller and the dashboard open their sessions here, so "never listen on all
interfaces by default" and "no multicast scouting" hold everywhere. The default listen
endpoint is loopback only; a peer that only connects (a client, a test) listens nowhere.
"""

from __future__ import annotations

import json
from collections.abc import Iterable

import zenoh

__all__ = ["DEFAULT_LISTEN", "check_endpoint", "open_session", "zenoh_config"]

#: The controller's default: loopback only, never all interfaces.
DEFAULT_LISTEN: tuple[str, ...] = ("tcp/127.0.0.1:7447",)

_PROTOCOLS = ("tcp/", "udp/", "tls/", "quic/", "unixsock-stream/", "ws/")


def check_endpoint(endpoint: str) -> str:
    """A Zenoh endpoint `proto/address` (e.g. tcp/127.0.0.1:7447); ValueError naming it if not."""
    if not isinstance(endpoint, str) or not endpoint.startswith(_PROTOCOLS):
        raise ValueError(
            f"endpoint {endpoint!r}: expected <proto>/<address>, e.g. tcp/127.0.0.1:7447"
        )
    return endpoint


def zenoh_config(
    listen: Iterable[str] = DEFAULT_LISTEN, connect: Iterable[str] = ()
) -> zenoh.Config:
    """A peer configuration with exactly these endpoints and multicast scouting off."""
    listen_l = [check_endpoint(e) for e in listen]
    connect_l = [check_endpoint(e) for e in connect]
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("listen/endpoints", json.dumps(listen_l))
    conf.insert_json5("connect/endpoints", json.dumps(connect_l))
    conf.insert_json5("scouting/multicast/enabled", "false")
    # A peer that connects to a controller not yet up keeps retrying instead of failing.
    conf.insert_json5("connect/exit_on_failure", "false")
    conf.insert_json5("listen/exit_on_failure", "true")
    return conf


def open_session(
    listen: Iterable[str] = DEFAULT_LISTEN, connect: Iterable[str] = ()
) -> zenoh.Session:
    """Open a peer session (use it as a context manager: `with open_session(...) as s:`).

    A session that declared a queryable must be closed, or the interpreter can hang at exit.
    """
    return zenoh.open(zenoh_config(listen, connect))
