"""What the Identify panel shows of a run, wherever it ran (no viser): adapters from an offline
`IdentifyResult` and from the controller's `IdentifyStatus` to one `IdentifyView`, and the
result as a small HTML block.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from controller import protocol as proto
from controller.core.arrays import ComplexArray, FloatArray
from controller.core.config import NominalModel
from controller.core.errors import ConfigError
from controller.gate.knowledge import MeasuredResponse
from controller.ident.report import nominal_from_summary
from controller.ident.result import (
    IdentifyResult,
    PositionRecord,
    position_name,
    position_uncertainty,
)
from server import charts
from server.escape import esc

__all__ = [
    "FitView",
    "IdentifyView",
    "curve_of",
    "format_result_html",
    "view_from_result",
    "view_from_status",
]


def _curve(
    index: int,
    center_deg: float,
    freq_hz: npt.ArrayLike,
    mag_db: npt.ArrayLike,
    phase_deg: npt.ArrayLike,
    mag_std_db: npt.ArrayLike,
    coherence: npt.ArrayLike,
    complete: bool,
) -> charts.MeasuredCurve:
    def arr(v: npt.ArrayLike) -> FloatArray:
        return np.asarray(v, dtype=np.float64)

    return charts.MeasuredCurve(
        label=f"pos {index + 1} ({center_deg:g} deg)",
        freq_hz=arr(freq_hz),
        mag_db=arr(mag_db),
        phase_deg=arr(phase_deg),
        mag_std_db=arr(mag_std_db),
        coherence=arr(coherence),
        complete=complete,
    )


def curve_of(p: PositionRecord) -> charts.MeasuredCurve | None:
    """A position's measured response for the charts (None if nothing was measured)."""
    e = p.estimate
    if e is None or e.freq_hz.size == 0:
        return None
    return _curve(
        p.index, p.center_deg, e.freq_hz, e.mag_db, e.phase_deg, e.mag_std_db, e.coherence,
        p.complete,
    )


def _hz(v: float | None) -> str:
    return "none accepted" if v is None else f"{v:.3g} Hz"


@dataclasses.dataclass(frozen=True)
class FitView:
    """The fitted Mn Pn = 1 / (a2 s^2 + a1 s + 1), as displayed."""

    a2: float
    a1: float
    natural_freq_hz: float
    natural_freq_std_hz: float
    zeta: float
    zeta_std: float
    residual_rms_db: float
    residual_rms_deg: float
    f_lo_hz: float
    f_hi_hz: float
    n_points: int

    def response(self, freq_hz: FloatArray) -> ComplexArray:
        s = 2j * np.pi * np.asarray(freq_hz, dtype=np.float64)
        return 1.0 / (self.a2 * s * s + self.a1 * s + 1.0)


@dataclasses.dataclass(frozen=True)
class IdentifyView:
    """What the panel shows of one run, wherever it ran."""

    n_positions: int
    complete: bool
    abort_reason: str | None
    positions_done: int
    curves: tuple[charts.MeasuredCurve | None, ...]
    fit: FitView | None = None
    agreement_hz: float | None = None
    agreement_tol: tuple[float, float] = (1.0, 10.0)
    agreement_text: str = ""
    """The agreement as the identification states it (`Agreement.describe`)."""
    recommended_cutoff_hz: dict[str, float | None] = dataclasses.field(default_factory=dict)
    checks: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    simulated_s: float | None = None
    nominal: NominalModel | None = None
    measured: tuple[MeasuredResponse, ...] = ()


def _check_text(
    q_type: str, cutoff_hz: float, accepted: bool, peak: float | None,
    reasons: Sequence[str] | None,
) -> str:
    why = "" if accepted or not reasons else f": {reasons[0]}"
    return (
        f"gate at {str(q_type).upper()} {float(cutoff_hz):.3g} Hz: "
        f"{'accept' if accepted else 'reject'}"
        + (f" (small-gain peak {float(peak):.2f})" if peak is not None else "")
        + why
    )


