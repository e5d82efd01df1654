"""A rig's drift trend: the watch's windows kept over days as MCAP channels, queryable by time.

Why MCAP: the project's recordings are MCAP already (Foxglove and PlotJuggler open them, so do
the field's tools), the `mcap` library is a dependency, and a trend is a few numbers per
window: no time-series server a user would have to run. One file per rig and UTC hour,
`<dir>/<rig>/<YYYYmmdd-HH>.mcap`, closed at the hour's end (a process killed mid-hour loses at
most that hour's open chunk; the files before are whole); a time range reads only the hours it
covers.

Channels (JSON, schemas embedded, zstd chunks), log time = the window's end:
- `/drift/residual`: plant_residual_rms_deg_s, fitted_residual_rms_deg_s, loop_measured_rms_deg,
  loop_predicted_rms_deg, loop_residual_rms_deg, delay_ticks;
- `/drift/parts`: per part value, std, state (a flat object: `<part>`, `<part>_std`,
  `<part>_state`);
- `/drift/health`: the loop's timing (compute p99 us, skipped ticks), config version, alarms;
- `/drift/alarm`: each alarm as published (controller.protocol.DriftAlarm's fields).
"""

from __future__ import annotations

import calendar
import itertools
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec

__all__ = ["TOPICS", "HourRead", "TrendPoint", "TrendWriter", "read_hour", "read_trend",
           "trend_files", "trend_rigs"]

TOPICS: tuple[str, ...] = ("/drift/residual", "/drift/parts", "/drift/health", "/drift/alarm")
_HOUR_S = 3600
#: A chunk is written (and readable) once this much is in it: about 20 windows of the watch's
#: four channels, i.e. the newest ~3 minutes of a 10 s watch are not on disk yet (64 KiB: ~12
#: minutes); 8 % more bytes than 64 KiB chunks on noisy values (2.26 against 2.09 MB a day).
CHUNK_BYTES = 16 * 1024
_MAGIC = b"\x89MCAP0\r\n"


def _hour_name(epoch_s: float) -> str:
    return time.strftime("%Y%m%d-%H", time.gmtime(epoch_s)) + ".mcap"


