"""The state stream again: `dobtune/<rig>/state/replay?from=<seq>;to=<seq>` (issue 33 item 4).

A recorder that finds a jump in the stream's sequence numbers (a batch lost in Zenoh, in its
own queue, or dropped by a test hook) asks for the missing range; this process (the loop's: it
alone holds the batches) answers from what the black box keeps of the published stream (its
last 30 s of StateBatches, `BlackBox.held`), cut to the range, and names every part it cannot
give with why (`ReplayMissing`): older than the window (`too_old`), within the window but never
published (`never_published`: the loop dropped them, its ring to the publisher was full),
newer than the last published batch (`not_yet`).

Budget: a range is at most `MAX_SAMPLES` samples (5 s at 1 kHz; a recorder asks in chunks), at
most `MAX_PENDING` queries wait (more are shed, the client times out), and one worker thread
serves them off the loop's thread and the publisher's. Readable by whoever may read the stream:
the public key, and with authentication each user's own scope (viewers included).
"""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Callable, Sequence
from typing import Any

from controller import protocol as proto
from controller.core.samples import STATE_COLUMNS

__all__ = ["MAX_PENDING", "MAX_SAMPLES", "ReplayServer", "parse_range", "replay"]

MAX_SAMPLES = proto.REPLAY_MAX_SAMPLES
"""Samples one query may ask for."""
MAX_PENDING = 8
"""Queries waiting for the worker; more are shed."""


def parse_range(parameters: str) -> tuple[int, int]:
    """`from=<seq>;to=<seq>` (Zenoh selector parameters, `&` also accepted) -> (from, to);
    ValueError naming the parameter."""
    got: dict[str, str] = {}
    for part in parameters.replace("&", ";").split(";"):
        if part:
            name, _, value = part.partition("=")
            got[name] = value
    out = []
    for name in ("from", "to"):
        text = got.get(name)
        if text is None:
            raise ValueError(f"{name}: missing (ask ?from=<seq>;to=<seq>)")
        if not text.isdigit() or len(text) > 18:
            raise ValueError(f"{name}: {text[:20]!r} is not a sequence number")
        out.append(int(text))
    lo, hi = out
    if hi < lo:
        raise ValueError(f"to: {hi} is before from ({lo})")
    if hi - lo + 1 > MAX_SAMPLES:
        raise ValueError(f"to: {hi - lo + 1} samples asked, at most {MAX_SAMPLES} per query")
    return lo, hi


def _cut(b: proto.StateBatch, lo: int, hi: int) -> proto.StateBatch:
    n = len(b.t_s)
    i0, i1 = max(lo - b.seq0, 0), min(hi - b.seq0 + 1, n)
    if i0 == 0 and i1 == n:
        return b
    cols = [getattr(b, c)[i0:i1] for c in STATE_COLUMNS]
    return proto.state_batch(rig=b.rig, seq0=b.seq0 + i0, rate_hz=b.rate_hz,
                             config_version=b.config_version, columns=cols,
                             epoch_s=b.epoch_s, mode=b.mode)


def replay(held: Sequence[proto.StateBatch], lo: int, hi: int,
           window_s: float = 30.0) -> proto.StateReplay:
    """What the batches `held` (in publication order) give of samples lo..hi, and what not."""
    batches: list[proto.StateBatch] = []
    missing: list[proto.ReplayMissing] = []
    held = [b for b in held if b.t_s]
    oldest = held[0].seq0 if held else -1
    newest = held[-1].seq0 + len(held[-1].t_s) - 1 if held else -1

    def miss(a: int, z: int) -> None:
        if held and z < oldest:
            why, text = "too_old", (f"older than the {window_s:g} s the controller keeps "
                                   f"(oldest sample held: {oldest})")
        elif not held or a > newest:
            why, text = "not_yet", f"not published yet (newest sample: {newest})"
        else:
            why, text = "never_published", ("the loop dropped these samples: its ring to the "
                                            "publisher was full (Status.timing.dropped_samples)")
        missing.append(proto.ReplayMissing(from_seq=a, to_seq=z, reason=why, text=text))

    nxt = lo
    for b in held:
        end = b.seq0 + len(b.t_s) - 1
        if end < nxt or b.seq0 > hi:
            continue
        if b.seq0 > nxt:
            if held and nxt < oldest <= b.seq0 - 1:  # part too old, part never published
                miss(nxt, oldest - 1)
                nxt = oldest
            if b.seq0 > nxt:
                miss(nxt, b.seq0 - 1)
        batches.append(_cut(b, max(nxt, b.seq0), hi))
        nxt = min(end, hi) + 1
        if nxt > hi:
            break
    if nxt <= hi:
        if held and nxt < oldest <= hi:
            miss(nxt, oldest - 1)
            nxt = oldest
        if nxt <= hi:
            miss(nxt, hi)
    return proto.StateReplay(batches=batches, missing=missing, oldest_seq=oldest,
                             newest_seq=newest)


class ReplayServer:
    """The queryable and its worker. `held()` returns the published batches still kept."""

    def __init__(self, rig: str, held: Callable[[], Sequence[proto.StateBatch]],
                 warn: Callable[[str], None], *, window_s: float = 30.0) -> None:
        self.rig = rig
        self.held = held
        self.warn = warn
        self.window_s = window_s
        self._q: queue.Queue[Any] = queue.Queue(maxsize=MAX_PENDING)
        self._entities: list[Any] = []
        self._thread: threading.Thread | None = None
        self.shed = 0
        self.served = 0

    def declare(self, session: Any, *, auth: bool) -> None:
        """The queryable on the public key and (`auth`) every user's scope; the worker."""
        import zenoh

        key = proto.key_state_replay(self.rig)
        keys = [key, proto.any_user_key(key)] if auth else [key]

        def put(query: Any) -> None:  # on Zenoh's thread: hand over, never block
            try:
                self._q.put_nowait(query)
            except queue.Full:
                self.shed += 1

        for k in keys:
            self._entities.append(session.declare_queryable(
                k, zenoh.handlers.Callback(put, indirect=False)))
        self._thread = threading.Thread(target=self._serve, name="state-replay", daemon=True)
        self._thread.start()

    def answer(self, parameters: str) -> tuple[bytes | None, str]:
        """(reply payload, "") or (None, the refusal naming the parameter)."""
        try:
            lo, hi = parse_range(parameters)
        except ValueError as exc:
            return None, str(exc)
        return proto.encode(replay(list(self.held()), lo, hi, self.window_s)), ""

    def _serve(self) -> None:
        encoding = proto.encoding(proto.StateReplay)
        while True:
            query = self._q.get()
            if query is None:
                return
            try:
                data, refused = self.answer(str(query.parameters))
                if data is None:
                    query.reply_err(refused.encode())
                else:
                    query.reply(query.key_expr, data, encoding=encoding)
                    self.served += 1
            except Exception as exc:  # never end the worker
                self.warn(f"state replay: {type(exc).__name__}: {exc}")
            finally:
                with contextlib.suppress(Exception):
                    query.drop()

    def close(self) -> None:
        for e in self._entities:
            with contextlib.suppress(Exception):
                e.undeclare()
        self._entities.clear()
        if self._thread is not None:
            with contextlib.suppress(queue.Full):
                self._q.put(None, timeout=1.0)
            self._thread.join(timeout=5.0)

    undeclare = close  # closed with the node's other entities
