"""viser's websocket protocol by hand, as an attacker (or a test) would speak it: connect with a
URL (its token), send any message, read what the server sends (decoded)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from typing import Any

import msgspec
import zstandard

#: A camera report as a page sends it at once (viser counts a client as connected then).
CAMERA = {"type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0),
          "position": (1.0, 1.0, 1.0), "fov": 1.0, "near": 0.01, "far": 100.0,
          "image_height": 600, "image_width": 800, "look_at": (0.0, 0.0, 0.0),
          "up_direction": (0.0, 0.0, 1.0)}


class RawViser:
    def __init__(self, url: str, origin: str | None = None) -> None:
        import viser
        from websockets.sync.client import connect

        self.ws = connect(url, open_timeout=30, max_size=None, ping_interval=None,
                          additional_headers={"Origin": origin} if origin else {},
                          subprotocols=[f"viser-v{viser.__version__}"])  # type: ignore[list-item]
        self.messages: list[dict[str, Any]] = []
        self._zstd = zstandard.ZstdDecompressor()
        self.send(CAMERA)

    def __enter__(self) -> RawViser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.ws.close()

    def send(self, message: dict[str, Any]) -> None:
        self.ws.send(msgspec.msgpack.encode(message))

    def update(self, uuid: str, updates: dict[str, Any]) -> None:
        """A GUI update message: what a page sends when a control changes."""
        self.send({"type": "GuiUpdateMessage", "uuid": uuid, "updates": updates})

    def _frame(self, raw: bytes) -> None:
        n_inner = int.from_bytes(raw[0:8], "little")
        n_comp = int.from_bytes(raw[8:16], "little")
        inner = self._zstd.decompress(raw[16:16 + n_comp], max_output_size=n_inner)
        self.messages.extend(msgspec.msgpack.decode(inner)["messages"])

    def pump_until(self, cond: Any, timeout_s: float, what: str) -> None:
        """Read what the server sends until `cond()` holds; fails with `what` after
        `timeout_s`."""
        end = time.monotonic() + timeout_s
        while not cond():
            left = end - time.monotonic()
            assert left > 0, what
            try:
                self._frame(self.ws.recv(timeout=min(left, 1.0)))
            except TimeoutError:
                continue


@contextlib.contextmanager
def connected(dash: Any, url: str | None = None) -> Iterator[RawViser]:
    """A raw client of the dashboard `dash` (a `server.dashboard.app.Dashboard`) through `url`
    (default: its printed URL, with its token), once viser counts it as connected."""
    from helpers import wait_for

    url = url or dash.url
    before = set(dash.server.get_clients())
    with RawViser(url.replace("http://", "ws://"), origin=url.split("/?")[0]) as c:
        wait_for(lambda: set(dash.server.get_clients()) - before, 20.0, "never connected")
        yield c
