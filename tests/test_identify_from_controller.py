"""`dobtune identify --from` end to end: a simulated controller process runs an identification
(`dobtune identify --connect`, a small plan) while `dobtune record` records it; the recording
analysed again gives the controller's estimates, fit and recommendations.

Real processes over Zenoh on loopback (the integration marker); every wait polls a condition
with a deadline.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import msgspec
import numpy as np
import pytest
from identify_from_common import RTOL, SMALL, same_structure

sys.path.insert(0, str(Path(__file__).resolve().parent / "integration"))

from procs import Client, ControllerProcess, start_controller, wait_until

from controller.cli.frd_files import read_frd_csv
from controller.cli.identify import EXIT_OK, identify_main
from controller.cli.record import record_main
from controller.recording.mcap_io import read_recording

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]



@pytest.fixture
def controller(tmp_path: Path) -> Iterator[ControllerProcess]:
    proc = start_controller(tmp_path / "state", extra_args=("--realtime-priority",))
    try:
        with Client(proc.endpoint, proc.rig) as c:
            c.wait_ready(proc, timeout_s=90.0)  # start-up takes long on a loaded machine
        yield proc
    finally:
        proc.stop()


def test_identify_from_a_recording_gives_the_runs_estimates(
    controller: ControllerProcess, tmp_path: Path
) -> None:
    mcap = tmp_path / "ident.mcap"
    stop = threading.Event()
    rec_out = io.StringIO()
    args = argparse.Namespace(connect=[controller.endpoint], rig_name=controller.rig, out=mcap,
                              duration=None, auth=None, user="", timeout_s=10.0)
    codes: list[int] = []
    recorder = threading.Thread(target=lambda: codes.append(record_main(args, rec_out, stop)))
    recorder.start()
    try:
        assert wait_until(lambda: mcap.exists() and mcap.stat().st_size > 0, 10.0)
        live_out, live_err = io.StringIO(), io.StringIO()
        code = identify_main(None, controller.endpoint, controller.rig,
                             msgspec.structs.asdict(SMALL), tmp_path / "live", True,
                             live_out, live_err)
        assert code == EXIT_OK, live_err.getvalue()
    finally:
        stop.set()  # after the run is done: the recorder polls once more and sees it
        recorder.join(30.0)
    assert codes == [0], rec_out.getvalue()
    rec = read_recording(mcap)
    kinds = [(e["kind"], e.get("state")) for e in rec.events if e["kind"] == "identify"]
    assert kinds[-1] == ("identify", "done"), rec.events
    assert np.all(np.diff(rec.state["seq"]) == 1), "no sample lost"

    out, err = io.StringIO(), io.StringIO()
    assert identify_main(None, None, None, {}, tmp_path / "again", True, out, err,
                         from_file=mcap) == EXIT_OK, err.getvalue()
    live = json.loads(live_out.getvalue())
    again = json.loads(out.getvalue())
    assert again["complete"] is True
    for key in ("fit", "recommended_cutoff_hz", "nominal", "gate_checks", "agreement"):
        same_structure(again[key], live[key], RTOL)
    same_structure([p["min_coherence"] for p in again["positions"]],
          [p["min_coherence"] for p in live["positions"]], RTOL)
    for a, b in zip(live["positions"], again["positions"], strict=True):
        fa = read_frd_csv(tmp_path / "live" / a["csv"])
        fb = read_frd_csv(tmp_path / "again" / b["csv"])
        np.testing.assert_allclose(fb.freq_hz, fa.freq_hz, rtol=RTOL)
        np.testing.assert_allclose(fb.mag_db, fa.mag_db, rtol=RTOL, atol=1e-12)
        np.testing.assert_allclose(fb.phase_deg, fa.phase_deg, rtol=RTOL, atol=1e-12)
