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
from controller.recording.mcap_io import (
    Recorder,
    Recording,
    _messages,
    _read_general,
    _read_scanned,
    read_recording,
    read_recordings,
)


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


def _same_recording(a: object, b: object) -> None:
    """Equal arrays (dtype, shape, values bit for bit, NaN where NaN) and equal dicts."""
    assert isinstance(a, Recording) and isinstance(b, Recording)
    assert list(a.state) == list(b.state)
    for k in a.state:
        x, y = a.state[k], b.state[k]
        assert x.dtype == y.dtype and x.shape == y.shape, k
        if x.dtype == object:
            assert x.tolist() == y.tolist(), k
        else:
            assert np.array_equal(x.view(np.uint64) if x.dtype == np.float64 else x,
                                  y.view(np.uint64) if y.dtype == np.float64 else y), k
    assert np.array_equal(a.log_time_s, b.log_time_s)
    assert (a.configs, a.events, a.statuses, a.channels) == (b.configs, b.events, b.statuses,
                                                            b.channels)


def _varied_batches() -> list[proto.StateBatch]:
    """Values of every kind the scan must copy: random doubles (17 digits), tiny and huge
    exponents, -0.0, integers, non-finite samples (null), modes that change, several config
    versions, a gap and batches out of order."""
    rng = np.random.default_rng(5)
    out = []
    for i, s in enumerate([0, 40, 80, 200, 120, 160, 240]):
        cols = [(np.arange(s, s + 40) / 1000.0).tolist()]
        for c in range(1, len(STATE_COLUMNS)):
            v = rng.standard_normal(40) * 10.0 ** rng.integers(-300, 300, 40)
            v[:3] = [-0.0, 1.0, float(c)]
            v[3 + c % 5] = (np.nan, np.inf, -np.inf, 1e-320, 5e-324)[c % 5]
            cols.append(v.tolist())
        out.append(proto.state_batch(rig="m", seq0=s, rate_hz=1000.0, config_version=1 + i // 3,
                                     columns=cols, epoch_s=1.7e9 + i,
                                     mode=("running", "estop", "running", "fault")[i % 4]))
    return out