def view_from_result(result: IdentifyResult, n_positions: int) -> IdentifyView:
    """Adapter: an offline IdentifyResult -> what the panel shows."""
    f = result.fit
    fit = None if f is None else FitView(
        a2=f.params["a2"], a1=f.params["a1"], natural_freq_hz=f.natural_freq_hz,
        natural_freq_std_hz=f.natural_freq_std_hz, zeta=float(f.zeta),
        zeta_std=float(f.zeta_std), residual_rms_db=f.residual_rms_db,
        residual_rms_deg=f.residual_rms_deg, f_lo_hz=f.f_lo_hz, f_hi_hz=f.f_hi_hz,
        n_points=f.n_points,
    )
    checks = [
        _check_text(c.q_type, c.cutoff_hz, c.accepted, c.small_gain_peak, c.reasons)
        for c in result.gate_checks
    ]
    a = result.agreement
    return IdentifyView(
        n_positions=n_positions,
        complete=result.complete,
        abort_reason=result.abort_reason,
        positions_done=sum(1 for p in result.positions if p.complete),
        curves=tuple(curve_of(p) for p in result.positions),
        fit=fit,
        agreement_hz=None if a is None else a.agree_below_hz,
        agreement_tol=(result.spec.agreement_tol_db, result.spec.agreement_tol_deg),
        agreement_text="" if a is None else a.describe(),
        recommended_cutoff_hz=dict(result.recommended_cutoff_hz) if result.complete else {},
        checks=tuple(checks),
        notes=tuple(result.notes),
        simulated_s=result.simulated_s,
        nominal=result.nominal if result.complete else None,
        measured=result.measured_responses(),
    )


def _fit_from_summary(fo: object) -> FitView | None:
    """The summary's ``fit`` object as a FitView (None if it is not one)."""
    if not isinstance(fo, dict):
        return None
    with contextlib.suppress(KeyError, TypeError, ValueError):
        band = fo.get("band_hz") or [float("nan"), float("nan")]
        return FitView(
            a2=float(fo["a2"]), a1=float(fo["a1"]),
            natural_freq_hz=float(fo["natural_freq_hz"]),
            natural_freq_std_hz=float(fo.get("natural_freq_std_hz") or float("nan")),
            zeta=float(fo["zeta"]), zeta_std=float(fo.get("zeta_std") or float("nan")),
            residual_rms_db=float(fo["residual_rms_db"]),
            residual_rms_deg=float(fo["residual_rms_deg"]),
            f_lo_hz=float(band[0]), f_hi_hz=float(band[1]), n_points=int(fo["n_points"]),
        )
    return None


def view_from_status(
    st: proto.IdentifyStatus, n_positions: int, base: NominalModel
) -> IdentifyView:
    """Adapter: the controller's IdentifyStatus (and its summary JSON) -> what the panel shows.

    Works for a running status too (the partial positions; nothing fitted). The band is the
    per-point magnitude std (NaN, so no band, from a controller that sends none). `base`
    supplies Mn when the summary carries no nominal (the article form: Pn = Mn_den / fit_den).
    """
    summary: dict[str, Any] = {}
    if st.summary_json:
        with contextlib.suppress(ValueError):
            summary = json.loads(st.summary_json)
    curves: list[charts.MeasuredCurve | None] = []
    measured: list[MeasuredResponse] = []
    for p in st.positions:
        if not p.freq_hz:
            curves.append(None)
            continue
        f = np.asarray(p.freq_hz, dtype=np.float64)
        mag = np.asarray(p.mag_db, dtype=np.float64)
        ph = np.degrees(np.unwrap(np.radians(np.asarray(p.phase_deg, dtype=np.float64))))
        std = p.mag_std_db if len(p.mag_std_db) == f.size else np.full(f.size, np.nan)
        curves.append(_curve(p.index, p.center_deg, f, mag, ph, std, p.coherence, p.complete))
        if p.complete and f.size >= 2:
            resp = (10.0 ** (mag / 20.0) * np.exp(1j * np.radians(ph))).astype(np.complex128)
            unc = position_uncertainty(p.freq_hz, p.coherence, p.mag_std_db, p.phase_std_deg)
            measured.append(MeasuredResponse(
                name=position_name(p.index, p.center_deg), freq_hz=f, response=resp,
                spread=None if unc is None else np.asarray(unc, dtype=np.float64)))
    complete = st.state == "done" and bool(st.positions) and all(
        p.complete for p in st.positions) and len(st.positions) == n_positions
    fit = _fit_from_summary(summary.get("fit")) if complete else None
    nominal: NominalModel | None = None
    if fit is not None:
        no = summary.get("nominal")
        with contextlib.suppress(ConfigError, KeyError, TypeError, ValueError):
            nominal = (
                nominal_from_summary(no)
                if isinstance(no, dict)
                else NominalModel(mn_den=base.mn_den, pn_num=base.mn_den,
                                  pn_den=(fit.a2, fit.a1, 1.0))
            )
    agree = summary.get("agreement") or {}
    checks = []
    for g in summary.get("gate_checks") or []:
        with contextlib.suppress(KeyError, TypeError, ValueError):
            checks.append(_check_text(
                g["q_type"], g["cutoff_hz"], g["accepted"], g.get("small_gain_peak"),
                g.get("reasons")))
    sim_s = summary.get("simulated_s")
    return IdentifyView(
        n_positions=n_positions,
        complete=complete,
        abort_reason=st.abort_reason or None,
        positions_done=sum(1 for p in st.positions if p.complete),
        curves=tuple(curves),
        fit=fit,
        agreement_hz=st.agreement_freq_hz,
        agreement_tol=(float(agree.get("tol_db", 1.0)), float(agree.get("tol_deg", 10.0))),
        agreement_text=str(agree.get("text", "")),
        recommended_cutoff_hz=dict(st.recommended_cutoff_hz) if complete else {},
        checks=tuple(checks),
        notes=tuple(str(x) for x in summary.get("notes") or ()),
        simulated_s=float(sim_s) if isinstance(sim_s, (int, float)) else None,
        nominal=nominal,
        measured=tuple(measured),
    )


