"""A synthetic week of a rig's trend, written as the watch writes it (`TrendWriter`, one window
every `window_s`), with known values: the Trends view's tests and its bench read it back.

- stiffness: 1.0 until `drop_at` (4.5 days in), then 0.6 (below its range 0.75..1.27), in
  alarm from the second window after, the alarm recorded on /drift/alarm at `alarm_at`;
- gain: 1 + 0.02 sin(2 pi t / 1 day) (a day's cycle: its peak 1.02 at 6 h into each day);
- inertia: 1.0, its state "not told" every 6th window; motor friction 1.0;
- plant residual 0.004 deg/s, rising to 0.02 after the drop; loop residual 0.003 deg;
- compute p99 40 us, skipped ticks +1 per window;
- `gap`: the watch off from 2 days to 2 days 6 h (no files for those hours).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from controller.recording.trend import TrendWriter

DAY_S = 86400.0
RANGES = {"gain": (0.80, 1.20), "stiffness": (0.75, 1.27), "inertia": (0.63, 1.44),
          "motor_friction": (0.5, 2.0)}


@dataclass(frozen=True)
class Week:
    t0_epoch_s: float
    window_s: float
    drop_at: float
    alarm_at: float
    gap: tuple[float, float]
    windows: int
    times: tuple[float, ...] = ()
    """Every window's time, as written."""

    def windows_in(self, t0_epoch_s: float, t1_epoch_s: float) -> int:
        return sum(1 for t in self.times if t0_epoch_s <= t <= t1_epoch_s)

    @property
    def t1_epoch_s(self) -> float:
        return self.t0_epoch_s + 7 * DAY_S


def gain_at(t_epoch_s: float, week: Week) -> float:
    return 1.0 + 0.02 * math.sin(2 * math.pi * (t_epoch_s - week.t0_epoch_s) / DAY_S)


def write_week(root: Path, rig: str, end_epoch_s: float, window_s: float = 60.0,
               with_ranges: bool = True, noise_seed: int | None = None) -> Week:
    """A week of windows ending at `end_epoch_s` under `root/rig` (`window_s`: the watch's is
    10 s; the tests write one a minute, the same files at a sixth of the windows).
    `noise_seed`: the values carry noise as a live watch's do (1 % on the parts, 25 % on the
    residuals, 5 us on the p99), for the storage a day takes (smooth values compress 3x
    better)."""
    rng = np.random.default_rng(noise_seed) if noise_seed is not None else None

    def noisy(v: float, rel: float) -> float:
        return v if rng is None else float(v * (1.0 + rel * rng.standard_normal()))

    t0 = end_epoch_s - 7 * DAY_S
    drop_at = t0 + 4.5 * DAY_S
    gap = (t0 + 2 * DAY_S, t0 + 2 * DAY_S + 6 * 3600)
    alarm_at = drop_at + 2 * window_s
    n = 0
    times: list[float] = []
    with TrendWriter(root, rig) as tw:
        i = 0
        while True:
            e = t0 + i * window_s
            i += 1
            if e > end_epoch_s:
                break
            if gap[0] <= e < gap[1]:
                continue
            dropped = e >= drop_at
            values = {"gain": gain_at(e, Week(t0, window_s, drop_at, alarm_at, gap, 0)),
                      "stiffness": 0.6 if dropped else 1.0, "inertia": 1.0,
                      "motor_friction": 1.0}
            parts: dict[str, object] = {}
            for name, v in values.items():
                state = "ok"
                if name == "stiffness" and dropped:
                    state = "alarm" if e >= alarm_at else "outside"
                if name == "inertia" and i % 6 == 0:
                    state = "not told"
                parts[name] = noisy(v, 0.01)
                parts[name + "_std"] = noisy(0.001, 0.5)
                parts[name + "_state"] = state
                if with_ranges:
                    parts[name + "_low"], parts[name + "_high"] = RANGES[name]
            tw.write("/drift/residual", e, {
                "plant_residual_rms_deg_s": noisy(0.02 if dropped else 0.004, 0.25),
                "fitted_residual_rms_deg_s": noisy(0.004, 0.25),
                "loop_measured_rms_deg": noisy(0.03, 0.25),
                "loop_predicted_rms_deg": noisy(0.03, 0.25),
                "loop_residual_rms_deg": noisy(0.003, 0.25),
                "delay_ticks": 0})
            tw.write("/drift/parts", e, parts)
            tw.write("/drift/health", e, {"config_version": 1, "alarms": [],
                                          "compute_p99_us": noisy(40.0, 0.125),
                                          "skipped_ticks": i,
                                          "mode": "running"})
            if abs(e - alarm_at) < window_s / 2:
                tw.write("/drift/alarm", e, {
                    "rig": rig, "seq": 1, "epoch_s": e, "part": "stiffness", "value": 0.6,
                    "std": 0.001, "unit": "x", "low": 0.75, "high": 1.27,
                    "since_epoch_s": drop_at, "text": "stiffness x0.6 +-0.001 of the twin's, "
                    "below its range 0.75-1.27", "action": "measure again", "cleared": False})
            n += 1
            times.append(e)
    return Week(t0, window_s, drop_at, alarm_at, gap, n, tuple(times))
