"""Dashboard wiring without a browser: two dashboards on one (real) controller, measured-response
upload, the 'controller gone' banner, ports released on exit, dependency direction."""

from __future__ import annotations

import contextlib
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import Output, free_port, port_is_free, spawn, wait_for

from controller.cli.frd_files import write_frd_csv
from controller.core.config import NominalModel
from controller.gate.loop_model import nominal_continuous_response
from server.dashboard.app import Dashboard, DashboardOptions
from server.dashboard.demo import controller_process, stop_process

#: The controller process's start (interpreter, imports, numba-compiled plant) on a cold machine.
CONTROLLER_START_S = 60.0








@pytest.mark.integration
def test_two_dashboards_watch_one_controller_then_it_goes_away(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ports = [free_port(), free_port()]
    with controller_process(endpoint, "apptest", tmp_path / "state") as proc:
        # Queries return when answered; the limit is only spent by a lost reply (at load 20 a
        # 1 s limit lost the plant knowledge fetch, and the upload below then failed).
        opts = [DashboardOptions(connect=(endpoint,), rig_name="apptest", port=p, verbose=False,
                                 query_timeout_s=30.0) for p in ports]
        with Dashboard(opts[0]) as a, Dashboard(opts[1]) as b:
            wait_for(lambda: a.client.connected, CONTROLLER_START_S)  # the process is up
            for d in (a, b):
                wait_for(lambda d=d: d.client.connected and d.client.ring.total > 500)
                assert d.live is not None
                wait_for(lambda d=d: "dt-ok" in d.live.banner.content)
            ta, tb = a.panel_in(a.server.gui), b.panel_in(b.server.gui)
            wait_for(lambda: ta.active_version == tb.active_version == 1)
            # The controller's plant knowledge fetched (the upload adds to it).
            wait_for(lambda: a.engine.plant.source != "not yet fetched")
            # Upload a measured response (the nominal model, 10 % high) into one dashboard.
            f = np.geomspace(0.1, 20, 40)
            csv = tmp_path / "frf.csv"
            write_frd_csv(csv, f, 1.1 * nominal_continuous_response(NominalModel(), f))
            a.knowledge.load_csv("frf.csv", csv.read_bytes())
            assert len(a.engine.measured) == 1
            assert ta.wait_preview_idle(120.0)
            ta.request_update()
            assert ta.wait_idle(120.0)
            ev = ta.last_evaluation
            assert ev is not None and ev.curves.inv_delta_measured_db is not None
            assert np.isfinite(ev.verdict.margins.small_gain_peak)
            # The controller goes away: both show the banner.
            stop_process(proc)
            for d in (a, b):
                assert d.live is not None
                wait_for(lambda d=d: "dt-gone" in d.live.banner.content, 60.0)
    for p in ports:
        wait_for(lambda p=p: port_is_free(p), 60.0)


@pytest.mark.integration
def test_a_dashboard_started_first_says_starting_and_connects_when_the_controller_comes(
    tmp_path: Path,
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    opts = DashboardOptions(connect=(endpoint,), rig_name="latetest", port=free_port(),
                            verbose=False, query_timeout_s=1.0)
    with Dashboard(opts) as d:
        assert d.live is not None
        wait_for(lambda: "dt-starting" in d.live.banner.content)
        assert "CONTROLLER STARTING" in d.live.banner.content
        assert "latetest" in d.live.banner.content and not d.client.connected
        with controller_process(endpoint, "latetest", tmp_path / "state"):
            wait_for(lambda: d.client.connected, CONTROLLER_START_S)
            wait_for(lambda: "dt-ok" in d.live.banner.content)
            # The controller's configuration reaches the candidate panel, as at a normal start.
            t = d.panel_in(d.server.gui)
            wait_for(lambda: t.active_version == 1)


@pytest.mark.integration
def test_the_demo_waits_for_its_controller_however_long_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`dobtune demo`'s wait: progress lines while the (real) controller starts, "ready" when
    its first status comes; no deadline. A controller that exits ends the wait (False)."""
    import threading

    from server.dashboard.demo import controller_command, wait_for_controller

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    opts = DashboardOptions(connect=(endpoint,), rig_name="demowait", port=free_port(),
                            verbose=False, query_timeout_s=1.0)
    with Dashboard(opts) as d, controller_process(endpoint, "demowait", tmp_path / "s") as proc:
        assert wait_for_controller(d, proc, threading.Event(), progress_every_s=0.2)
    out = capsys.readouterr().out
    assert out.count("dobtune demo: controller starting (") >= 2, out  # it said so, and waited
    ready = [x for x in out.splitlines() if x.startswith("dobtune demo: controller")][-1]
    assert ready.startswith("dobtune demo: controller ready after"), out
    # --rate-hz nan: refused at start, exits 2.
    bad = spawn([*controller_command(endpoint, "demowait", tmp_path / "s2"),
                 "--rate-hz", "nan"])
    with Dashboard(opts) as d:
        assert not wait_for_controller(d, bad, threading.Event(), progress_every_s=0.2)
    assert bad.wait() == 2


def test_bad_upload_is_reported_not_raised() -> None:
    opts = DashboardOptions(port=free_port(), connect=(f"tcp/127.0.0.1:{free_port()}",),
                            verbose=False)
    with Dashboard(opts) as d:
        d.knowledge.load_csv("x.csv", b"not,a,response\n1,2\n")
        assert "x.csv" in d.knowledge.text.content
        assert len(d.engine.measured) == 0


@pytest.mark.slow
def test_controller_never_imports_server_or_viser() -> None:
    code = (
        "import sys, controller.core.loop, controller.protocol, controller.gate.analysis, "
        "controller.sim.experiment; "
        "bad = [m for m in sys.modules if m.split('.')[0] in ('server', 'viser')]; "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 0, r.stdout + r.stderr


@contextlib.contextmanager
def _dashboard_and_controller(tmp_path: Path, rig: str, **opts: Any) -> Iterator[Dashboard]:
    """A controller process of `rig` and a dashboard on it (`opts`: DashboardOptions fields),
    once the dashboard's client has reached the controller. Its queries wait up to 30 s for a
    reply (they return when answered: an apply judged at load 30 took over 2 s)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    opts = {"query_timeout_s": 30.0, **opts}
    with controller_process(endpoint, rig, tmp_path / "state"), Dashboard(DashboardOptions(
            connect=(endpoint,), rig_name=rig, port=free_port(), verbose=False, **opts)) as d:
        wait_for(lambda: d.client.connected, CONTROLLER_START_S)
        yield d


@pytest.mark.integration
def test_the_trajectory_dropdown_follows_the_controller(tmp_path: Path) -> None:
    from controller import protocol as proto
    from controller.core.trajectory import default_trajectory

    with _dashboard_and_controller(tmp_path, "trajtest") as d:
        assert d.live is not None
        wait_for(lambda: d.live.trajectory.value == "sine")
        reply = d.client.command(proto.SetTrajectory(trajectory=default_trajectory("ramp")))
        assert reply.ok, reply.message
        wait_for(lambda: d.live.trajectory.value == "ramp")


@pytest.mark.integration
def test_history_lists_versions_and_loads_one_as_the_candidate(tmp_path: Path) -> None:
    from controller.core.config import LoopConfig

    with _dashboard_and_controller(tmp_path, "histtest") as d:
        first = d.client.get_config()
        reply = d.client.apply(first.config.with_(q_cutoff_hz=0.8, cv_kp=1.2))
        assert reply.accepted, reply.reasons
        wait_for(lambda: "v2" in d.history.table.content and "v1" in d.history.table.content)
        # The History tab shows the difference between any two versions (newest vs the one
        # before by default).
        wait_for(lambda: "q_cutoff_hz" in d.history.diff.content)
        diff = d.history.diff.content
        assert "v2 vs v1" in diff and "q_cutoff_hz: 0.5 &rarr; <b>0.8</b>" in diff
        assert "rate_hz" not in d.history.diff.content
        d.history.other.value = "v2"
        wait_for(lambda: "same as v2" in d.history.diff.content)
        h = d.client.history(10)
        assert [e.version for e in h.entries] == [1, 2]
        judged = h.entries[1].verdict  # the verdict the apply got, whole, as it was logged
        assert judged is not None and judged.verdict == "accept" == reply.verdict.verdict
        assert judged.margins == reply.verdict.margins and judged.knowledge_version >= 1
        start = h.entries[0].verdict  # the start-up line carries the start-up gate's verdict
        assert start is not None and start.verdict in ("accept", "caution")
        assert "accept" in d.history.table.content
        assert h.entries[1].config.q_cutoff_hz == 0.8
        t = d.panel_in(d.server.gui)
        wait_for(lambda: t.active_version == 2)
        d.history.pick.value = "v1"
        d.history.use_version()
        assert t.wait_idle(5.0)
        assert t.candidate() == first.config  # version 1, to go through the gate again
        assert "q_cutoff_hz" in t.diff_text.content and "active v2" in t.diff_text.content
        assert d.client.history(0).field == "last"
        assert LoopConfig() == first.config


@pytest.mark.integration
def test_record_from_the_dashboard_then_replay(tmp_path: Path) -> None:
    """Record / Stop in the Recordings tab writes a complete MCAP of the rig into the
    directory; the file is listed with its samples and configuration; the scrubber replays it
    through a window."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rec_dir = tmp_path / "recordings"  # made by the first recording
    with controller_process(endpoint, "rectest", tmp_path / "state"):
        opts = DashboardOptions(connect=(endpoint,), rig_name="rectest", port=free_port(),
                                verbose=False, recordings_dir=rec_dir)
        with Dashboard(opts) as d:
            wait_for(lambda: d.client.connected and d.client.ring.total > 100,
                     CONTROLLER_START_S)
            p = d.recordings
            assert p is not None
            out = p.start_recording()
            assert out is not None and out.parent == rec_dir
            assert p.start_recording() is None  # one at a time
            first = d.client.ring.total
            wait_for(lambda: d.client.ring.total > first + 3000, 30.0)  # 3 s of ticks
            assert p.stop_recording()
            said = re.search(r"recorded (\d+) samples \((\d+) lost", p.last_record_output)
            assert said is not None, p.last_record_output
            rows = p.refresh()
            assert [r.name for r in rows] == [out.name]
            row = rows[0]
            # What the recording said it lost is what its file holds as gaps. On a quiet
            # machine nothing is lost; with two busy loops beside the suite the dashboard fell
            # behind the stream and 20 of 3060 samples were lost (and said): a few, never many.
            assert (row.samples, row.gaps) == (int(said[1]), int(said[2])), (row, said[0])
            assert row.samples >= 2000 and row.gaps <= 0.05 * row.samples
            assert row.config_version == 1
            assert row.config["q_cutoff_hz"] == 0.5
            # The run against itself: no lag; the scrubber windows it (a comparison of its
            # own, as each browser gets).
            view = p.compare_in(p.gui)
            view.compare(out.name, out.name)
            whole = view.replay(float("inf"))
            assert whole is not None
            t_end = float(whole[0][-1])
            assert t_end > 2.0
            window = view.replay(t_end / 2)
            assert window is not None
            assert window[0][0] >= t_end / 2 - 10.0 - 1e-9 and window[0][-1] <= t_end / 2 + 1e-9
            np.testing.assert_array_equal(window[1], window[2])  # A and B are the same run


def test_recordings_go_to_a_data_directory_outside_the_working_tree(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from server.dashboard.app import DashboardOptions

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    assert DashboardOptions().recordings_dir == tmp_path / "data" / "dobtune" / "recordings"
    monkeypatch.delenv("XDG_DATA_HOME")
    d = DashboardOptions().recordings_dir
    assert d == Path.home() / ".local" / "share" / "dobtune" / "recordings"
    assert not d.is_relative_to(Path.cwd())


def test_the_dashboard_prints_only_the_url_with_the_token(tmp_path: Path) -> None:
    """viser's own banner printed http://host:port without the token (a 401 page) before the
    dashboard's URL: every http URL the dashboard prints must carry ?token=."""
    import os
    import re

    port = free_port()
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "XDG_DATA_HOME": str(tmp_path)}
    proc = spawn(
        [sys.executable, "-m", "controller.cli.main", "dashboard", "--port", str(port),
         "--connect", f"tcp/127.0.0.1:{free_port()}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    out = Output(proc)
    try:
        out.wait_url(CONTROLLER_START_S)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        out.reader.join(timeout=10)
    text = out.text()
    urls = re.findall(r"https?://\S+", text)
    assert any(f":{port}/?token=" in u for u in urls), text
    assert all("?token=" in u for u in urls), text


def test_kept_candidates_go_to_the_data_directory_unless_told(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import argparse

    from controller.cli.dashboard import candidates_dir

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    told = argparse.Namespace(candidates=tmp_path / "mine")
    assert candidates_dir(argparse.Namespace(candidates=None)) == (
        tmp_path / "data" / "dobtune" / "candidates")
    assert candidates_dir(told) == tmp_path / "mine"