class TrendWriter:
    """Appends windows to the rig's hourly files (one writer thread)."""

    def __init__(self, root: Path, rig: str) -> None:
        self.dir = Path(root) / rig
        self.dir.mkdir(parents=True, exist_ok=True)
        self.rig = rig
        self._hour = -1
        self._f: IO[bytes] | None = None
        self._w: Any = None
        self._chan: dict[str, int] = {}
        self.messages = 0

    def _open(self, epoch_s: float) -> None:
        from mcap.writer import CompressionType, Writer

        hour = int(epoch_s // _HOUR_S)
        if hour == self._hour and self._w is not None:
            return
        self.close()
        path = self.dir / _hour_name(epoch_s)
        if path.exists():  # a restart within the hour: a file of its own beside it
            path = path.with_name(f"{path.stem}.{int(epoch_s)}.mcap")
        self._f = open(path, "wb")  # noqa: SIM115 (closed by close())
        self._w = Writer(self._f, compression=CompressionType.ZSTD, chunk_size=CHUNK_BYTES)
        self._w.start(profile="", library="dobtune")
        self._chan = {}
        for topic in TOPICS:
            sid = self._w.register_schema(
                name="dobtune." + topic.strip("/").replace("/", "."), encoding="jsonschema",
                data=json.dumps({"type": "object"}).encode())
            self._chan[topic] = self._w.register_channel(
                topic=topic, message_encoding="json", schema_id=sid, metadata={"rig": self.rig})
        self._hour = hour

    def write(self, topic: str, epoch_s: float, data: dict[str, Any]) -> None:
        self._open(epoch_s)
        t_ns = max(0, round(epoch_s * 1e9))
        self._w.add_message(channel_id=self._chan[topic], log_time=t_ns, publish_time=t_ns,
                            data=msgspec.json.encode(data), sequence=self.messages)
        self.messages += 1
        assert self._f is not None
        self._f.flush()  # a chunk just closed is on disk for the readers (the Trends tab)

    def close(self) -> None:
        if self._w is not None:
            self._w.finish()
            self._w = None
        if self._f is not None:
            self._f.close()
            self._f = None
        self._hour = -1

    def __enter__(self) -> TrendWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class TrendPoint:
    epoch_s: float
    data: dict[str, Any] = field(default_factory=dict)


def trend_rigs(root: Path) -> list[str]:
    """The rigs with a trend under `root` (a directory holding at least one .mcap file)."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(d.name for d in root.iterdir() if d.is_dir() and any(d.glob("*.mcap")))


def trend_files(root: Path, rig: str, t0_epoch_s: float, t1_epoch_s: float) -> list[Path]:
    """The hourly files of `rig` whose hour lies in t0..t1 (UNIX seconds), oldest first (a
    restart's file beside its hour's after it)."""
    lo = int(t0_epoch_s // _HOUR_S)
    hi = int(t1_epoch_s // _HOUR_S)
    out: list[Path] = []
    for path in sorted((Path(root) / rig).glob("*.mcap")):
        try:
            hour = calendar.timegm(time.strptime(path.name[:11], "%Y%m%d-%H")) // _HOUR_S
        except ValueError:
            continue
        if lo <= hour <= hi:
            out.append(path)
    return out


@dataclass
class HourRead:
    """One hourly file's messages by topic, oldest first: their times (UNIX seconds) and
    their data; `cut_short`: why the file ended before its end ("" when whole: an hour still
    being written ends after its last whole chunk, with no error)."""

    epoch_s: dict[str, list[float]]
    data: dict[str, list[dict[str, Any]]]
    cut_short: str = ""

    def points(self, topic: str) -> list[TrendPoint]:
        return [TrendPoint(t, d) for t, d in zip(self.epoch_s[topic], self.data[topic],
                                                 strict=True)]


_json_objects = msgspec.json.Decoder(list[dict[str, Any]])


def read_hour(path: Path) -> HourRead:
    """Every message of one hourly file (all topics, one pass: the chunks walked directly,
    `mcap_io.file_messages`; each topic's JSON decoded in one call). Raises ValueError
    (naming the file) when it is not a trend file at all; a file cut short gives what came
    before the cut and says where."""
    from controller.recording.mcap_io import file_messages

    path = Path(path)
    times: dict[str, list[float]] = {t: [] for t in TOPICS}
    raws: dict[str, list[bytes]] = {t: [] for t in TOPICS}
    with open(path, "rb") as f:
        head = f.read(len(_MAGIC))
    if not _MAGIC.startswith(head):
        raise ValueError(f"{path.name}: not a trend file (no MCAP magic)")
    cut = ""
    if len(head) == len(_MAGIC):  # shorter: a file just opened, its header still buffered
        n = 0
        try:
            for topic, _schema, t_ns, raw in file_messages(path):
                if topic in raws:
                    times[topic].append(t_ns / 1e9)
                    raws[topic].append(raw)
                    n += 1
        except Exception as exc:  # struct, zstd errors: a chunk cut short or damaged
            cut = f"{path.name}: cut short after {n} messages ({type(exc).__name__}: {exc})"
    data: dict[str, list[dict[str, Any]]] = {}
    for topic, rs in raws.items():
        try:
            data[topic] = _json_objects.decode(b"[" + b",".join(rs) + b"]")
        except msgspec.DecodeError as exc:
            raise ValueError(f"{path.name}: {topic}: not JSON objects ({exc})") from exc
        ts = times[topic]
        if any(b < a for a, b in itertools.pairwise(ts)):  # written out of order
            order = sorted(range(len(ts)), key=ts.__getitem__)
            times[topic] = [ts[i] for i in order]
            data[topic] = [data[topic][i] for i in order]
    return HourRead(times, data, cut)


def read_trend(root: Path, rig: str, t0_epoch_s: float, t1_epoch_s: float,
               topic: str = "/drift/parts") -> list[TrendPoint]:
    """The `topic`'s messages of `rig` from t0 to t1 (UNIX seconds), oldest first; only the
    hours in the range are opened. A file cut short (a process killed mid-hour) gives what
    its whole chunks hold."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    if topic not in TOPICS:
        raise ValueError(f"topic: one of {', '.join(TOPICS)}")
    out: list[TrendPoint] = []
    for path in trend_files(root, rig, t0_epoch_s, t1_epoch_s):
        with open(path, "rb") as f:
            try:
                for _s, _c, m in make_reader(f).iter_messages(
                        topics=[topic], starting_at=round(t0_epoch_s * 1e9),
                        ending_at=round(t1_epoch_s * 1e9)):
                    out.append(TrendPoint(m.log_time / 1e9, json.loads(m.data)))
            except (McapError, EOFError, ValueError):
                pass  # the cut-off end of a file; what came before is kept
    out.sort(key=lambda p: p.epoch_s)
    return out
