"""Wall time of the identification math: 3 positions x 30 stepped-sine frequencies.

    .venv/bin/python tests/bench/bench_identify_math.py

Data: three ZOH-discretised second-order plants around M(s)P(s) = 1935 / (s^2 + 62.2 s + 1935)
whose natural frequency and damping change with the turntable position (belt tension), plus
output noise. Timed: the three stepped-sine
estimates, one second-order fit per position and one on all positions together, the agreement
frequency and the model uncertainty Delta. Target: <= 200 ms. Generating the excitation and
simulating the plant are reported separately (not part of the target).
"""

from __future__ import annotations

import math
import statistics
import time

import numpy as np
import scipy.signal as sig

from controller.ident.estimate import FrdEstimate, agreement, estimate_stepped_sine
from controller.ident.excitation import SteppedSine, SteppedSineSpec, stepped_sine
from controller.ident.model_fit import SecondOrderFit, fit_frd, uncertainty_bound

FS = 1000.0
#: (natural frequency Hz, damping) at the three positions; the middle one is the article's
POSITIONS = (
    (6.3, 0.62),
    (math.sqrt(1935.0) / (2 * math.pi), 62.2 / (2 * math.sqrt(1935.0))),
    (7.7, 0.80),
)


def simulate(ss: SteppedSine, rng: np.random.Generator) -> list[np.ndarray]:
    outputs = []
    for fn, zeta in POSITIONS:
        wn = 2 * math.pi * fn
        b, a, _ = sig.cont2discrete(([wn**2], [1.0, 2 * zeta * wn, wn**2]), 1.0 / FS, method="zoh")
        w = sig.lfilter(np.ravel(b), np.ravel(a), ss.signal)
        outputs.append(w + 0.5 * rng.standard_normal(w.size))
    return outputs


def identify(
    ss: SteppedSine, outputs: list[np.ndarray]
) -> tuple[list[FrdEstimate], list[SecondOrderFit], SecondOrderFit, float, float]:
    estimates = [estimate_stepped_sine(ss, ss.signal, w) for w in outputs]
    fits = [fit_frd(e, f_hi_hz=10.0, delay_s=0.5 / FS) for e in estimates]
    joint = fit_frd(estimates, f_hi_hz=10.0, delay_s=0.5 / FS)
    agree = agreement(estimates, tol_db=1.0, tol_deg=10.0)
    bound = uncertainty_bound(joint, estimates)
    return estimates, fits, joint, agree.agree_below_hz, float(np.max(bound.bound))


def main() -> None:
    spec = SteppedSineSpec(f_min_hz=0.1, f_max_hz=25.0, points_per_decade=12, window_deg=5.0)
    t0 = time.perf_counter()
    ss = stepped_sine(spec)
    t_gen = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    outputs = simulate(ss, rng)
    t_sim = time.perf_counter() - t0
    print(
        f"stepped sine: {len(ss.points)} frequencies, {ss.duration_s:.0f} s per position, "
        f"{ss.signal.size} samples; generated in {t_gen * 1e3:.1f} ms, "
        f"3 plants simulated in {t_sim * 1e3:.1f} ms"
    )
    identify(ss, outputs)  # warm-up
    times = []
    for _ in range(10):
        t0 = time.perf_counter()
        _, fits, joint, agree_hz, delta_max = identify(ss, outputs)
        times.append(time.perf_counter() - t0)
    for (fn, zeta), fit in zip(POSITIONS, fits, strict=True):
        print(
            f"  true {fn:.3f} Hz / {zeta:.4f}: fit fn = {fit.natural_freq_hz:.3f} +- "
            f"{fit.natural_freq_std_hz:.4f} Hz, zeta = {fit.zeta:.4f} +- {fit.zeta_std:.4f}, res. "
            f"{fit.residual_rms_db:.3f} dB / {fit.residual_rms_deg:.2f} deg"
        )
    print(
        f"  joint fit: fn = {joint.natural_freq_hz:.3f} +- {joint.natural_freq_std_hz:.3f} Hz, "
        f"zeta = {joint.zeta:.4f} +- {joint.zeta_std:.4f}"
    )
    print(f"  curves agree (1 dB, 10 deg) below {agree_hz:.2f} Hz; max |Delta| = {delta_max:.2f}")
    print(
        f"estimate x3 + fit x4 + agreement + Delta: median {statistics.median(times) * 1e3:.1f} ms,"
        f" min {min(times) * 1e3:.1f} ms (target <= 200 ms)"
    )


if __name__ == "__main__":
    main()