def format_result_html(view: IdentifyView | None) -> str:
    """Fit, agreement, recommended cut-offs and notes as a small HTML block."""
    if view is None:
        return "<div class='dt-identify-result' style='font-size:12px;color:#555'>No result yet."\
               "</div>"
    rows: list[str] = []
    if not view.complete:
        rows.append(
            "<div class='dt-id-incomplete' style='color:#d62728'><b>INCOMPLETE</b>: "
            f"{view.positions_done} of {view.n_positions} position(s) measured"
            + (f" ({esc(view.abort_reason)})" if view.abort_reason else "")
            + "; nothing fitted.</div>"
        )
    fit = view.fit
    if fit is not None:
        wn, wn_std = 2 * np.pi * fit.natural_freq_hz, 2 * np.pi * fit.natural_freq_std_hz
        rows.append(
            "<div class='dt-id-fit'><b>Fit Mn Pn</b> = 1/(a2 s&sup2; + a1 s + 1): "
            f"f<sub>n</sub> = <b>{fit.natural_freq_hz:.3f} &plusmn; "
            f"{fit.natural_freq_std_hz:.3f} Hz</b> "
            f"(&omega;<sub>n</sub> {wn:.2f} &plusmn; {wn_std:.2f} rad/s), "
            f"&zeta; = <b>{fit.zeta:.3f} &plusmn; {fit.zeta_std:.3f}</b>; residual "
            f"{fit.residual_rms_db:.2f} dB / {fit.residual_rms_deg:.1f} deg rms over "
            f"{fit.f_lo_hz:.3g}-{fit.f_hi_hz:.3g} Hz ({fit.n_points} points)</div>"
        )
    if view.complete:
        if view.agreement_text:
            said = view.agreement_text
            rows.append(f"<div class='dt-id-agree'>{esc(said[:1].upper() + said[1:])}</div>")
        elif view.agreement_hz is not None:
            tol_db, tol_deg = view.agreement_tol
            rows.append(
                f"<div class='dt-id-agree'>Positions agree (within {tol_db:g} dB / "
                f"{tol_deg:g} deg) below <b>{view.agreement_hz:.3g} Hz</b></div>"
            )
        else:
            rows.append("<div class='dt-id-agree'>Agreement across positions: needs at least "
                        "two positions.</div>")
        rec = view.recommended_cutoff_hz
        if rec:
            rows.append(
                "<div class='dt-id-cutoff'>Gate's recommended max cut-off with the fitted "
                f"nominal: <b>Q31 {_hz(rec.get('q31'))}</b>, <b>Q20 {_hz(rec.get('q20'))}</b>"
                "</div>"
            )
        for c in view.checks:
            rows.append(
                f"<div class='dt-id-check' style='font-size:11px;color:#555'>{esc(c)}</div>")
    for note in view.notes:
        rows.append(f"<div class='dt-id-note' style='color:#b36b00'>{esc(note)}</div>")
    if view.simulated_s is not None:
        rows.append(
            f"<div style='font-size:11px;color:#888'>{view.simulated_s:.1f} s on the rig</div>"
        )
    return "<div class='dt-identify-result' style='font-size:12px'>" + "".join(rows) + "</div>"
