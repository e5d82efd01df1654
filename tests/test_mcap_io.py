"""The recording reader walks MCAP chunks itself: it must give what the `mcap` library's reader
gives (the reference), for our own files and for other compressions."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from controller import protocol as proto
from controller.core.samples import STATE_COLUMNS
from controller.recording.mcap_io import Recorder, _messages, read_recording


def _reference(path: Path) -> list[tuple[str, str, int, bytes]]:
    with open(path, "rb") as f:
        return [(c.topic, s.name if s else "", m.log_time, m.data)
                for s, c, m in make_reader(f).iter_messages(log_time_order=False)]


def _batches(n: int, seq0: int = 0) -> list[proto.StateBatch]:
    out = []
    for s in range(seq0, seq0 + n, 20):
        t = np.arange(s, s + 20) / 1000.0
        cols = [t, np.sin(t), np.sin(t) + 1e-3, np.cos(t), np.cos(t), np.cos(t), 0.01 * t,
                np.full(20, np.nan if s == 40 else 1e-3)]
        out.append(proto.state_batch(rig="m", seq0=s, rate_hz=1000.0, config_version=1 + s // 1000,
                                     columns=[c.tolist() for c in cols], epoch_s=1.7e9,
                                     mode="running"))
    return out


def test_our_recordings_read_as_the_mcap_library_reads_them(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    with Recorder(path, rig="m") as r:
        r.config(1, {"q_cutoff_hz": 0.5}, t_s=1.7e9)
        r.event("note", "hello", t_s=1.7e9)
        for b in _batches(3000):  # several chunks
            r.state(b)
        for b in _batches(200, seq0=3500):  # a gap
            r.state(b)
    ours, ref = list(_messages(path)), _reference(path)
    assert len(ref) > 3200 and ours == ref
    rec = read_recording(path)
    assert rec.n == 3200 and rec.events and rec.configs[1] == {"q_cutoff_hz": 0.5}
    assert np.isnan(rec.state[STATE_COLUMNS[-1]][40])  # a sample that was not finite


@pytest.mark.parametrize("compression", [CompressionType.LZ4, CompressionType.NONE])
def test_other_compressions_and_chunk_sizes(tmp_path: Path, compression: CompressionType) -> None:
    path = tmp_path / "x.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=compression, chunk_size=4096)
        w.start()
        sid = w.register_schema(name="S", encoding="jsonschema", data=b"{}")
        a = w.register_channel(topic="/a", message_encoding="json", schema_id=sid)
        b = w.register_channel(topic="/b", message_encoding="json", schema_id=0)
        for i in range(2000):
            w.add_message(channel_id=a if i % 3 else b, log_time=i * 1000, publish_time=i,
                          sequence=i, data=b'{"i": %d}' % i)
        w.finish()
    assert list(_messages(path)) == _reference(path)


def test_a_damaged_file_is_refused_with_its_name(tmp_path: Path) -> None:
    buf = io.BytesIO()
    with Recorder(buf) as r:
        for b in _batches(2000):
            r.state(b)
    data = buf.getvalue()
    for cut in (b"not an mcap at all", data[: len(data) // 2]):
        bad = tmp_path / "bad.mcap"
        bad.write_bytes(cut)
        with pytest.raises(ValueError, match=r"bad\.mcap"):
            read_recording(bad)
