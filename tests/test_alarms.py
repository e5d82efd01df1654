"""The alarm board (server/alarms.py) on sequences of controller status messages."""

from __future__ import annotations

from statuses import status

from server.alarms import AlarmBoard, alarms_html


def test_a_rollback_raises_one_amber_alarm_with_its_reason_until_acknowledged() -> None:
    b = AlarmBoard()
    assert not b.observe(status(rollbacks=0), 100.0)
    assert not b.observe(status(rollbacks=0, t_s=1.0), 101.0)
    why = "watchdog: oscillates at 11 Hz; rolled back from v2 to the previous configuration as v3"
    assert b.observe(status(rollbacks=1, config_version=3, watchdog=why), 102.0)
    assert not b.observe(status(rollbacks=1, config_version=3, watchdog=why, t_s=2.0), 103.0)
    [a] = b.alarms
    assert (a.kind, a.level, a.at_s) == ("rollback", "amber", 102.0)
    assert "v3" in a.title and a.reason == why
    html = alarms_html(b)
    assert "dt-alarm-rollback" in html and "rolled back from v2" in html
    assert b.acknowledge() == 1 and b.alarms == [] and "dt-alarm " not in alarms_html(b)


def test_a_rollback_before_the_dashboard_started_is_no_alarm_an_estop_in_force_is() -> None:
    b = AlarmBoard()
    assert b.observe(status(rollbacks=4, mode="estop", estop_seq=7), 1.0)
    assert [a.kind for a in b.alarms] == ["estop"]
    assert not b.observe(status(rollbacks=4, mode="estop", estop_seq=7), 2.0)  # the same one
    b.observe(status(rollbacks=4, mode="running"), 3.0)
    assert b.observe(status(rollbacks=4, mode="estop", estop_seq=99), 4.0)  # a new one
    assert [a.level for a in b.alarms] == ["red", "red"]


def test_a_press_is_one_estop_alarm_while_the_latch_stands_unacknowledged() -> None:
    """A dashboard press is two e-stops (the put on the e-stop key, then the EStop command),
    each with its estop_seq: a status between them showed two red alarms for one press."""
    b = AlarmBoard()
    b.observe(status(mode="running"), 0.0)
    assert b.observe(status(mode="estop", estop_seq=100), 1.0)
    assert not b.observe(status(mode="estop", estop_seq=103), 1.2)  # the command, latched
    assert [a.kind for a in b.alarms] == ["estop"]
    assert b.acknowledge() == 1
    assert b.observe(status(mode="estop", estop_seq=900), 9.0)  # pressed again, seen anew
    assert [(a.kind, a.at_s) for a in b.alarms] == [("estop", 9.0)]


def test_a_fault_is_red_once_per_fault_set() -> None:
    b = AlarmBoard()
    b.observe(status(), 0.0)
    assert b.observe(status(mode="fault", faults=["watchdog: no config left"]), 1.0)
    assert not b.observe(status(mode="fault", faults=["watchdog: no config left"]), 2.0)
    assert b.observe(status(mode="fault", faults=["drive: lost"]), 3.0)
    assert [(a.kind, a.reason) for a in b.alarms] == [
        ("fault", "watchdog: no config left"), ("fault", "drive: lost")]
    b.observe(status(), 4.0)
    assert b.observe(status(mode="fault", faults=["drive: lost"]), 5.0)  # again after a clear


def test_alarms_of_one_kind_are_one_box_with_their_count() -> None:
    """Issue 33: three e-stops were three boxes pushing the controls down. Now one box per
    kind: the newest, "x3 (first at ...)"; a rollback beside them is its own box."""
    b = AlarmBoard()
    b.observe(status(mode="running", rollbacks=0), 0.0)
    for k in range(3):
        assert b.observe(status(mode="estop", estop_seq=10 + k), 10.0 + 10 * k)
        b.observe(status(mode="running"), 11.0 + 10 * k)
    assert b.observe(status(mode="running", rollbacks=1, config_version=4, watchdog="why"), 40.0)
    html = alarms_html(b)
    assert html.count("class='dt-alarm ") == 2
    assert html.index("dt-alarm-rollback") < html.index("dt-alarm-estop")  # newest kind first
    assert html.count("dt-alarm-count") == 1 and "&times;3 (first at" in html
    assert b.acknowledge() == 4
