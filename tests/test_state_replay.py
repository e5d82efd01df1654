"""The state stream's replay (issue 33 item 4): what `replay` gives of a seq range and what it
names as missing; the range parser's refusals; and a recording that loses batches
deterministically (the recorder's `drop_batch` hook) over real Zenoh on loopback, its replay
served by `ReplayServer` from a fixed set of held batches: the lost batches the replay holds are
recovered in seq order, the rest named as gaps with their reason (too old, never published)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import zenoh
from helpers import free_port

from controller import protocol as proto
from controller.client.recorder import Recorder, RecordOptions
from controller.client.session import SessionOptions, connect
from controller.core.samples import STATE_COLUMNS
from controller.process.replay import MAX_SAMPLES, ReplayServer, parse_range, replay
from controller.recording.mcap_io import read_recording

N = 20  # samples per batch


def _batch(k: int, rig: str = "rp") -> proto.StateBatch:
    seq0 = k * N
    t = [(seq0 + i) / 1000.0 for i in range(N)]
    cols = [t] + [[float(seq0 + i) + j / 10 for i in range(N)]
                  for j in range(1, len(STATE_COLUMNS))]
    return proto.state_batch(rig=rig, seq0=seq0, rate_hz=1000.0, config_version=1,
                             columns=cols, epoch_s=1.7e9, mode="running")


def test_replay_cuts_the_range_and_names_what_it_lacks() -> None:
    held = [_batch(k) for k in range(10, 20) if k != 14]  # seq 200..399, 280..299 never put
    got = replay(held, 195, 305)
    assert [(b.seq0, len(b.t_s)) for b in got.batches] == [
        (200, 20), (220, 20), (240, 20), (260, 20), (300, 6)]
    assert got.batches[-1].pos_deg == [300.2 + i for i in range(6)]
    assert [(m.from_seq, m.to_seq, m.reason) for m in got.missing] == [
        (195, 199, "too_old"), (280, 299, "never_published")]
    assert (got.oldest_seq, got.newest_seq) == (200, 399)
    inside = replay(held, 205, 214)
    assert [(b.seq0, len(b.t_s)) for b in inside.batches] == [(205, 10)] and not inside.missing
    ahead = replay(held, 390, 420)
    assert [(m.from_seq, m.to_seq, m.reason) for m in ahead.missing] == [(400, 420, "not_yet")]
    old = replay(held, 0, 50)
    assert not old.batches and [(m.from_seq, m.to_seq, m.reason) for m in old.missing] == [
        (0, 50, "too_old")]


@pytest.mark.parametrize(("params", "field"), [
    ("to=5", "from"), ("from=1", "to"), ("from=-1;to=5", "from"), ("from=x;to=5", "from"),
    ("from=9;to=5", "to"), (f"from=0;to={MAX_SAMPLES}", "to"),
])
def test_a_bad_range_is_refused_naming_the_parameter(params: str, field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field}: "):
        parse_range(params)


def test_a_range_parses() -> None:
    assert parse_range("from=3;to=7") == (3, 7)
    assert parse_range("from=3&to=3") == (3, 3)


def test_lost_batches_are_recovered_or_named(tmp_path: Path) -> None:
    rig = "rp"
    batches = [_batch(k, rig) for k in range(100)]
    # The publisher keeps batches 50..99 but 80, which the loop never published.
    held = [b for b in batches[50:] if b.seq0 != 80 * N]
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    seen: list[int] = []
    seen_cv = threading.Condition()
    first: list[int] = []

    def drop(b: proto.StateBatch) -> bool:
        with seen_cv:
            seen.append(b.seq0)
            seen_cv.notify_all()
        if not first:
            first.append(b.seq0 // N)
        k = b.seq0 // N
        return k in (first[0] + 3, 60, 61, 75, 80)

    with connect(SessionOptions(listen=(endpoint,))) as server:
        rs = ReplayServer(rig, lambda: held, lambda text: None)
        rs.declare(server, auth=False)
        pub = server.declare_publisher(proto.key_state(rig),
                                       congestion_control=zenoh.CongestionControl.BLOCK)
        stop = threading.Event()
        out = tmp_path / "r.mcap"
        recorder = Recorder(RecordOptions(connect=(endpoint,), out=out, rig_name=rig,
                                          timeout_s=60.0, drop_batch=drop))
        result: list[object] = []
        th = threading.Thread(target=lambda: result.append(recorder.run(stop)))
        th.start()
        try:
            # Batches one at a time until the recorder has one (its subscriber is declared),
            # then the rest: nothing depends on timing but that first one.
            k = 0
            while True:
                pub.put(proto.encode(batches[k]))
                with seen_cv:
                    if seen_cv.wait_for(lambda: bool(seen), timeout=0.5):
                        break
                k += 1
                assert k < 40, "the recorder received nothing"
            for b in batches[k + 1:]:
                pub.put(proto.encode(b))
            with seen_cv:
                assert seen_cv.wait_for(lambda: bool(seen) and seen[-1] == 99 * N, timeout=60)
        finally:
            stop.set()
            th.join(60)
            rs.close()
    res = result[0]
    k0 = first[0]
    assert res.recovered == 3 * N  # 60, 61, 75: held
    assert res.missing == ((k0 * N + 3 * N, k0 * N + 4 * N - 1, "too_old"),
                           (80 * N, 81 * N - 1, "never_published"))
    assert res.lost == 2 * N
    assert res.samples == (100 - k0) * N - 2 * N
    rec = read_recording(out)
    seq = rec.state["seq"]
    expect = [s for s in range(k0 * N, 100 * N)
              if not (k0 * N + 3 * N <= s < k0 * N + 4 * N or 80 * N <= s < 81 * N)]
    assert seq.tolist() == expect  # every sample once, in seq order
    assert np.allclose(rec.state["pos_deg"], np.array(expect, dtype=float) + 0.2)
    gaps = [(e["from_seq"], e["to_seq"], e["reason"]) for e in rec.events
            if e.get("kind") == "gap"]
    assert gaps == list(res.missing)
    assert "missing seq" in res.summary() and "too_old" in res.summary()
