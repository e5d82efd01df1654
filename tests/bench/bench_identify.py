"""Offline identification on the simulated rig: 0.1-20 Hz, about 30 frequencies, 3 positions.

    .venv/bin/python tests/bench/bench_identify.py [--mode open|closed] [--signal sine|multisine]

Timed: the whole `run_identification` (moves, excitation through the loop tick by tick, the
estimates, the fit, Delta, and the gate's recommended Q31 and Q20 cut-offs for both the
fitted and the configured nominal). Target: <= 15 s wall. Prints the wall time, the simulated
time, their ratio, and the figures the run produced (match to M(s)P(s), fit, agreement,
cut-offs).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from controller.core.config import LoopConfig
from controller.ident.engine import run_identification
from controller.ident.result import IdentifyResult
from controller.ident.spec import IdentifySpec

WN_TRUE = math.sqrt(1935.0)
ZETA_TRUE = 62.2 / (2.0 * WN_TRUE)


def _mp(freq_hz: np.ndarray) -> np.ndarray:
    s = 2j * np.pi * freq_hz
    return np.asarray(1935.0 / (s * s + 62.2 * s + 1935.0))


def report(result: IdentifyResult, wall_s: float) -> None:
    f = result.positions[0].estimate.freq_hz  # type: ignore[union-attr]
    print(
        f"{result.spec.mode} / {result.spec.signal}: {f.size} frequencies "
        f"{f[0]:.3g}-{f[-1]:.3g} Hz, {len(result.positions)} positions"
    )
    print(
        f"  wall {wall_s:.2f} s (target <= 15 s), simulated {result.simulated_s:.0f} s, "
        f"{result.simulated_s / wall_s:.0f}x real time"
    )
    for p in result.positions:
        assert p.estimate is not None
        m = p.estimate.freq_hz <= 5.0 + 1e-9
        r = p.estimate.response[m] / _mp(p.estimate.freq_hz[m])
        print(
            f"  {p.name}: max error vs M(s)P(s) 0.1-5 Hz: "
            f"{np.max(np.abs(20 * np.log10(np.abs(r)))):.2f} dB, "
            f"{np.max(np.abs(np.degrees(np.angle(r)))):.2f} deg"
        )
    fit = result.fit
    if fit is not None:
        print(
            f"  fit: wn {fit.wn_rad_s:.2f} +- {fit.wn_std_rad_s:.2f} rad/s "
            f"({100 * (fit.wn_rad_s / WN_TRUE - 1):+.1f} %), zeta {fit.zeta:.4f} +- "
            f"{fit.zeta_std:.4f} ({100 * (fit.zeta / ZETA_TRUE - 1):+.1f} %)"
        )
    if result.agreement is not None:
        print(f"  curves agree below {result.agreement.agree_below_hz:.3g} Hz")
    print(f"  recommended (fitted nominal): {result.recommended_cutoff_hz}")
    print(f"  recommended (configured nominal): {result.recommended_cutoff_hz_config}")
    for g in result.gate_checks:
        print(f"  gate {g.q_type} {g.cutoff_hz:.3g} Hz: {'accept' if g.accepted else 'reject'}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", default="open")
    ap.add_argument("--signal", default="sine")
    args = ap.parse_args()
    # 13 points per decade over 0.1-20 Hz: 31 frequencies (the grid has whole decades only)
    spec = IdentifySpec(
        mode=args.mode, signal=args.signal, f_min_hz=0.1, f_max_hz=20.0, points_per_decade=13
    )
    cfg = LoopConfig()
    # warm-up: numba's cached kernel load and first-call costs, not part of the figure
    run_identification(spec.with_(f_min_hz=5.0, positions=1), cfg)
    t0 = time.perf_counter()
    result = run_identification(spec, cfg)
    wall = time.perf_counter() - t0
    report(result, wall)


if __name__ == "__main__":
    main()
