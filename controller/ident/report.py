"""The report of an identification: the summary object (``summary.json`` of ``dobtune
identify``, also carried by the controller's IdentifyStatus) and its readable table (no I/O).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from controller.core.config import NominalModel, config_to_builtins
from controller.gate.knowledge import DIVERGENCE_FRACTION, UNCERTAINTY_SIGMAS, PositionSpread
from controller.gate.search import SPREAD_MARGIN
from controller.ident.result import IdentifyResult, PositionRecord, relative_uncertainty_of

__all__ = [
    "FITTED_CONFIG_NAME",
    "csv_name",
    "nominal_from_summary",
    "raw_name",
    "report_text",
    "summary_json",
]

#: The file name of the run's configuration with the fitted nominal.
FITTED_CONFIG_NAME = "config_fitted.json"


def _finite(v: float | None) -> float | None:
    return v if v is not None and math.isfinite(v) else None


def csv_name(p: PositionRecord) -> str:
    """The response CSV of a position (``dobtune check --frd`` reads it)."""
    return f"{p.name}.csv"


def raw_name(p: PositionRecord) -> str:
    """The raw records of a position (offline runs only)."""
    return f"raw_pos{p.index}.npz"


def nominal_from_summary(obj: dict[str, Any]) -> NominalModel:
    """The summary's ``nominal`` object as a NominalModel (ConfigError, KeyError, TypeError
    if it is not one)."""
    return NominalModel(
        mn_den=tuple(obj["mn_den"]), pn_num=tuple(obj["pn_num"]), pn_den=tuple(obj["pn_den"])
    )


def _gain_text(fit: dict[str, Any]) -> str:
    """The fit's numerator: "1", or the fitted DC gain with its uncertainty."""
    k = fit.get("k", 1.0)
    return "1" if fit.get("k_std", 0.0) == 0.0 and k == 1.0 else (
        f"k (k = {k:.3g} +- {fit.get('k_std', 0.0):.2g})")


def summary_json(
    result: IdentifyResult,
    files: dict[int, tuple[str | None, str]],
    wall_s: float,
    files_config: str | None = None,
) -> dict[str, Any]:
    """The object written to summary.json and printed by ``--json``."""
    spec = result.spec
    exc = result.excitation
    fit = result.fit
    agree = result.agreement
    unc = result.uncertainty
    positions = []
    for i, p in enumerate(result.positions):
        est = p.estimate
        entry: dict[str, Any] = {
            "index": p.index,
            "center_deg": p.center_deg,
            "complete": p.complete,
            "points_done": p.points_done,
            "points_total": p.points_total,
            "csv": files.get(p.index, (None, ""))[0],
            "raw": files.get(p.index, (None, ""))[1],
            "min_coherence": None if est is None else float(np.min(est.coherence)),
        }
        if est is not None:
            # what the non-excited lines next to each excited one hold (nonlinear distortion
            # and noise), relative to the response there: stated beside it, not fitted
            u = relative_uncertainty_of(est)
            j = int(np.argmax(u))
            entry["distortion_db"] = float(20.0 * np.log10(max(float(u[j]), 1e-12)))
            entry["distortion_at_hz"] = float(est.freq_hz[j])
        if unc is not None and p.complete and i < unc.delta.shape[0]:
            k = int(np.argmax(np.abs(unc.delta[i])))
            entry["delta_peak"] = float(np.abs(unc.delta[i][k]))
            entry["delta_peak_hz"] = float(unc.freq_hz[k])
        positions.append(entry)
    fit_obj = None
    if fit is not None:
        fit_obj = {
            "model": ("Mn Pn = k / (a2 s^2 + a1 s + 1)" if "k" in fit.params
                      else "Mn Pn = 1 / (a2 s^2 + a1 s + 1)"),
            "k": fit.params.get("k", 1.0),
            "k_std": fit.param_std.get("k", 0.0),
            "a2": fit.params["a2"],
            "a2_std": fit.param_std["a2"],
            "a1": fit.params["a1"],
            "a1_std": fit.param_std["a1"],
            "natural_freq_hz": _finite(fit.natural_freq_hz),
            "natural_freq_std_hz": _finite(fit.natural_freq_std_hz),
            "zeta": _finite(fit.zeta),
            "zeta_std": _finite(fit.zeta_std),
            "band_hz": [fit.f_lo_hz, fit.f_hi_hz],
            "n_points": fit.n_points,
            "residual_rms_db": fit.residual_rms_db,
            "residual_rms_deg": fit.residual_rms_deg,
            "converged": fit.converged,
        }
    freqs = exc.freq_hz
    return {
        "complete": result.complete,
        "abort_reason": result.abort_reason,
        "plant": "sim",
        "mode": spec.mode,
        "signal": spec.signal,
        "f_min_hz": spec.f_min_hz,
        "f_max_hz": spec.f_max_hz,
        "n_frequencies": int(freqs.size),
        "amplitude_deg_s": spec.amplitude_deg_s,
        "window_deg": spec.window_deg,
        "simulated_s": result.simulated_s,
        "wall_s": wall_s,
        "positions": positions,
        "fit": fit_obj,
        "nominal": None
        if result.nominal is None
        else {
            "mn_den": list(result.nominal.mn_den),
            "pn_num": list(result.nominal.pn_num),
            "pn_den": list(result.nominal.pn_den),
        },
        "agreement": None
        if agree is None
        else {
            "agree_below_hz": agree.agree_below_hz,
            "first_disagree_hz": agree.first_disagree_hz,
            "tol_db": agree.tol_db,
            "tol_deg": agree.tol_deg,
            "unresolved_hz": list(agree.unresolved_hz),
            "text": agree.describe(),
        },
        "agreement_freq_hz": None if agree is None else agree.agree_below_hz,
        "recommended_cutoff_hz": dict(result.recommended_cutoff_hz),
        "recommended_cutoff_hz_config_nominal": dict(result.recommended_cutoff_hz_config),
        "recommended_cutoff_hz_gate_only": dict(result.recommended_cutoff_hz_gate_only),
        "position_spread": _spread_json(result.position_spread),
        "search_limit_hz": 0.1 * result.config.rate_hz,
        "fitted_config": files_config,
        "gate_checks": [
            {
                "q_type": g.q_type,
                "cutoff_hz": g.cutoff_hz,
                "accepted": g.accepted,
                "small_gain_peak": _finite(g.small_gain_peak),
                "reasons": list(g.reasons),
            }
            for g in result.gate_checks
        ],
        "notes": list(result.notes),
        "config": config_to_builtins(result.config),
    }


