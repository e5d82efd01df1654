"""Recordings as MCAP files (the robotics log format Foxglove and PlotJuggler open directly),
written with the `mcap` library and read by walking the file's chunks directly (`_messages`:
the library's pure-Python reader took 17 s for a 10-minute recording), the /state messages
taken straight into columns (`state_scan`).

Channels (message encoding "json", schemas embedded as JSON Schema, zstd-compressed chunks):

- `/state`: one message per loop tick, log time = the sample's time (`epoch_s + t_s`): seq,
  t_s, ref_deg, pos_deg, speed_deg_s, speed_ref_deg_s, command_deg_s, d_hat_deg_s, error_deg,
  config_version, mode.
- `/status`: every controller Status received (as its JSON form).
- `/config`: each configuration version the first time it is seen (version, config).
- `/events`: what happened: `gap` (samples missing: from_seq, to_seq, and `reason`: why they
  could not be had, e.g. `too_old`, `never_published`, `not_received`; a recorder fetches a
  jump in seq again from the controller's replay before it calls it a gap), `mode` (estop, fault,
  running...), `config` (a new version), `watchdog`, `note`, and whatever a caller adds
  (e-stop, rollback, the black box's reason).

Pure I/O on files: no Zenoh here (`dobtune record` and the controller's black box feed it).
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
import numpy as np

from controller.core.samples import STATE_COLUMNS

__all__ = ["SCHEMAS", "Recorder", "Recording", "file_messages", "read_recording",
           "read_recordings"]

_NUM = {"type": "number"}
SCHEMAS: dict[str, dict[str, Any]] = {
    "/state": {
        "title": "dobtune.State",
        "description": "one loop tick (load-side degrees and deg/s)",
        "type": "object",
        "properties": {
            "seq": {"type": "integer"},
            **{c: _NUM for c in STATE_COLUMNS},
            "config_version": {"type": "integer"},
            "mode": {"type": "string"},
        },
    },
    "/status": {"title": "dobtune.Status", "type": "object",
                "description": "the controller's Status message (docs/protocol.md)"},
    "/config": {"title": "dobtune.Config", "type": "object",
                "properties": {"version": {"type": "integer"}, "config": {"type": "object"}}},
    "/events": {"title": "dobtune.Event", "type": "object",
                "properties": {"kind": {"type": "string"}, "text": {"type": "string"},
                               "seq": {"type": "integer"}}},
}
_enc = msgspec.json.Encoder()


def _ns(t_s: float) -> int:
    return max(0, round(t_s * 1e9))


class Recorder:
    """Writes one recording (context manager). Not thread-safe: one writer thread."""

    def __init__(self, out: str | Path | IO[bytes], *, rig: str = "", profile: str = "") -> None:
        from mcap.writer import CompressionType, Writer

        self._own = isinstance(out, (str, Path))
        self._f: IO[bytes] = open(out, "wb") if isinstance(out, (str, Path)) else out  # noqa: SIM115
        self._w = Writer(self._f, compression=CompressionType.ZSTD)
        self._w.start(profile=profile, library="dobtune")
        self._chan: dict[str, int] = {}
        for topic, schema in SCHEMAS.items():
            sid = self._w.register_schema(
                name=schema["title"], encoding="jsonschema", data=json.dumps(schema).encode()
            )
            self._chan[topic] = self._w.register_channel(
                topic=topic, message_encoding="json", schema_id=sid, metadata={"rig": rig}
            )
        self._seq = 0
        self.next_seq: int | None = None
        """The sample sequence number expected next (gaps are recorded as events)."""
        self.samples = 0
        self.gaps = 0
        self.missing: list[tuple[int, int, str]] = []
        """Each gap as (from_seq, to_seq, reason)."""
        self._versions: set[int] = set()
        self._mode = ""
        self._last_ns = 0
        self._closed = False

    def _put(self, topic: str, t_ns: int, data: bytes) -> None:
        self._w.add_message(channel_id=self._chan[topic], log_time=t_ns, data=data,
                            publish_time=t_ns, sequence=self._seq)
        self._seq += 1
        self._last_ns = max(self._last_ns, t_ns)

    def event(self, kind: str, text: str = "", t_s: float | None = None, **fields: Any) -> None:
        t_ns = _ns(t_s) if t_s is not None else self._last_ns
        self._put("/events", t_ns, _enc.encode({"kind": kind, "text": text, **fields}))

    def config(self, version: int, config: Any, t_s: float | None = None) -> None:
        if version in self._versions:
            return
        self._versions.add(version)
        t_ns = _ns(t_s) if t_s is not None else self._last_ns
        self._put("/config", t_ns, _enc.encode({"version": version,
                                                "config": msgspec.to_builtins(config)}))

    def state(self, batch: Any) -> None:
        """A `StateBatch`: one message per sample; a jump in seq is recorded as a gap."""
        n = len(batch.t_s)
        if n == 0:
            return
        t0 = batch.epoch_s
        if self.next_seq is not None and batch.seq0 > self.next_seq:
            self.gap(self.next_seq, batch.seq0 - 1, "not_received", t0 + batch.t_s[0])
        elif self.next_seq is not None and batch.seq0 < self.next_seq:
            self.event("note", f"sequence went back from {self.next_seq} to {batch.seq0} (the "
                       "controller restarted)", t0 + batch.t_s[0], seq=batch.seq0)
        if batch.mode != self._mode:
            if self._mode:
                self.event("mode", f"{self._mode} -> {batch.mode}", t0 + batch.t_s[0],
                           seq=batch.seq0)
            self._mode = batch.mode
        cols = [getattr(batch, c) for c in STATE_COLUMNS]
        for i in range(n):
            rec = {"seq": batch.seq0 + i}
            for name, col in zip(STATE_COLUMNS, cols, strict=True):
                v = col[i]
                rec[name] = v if math.isfinite(v) else None
            rec["config_version"] = batch.config_version
            rec["mode"] = batch.mode
            self._put("/state", _ns(t0 + batch.t_s[i]), _enc.encode(rec))
        self.samples += n
        self.next_seq = batch.seq0 + n

    def gap(self, from_seq: int, to_seq: int, reason: str, t_s: float | None = None,
            text: str = "") -> None:
        """Samples from_seq..to_seq are missing, for `reason` (recorded as a `gap` event); the
        next sample expected is then to_seq + 1."""
        lost = to_seq - from_seq + 1
        self.gaps += max(lost, 0)
        self.missing.append((from_seq, to_seq, reason))
        self.event("gap", f"{lost} sample(s) lost ({reason}{': ' + text if text else ''})",
                   t_s, from_seq=from_seq, to_seq=to_seq, reason=reason)
        self.next_seq = to_seq + 1

    def status(self, st: Any, t_s: float) -> None:
        """A `Status` (also records its configuration version the first time)."""
        self.config(st.config_version, st.config, t_s)
        self._put("/status", _ns(t_s), msgspec.json.encode(st))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._w.finish()
        if self._own:
            self._f.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class Recording:
    """A recording read back: the state columns as arrays (sorted by seq), the rest as dicts."""

    state: dict[str, np.ndarray]
    log_time_s: np.ndarray
    configs: dict[int, dict[str, Any]] = field(default_factory=dict)
    events: list[dict[str, Any]] = field(default_factory=list)
    statuses: list[dict[str, Any]] = field(default_factory=list)
    channels: dict[str, str] = field(default_factory=dict)
    """topic -> schema name."""

    @property
    def n(self) -> int:
        return int(self.state["seq"].size)


_MAGIC = b"\x89MCAP0\r\n"
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_DATA_END = 0x03, 0x04, 0x05, 0x06, 0x0F
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, content length


def _string(buf: memoryview | bytes, at: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(buf, at)
    return bytes(buf[at + 4 : at + 4 + n]).decode(), at + 4 + n


def _messages(path: Path) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, schema name, log time ns, data) of every message, in file order: the data
    section's records walked directly (MCAP spec: opcode, length, content), each chunk
    decompressed whole (zstd, lz4 or none). The `mcap` library's reader builds an object per
    record in Python: a 10-minute recording took it 17 s."""
    buf = memoryview(path.read_bytes())
    if bytes(buf[:8]) != _MAGIC:
        raise ValueError("not an MCAP file (no magic)")
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}  # id -> (topic, schema name)

    def records(data: memoryview, out_of_chunk: bool) -> Iterator[tuple[str, str, int, bytes]]:
        at, end = 0, len(data)
        while at < end:
            op, body, at = _record(data, at, end)
            if op == _OP_MESSAGE:
                cid, _seq, t_ns, _pub = _MESSAGE_HEAD.unpack_from(data, body)
                topic, schema = channels[cid]
                yield topic, schema, t_ns, bytes(data[body + 22 : at])
            elif op == _OP_CHUNK and out_of_chunk:
                yield from records(_chunk(data, body), False)
            elif op == _OP_DATA_END and out_of_chunk:
                return
            else:
                _take_meta(op, data, body, schemas, channels)

    yield from records(buf[8:], True)


