"""Zenoh client of one controller: state/status into ring buffers, config and command queries.

Subscribers hand samples to Zenoh ring channels; one reader thread of ours drains them, decodes
and appends to `StateRing` (never any work inside a Zenoh callback). Queries are blocking and
meant for worker threads, not for GUI callbacks.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import msgspec
import numpy as np

from controller import protocol as proto
from controller.client.session import SessionOptions, connect, put_estop
from controller.core.config import LoopConfig

__all__ = [
    "ClientOptions",
    "ControllerClient",
    "ControllerUnavailable",
    "StateRing",
    "open_client_session",
    "quietly",
]

log = logging.getLogger(__name__)

COLUMNS = proto.STATE_COLUMNS
M = TypeVar("M")
R = TypeVar("R", bound=proto.Message)


class ControllerUnavailable(RuntimeError):
    """No reply from the controller (gone, or not started yet)."""


class StateRing:
    """The newest `capacity` loop samples, column-wise; appended by one thread, read by others."""

    def __init__(self, capacity: int = 1 << 16) -> None:
        self.capacity = capacity
        self._cols = {c: np.zeros(capacity) for c in COLUMNS}
        self._version = np.zeros(capacity)
        self._n = 0  # total samples ever appended
        self._next_seq: int | None = None
        self.gaps = 0  # samples missing according to sequence numbers
        self.batches = 0
        self.mode = ""
        """The loop's mode in the newest batch ("" before any, or from an older sender): an
        e-stop shows here within a batch, the Status says it within its period (0.2 s)."""
        self._lock = threading.Lock()

    @property
    def total(self) -> int:
        return self._n

    def append(self, b: proto.StateBatch) -> None:
        k = len(b.t_s)
        if k == 0:
            return
        if k > self.capacity:
            raise ValueError("batch larger than the ring")
        with self._lock:
            if self._next_seq is not None and b.seq0 > self._next_seq:
                self.gaps += b.seq0 - self._next_seq
            self._next_seq = b.seq0 + k
            i0 = self._n % self.capacity
            first = min(k, self.capacity - i0)
            for c in COLUMNS:
                src = getattr(b, c)
                col = self._cols[c]
                col[i0 : i0 + first] = src[:first]
                if first < k:
                    col[: k - first] = src[first:]
            self._version[i0 : i0 + first] = b.config_version
            if first < k:
                self._version[: k - first] = b.config_version
            self._n += k
            self.batches += 1
            self.mode = b.mode

    def reset(self) -> None:
        with self._lock:
            self._n = 0
            self._next_seq = None

    def window(self, window_s: float) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Copies of the samples of the last `window_s` seconds (oldest first), and versions."""
        with self._lock:
            n = min(self._n, self.capacity)
            if n == 0:
                return {c: np.zeros(0) for c in COLUMNS}, np.zeros(0)
            end = self._n % self.capacity
            idx = (np.arange(end - n, end)) % self.capacity
            t = self._cols["t_s"]
            t_last = t[(end - 1) % self.capacity]
            # Binary search on the (monotonic) time column through the index map.
            lo = int(np.searchsorted(t[idx], t_last - window_s, side="left"))
            sel = idx[lo:]
            out = {c: self._cols[c][sel] for c in COLUMNS}
            ver = self._version[sel]
        return out, ver

    def latest(self) -> dict[str, float] | None:
        with self._lock:
            if self._n == 0:
                return None
            i = (self._n - 1) % self.capacity
            return {c: float(self._cols[c][i]) for c in COLUMNS}


#: The error payload Zenoh itself yields when a get's timeout passes with no final reply.
ZENOH_TIMEOUT = "Timeout"


@dataclass(frozen=True)
class ClientOptions:
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    rig_name: str = "demo"
    listen: tuple[str, ...] = ()
    query_timeout_s: float = 3.0
    #: An apply's reply waits on the controller's gate, which also loads the analysis worker
    #: after a start and saves the configuration (seconds on a loaded machine): a read's
    #: timeout there tells the user "no reply" about a change that then happens. A reply
    #: returns as soon as it is sent; this bounds only a controller that never answers.
    #: 60 s: at load 17-20 (four busy loops on 2 cores) an adoption's and a confirmed
    #: caution's gate check took more than 30 s.
    apply_timeout_s: float = 60.0
    #: The controller counts as gone when no status arrived for this long.
    gone_after_s: float = 2.0
    client_name: str = "dashboard"
    ring_capacity: int = 1 << 16
    #: With authentication: the `dobtune auth init` directory (or a password file) and the
    #: user to log in as; requests then go to that user's key scope.
    auth: Path | None = None
    user: str = ""
    #: With `auth`: opening fails (ControllerUnavailable) if no connection is made in this
    #: long: wrong credentials and an unreachable controller look the same to Zenoh.
    connect_timeout_s: float = 5.0
    #: False: requests only (no state and status subscriptions), e.g. one client per user
    #: behind a dashboard that already receives the streams.
    subscribe: bool = True
    #: The session's Zenoh mode (None: peer without auth, client with it). "client": what this
    #: session publishes or answers reaches the controller's other peers through it (a peer
    #: routes for its clients, never between two peers): the watch's drift states and alarms.
    mode: str | None = None


