"""A controller status message (`proto.Status`) as the dashboard's pure tests feed it
(tests/test_alarms.py, tests/test_guide.py, tests/test_health.py): rig "r", simulated plant,
running version 1 of the default loop, one tick on time; every field replaceable."""

from __future__ import annotations

from typing import Any

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory

__all__ = ["status", "timing"]


def timing(**kw: Any) -> proto.Timing:
    """One tick on time at 1 kHz with 10 us of compute; `kw` replaces any field."""
    base: dict[str, Any] = dict(period_p50_us=1000.0, period_p99_us=1000.0, period_max_us=1000.0,
                                compute_p50_us=10.0, compute_p99_us=10.0, compute_max_us=10.0,
                                ticks=1, overruns=0, skipped_ticks=0)
    return proto.Timing(**{**base, **kw})


def status(**kw: Any) -> proto.Status:
    """A running rig's status with `timing()`; `kw` replaces any field."""
    base: dict[str, Any] = dict(rig="r", plant="sim", mode="running", t_s=0.0, seq=0,
                                trajectory=Trajectory(), config_version=1, config=LoopConfig(),
                                timing=timing(), faults=[])
    return proto.Status(**{**base, **kw})