def _spread_json(sp: PositionSpread | None) -> dict[str, Any] | None:
    """The position spread: where the responses diverge, and the spread by frequency."""
    if sp is None:
        return None
    return {
        "divergence_hz": sp.divergence_hz,
        "divergence_fraction": DIVERGENCE_FRACTION,
        "spread_margin": SPREAD_MARGIN,
        "freq_hz": sp.freq_hz.tolist(),
        "relative": sp.relative.tolist(),
        "mag_db": sp.mag_db.tolist(),
        "phase_deg": sp.phase_deg.tolist(),
        "uncertainty": None if sp.uncertainty is None else sp.uncertainty.tolist(),
    }


def _fmt(v: float | None, spec: str = ".3g", unit: str = "") -> str:
    if v is None or not math.isfinite(v):
        return "none"
    return f"{v:{spec}}{unit}"


def report_text(summary: dict[str, Any], out_dir: Path) -> str:
    """The readable table printed without ``--json``."""
    lines = [
        f"dobtune identify: {summary['mode']} loop, "
        f"{'stepped sine' if summary['signal'] == 'sine' else 'multisine'} "
        f"{summary['f_min_hz']:g}-{summary['f_max_hz']:g} Hz ({summary['n_frequencies']} "
        f"frequencies), {len(summary['positions'])} position(s); "
        f"{summary['simulated_s']:.0f} s simulated in {summary['wall_s']:.1f} s",
        f"  {'position':<16}{'points':>8}{'min coh.':>10}{'max |Delta|':>13}  at"
        f"{'distortion+noise':>22}",
    ]
    for p in summary["positions"]:
        lines.append(
            f"  {p['center_deg']:>8g} deg     {p['points_done']:>3}/{p['points_total']:<3}"
            f"{_fmt(p['min_coherence'], '.4f'):>10}{_fmt(p.get('delta_peak'), '.3g'):>13}"
            f"  {_fmt(p.get('delta_peak_hz'), '.3g', ' Hz'):<8}"
            + (f"{p['distortion_db']:>8.1f} dB at {p['distortion_at_hz']:.3g} Hz"
               if p.get("distortion_db") is not None else "")
            + ("" if p["complete"] else "  INCOMPLETE")
        )
    fit = summary["fit"]
    if fit is not None:
        lines.append(
            f"  fit Mn Pn = {_gain_text(fit)}/(a2 s^2 + a1 s + 1), "
            f"{fit['band_hz'][0]:.3g}-{fit['band_hz'][1]:.3g} Hz: natural frequency "
            f"{_fmt(fit['natural_freq_hz'], '.3f')} +- "
            f"{_fmt(fit['natural_freq_std_hz'], '.2g')} Hz, damping {_fmt(fit['zeta'], '.3f')} +- "
            f"{_fmt(fit['zeta_std'], '.2g')}; residual {fit['residual_rms_db']:.2f} dB / "
            f"{fit['residual_rms_deg']:.2f} deg rms"
        )
    agree = summary["agreement"]
    if agree is not None:
        lines.append(f"  {agree['text']}")
    top = summary["search_limit_hz"]

    def cutoffs(rec: dict[str, float | None]) -> str:
        def one(v: float | None) -> str:
            if v is None:
                return "none (even the lowest is rejected)"
            return f">= {top:g} Hz (search limit)" if v >= 0.999 * top else f"{v:.3g} Hz"

        return ", ".join(f"{q.upper()} {one(v)}" for q, v in rec.items())

    if summary["recommended_cutoff_hz"]:
        lines.append(
            "  recommended max Q cut-off, fitted model + measured responses: "
            + cutoffs(summary["recommended_cutoff_hz"])
        )
    sp = summary.get("position_spread")
    if sp is not None:
        div = sp["divergence_hz"]
        f = np.asarray(sp["freq_hz"])
        db = np.asarray(sp["mag_db"])
        marks = [x for x in (0.5, 1.0, 2.0, 5.0, 10.0, 20.0) if f[0] <= x <= f[-1]]
        by_f = ", ".join(
            f"{x:g} Hz {np.interp(np.log(x), np.log(f), db):.2f} dB" for x in marks)
        lines.append(
            "  position spread (max - min |H|): " + (by_f or "outside the marks")
            + "; beyond the measurement's uncertainty the responses diverge (> "
            + f"{20 * math.log10(1 + sp['divergence_fraction']):.2g} dB) "
            + (f"above {div:.3g} Hz" if div is not None else "nowhere on the band")
        )
        unc = sp.get("uncertainty")
        if unc is not None:
            u = np.asarray(unc)
            worst = int(np.argmax(u))
            if u[worst] > sp["divergence_fraction"]:
                lines.append(
                    f"  the measurement's own uncertainty ({UNCERTAINTY_SIGMAS:g} sigma) reaches "
                    f"{20 * math.log10(1 + u[worst]):.2g} dB at {f[worst]:.3g} Hz (noise lines, "
                    "friction at small amplitude): differences there are not the plant's")
        if summary.get("recommended_cutoff_hz_gate_only"):
            lines.append(
                "  without the spread as evidence (gate alone): "
                + cutoffs(summary["recommended_cutoff_hz_gate_only"])
                + f"; with it, |Delta Q| <= {1 / sp['spread_margin']:.3g}"
                  " wherever the turntable stands"
            )
    if summary["recommended_cutoff_hz_config_nominal"]:
        lines.append(
            "  (with the configured nominal instead: "
            + cutoffs(summary["recommended_cutoff_hz_config_nominal"])
            + ")"
        )
    for g in summary["gate_checks"]:
        verdict = "accept" if g["accepted"] else "REJECT"
        why = f" ({g['reasons'][0]})" if g["reasons"] else ""
        lines.append(f"  gate at {g['q_type'].upper()} {g['cutoff_hz']:.3g} Hz: {verdict}{why}")
    tw = summary.get("twin")
    if tw:
        fac = ", ".join(f"{k} {v:.3g}" for k, v in tw["fitted"].items())
        lines.append(f"  twin ({tw['file']}, from {tw['knowledge_file']}): {fac}")
        for p in tw["positions"]:
            lines.append(
                f"    {p['name']}: {p['rms_db']:.2f} dB / {p['rms_deg']:.1f} deg rms, worst "
                f"{p['max_db']:.2f} dB (at {p['max_at_hz']:.3g} Hz) / {p['max_deg']:.1f} deg "
                f"({p['f_lo_hz']:.3g}-{p['f_hi_hz']:.3g} Hz)")
        lines += [f"    {h}" for h in tw["nonlinear"]]
    lines += [f"  note: {n}" for n in summary["notes"]]
    if not summary["complete"]:
        lines.append(f"ABORTED: {summary['abort_reason']} (partial data kept)")
    if any(p.get("distortion_db") is not None for p in summary["positions"]):
        lines.append("  distortion+noise: the non-excited lines beside the excited ones, worst "
                     "point, relative to the response (0 dB: as large as the response)")
    lines.append(
        f"  files in {out_dir}"
        + (
            f"; check: dobtune check {out_dir / summary['fitted_config']} --frd "
            f"{out_dir}/pos*.csv --cutoff-hz HZ"
            if summary["fitted_config"]
            else ""
        )
    )
    return "\n".join(lines) + "\n"
