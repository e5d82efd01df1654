"""Cost of one stability check (the gate, also run on every dashboard slider move).

    .venv/bin/python tests/bench/bench_analysis.py

One candidate, the default 500-point grid, three measured responses (CSV-like data on their
own 200-point grid) and an uncertainty bound. Compared with the same quantities computed
naively through python-control objects: state-space blocks composed with series/parallel/
feedback, frequency responses of the closed loops, FRD objects for the measured loops,
`stability_margins` on FRD data (the transfer-function route is numerically unusable here:
Q poles near z = 1) and the closed-loop poles.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import control as ct
import numpy as np

from controller.core.config import LoopConfig
from controller.core.dob import design_dob
from controller.gate.analysis import analyse
from controller.gate.knowledge import MeasuredResponse, PlantKnowledge, WeightBound
from controller.gate.loop_model import (
    default_grid,
    discrete_equivalent,
    nominal_continuous_response,
)
from controller.gate.search import recommended_max_cutoff_hz


def _measured(cfg: LoopConfig) -> tuple[MeasuredResponse, ...]:
    f = np.geomspace(0.02, 200.0, 200)
    s = 2j * np.pi * f
    base = nominal_continuous_response(cfg.nominal, f)
    out = []
    for name, gain, fr in (
        ("pos_0deg", 1.2, None),
        ("pos_120deg", 0.8, 15.0),
        ("pos_240", 1.0, 30.0),
    ):
        h = gain * base
        if fr is not None:
            w = 2 * np.pi * fr
            h = h * w * w / (s * s + 2 * 0.1 * w * s + w * w)
        out.append(MeasuredResponse(name, f, h))
    return tuple(out)


def _naive(cfg: LoopConfig, plant: PlantKnowledge) -> dict[str, object]:
    ts = cfg.period_s
    f = default_grid(cfg.rate_hz)
    w = 2 * np.pi * f
    z = np.exp(1j * w * ts)
    one = ct.ss([], [], [], [[1.0]], ts)
    n = cfg.nominal
    mp = ct.minreal(ct.tf(n.pn_num, np.polymul(n.mn_den, n.pn_den)), verbose=False)
    gth = ct.c2d(ct.ss(mp * ct.tf([1], [1, 0])), ts, "zoh")
    diff = ct.ss(ct.tf([1, -1], [ts, 0], ts))
    g = ct.series(gth, diff)

    def pi(kp: float, ki: float) -> ct.StateSpace:
        a = ki * ts / 2
        return ct.ss(ct.tf(kp * np.array([1 + a, a - 1]), [1, -1], ts))

    def sos(sections: np.ndarray) -> ct.StateSpace:
        h = one
        for s in sections:
            h = ct.series(h, ct.ss(ct.tf(s[:3], s[3:], ts)))
        return h

    cv, cp = pi(cfg.cv_kp, cfg.cv_ki_per_s), pi(cfg.pos_kp_per_s, cfg.pos_ki_per_s)
    d = design_dob(cfg)
    f1 = sos(d.f1_sos)
    f2d = ct.series(ct.ss(ct.tf([1], [1, 0], ts)), sos(d.f2_sos))
    kq = ct.feedback(one, f2d, sign=1)
    loop = ct.series(ct.parallel(cv, f1), kq, g)
    gyw = ct.feedback(ct.series(cv, ct.feedback(ct.series(kq, g), f1)), one)
    sens = ct.feedback(one, loop)
    comp = ct.feedback(loop, one)
    plain = ct.series(cv, g)
    responses = [s(z) for s in (loop, gyw, sens, comp, ct.feedback(plain, one))]
    margins = ct.stability_margins(ct.frd(responses[0], w))
    c = ct.series(ct.parallel(cp, diff), cv)
    k = ct.series(ct.parallel(ct.series(diff, f1), c), kq)
    poles = ct.feedback(ct.series(k, gth), one).poles()
    per_source = []
    for m in plant.measured:
        gc = np.interp(np.log(f), np.log(m.freq_hz), m.response.real) + 1j * np.interp(
            np.log(f), np.log(m.freq_hz), m.response.imag
        )
        gm = ct.frd(discrete_equivalent(gc, f, cfg.rate_hz), w)
        cvf, f1f, f2f = (ct.frd(b(z), w) for b in (cv, f1, f2d))
        x = (gm * f1f - f2f) / (1 + gm * cvf)
        lm = gm * (cvf + f1f) / (1 - f2f)
        per_source.append((np.max(np.abs(x.frdata)), ct.stability_margins(lm)))
    return {"responses": responses, "margins": margins, "poles": poles, "src": per_source}


def _time(fn: Callable[[], object], n: int) -> tuple[float, float]:
    fn()  # warm caches
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    ts.sort()
    return statistics.median(ts) * 1e3, ts[int(0.9 * (len(ts) - 1))] * 1e3


def main() -> None:
    cfg = LoopConfig()
    plant = PlantKnowledge(measured=_measured(cfg), bound=WeightBound(0.2, 15.0))
    cutoffs = iter(np.geomspace(0.3, 3.0, 10_000))

    def fresh() -> object:  # a new cut-off each call: DOB design not cached
        return analyse(cfg.with_(q_cutoff_hz=float(next(cutoffs))), plant)

    med, p90 = _time(lambda: analyse(cfg, plant), 200)
    print(f"analyse(), same candidate (DOB design cached): median {med:.2f} ms, p90 {p90:.2f} ms")
    med_f, p90_f = _time(fresh, 200)
    print(
        f"analyse(), new cut-off each call:             median {med_f:.2f} ms, p90 {p90_f:.2f} ms"
    )
    med_n, p90_n = _time(lambda: _naive(cfg, plant), 10)
    print(
        f"naive python-control objects:                 median {med_n:.1f} ms, p90 {p90_n:.1f} ms"
    )
    print(f"ratio naive / analyse (new cut-off): {med_n / med_f:.0f}x; target <= 20 ms median")
    t0 = time.perf_counter()
    rec = recommended_max_cutoff_hz(cfg, plant)
    took_ms = (time.perf_counter() - t0) * 1e3
    shown = f"{rec:.3g} Hz" if rec is not None else "none"
    print(f"recommended_max_cutoff_hz: {shown} in {took_ms:.0f} ms")


if __name__ == "__main__":
    main()
