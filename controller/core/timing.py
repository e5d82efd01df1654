"""The loop's timing over an interval, as plain data: what the runtime measures and the status
message carries (one definition: `controller.protocol.Timing` is this type)."""

from __future__ import annotations

import msgspec


class LoopTiming(msgspec.Struct, frozen=True, kw_only=True):
    """Loop timing over the last interval (microseconds), and counters since start."""

    period_p50_us: float
    period_p99_us: float
    period_max_us: float
    compute_p50_us: float
    compute_p99_us: float
    compute_max_us: float
    ticks: int
    overruns: int
    skipped_ticks: int
    dropped_samples: int = 0  # samples the publisher could not take (gaps in `state`)
    samples: int = 0  # ticks the percentiles are over (those since the previous interval)
