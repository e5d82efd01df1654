"""The one way to reach a controller: the Zenoh session and the clients built on it.

- `session`: `connect(SessionOptions)`, the only place that opens a Zenoh session (endpoints,
  mode, credentials, TLS), for the controller and router too.
- `controller_client`: `ControllerClient`, one controller's state, status, queries and commands.

The CLI (`controller/cli`) and the dashboard (`server/`) are front ends over these objects.
"""

from __future__ import annotations

from controller.client.controller_client import (
    ClientOptions,
    ControllerClient,
    ControllerUnavailable,
    StateRing,
    open_client_session,
)
from controller.client.session import DEFAULT_LISTEN, SessionOptions, check_endpoint, connect

__all__ = [
    "DEFAULT_LISTEN",
    "ClientOptions",
    "ControllerClient",
    "ControllerUnavailable",
    "SessionOptions",
    "StateRing",
    "check_endpoint",
    "connect",
    "open_client_session",
]