def file_messages(path: Path) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, schema name, log time ns, data) of every message of the MCAP file `path`, in
    file order (the chunks walked directly, as `read_recording` does; the trend's reader).
    Raises ValueError for a file that is not MCAP; a record cut short raises ValueError (or
    zstd's error) where it is met, after the messages before it."""
    return _messages(path)


def _record(data: memoryview, at: int, end: int) -> tuple[int, int, int]:
    """(opcode, where its content starts, where the next record starts) of the record at
    `at` (MCAP spec: opcode, u64 length, content)."""
    op, n = _RECORD_HEAD.unpack_from(data, at)
    body = at + 9
    if body + n > end:
        raise ValueError("truncated record")
    return op, body, body + n


def _take_meta(op: int, data: memoryview, body: int, schemas: dict[int, str],
               channels: dict[int, tuple[str, str]]) -> None:
    """A schema or channel record into the maps (other records are not needed)."""
    if op == _OP_SCHEMA:
        (sid,) = _U16.unpack_from(data, body)
        schemas[sid] = _string(data, body + 2)[0]
    elif op == _OP_CHANNEL:
        cid, sid = struct.unpack_from("<HH", data, body)
        topic = _string(data, body + 4)[0]
        channels[cid] = (topic, schemas.get(sid, ""))


def _chunk(data: memoryview, at: int) -> memoryview:
    """A chunk record's records, decompressed."""
    size = _U64.unpack_from(data, at + 16)[0]
    compression, at = _string(data, at + 28)
    (n,) = _U64.unpack_from(data, at)
    raw = data[at + 8 : at + 8 + n]
    if compression == "zstd":
        import zstandard

        return memoryview(zstandard.ZstdDecompressor().decompress(raw, max_output_size=size))
    if compression == "lz4":
        import lz4.frame

        return memoryview(lz4.frame.decompress(raw))
    if compression == "":
        return raw
    raise ValueError(f"chunk compression {compression!r} not supported")


#: One /state message as read back (a null column is a sample that was not finite).
_StateMsg = msgspec.defstruct(
    "StateMsg",
    [("seq", int), *[(c, float | None, None) for c in STATE_COLUMNS],
     ("config_version", int, 0), ("mode", str, "")],
)
_state_list = msgspec.json.Decoder(list[_StateMsg])  # type: ignore[valid-type]


def read_recording(path: str | Path) -> Recording:
    """Read a dobtune MCAP file. Raises ValueError naming the file for anything else.

    The /state messages (one per tick: most of the file) go straight into columns
    (`state_scan`); a file whose /state messages are not in `Recorder.state`'s exact form is
    read by the general decoder (`_read_general`), which gives the same arrays."""
    path = Path(path)
    try:
        rec = _read_scanned(path)
        if rec is None:
            rec = _read_general(path)
    except Exception as exc:  # damaged files raise struct, zstd, msgspec errors
        raise ValueError(f"{path}: not a readable dobtune recording: {exc}") from exc
    if "/state" not in rec.channels:
        raise ValueError(f"{path}: no /state channel (not a dobtune recording)")
    return rec


def read_recordings(paths: Iterable[str | Path]) -> list[Recording]:
    """`read_recording` of several files at once, on threads (the scan and zstd run without
    the GIL, so one file's scan overlaps the other's decode: the overlay of two recordings
    reads both together). The first file that cannot be read raises, as read_recording."""
    files = list(paths)
    if len(files) < 2:
        return [read_recording(f) for f in files]
    with ThreadPoolExecutor(len(files), thread_name_prefix="read-recordings") as pool:
        return list(pool.map(read_recording, files))


def _take_other(rec: Recording, topic: str, t_ns: int, data: bytes | memoryview) -> None:
    """A message that is not /state, into the recording."""
    obj = json.loads(bytes(data))
    if topic == "/config":
        rec.configs[int(obj["version"])] = obj["config"]
    elif topic == "/events":
        rec.events.append({**obj, "log_time_s": t_ns / 1e9})
    elif topic == "/status":
        rec.statuses.append(obj)


def _sorted_state(rec: Recording, cols: dict[str, np.ndarray], times_ns: np.ndarray) -> None:
    seq = cols["seq"].astype(np.int64)
    if seq.size and np.all(seq[1:] >= seq[:-1]):  # in order already (the usual case): the
        rec.state = dict(cols)  # stable sort's permutation is the identity
        log_time_s = np.asarray(times_ns, dtype=np.float64) / 1e9
    else:
        order = np.argsort(seq, kind="stable")
        rec.state = {k: v[order] for k, v in cols.items()}
        log_time_s = np.asarray(times_ns, dtype=np.float64)[order] / 1e9
    rec.state["seq"] = rec.state["seq"].astype(np.int64)
    rec.state["config_version"] = rec.state["config_version"].astype(np.int64)
    rec.log_time_s = log_time_s


def _read_scanned(path: Path) -> Recording | None:
    """The file's records walked as `_messages` walks them, runs of /state messages scanned
    by `state_scan` (None: a /state message not in the recorder's form)."""

    buf = memoryview(path.read_bytes())
    if bytes(buf[:8]) != _MAGIC:
        raise ValueError("not an MCAP file (no magic)")
    with ThreadPoolExecutor(2, thread_name_prefix="read-recording") as pool:
        try:
            return _scan_records(buf[8:], pool)
        finally:
            pool.shutdown(cancel_futures=True)


def _chunks_ahead(data: memoryview, pool: ThreadPoolExecutor) -> dict[int, Future[memoryview]]:
    """Every chunk of the data section, decompressed on `pool` (in file order) while the
    records before it are taken: chunk body offset -> its records."""
    out: dict[int, Future[memoryview]] = {}
    at, end = 0, len(data)
    while at + 9 <= end:
        op, n = _RECORD_HEAD.unpack_from(data, at)
        body = at + 9
        if op == _OP_DATA_END or body + n > end:
            break
        if op == _OP_CHUNK:
            out[body] = pool.submit(_chunk, data, body)
        at = body + n
    return out


def _scan_records(top: memoryview, pool: ThreadPoolExecutor) -> Recording | None:
    from controller.recording import state_scan

    rec = Recording(state={}, log_time_s=np.empty(0))
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    ahead = _chunks_ahead(top, pool)
    state = state_scan.StateColumns(pool)
    state_cid = -1

    def records(data: memoryview, out_of_chunk: bool) -> bool:
        nonlocal state_cid
        arr = np.frombuffer(data, dtype=np.uint8)
        at, end = 0, len(data)
        while at < end:
            if state_cid >= 0:
                before = state.n
                at, status = state.take(arr, at, end, state_cid)
                if status == state_scan.SHAPE_MISMATCH:
                    return False
                if status == state_scan.TRUNCATED:
                    raise ValueError("truncated record")
                if state.n > before:
                    rec.channels["/state"] = channels[state_cid][1]
                if at >= end:
                    break
            op, body, at = _record(data, at, end)
            if op == _OP_MESSAGE:
                cid, _seq, t_ns, _pub = _MESSAGE_HEAD.unpack_from(data, body)
                topic, schema = channels[cid]
                if topic == "/state":  # not the channel the scan takes
                    return False
                rec.channels[topic] = schema
                _take_other(rec, topic, t_ns, data[body + 22 : at])
            elif op == _OP_CHUNK and out_of_chunk:
                got = ahead.pop(body, None) if data is top else None
                if not records(got.result() if got else _chunk(data, body), False):
                    return False
            elif op == _OP_DATA_END and out_of_chunk:
                return True
            else:
                _take_meta(op, data, body, schemas, channels)
                if op == _OP_CHANNEL and state_cid < 0:
                    state_cid = next((c for c, (t, _) in channels.items() if t == "/state"), -1)
        return True

    if not records(top, True):
        return None
    _sorted_state(rec, *state.columns())
    return rec


def _read_general(path: Path) -> Recording:
    """Every message through `_messages`; the /state messages decoded in one msgspec call."""
    states: list[bytes] = []
    times: list[int] = []
    rec = Recording(state={}, log_time_s=np.empty(0))
    for topic, schema, t_ns, data in _messages(path):
        rec.channels[topic] = schema
        if topic == "/state":
            states.append(data)
            times.append(t_ns)
            continue
        _take_other(rec, topic, t_ns, data)
    msgs: list[Any] = _state_list.decode(b"[" + b",".join(states) + b"]")
    cols = {c: np.array([getattr(m, c) for m in msgs], dtype=np.float64)
            for c in ("seq", *STATE_COLUMNS, "config_version")}
    cols["mode"] = np.asarray([m.mode for m in msgs], dtype=object)
    _sorted_state(rec, cols, np.asarray(times, dtype=np.float64))
    return rec


def write_batches(path: str | Path, batches: Iterable[Any], *, rig: str = "",
                  events: Iterable[tuple[str, str]] = ()) -> Path:
    """A whole recording from StateBatches (the black box), with events first."""
    path = Path(path)
    with Recorder(path, rig=rig) as r:
        first = True
        for b in batches:
            if first:
                t0 = b.epoch_s + (b.t_s[0] if b.t_s else 0.0)
                for kind, text in events:
                    r.event(kind, text, t0)
                first = False
            r.state(b)
    return path
