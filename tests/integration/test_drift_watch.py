"""The watch beside a real controller (issue 34): `dobtune watch` as its own process, reading
the state stream of a simulated controller (the article rig, the demo's) over Zenoh on
loopback; normal running raises no alarm; the belt losing 40 % of its stiffness during the run
(`SimDrift`, the operator's command) is an alarm naming the stiffness, sized within 10 %,
that `dobtune ctl wait-alarm` returns (exit 0), `dobtune ctl drift` shows, the rig's trend
keeps, and a dashboard on the controller (with its Fleet tab) shows: an amber box on its
alarm board and the drift state in the rig's fleet row. Waits on conditions only; the time to
detect is the bench's (tests/bench/bench_watch.py).
"""

from __future__ import annotations

import time
from pathlib import Path

import msgspec
import pytest
from helpers import free_port, wait_until
from procs import Client, ControllerProcess, run_ctl, watching

from controller import protocol as proto
from controller.recording.trend import read_trend

pytestmark = [pytest.mark.integration, pytest.mark.timeout(600)]

WINDOW_S = 8.0



@pytest.fixture
def article_controller(start_controller_factory: object) -> ControllerProcess:
    return start_controller_factory(  # type: ignore[operator,no-any-return]
        extra_args=("--realtime-priority", "--disturbance", "article-rig"))


def test_the_watch_names_a_drifting_belt(article_controller: ControllerProcess,
                                         tmp_path: Path) -> None:
    proc = article_controller
    trend = tmp_path / "trend"
    with Client(proc.endpoint, proc.rig, timeout_s=30.0) as client:
        client.wait_ready(proc)
        states: list[bytes] = []
        sub = client.session.declare_subscriber(proto.key_drift(proc.rig),
                                                lambda s: states.append(s.payload.to_bytes()))
        from server.alarms import alarms_html
        from server.dashboard.app import Dashboard, DashboardOptions

        dash_opts = DashboardOptions(connect=(proc.endpoint,), rig_name=proc.rig,
                                     port=free_port(), verbose=False, fleet=True)
        try:
            with Dashboard(dash_opts) as dash, watching(
                    proc, tmp_path / "watch.log", "--window-s", str(WINDOW_S),
                    "--trend-dir", str(trend)):
                # Normal running: three windows judged, no part in alarm, each part told.
                assert wait_until(lambda: len(states) >= 3, timeout_s=300.0), \
                    (tmp_path / "watch.log").read_text()
                normal = [proto.decode(s, proto.DriftState) for s in states[:3]]
                for st in normal:
                    assert st.alarms == [], st
                    assert all(abs(p.value - 1.0) < 0.1 for p in st.parts if p.told), st.parts
                rc, text = run_ctl(proc, "drift")
                assert rc == 0 and "stiffness" in text and "alarms: none" in text, text
                # Nobody waits for ever: no alarm in a short wait is exit 5.
                rc, text = run_ctl(proc, "wait-alarm", "--wait-s", "0.5")
                assert rc == 5 and "no drift alarm" in text, text
                # The belt loses 40 % of its stiffness during the run.
                t_change = time.time()
                assert client.command(proto.SimDrift(belt_stiffness_factor=0.6)).ok
                rc, text = run_ctl(proc, "wait-alarm", "--since", str(t_change), "--wait-s", "400",
                                "--json")
                assert rc == 0, text
                alarm = msgspec.json.decode(text, type=proto.DriftAlarm)
                assert alarm.part == "stiffness" and not alarm.cleared, alarm
                assert alarm.epoch_s >= t_change
                assert alarm.value == pytest.approx(0.6, rel=0.10), alarm
                assert alarm.value < alarm.low  # below its range, which the text states
                assert "measure again" in alarm.action and alarm.gate_verdict in (
                    "accept", "caution", "reject")
                rc, text = run_ctl(proc, "drift")
                assert rc == 0 and "alarms: stiffness" in text, text
                # The dashboard: the alarm on its board (amber, what and what to do), the
                # drift state in the fleet row beside the loop's state.
                live, mon = dash.live, dash._fleet_monitor
                assert live is not None and mon is not None
                assert wait_until(lambda: any(a.kind == "drift"
                                              for a in live.alarm_board.alarms), 60.0)
                html = alarms_html(live.alarm_board)
                assert "PLANT DRIFT: stiffness" in html and "measure again" in html, html
                assert wait_until(lambda: any(r.rig == proc.rig and r.drift_alarm
                                              for r in mon.rows()), 60.0)
                row = next(r for r in mon.rows() if r.rig == proc.rig)
                assert row.drift.startswith("ALARM: stiffness x0.") and row.mode == "running"
        finally:
            sub.undeclare()
    points = read_trend(trend, proc.rig, time.time() - 3600, time.time() + 60)
    assert len(points) >= 4 and all("stiffness" in p.data for p in points)
    assert points[-1].data["stiffness"] == pytest.approx(0.6, rel=0.10)
