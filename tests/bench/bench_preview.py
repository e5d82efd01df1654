"""The dashboard's nonlinear preview (one period of the article's sine on the simulated rig):
time per call, p50 and p90 over 20 calls after the numba warm-up (was a 200 ms limit inside
tests/test_server_engine.py; a figure, not a test).

    PYTHONPATH=. .venv/bin/python tests/bench/bench_preview.py
"""

from __future__ import annotations

import numpy as np

from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from server.engine import TuningEngine


def main() -> None:
    eng, cfg, traj = TuningEngine(), LoopConfig(), Trajectory()
    eng.preview(cfg.with_(q_cutoff_hz=0.3), traj)  # warm-up (numba compile)
    times = [eng.preview(cfg.with_(q_cutoff_hz=0.4 + 0.01 * i), traj).elapsed_s
             for i in range(20)]
    p50, p90 = np.percentile(times, [50, 90]) * 1e3
    print(f"preview of one 12.6 s sine period: p50 {p50:.0f} ms, p90 {p90:.0f} ms (20 calls)")


if __name__ == "__main__":
    main()
