"""The controller's request handlers' side products: log records of what the loop did."""

from __future__ import annotations

import logging
from types import SimpleNamespace
from typing import Any

import pytest

from controller.core.config import LoopConfig
from controller.process.service import RuntimeEvents, config_changes


def fake_runtime() -> Any:
    return SimpleNamespace(
        mode="running",
        fault=None,
        estop_seq=-1,
        estop_source="",
        overruns=0,
        skipped_ticks=0,
        dropped_samples=0,
        ticks=0,
    )


def test_mode_changes_estops_faults_and_lost_ticks_are_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="controller.process.service")
    rt = fake_runtime()
    events = RuntimeEvents(rt, summary_period_s=3600.0)
    events.poll()
    assert caplog.records == []  # nothing happened, nothing logged
    rt.mode, rt.estop_seq, rt.estop_source = "estop", 120, "estop key"
    events.poll()
    rt.mode, rt.fault = "fault", "no complete feedback for 3 ticks"
    events.poll()
    rt.mode, rt.fault = "stopped", None
    events.poll()
    rt.overruns, rt.skipped_ticks, rt.ticks = 3, 1, 5000
    events.summary()
    events.summary()  # nothing lost since: INFO
    got = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert got == [
        ("WARNING", "e-stop (estop key) at seq 120"),
        ("WARNING", "fault: no complete feedback for 3 ticks (mode fault)"),
        ("INFO", "mode fault -> stopped"),
        (
            "WARNING",
            "loop: 3 overruns, 1 skipped ticks, 0 dropped samples since the last summary "
            "(5000 ticks in all)",
        ),
        (
            "INFO",
            "loop: 0 overruns, 0 skipped ticks, 0 dropped samples since the last summary "
            "(5000 ticks in all)",
        ),
    ]


def test_config_changes_name_the_fields() -> None:
    old = LoopConfig()
    assert config_changes(old, old) == "no change"
    new = old.with_(q_cutoff_hz=2.0, dob_on=False)
    assert config_changes(old, new) == "dob_on True -> False, q_cutoff_hz 0.5 -> 2.0"