@dataclass
class VersionMark:
    t_s: float
    version: int


@dataclass
class _Counters:
    decode_errors: int = 0
    last_decode_error: str = ""
    #: The latest message refused for its protocol version ("" none): the controller runs
    #: another dobtune version, and no status of it can be read.
    version_mismatch: str = ""
    status_count: int = 0
    version_marks: list[VersionMark] = field(default_factory=list)


class ControllerClient:
    """One Zenoh session to one controller (context manager)."""

    def __init__(self, opts: ClientOptions) -> None:
        proto.check_rig_name(opts.rig_name)
        self.opts = opts
        self.ring = StateRing(opts.ring_capacity)
        self.counters = _Counters()
        self._status: proto.Status | None = None
        self._status_at = -1e9
        self._session: Any = None
        self._subs: list[Any] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_version: int | None = None
        self._status_listeners: list[Any] = []
        #: The operator lease token this client holds ("" none).
        self.lease_token = ""
        self._source_id: Any = None
        self._source_sn = 0

    # -- lifecycle -----------------------------------------------------------------------------

    def __enter__(self) -> ControllerClient:
        import zenoh

        rig = self.opts.rig_name
        self._session = self._open()
        if not self.opts.subscribe:
            return self
        try:
            self._state_sub = self._session.declare_subscriber(
                proto.key_state(rig), zenoh.handlers.RingChannel(4096)
            )
            self._status_sub = self._session.declare_subscriber(
                proto.key_status(rig), zenoh.handlers.RingChannel(64)
            )
            self._subs = [self._state_sub, self._status_sub]
            self._thread = threading.Thread(target=self._reader, name="zenoh-reader", daemon=True)
            self._thread.start()
        except BaseException:
            self._close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self._close()

    def _open(self) -> Any:
        return open_client_session(self.opts)

    @property
    def session(self) -> Any:
        """The open Zenoh session (None before `__enter__` and after closing)."""
        return self._session

    def key(self, key: str) -> str:
        """`key` as this client sends on it: its user's scope with authentication."""
        return proto.user_key(key, self.opts.user) if self.opts.user else key

    def _close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for s in self._subs:
            quietly("undeclaring a subscriber", s.undeclare)
        self._subs = []
        if self._session is not None:
            quietly("closing the Zenoh session", self._session.close)
            self._session = None

    # -- the reader thread ---------------------------------------------------------------------

    def _reader(self) -> None:
        while not self._stop.is_set():
            try:
                got = self._drain()
            except Exception:  # the reader must outlive any one message
                log.exception("zenoh reader: unexpected error; going on")
                got = False
            if not got:
                self._stop.wait(0.004)

    def _drain(self) -> bool:
        """Handle every queued state batch and status; True if there was any."""
        got = False
        for sub, handle in ((self._state_sub, self._on_state), (self._status_sub, self._on_status)):
            sample = sub.try_recv()
            while sample is not None:
                got = True
                handle(sample.payload.to_bytes())
                sample = sub.try_recv()
        return got

    def _bad_message(self, error: str) -> None:
        """Count a message that could not be used; log the first and then every 100th."""
        c = self.counters
        c.decode_errors += 1
        c.last_decode_error = error
        if c.decode_errors % 100 == 1:
            log.warning("bad message from the controller (%d so far): %s", c.decode_errors, error)

    def _decoded(self, decode: Callable[[], M]) -> M | None:
        """`decode()`, or None (counted and logged) when the message is invalid."""
        try:
            return decode()
        except proto.ProtocolError as exc:
            if exc.field == "v":
                self.counters.version_mismatch = str(exc)
            self._bad_message(str(exc))
            return None

    def _on_state(self, data: bytes) -> None:
        b = self._decoded(lambda: proto.decode(data, proto.StateBatch))
        if b is None:
            return
        if b.rig != self.opts.rig_name:
            return
        if len(b.t_s) and (self._last_version is None or b.config_version != self._last_version):
            if self._last_version is not None:
                marks = self.counters.version_marks
                marks.append(VersionMark(b.t_s[0], b.config_version))
                del marks[:-20]
            self._last_version = b.config_version
        # A restarted controller starts again from small times: drop the old trace.
        last = self.ring.latest()
        if last is not None and len(b.t_s) and b.t_s[0] < last["t_s"] - 1.0:
            self.ring.reset()
        try:
            self.ring.append(b)
        except ValueError as exc:
            self._bad_message(str(exc))

    def _on_status(self, data: bytes) -> None:
        st = self._decoded(lambda: proto.decode(data, proto.Status))
        if st is None:
            return
        if self._status is None:
            log.info("first status from rig '%s': %s, config v%d", st.rig, st.mode,
                     st.config_version)
        self._status = st
        self._status_at = time.monotonic()
        self.counters.status_count += 1

    # -- read side -----------------------------------------------------------------------------

    @property
    def status(self) -> proto.Status | None:
        return self._status

    @property
    def status_age_s(self) -> float:
        return time.monotonic() - self._status_at

    @property
    def connected(self) -> bool:
        return self._status is not None and self.status_age_s < self.opts.gone_after_s

    # -- queries (blocking: call from worker threads) ------------------------------------------

    def _source_info(self) -> Any:
        """This session's id on every query: the controller's request budget gives each
        session its share of the user's (`controller.process.budget`)."""
        import zenoh

        if self._source_id is None:
            assert self._session is not None
            querier = self._session.declare_querier(self.key(proto.key_config(self.opts.rig_name)))
            self._source_id = querier.id  # an EntityGlobalId has no constructor of its own
            querier.undeclare()
        self._source_sn += 1
        return zenoh.SourceInfo(self._source_id, self._source_sn)

    def _query(self, key: str, payload: bytes, timeout_s: float | None = None) -> bytes:
        if self._session is None:
            raise ControllerUnavailable("not connected")
        timeout_s = self.opts.query_timeout_s if timeout_s is None else timeout_s
        no_reply = f"no reply from the controller on {key} within {timeout_s:.1f} s"
        t0 = time.monotonic()
        replies = self._session.get(key, payload=payload, timeout=timeout_s,
                                    source_info=self._source_info())
        for reply in replies:
            if reply.ok is not None:
                data: bytes = reply.ok.payload.to_bytes()
                return data
            err = reply.err
            text = err.payload.to_string() if err is not None else "error reply"
            if text == ZENOH_TIMEOUT and time.monotonic() - t0 >= 0.9 * timeout_s:
                # Zenoh's own end of the wait, not the controller's answer (it read
                # "controller replied with an error: Timeout")
                raise ControllerUnavailable(no_reply)
            raise ControllerUnavailable(f"controller replied with an error: {text}")
        raise ControllerUnavailable(no_reply)

    def query(self, key: str, msg: msgspec.Struct, reply_type: type[R],
              timeout_s: float | None = None) -> R:
        """Send `msg` on `key` (this client's scope of it) and decode the reply as
        `reply_type` (waiting `timeout_s`, default `query_timeout_s`). Raises
        ControllerUnavailable (no reply, an error reply) or ProtocolError."""
        raw = self._query(self.key(key), proto.encode(msg), timeout_s)
        return proto.decode(raw, reply_type)

    def history(self, last: int = 50) -> proto.HistoryReply:
        """The controller's newest `last` applied configurations (oldest first)."""
        req = proto.HistoryRequest(last=last)
        return self.query(proto.key_history(self.opts.rig_name), req, proto.HistoryReply)

    def prediction_checks(self, timeout_s: float | None = None) -> list[proto.PredictionCheck]:
        """Every version's prediction check the watch keeps (`dobtune watch`, started by the
        controller), oldest version first; [] when no watch answers."""
        import zenoh

        checks: dict[int, proto.PredictionCheck] = {}
        # One reply per version on the same key: NONE keeps them all (the default
        # consolidation keeps the latest reply per key).
        for reply in self.session.get(
                proto.key_prediction(self.opts.rig_name),
                timeout=self.opts.query_timeout_s if timeout_s is None else timeout_s,
                consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is not None:
                k = proto.decode(reply.ok.payload.to_bytes(), proto.PredictionCheck)
                checks[k.config_version] = k
        return [checks[v] for v in sorted(checks)]

    def identify_status(self) -> proto.IdentifyStatus:
        """The controller's latest identification run."""
        raw = self._query(self.key(proto.key_identify(self.opts.rig_name)), b"")
        return proto.decode(raw, proto.IdentifyStatus)

    def get_config(self) -> proto.ConfigReply:
        req = proto.ConfigRequest(client=self.opts.client_name)
        return self.query(proto.key_config(self.opts.rig_name), req, proto.ConfigReply)

    def apply(
        self, candidate: LoopConfig, *, confirm: bool = False, expect_version: int | None = None
    ) -> proto.ConfigReply:
        """Apply `candidate` through the controller's gate; a `caution` needs `confirm`;
        `expect_version`: only if that is still the active version."""
        req = proto.ConfigRequest(
            candidate=candidate, client=self.opts.client_name, confirm=confirm,
            expect_version=expect_version, lease=self.lease_token,
        )
        return self.query(proto.key_config(self.opts.rig_name), req, proto.ConfigReply,
                          self.opts.apply_timeout_s)

    def knowledge(self, request: proto.KnowledgeRequest | None = None) -> proto.KnowledgeReply:
        """The controller's plant knowledge, or (with a request) adopt new knowledge: that
        judges the active configuration on it through the gate, as an apply does, so it is
        given an apply's time (a loaded machine took more than a plain query's)."""
        req = request if request is not None else proto.KnowledgeRequest()
        req = msgspec.structs.replace(req, client=self.opts.client_name, lease=self.lease_token)
        adopting = req.record is not None or req.adopt_run is not None
        timeout_s = self.opts.apply_timeout_s if adopting else None
        return self.query(proto.key_knowledge(self.opts.rig_name), req, proto.KnowledgeReply,
                          timeout_s)

    def command(self, body: proto.CommandBody) -> proto.CommandReply:
        msg = proto.Command(body=body, client=self.opts.client_name, lease=self.lease_token)
        return self.query(proto.key_command(self.opts.rig_name), msg, proto.CommandReply)

    def reset(self, estop_seq: int | None = None) -> proto.CommandReply:
        """ResetFault acknowledging the e-stop at `estop_seq` (default: the latest this client's
        Status shows): refused when a newer e-stop exists. ControllerUnavailable when no Status
        has arrived (what would the reset acknowledge?)."""
        if estop_seq is None:
            st = self._status
            if st is None:
                raise ControllerUnavailable("reset: no status received yet (the reset names the "
                                            "latest e-stop seen in it)")
            estop_seq = st.estop_seq
        return self.command(proto.ResetFault(estop_seq=estop_seq))

    def lease(self, action: str = "status", duration_s: float = 60.0) -> proto.LeaseReply:
        """The operator lease: acquire / renew / release / takeover / status. A granted or
        renewed lease's token is kept and sent with every change from this client."""
        req = proto.LeaseRequest(action=action, token=self.lease_token, duration_s=duration_s,
                                 client=self.opts.client_name)
        reply = self.query(proto.key_lease(self.opts.rig_name), req, proto.LeaseReply)
        if reply.ok and reply.token:
            self.lease_token = reply.token
        elif action == "release" and reply.ok:
            self.lease_token = ""
        return reply

    def put_estop(self) -> None:
        """Fire-and-forget put on the e-stop key: any payload stops the loop, no reply needed."""
        if self._session is None:
            raise ControllerUnavailable("not connected")
        put_estop(self._session, self.key(proto.key_estop(self.opts.rig_name)),
                  self.opts.client_name)

    def estop(self) -> proto.CommandReply | None:
        """The e-stop put first (always works), then the EStop command for a reply."""
        self.put_estop()
        try:
            return self.command(proto.EStop())
        except ControllerUnavailable as exc:
            log.warning("e-stop put sent; no reply to the EStop command: %s", exc)
            return None


def open_client_session(o: ClientOptions) -> Any:
    """A Zenoh session as `o` says (with `o.auth`: logged in as `o.user`); ControllerUnavailable
    when the credentials reach nothing within `o.connect_timeout_s`."""
    import zenoh

    from controller.auth import AuthError

    so = SessionOptions(connect=tuple(o.connect), listen=tuple(o.listen), auth=o.auth,
                        user=o.user, fail_after_s=o.connect_timeout_s if o.auth else None,
                        mode=o.mode)
    if o.auth is None:
        try:
            return connect(so)
        except zenoh.ZError as exc:
            raise ControllerUnavailable(
                f"no connection to {', '.join(o.connect)}: {exc}") from exc
    if not o.user:
        raise ValueError("user: required with auth")
    try:
        return connect(so)
    except (AuthError, KeyError, OSError) as exc:
        raise ControllerUnavailable(f"credentials of {o.user!r}: {exc}") from exc
    except zenoh.ZError as exc:
        raise ControllerUnavailable(
            f"no connection to {', '.join(o.connect)} as {o.user!r} within "
            f"{o.connect_timeout_s:g} s: wrong credentials, or the controller is not "
            f"reachable ({exc})"
        ) from exc


def quietly(what: str, fn: Callable[[], Any]) -> None:
    """Teardown that must go on: a failure is logged, not raised."""
    try:
        fn()
    except Exception:
        log.warning("%s failed", what, exc_info=True)
