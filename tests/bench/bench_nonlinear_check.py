"""The gate's nonlinear check: its figures over a Q sweep, and its cost.

    .venv/bin/python tests/bench/bench_nonlinear_check.py

Prints, per Q type and cut-off: band RMS of the speed command after the reversal and at hold
(deg/s), the hold's peak-to-peak error (deg), their frequencies, and the findings; then the
run time p50/p99 over 40 runs after the numba kernel is compiled (and the compile time).
"""

from __future__ import annotations

import statistics
import time

from controller.core.config import LoopConfig
from controller.sim.nonlinear_check import nonlinear_check


def main() -> None:
    t0 = time.perf_counter()
    nonlinear_check(LoopConfig())
    print(f"first run (numba compile or cache load): {time.perf_counter() - t0:.2f} s")
    print(f"{'Q':<4} {'fc Hz':>6} {'rev RMS':>8} {'at Hz':>6} {'hold RMS':>9} {'at Hz':>6}"
          f" {'hold p2p':>9}  findings")
    for q in ("q31", "q20"):
        for fc in (0.5, 1.0, 2.0, 4.0, 8.0, 14.4, 20.0):
            r = nonlinear_check(LoopConfig(q_type=q, q_cutoff_hz=fc))
            print(f"{q:<4} {fc:>6.3g} {r.reversal_rms_deg_s:>8.2f} {r.reversal_freq_hz or 0:>6.1f}"
                  f" {r.hold_rms_deg_s:>9.2f} {r.hold_freq_hz or 0:>6.1f}"
                  f" {r.hold_error_p2p_deg:>9.3f}  {len(r.reasons)}")
    times = sorted(nonlinear_check(LoopConfig(q_cutoff_hz=1.0 + 0.01 * k)).run_time_s
                   for k in range(40))
    print(f"run time: p50 {1e3 * statistics.median(times):.1f} ms, "
          f"p99 {1e3 * times[int(0.99 * len(times))]:.1f} ms (4.5 s simulated)")


if __name__ == "__main__":
    main()
