"""Identification plans on the simulated rig: rig time against accuracy (issue 15 item 4).

    .venv/bin/python tests/bench/bench_identify.py [--mode open|closed] [--seeds N]
        [--plans sine,multisine,multisine2]

Each plan runs the whole `run_identification` (moves, excitation through the loop tick by tick,
the estimates, the fit, Delta and the gate's recommended cut-offs) at the 3 default positions,
0.1-20 Hz, once per rig seed. Printed per plan (median over seeds, worst in brackets):

* rig time (the simulated seconds the rig moves: what a real rig would take) and wall time;
* per-point error of the estimate against the simulated rig's true linear response
  (`linear_response`: its drive, gearbox, belt and load linearised about a one-way motion,
  built here from `RigParams`; checked against the rig with its nonlinearities switched off,
  `--check-reference`): RMS and max of |H/G - 1| over 0.1-20 Hz, and max dB / deg in 0.1-10 Hz;
* the reported spread (median of mag_std_db / phase_std_deg) and its honesty: the RMS of the
  error divided by the reported standard deviation (about 1 when the spread is right, >> 1 when
  it hides the error);
* coherence (min, median);
* the fit of Mn Pn = 1 / (a2 s^2 + a1 s + 1) (0.1-10 Hz, all positions): natural frequency and
  damping against the same fit of the true linear response, in units of the fit's own standard
  deviation too;
* multisine: its crest factor and the largest odd and even detection line below 3 Hz relative
  to the excited lines (nonlinear distortion and the belt tooth's disturbance).

Errors are against the plan's own measurement of the rig without nonlinearities and noise
(`true_response`; `--analytic`: against `linear_response` itself).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from controller.core.config import LoopConfig
from controller.ident.engine import run_identification
from controller.ident.estimate import detection_lines
from controller.ident.excitation import Multisine
from controller.ident.model_fit import fit_second_order
from controller.ident.plan import plan_program
from controller.ident.result import IdentifyResult
from controller.ident.spec import IdentifySpec, OfflineOptions

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: the shared reference
from rig_linear import linear_response, linear_rig

#: name -> IdentifySpec fields (the rest are the spec's defaults)
PLANS: dict[str, dict[str, Any]] = {
    "sine": {"signal": "sine"},
    "multisine": {"signal": "multisine", "multisine_periods": 1},
    "multisine2": {"signal": "multisine", "multisine_periods": 2},
    "multisine3": {"signal": "multisine", "multisine_periods": 3},
}


@dataclass
class Figures:
    rig_s: float
    wall_s: float
    err_rms: float
    err_max: float
    db_max: float
    deg_max: float
    std_db: float
    std_deg: float
    z_median: float
    z_p90: float
    coh_min: float
    coh_median: float
    fn_hz: float
    fn_std_hz: float
    zeta: float
    zeta_std: float
    n_freq: int
    odd_db: float = math.nan
    even_db: float = math.nan
    crest: float = math.nan


def _truth_fit(f_lo: float, f_hi: float) -> tuple[float, float]:
    f = np.logspace(math.log10(f_lo), math.log10(f_hi), 200)
    fit = fit_second_order(f, linear_response(f), model="unit_dc")
    return fit.natural_freq_hz, fit.zeta


def figures(result: IdentifyResult, wall_s: float, reference: np.ndarray | None) -> Figures:
    """The figures of one run; `reference`: the true response on its grid (None: the analytic
    `linear_response`)."""
    errs, z2, dbs, degs, sdb, sdeg, coh = [], [], [], [], [], [], []
    for pos in result.positions:
        e = pos.estimate
        assert e is not None
        g = linear_response(e.freq_hz) if reference is None else reference
        rel = e.response / g - 1.0
        errs.append(np.abs(rel))
        sigma = math.sqrt(2.0) * np.log(10.0) / 20.0 * e.mag_std_db  # complex relative std
        z2.append(np.abs(rel) / sigma)
        band = e.freq_hz <= 10.0 + 1e-9
        ratio = e.response[band] / g[band]
        dbs.append(np.max(np.abs(20.0 * np.log10(np.abs(ratio)))))
        degs.append(np.max(np.abs(np.degrees(np.angle(ratio)))))
        sdb.append(e.mag_std_db)
        sdeg.append(e.phase_std_deg)
        coh.append(e.coherence)
    err = np.concatenate(errs)
    fit = result.fit
    assert fit is not None
    odd_db = even_db = crest = math.nan
    exc = result.excitation
    if isinstance(exc, Multisine):  # the detection lines of the output, below 3 Hz
        odd, even = [], []
        for pos in result.positions:
            lines = detection_lines(exc, pos.raw.aligned("w_deg_s", exc.signal.size))
            low = lines.freq_hz <= 3.0
            ref = np.median(lines.amplitude[low & (lines.kind == 0)])
            odd.append(np.max(lines.amplitude[low & (lines.kind == 1)]) / ref)
            even.append(np.max(lines.amplitude[low & (lines.kind == 2)]) / ref)
        odd_db, even_db = 20 * math.log10(max(odd)), 20 * math.log10(max(even))
        crest = exc.crest_factor
    return Figures(
        rig_s=result.simulated_s,
        wall_s=wall_s,
        err_rms=float(np.sqrt(np.mean(err**2))),
        err_max=float(np.max(err)),
        db_max=float(max(dbs)),
        deg_max=float(max(degs)),
        std_db=float(np.median(np.concatenate(sdb))),
        std_deg=float(np.median(np.concatenate(sdeg))),
        z_median=float(np.median(np.concatenate(z2))),
        z_p90=float(np.percentile(np.concatenate(z2), 90)),
        coh_min=float(np.min(np.concatenate(coh))),
        coh_median=float(np.median(np.concatenate(coh))),
        fn_hz=fit.natural_freq_hz,
        fn_std_hz=fit.natural_freq_std_hz,
        zeta=fit.zeta,
        zeta_std=fit.zeta_std,
        n_freq=int(result.positions[0].estimate.freq_hz.size),  # type: ignore[union-attr]
        odd_db=odd_db,
        even_db=even_db,
        crest=crest,
    )


def true_response(spec: IdentifySpec) -> np.ndarray:
    """The plan's own measurement of the rig without nonlinearities and noise (`linear_rig`):
    the simulated rig's true linear response on the plan's grid, through the same sampling
    and estimator (within 0.04 dB / 0.3 deg of the analytic `linear_response` up to 20 Hz:
    `--check-reference`)."""
    result = run_identification(spec.with_(positions=1), LoopConfig(), rig_factory=linear_rig)
    e = result.positions[0].estimate
    assert e is not None
    return e.response


def controller_s(spec: IdentifySpec) -> float:
    """Rig time of the plan the controller runs (a move before every segment), from 0 deg."""
    cfg = LoopConfig()
    return plan_program(spec, cfg, 0.0).n_ticks / cfg.rate_hz


def run_plan(spec: IdentifySpec, seed: int, reference: np.ndarray | None) -> Figures:
    t0 = time.perf_counter()
    result = run_identification(spec, LoopConfig(), offline=OfflineOptions(seed=seed))
    return figures(result, time.perf_counter() - t0, reference)


def _med(rows: list[Figures], get: Callable[[Figures], float]) -> float:
    return statistics.median(get(r) for r in rows)


def _worst(rows: list[Figures], get: Callable[[Figures], float]) -> float:
    return max(get(r) for r in rows)


def report(
    name: str, rows: list[Figures], fn_true: float, zeta_true: float, ref_name: str
) -> None:
    r0 = rows[0]
    fn_dev = [abs(r.fn_hz / fn_true - 1.0) for r in rows]
    zeta_dev = [abs(r.zeta / zeta_true - 1.0) for r in rows]
    fn_sig = [abs(r.fn_hz - fn_true) / r.fn_std_hz for r in rows]
    zeta_sig = [abs(r.zeta - zeta_true) / r.zeta_std for r in rows]
    print(
        f"{name:<11} rig {r0.rig_s:6.1f} s  wall {_med(rows, lambda r: r.wall_s):5.2f} s  "
        f"{r0.n_freq} freq/position"
    )
    print(
        f"  error vs {ref_name}: rms {100 * _med(rows, lambda r: r.err_rms):.2f} % "
        f"[{100 * _worst(rows, lambda r: r.err_rms):.2f}], max "
        f"{100 * _med(rows, lambda r: r.err_max):.2f} % "
        f"[{100 * _worst(rows, lambda r: r.err_max):.2f}]; 0.1-10 Hz max "
        f"{_med(rows, lambda r: r.db_max):.3f} dB [{_worst(rows, lambda r: r.db_max):.3f}] / "
        f"{_med(rows, lambda r: r.deg_max):.2f} deg [{_worst(rows, lambda r: r.deg_max):.2f}]"
    )
    print(
        f"  reported spread: median {_med(rows, lambda r: r.std_db):.4f} dB / "
        f"{_med(rows, lambda r: r.std_deg):.3f} deg; |error| / spread median "
        f"{_med(rows, lambda r: r.z_median):.2f}, 90th percentile "
        f"{_med(rows, lambda r: r.z_p90):.1f} [{_worst(rows, lambda r: r.z_p90):.1f}]; "
        f"coherence min {min(r.coh_min for r in rows):.4f}, median "
        f"{_med(rows, lambda r: r.coh_median):.5f}"
    )
    print(
        f"  fit: fn {_med(rows, lambda r: r.fn_hz):.4f} +- {_med(rows, lambda r: r.fn_std_hz):.4f}"
        f" Hz (off the linear rig's {100 * statistics.median(fn_dev):.2f} % "
        f"[{100 * max(fn_dev):.2f}], {statistics.median(fn_sig):.1f} sigma), zeta "
        f"{_med(rows, lambda r: r.zeta):.4f} +- {_med(rows, lambda r: r.zeta_std):.4f} "
        f"({100 * statistics.median(zeta_dev):.2f} % [{100 * max(zeta_dev):.2f}], "
        f"{statistics.median(zeta_sig):.1f} sigma)"
    )
    if math.isfinite(r0.crest):
        print(
            f"  crest factor {r0.crest:.2f}; largest detection line below 3 Hz relative to the "
            f"excited lines: odd {_worst(rows, lambda r: r.odd_db):.1f} dB, even "
            f"{_worst(rows, lambda r: r.even_db):.1f} dB (a belt tooth's line and its "
            f"intermodulation)"
        )


def check_reference() -> None:
    """The analytic linear response against the rig with its nonlinearities switched off."""
    spec = IdentifySpec(signal="multisine", multisine_periods=2, positions=1)
    result = run_identification(spec, LoopConfig(), rig_factory=linear_rig)
    e = result.positions[0].estimate
    assert e is not None
    ratio = e.response / linear_response(e.freq_hz)
    print(
        f"reference check (rig without nonlinearities, {e.freq_hz.size} lines 0.1-20 Hz): "
        f"max {np.max(np.abs(20 * np.log10(np.abs(ratio)))):.4f} dB, "
        f"{np.max(np.abs(np.degrees(np.angle(ratio)))):.3f} deg"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", default="open", choices=("open", "closed"))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--plans", default="sine,multisine")
    ap.add_argument("--check-reference", action="store_true")
    ap.add_argument(
        "--analytic", action="store_true", help="errors against the analytic linear response"
    )
    args = ap.parse_args()
    if args.check_reference:
        check_reference()
    base = IdentifySpec(mode=args.mode)
    fn_true, zeta_true = _truth_fit(base.f_min_hz, base.fit_f_hi_hz or base.f_max_hz)
    print(
        f"{args.mode} loop, {base.positions} positions, {base.f_min_hz:g}-{base.f_max_hz:g} Hz, "
        f"seeds 0-{args.seeds - 1}; the linear rig's own second-order fit (0.1-10 Hz): "
        f"fn {fn_true:.4f} Hz, zeta {zeta_true:.4f}"
    )
    # warm-up: numba's cached kernel load and first-call costs, not part of the figures
    run_identification(base.with_(f_min_hz=5.0, positions=1), LoopConfig())
    for name in args.plans.split(","):
        spec = base.with_(**PLANS[name])
        ref = None if args.analytic else true_response(spec)
        rows = [run_plan(spec, seed, ref) for seed in range(args.seeds)]
        print(f"{name}: the controller's plan takes {controller_s(spec):.1f} s of rig time")
        report(name, rows, fn_true, zeta_true, "analytic" if ref is None else "linear rig")


if __name__ == "__main__":
    main()
