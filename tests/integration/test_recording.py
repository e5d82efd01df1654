"""Recording a real controller into MCAP, the black box on an e-stop, the report, the Zenoh
encodings: a real controller process over Zenoh on loopback; files read back with the `mcap`
library and metrics recomputed with numpy. The tests share one controller
(`module_controller`); the e-stop is reset in `finally`."""

from __future__ import annotations

import argparse
import io
import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from procs import Client, ControllerProcess, wait_until

from controller import protocol as proto
from controller.cli.record import record_main
from controller.cli.report import report_main
from controller.client.session import SessionOptions, connect
from controller.recording.mcap_io import read_recording


@pytest.fixture(scope="module")
def controller(module_controller: ControllerProcess) -> ControllerProcess:
    return module_controller


def _record(controller: ControllerProcess, out: Path, seconds: float) -> tuple[int, str]:
    args = argparse.Namespace(connect=[controller.endpoint], rig_name=controller.rig, out=out,
                              duration=seconds, auth=None, user="", timeout_s=10.0)
    buf = io.StringIO()
    return record_main(args, buf, threading.Event()), buf.getvalue()


def test_record_read_back_and_report(
    controller: ControllerProcess, client: Client, tmp_path: Path
) -> None:
    out = tmp_path / "run.mcap"
    code, text = _record(controller, out, 3.0)
    assert code == 0, text
    rec = read_recording(out)
    assert rec.channels == {"/state": "dobtune.State", "/status": "dobtune.Status",
                            "/config": "dobtune.Config", "/events": "dobtune.Event"} or (
        set(rec.channels) >= {"/state", "/status", "/config"})
    seq = rec.state["seq"]
    assert rec.n >= 2000  # ~3 s at 1 kHz
    assert np.all(np.diff(seq) == 1), "one message per tick, no sequence gap"
    assert np.all(np.diff(rec.log_time_s) > 0)  # log time = the sample's time
    assert 0.9e-3 < float(np.median(np.diff(rec.log_time_s))) < 1.1e-3
    assert rec.configs and 1 in rec.configs
    # The report's metrics are numpy's on the same samples.
    html_path = tmp_path / "report.html"
    csv_path = tmp_path / "run.csv"
    buf = io.StringIO()
    assert report_main([out], html_path, csv_path, buf) == 0, buf.getvalue()
    e = rec.state["error_deg"]
    peak, rmse = float(np.max(np.abs(e))), float(np.sqrt(np.mean(e**2)))
    page = html_path.read_text()
    assert f"{peak:.4g} deg" in page and f"{rmse:.4g} deg" in page
    assert "orders of rotation" in page and "<svg" in page
    data = np.loadtxt(csv_path, delimiter=",", skiprows=1)
    assert data.shape[0] == rec.n and np.allclose(data[:, 8], e, atol=1e-9)
    # Two recordings compared.
    out2 = tmp_path / "run2.mcap"
    assert _record(controller, out2, 1.0)[0] == 0
    assert report_main([out, out2], tmp_path / "cmp.html", None, io.StringIO()) == 0
    assert "Configuration difference" in (tmp_path / "cmp.html").read_text()


def test_the_black_box_is_written_on_an_estop(
    controller: ControllerProcess, client: Client
) -> None:
    box = controller.state_dir / "blackbox"
    assert not any(box.glob("*estop*.mcap"))
    with client.state() as col:
        assert wait_until(lambda: col.last_seq() > 3000, 15.0)  # 3 s of history
    try:
        client.put_estop()
        assert wait_until(lambda: any(box.glob("*estop*.mcap")), 10.0)
        path = next(box.glob("*estop*.mcap"))
        rec = read_recording(path)
        assert rec.n >= 2500 and np.all(np.diff(rec.state["seq"]) == 1)
        assert rec.events[0]["kind"] == "estop" and "estop key" in rec.events[0]["text"]
    finally:  # running again for the module's next test
        assert wait_until(lambda: client.fresh_status().mode == "estop", 10.0)
        assert client.reset().ok
        assert client.command(proto.Start()).ok


def test_zenoh_samples_carry_their_encoding(
    controller: ControllerProcess, client: Client
) -> None:
    got: dict[str, str] = {}
    with connect(SessionOptions(connect=(controller.endpoint,))) as s:
        sub = s.declare_subscriber(proto.key_state(controller.rig),
                                   zenoh.handlers.FifoChannel(64))
        sub2 = s.declare_subscriber(proto.key_status(controller.rig),
                                    zenoh.handlers.FifoChannel(64))
        deadline = time.monotonic() + 10
        while len(got) < 2 and time.monotonic() < deadline:
            for sample in iter(sub.try_recv, None):
                got["state"] = str(sample.encoding)
            for sample in iter(sub2.try_recv, None):
                got["status"] = str(sample.encoding)
            time.sleep(0.02)
        replies = list(s.get(proto.key_config(controller.rig), timeout=5.0))
        got["config"] = str(replies[0].ok.encoding)
    assert got == {"state": "application/msgpack;StateBatch",
                   "status": "application/msgpack;Status",
                   "config": "application/msgpack;ConfigReply"}
    json.dumps(got)


def test_a_recording_recovers_the_batches_it_lost(
    controller: ControllerProcess, client: Client, tmp_path: Path
) -> None:
    """Every 7th received batch dropped by the recorder's test hook: each is had again from
    the controller's replay (the loop's black box), so the file has every sample in order."""
    from controller.client.recorder import Recorder, RecordOptions

    dropped: list[int] = []

    def drop(b: proto.StateBatch) -> bool:
        if b.seq0 // 20 % 7 == 3:
            dropped.append(b.seq0)
            return True
        return False

    with client.state() as col:
        assert wait_until(lambda: col.last_seq() > 0, 60.0)  # the loop publishes
    out = tmp_path / "lossy.mcap"
    res = Recorder(RecordOptions(connect=(controller.endpoint,), out=out,
                                 rig_name=controller.rig, duration_s=3.0, timeout_s=30.0,
                                 drop_batch=drop)).run()
    assert len(dropped) >= 5, dropped
    assert res.lost == 0 and res.missing == (), res.summary()
    assert res.recovered >= 20 * (len(dropped) - 1)  # the last one may end the recording
    rec = read_recording(out)
    seq = rec.state["seq"]
    assert np.all(np.diff(seq) == 1), "every sample, once, in seq order"
    # Each batch dropped inside the recorded span is in the file (recovered: the span has
    # every seq once); batches dropped after the recording's end are not its samples (under
    # load they arrive in bursts: at load ~12 two came after the end, not only the last).
    inside = [s for s in dropped if int(seq[0]) <= s <= int(seq[-1])]
    have = set(seq.tolist())
    assert len(inside) >= 4 and all(s in have for s in inside), (
        dropped, int(seq[0]), int(seq[-1]))
    assert all(s > int(seq[-1]) for s in dropped if s not in have), (dropped, int(seq[-1]))
    assert not [e for e in rec.events if e.get("kind") == "gap"]
