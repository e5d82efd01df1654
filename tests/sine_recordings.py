"""Recordings of a known sine run written as real MCAP files (the dashboard's recorder format):
the article's 5 sin(0.5 t) deg started anywhere along the trajectory, with an error whose size
is a known gain, so an alignment and the metrics of two runs are known by construction. Used
by the comparison's unit tests and the browser test of the Compare runs tab."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.recording.mcap_io import Recorder

__all__ = ["sine_run", "write_sine_recording"]


def sine_run(t0_s: float, seconds: float, gain: float, rate_hz: float = 1000.0
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, ref, error) of 5 sin(0.5 t) started at trajectory time t0_s; the error is a
    function of the trajectory time (so aligned runs have proportional errors)."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    tt = t + t0_s
    ref = 5.0 * np.sin(0.5 * tt)
    err = gain * (0.01 * np.cos(0.5 * tt) + 0.004 * np.sin(3.1 * tt))
    return t + 100.0, ref, err  # any time origin


def write_sine_recording(path: Path, cfg: LoopConfig, t0_s: float, gain: float,
                         seconds: float = 30.0) -> Path:
    """`sine_run` as a recording of configuration version 1 = `cfg`."""
    t, ref, err = sine_run(t0_s, seconds, gain)
    with Recorder(path, rig="t") as rec:
        rec.config(1, cfg, 1.7e9)
        for i0 in range(0, t.size, 20):
            sl = slice(i0, i0 + 20)
            zeros = np.zeros(len(t[sl])).tolist()
            cols = [t[sl].tolist(), ref[sl].tolist(), (ref[sl] - err[sl]).tolist(), zeros,
                    zeros, zeros, zeros, err[sl].tolist()]
            rec.state(proto.state_batch(rig="t", seq0=i0 + 1, rate_hz=1000.0,
                                        config_version=1, columns=cols, epoch_s=1.7e9,
                                        mode="running"))
    return path