def test_the_column_scan_gives_the_general_decoders_arrays(tmp_path: Path) -> None:
    path = tmp_path / "v.mcap"
    with Recorder(path, rig="m") as r:
        r.config(1, {"q_cutoff_hz": 0.5}, t_s=1.7e9)
        for i, b in enumerate(_varied_batches()):
            r.state(b)
            r.event("note", f"batch {i} \u00e9\"\\", t_s=1.7e9 + i)
            r.config(1 + i // 3, {"q_cutoff_hz": 0.5 + i}, t_s=1.7e9 + i)
        for b in _batches(3000, seq0=1000):  # several chunks
            r.state(b)
    scanned, general = _read_scanned(path), _read_general(path)
    assert scanned is not None and scanned.n == 7 * 40 + 3000
    _same_recording(scanned, general)
    _same_recording(read_recording(path), general)
    assert np.all(np.diff(scanned.state["seq"]) >= 0)  # sorted by seq (batches were not)
    assert set(scanned.state["mode"]) == {"running", "estop", "fault"}
    assert np.isnan(scanned.state["ref_deg"]).sum() == 7  # one null per batch in that column


@pytest.mark.parametrize("compression", [CompressionType.LZ4, CompressionType.NONE])
def test_the_scan_on_small_chunks_of_other_compressions(tmp_path: Path,
                                                        compression: CompressionType) -> None:
    """Another writer's file: small chunks, /state interleaved with /status, the /state
    channel registered after another."""
    buf = io.BytesIO()
    with Recorder(buf) as r:
        for b in _varied_batches():
            r.state(b)
    states = [(m.log_time, m.data) for _, c, m in make_reader(io.BytesIO(buf.getvalue()))
              .iter_messages(log_time_order=False) if c.topic == "/state"]
    path = tmp_path / "o.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=compression, chunk_size=1500)
        w.start()
        st = w.register_channel(topic="/status", message_encoding="json", schema_id=0)
        sc = w.register_channel(topic="/state", message_encoding="json", schema_id=0)
        for i, (t, data) in enumerate(states):
            w.add_message(channel_id=sc, log_time=t, publish_time=t, sequence=i, data=data)
            if i % 7 == 0:
                w.add_message(channel_id=st, log_time=t, publish_time=t, sequence=i,
                              data=b'{"i": %d}' % i)
        w.finish()
    scanned = _read_scanned(path)
    assert scanned is not None and scanned.n == len(states) and len(scanned.statuses) > 30
    _same_recording(scanned, _read_general(path))


@pytest.mark.parametrize("odd", [
    b'{"t_s":0.0,"seq":1,"ref_deg":0.0,"pos_deg":0.0,"speed_deg_s":1.0,"speed_ref_deg_s":1.0,'
    b'"command_deg_s":1.0,"d_hat_deg_s":0.0,"error_deg":0.0,"config_version":1,"mode":"x"}',
    b'{"seq":1,"t_s":0.0,"ref_deg":0.0,"pos_deg":0.0,"speed_deg_s":1.0,"speed_ref_deg_s":1.0,'
    b'"command_deg_s":1.0,"d_hat_deg_s":0.0,"error_deg":0.0,"config_version":1,"mode":"a\\"b"}',
    b'{"seq":1, "t_s":0.0,"ref_deg":0.0,"pos_deg":0.0,"speed_deg_s":1.0,"speed_ref_deg_s":1.0,'
    b'"command_deg_s":1.0,"d_hat_deg_s":0.0,"error_deg":0.0,"config_version":1,"mode":"x"}',
    b'{"seq":1,"t_s":0.0,"ref_deg":0.0,"pos_deg":0.0,"speed_deg_s":1.0,"speed_ref_deg_s":1.0,'
    b'"command_deg_s":1.0,"d_hat_deg_s":0.0,"error_deg":0.0,"mode":"x"}',
])
def test_state_messages_of_another_form_are_read_by_the_general_decoder(
        tmp_path: Path, odd: bytes) -> None:
    """Key order, an escaped mode, whitespace, a missing key: the scan declines (None) and
    read_recording gives the general decoder's arrays."""
    buf = io.BytesIO()
    with Recorder(buf) as r:
        for b in _batches(200):
            r.state(b)
    path = tmp_path / "odd.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        sc = w.register_channel(topic="/state", message_encoding="json", schema_id=0)
        msgs = [m for _, _, m in make_reader(io.BytesIO(buf.getvalue()))
                .iter_messages(log_time_order=False)]
        for i, m in enumerate(msgs):
            w.add_message(channel_id=sc, log_time=m.log_time, publish_time=0, sequence=i,
                          data=odd if i == 150 else m.data)
        w.finish()
    assert _read_scanned(path) is None
    _same_recording(read_recording(path), _read_general(path))
    assert read_recording(path).n == 200


def test_a_state_message_the_general_decoder_refuses_is_refused(tmp_path: Path) -> None:
    """seq not an integer: the scan declines, the general decoder names the file."""
    path = tmp_path / "badseq.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sc = w.register_channel(topic="/state", message_encoding="json", schema_id=0)
        w.add_message(channel_id=sc, log_time=1, publish_time=0, sequence=0, data=(
            b'{"seq":1.5,"t_s":0.0,"ref_deg":0.0,"pos_deg":0.0,"speed_deg_s":1.0,'
            b'"speed_ref_deg_s":1.0,"command_deg_s":1.0,"d_hat_deg_s":0.0,"error_deg":0.0,'
            b'"config_version":1,"mode":"x"}'))
        w.finish()
    with pytest.raises(ValueError, match=r"badseq\.mcap"):
        read_recording(path)


def test_several_files_read_together_are_read_as_one_by_one(tmp_path: Path) -> None:
    paths = []
    for i in range(3):
        paths.append(tmp_path / f"r{i}.mcap")
        with Recorder(paths[-1], rig="m") as r:
            for b in _batches(1000 + 500 * i):
                r.state(b)
    together = read_recordings(paths)
    assert [x.n for x in together] == [1000, 1500, 2000]
    for one, path in zip(together, paths, strict=True):
        _same_recording(one, read_recording(path))
    (tmp_path / "bad.mcap").write_bytes(b"not an mcap at all")
    with pytest.raises(ValueError, match=r"bad\.mcap"):
        read_recordings([paths[0], tmp_path / "bad.mcap"])
