"""Stability analysis of a candidate configuration and the apply gate (pure math, no I/O).

The loop analysed is exactly the one `controller.core.loop` runs at fs = cfg.rate_hz (Ts = 1/fs):

    w[k]  = (theta[k] - theta[k-1]) / Ts          backward difference of the load encoder
    r     = Cp(z) (theta_ref - theta) + ff        Cp = kp_pos (1 + ki_pos Ts/2 (z+1)/(z-1))
    u     = Cv(z) (r - w) - d_hat                 Cv = cv_kp (1 + cv_ki Ts/2 (z+1)/(z-1))
    d_hat = F1(z) w - F2(z) z^-1 u                F1, F2: the implemented SOS of `design_dob`

and u is held (ZOH) until the next tick. The nominal plant from u to w is therefore

    G(z) = (1 - z^-1)/Ts * ZOH{ Mn(s) Pn(s) / s }

(exact, built once per (nominal, rate) from a matrix exponential); it holds the one-sample
delay of a sampled loop. With C = Cv, and D = 1 - F2 z^-1 + G (Cv + F1) (DOB off: 1 + G Cv):

    speed closed loop   Gyw = G Cv / D                       (eq. 15; DOB off eq. 18)
    disturbance         Gdw = Pd (1 - F2 z^-1) / D           (eq. 16; DOB off Pd/(1 + G Cv))
    noise               Gzw = G (Cv + F1) / D                (eq. 17)
    loop at plant input L_u = G (Cv + F1) / (1 - F2 z^-1),   S = 1/(1 + L_u) = (1 - F2 z^-1)/D
    eq. 23              E_without / E_with = D / ((1 - F2 z^-1)(1 + G Cv))   (> 1: DOB helps)
    eq. 21              X = (G_m F1 - F2 z^-1) / (1 + G_m Cv)  for a measured plant G_m

Pd, the path of a load-side rate disturbance (d enters at the input of P), is taken as
G(z) / Mn(j w): the sampled plant without the drive's speed loop.

With the position loop closed the controller seen from w is C_tot = Cv (1 + Cp Ts/(1 - z^-1))
(theta = Ts/(1 - z^-1) w exactly). The gate checks the loop the controller really runs, so the
small-gain tests are evaluated twice: with the speed loop alone (the article's eq. 21, reported)
and with C_tot in place of Cv (what makes the verdict sound for the full three-loop servo).

Why the gate is sound, and what it assumes:
* nominal plant: exact closed-loop eigenvalues of the whole discrete loop (plant, w and theta,
  Cp, Cv, F1, F2 and the one-sample delay), all strictly inside the unit circle;
* measured plant G_m (no poles known): D_m = (1 + G_m C)(1 + X). If the loop without DOB,
  1 + G_m C, is stable (checked from the data by the argument principle: the phase of
  1 + G_m C must turn by m*90 deg from 0+ to Nyquist, m = integrators of C) and |X| < 1 on the
  whole unit circle, then D_m has no zero outside the circle (small-gain theorem, eq. 21-22);
* uncertainty bound |Delta| <= |W|: D_Delta = D (1 + Delta T), T = G (C + F1) / D, so
  ||W T||_inf < 1 is the exact robust-stability test for all such Delta. ||Delta Q|| < 1
  alone is not sufficient (control.md) and is only reported.
Measured continuous responses G_c(jw) become discrete by the ZOH + backward-difference
equivalent G_c(jw) e^{-jwTs} sinc^2(w Ts/2), valid well below Nyquist (aliasing neglected).
Measured data are interpolated as their ratio R = G_c / (Mn Pn) to the nominal model (log
magnitude and unwrapped phase, linear in log f), so a response equal to the model gives
Delta = 0 exactly; outside the measured band Delta is held at its value at the nearest end.
The argument-principle test assumes the grid starts where the integrators dominate and ends
where |L| << 1 (the default grid, 0.01 Hz to Nyquist, does); if not, it reports "not proven".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from controller.core.config import LoopConfig
from controller.gate.knowledge import (
    MeasuredResponse,
    PlantKnowledge,
    readonly,
)
from controller.gate.loop_model import (
    DB_3,
    TWO_PI,
    DobFilters,
    LoopBlocks,
    closed_loop_matrix,
    default_grid,
    discrete_equivalent,
    discrete_plant,
    dob_filters,
    loop_blocks,
    nominal_continuous_response,
    plant_response,
)
from controller.gate.margins import (
    Margins,
    Outputs,
    RefineTask,
    bandwidth_of,
    loop_tasks,
    margins_of,
    peak_task,
    solve,
    winding_ok,
)

__all__ = ["Analysis", "GateLimits", "SourceResult", "analyse"]

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
Verdict = Literal["accept", "reject"]


@dataclass(frozen=True)
class GateLimits:
    """Acceptance limits of the apply gate (validated on construction)."""

    phase_margin_min_deg: float = 30.0
    gain_margin_min_db: float = 6.0
    """Applies to |GM| in dB: an upper margin must exceed it, a gain-reduction margin too."""
    peak_sensitivity_max_db: float = 6.0
    small_gain_max: float = 0.8
    """Limit for eq. 21 (measured responses) and ||W T|| (uncertainty bound); < 1 is proof."""
    pole_radius_max: float = 1.0
    """Strict: every closed-loop pole radius must be < this."""
    check_measured_margins: bool = True
    """Also hold the margins of L_u computed with each measured response to the limits."""
    noise_to_command_max_db: float = 20.0
    """Peak gain from speed-measurement noise to the command, |(Cv + F1) / D|: a high Q
    cut-off makes F1 ~ Q (Mn Pn)^-1 differentiate twice and floods the drive with noise."""

    def __post_init__(self) -> None:
        def need(ok: bool, what: str) -> None:
            if not ok:
                raise ValueError(f"GateLimits: {what}")

        need(0.0 <= self.phase_margin_min_deg < 90.0, "phase_margin_min_deg in [0, 90)")
        need(0.0 <= self.gain_margin_min_db < 60.0, "gain_margin_min_db in [0, 60)")
        need(0.0 < self.peak_sensitivity_max_db < 60.0, "peak_sensitivity_max_db in (0, 60)")
        need(0.0 < self.small_gain_max <= 1.0, "small_gain_max in (0, 1]")
        need(0.0 < self.pole_radius_max <= 1.0, "pole_radius_max in (0, 1]")
        need(0.0 < self.noise_to_command_max_db <= 80.0, "noise_to_command_max_db in (0, 80]")


# --------------------------------------------------------------------------- result objects


@dataclass(frozen=True, eq=False)
class SourceResult:
    """Robustness figures for one source of plant knowledge (a measured response or a bound)."""

    name: str
    kind: Literal["measured", "bound"]
    small_gain_peak: float
    """Measured: max |X| of eq. 21 (speed loop); bound: ||W T||_inf with the speed loop."""
    small_gain_freq_hz: float
    small_gain_full_peak: float
    """The same with the position loop closed (C_tot in place of Cv)."""
    small_gain_full_freq_hz: float
    delta_q_peak: float
    """||Delta Q||_inf (display only; not a sufficient condition)."""
    delta_q_freq_hz: float
    base_loop_stable: bool
    """Measured: the loop without DOB, with and without the position loop, passes the
    argument-principle test (always True for a bound: the nominal poles cover it)."""
    full_loop_winding_ok: bool
    """Measured: the whole loop (DOB and position loop as configured) passes the argument-
    principle test on D_m = 1 - F2 z^-1 + G_m (C_tot + F1) itself. Exact where the grid is
    adequate, unlike the sufficient eq. 21; reported only, not part of the verdict."""
    margins: Margins | None
    """Margins of L_u computed with this response (None for a bound)."""
    inv_delta_db: FloatArray
    """20 log10 (1/|Delta|) on the analysis grid (for a bound: 1/|W|)."""


@dataclass(frozen=True, eq=False)
class Analysis:
    """Everything the dashboard plots and the gate decides on, for one candidate."""

    config: LoopConfig
    tau_s: float
    freq_hz: FloatArray
    open_loop: ComplexArray
    """L_u on the grid (nominal plant; DOB off: G Cv)."""
    open_loop_mag_db: FloatArray
    open_loop_phase_deg: FloatArray
    """Unwrapped."""
    closed_loop: ComplexArray
    """Gyw with the configured DOB state (eq. 15, or eq. 18 when the DOB is off)."""
    closed_loop_dob: ComplexArray
    """Gyw with the DOB on (eq. 15), whatever cfg.dob_on."""
    closed_loop_no_dob: ComplexArray
    """Gyw without the DOB (eq. 18)."""
    disturbance_dob: ComplexArray
    """Gdw with the DOB (eq. 16)."""
    disturbance_no_dob: ComplexArray
    """Gdw without the DOB (eq. 18)."""
    noise_dob: ComplexArray
    """Gzw with the DOB (eq. 17)."""
    noise_no_dob: ComplexArray
    q_mag_db: FloatArray
    """|F2| (the implemented Q) in dB."""
    rejection_db: FloatArray
    """eq. 23: 20 log10 |E_without / E_with|; > 0 where the DOB helps."""
    margins: Margins
    bandwidth_hz: float
    """-3 dB bandwidth of the speed closed loop Gyw (configured DOB state)."""
    poles: ComplexArray
    """Closed-loop eigenvalues of the whole discrete loop with the nominal plant."""
    max_pole_radius: float
    sources: tuple[SourceResult, ...]
    small_gain_peak: float
    """Largest small-gain value over all sources and both loops (nan without sources)."""
    verdict: Verdict
    reasons: tuple[str, ...]
    noise_to_command_peak_db: float = math.nan
    """max |(Cv + F1)/D| in dB: how much speed-measurement noise reaches the command."""

    @property
    def accepted(self) -> bool:
        return self.verdict == "accept"

    @property
    def gain_margin_db(self) -> float:
        return self.margins.gain_margin_db

    @property
    def phase_margin_deg(self) -> float:
        return self.margins.phase_margin_deg

    @property
    def peak_sensitivity_db(self) -> float:
        return self.margins.peak_sensitivity_db

    @property
    def delay_margin_s(self) -> float:
        return self.margins.delay_margin_s


# --------------------------------------------------------------------------- analyse


class _MeasuredModel:
    """A measured response as a function of frequency: nominal x interpolated ratio R."""

    def __init__(self, m: MeasuredResponse, cfg: LoopConfig) -> None:
        self.sampled = m.sampled
        self.cfg = cfg
        if m.sampled:
            zinv = np.exp(-1j * TWO_PI * m.freq_hz / cfg.rate_hz)
            nom = plant_response(discrete_plant(cfg.nominal, cfg.rate_hz), zinv)
        else:
            nom = nominal_continuous_response(cfg.nominal, m.freq_hz)
        ratio = m.response / nom
        self.xm = np.log(m.freq_hz)
        self.logmag = np.log(np.abs(ratio))
        self.phase = np.unwrap(np.angle(ratio))

    def ratio(self, f: FloatArray) -> ComplexArray:
        xf = np.log(f)
        return np.exp(np.interp(xf, self.xm, self.logmag) + 1j * np.interp(xf, self.xm, self.phase))

    def discrete(self, f: FloatArray, g_nominal: ComplexArray) -> tuple[ComplexArray, ComplexArray]:
        """(G_m, Delta) at f given the exact nominal G at f."""
        r = self.ratio(f)
        if self.sampled:
            return g_nominal * r, r - 1.0
        gc = nominal_continuous_response(self.cfg.nominal, f) * r
        return discrete_equivalent(gc, f, self.cfg.rate_hz), r - 1.0


def _integrators(cfg: LoopConfig, with_position: bool) -> int:
    m = 1 if cfg.cv_ki_per_s > 0 else 0
    if with_position:
        m += 1 + (1 if cfg.pos_ki_per_s > 0 else 0)
    return m


def _fmt_hz(f: float) -> str:
    return f"{f:.3g} Hz"


def analyse(
    cfg: LoopConfig,
    plant: PlantKnowledge | None = None,
    limits: GateLimits | None = None,
    freq_hz: ArrayLike | None = None,
) -> Analysis:
    """Analyse a candidate configuration and decide whether it may be applied."""
    plant = plant if plant is not None else PlantKnowledge()
    limits = limits if limits is not None else GateLimits()
    if freq_hz is None:
        f = default_grid(cfg.rate_hz)
    else:
        f = np.asarray(freq_hz, dtype=np.float64)
        if f.ndim != 1 or f.size < 8 or np.any(np.diff(f) <= 0) or f[0] <= 0:
            raise ValueError("freq_hz: need >= 8 increasing positive frequencies")
        if f[-1] >= cfg.rate_hz / 2:
            raise ValueError(f"freq_hz: must stay below Nyquist {cfg.rate_hz / 2} Hz")
    x = np.log(f)
    dob = dob_filters(cfg)
    on = cfg.dob_on
    used = dob if on else None
    bk = loop_blocks(cfg, dob, f)
    g, cv, ctot, f1, f2d = bk.g, bk.cv, bk.ctot, bk.f1, bk.f2d
    one_f2 = 1.0 - f2d
    gcv = g * cv
    d_on = one_f2 + g * (cv + f1)
    d_off = 1.0 + gcv
    mn = 1.0 / np.polyval(cfg.nominal.mn_den, 1j * TWO_PI * f)
    pd = g / mn
    gyw_on = gcv / d_on
    gyw_off = gcv / d_off
    loop = g * (cv + f1) / one_f2 if on else gcv
    gyw = gyw_on if on else gyw_off
    bound = plant.bound

    def ev(ff: FloatArray) -> Outputs:
        b = loop_blocks(cfg, used, ff)
        k_speed = b.cv + b.f1
        one = 1.0 - b.f2d
        out = {"L": b.g * k_speed / one, "gyw": b.g * b.cv / (one + b.g * k_speed)}
        if bound is not None:
            w = bound.magnitude(ff)
            k_full = b.ctot + b.f1
            out["wts"] = w * b.g * k_speed / (one + b.g * k_speed)
            out["wtf"] = w * b.g * k_full / (one + b.g * k_full)
        return out

    lt = loop_tasks(x, loop, "L")
    tasks = lt.all()
    below = np.nonzero(np.abs(gyw) < DB_3)[0]
    bw_task = None
    if below.size and below[0] > 0:
        i = int(below[0])
        bw_task = RefineTask("gyw", 0, bandwidth_of, float(x[i - 1]), float(x[i]))
        tasks.append(bw_task)
    bound_tasks: list[RefineTask] = []
    if bound is not None:
        wmag = bound.magnitude(f)
        d_full = one_f2 + g * (ctot + f1) if on else 1.0 + g * ctot
        t_speed = g * (cv + f1) / d_on if on else gyw_off
        t_full = g * (ctot + f1) / d_full
        bound_tasks = [
            peak_task(x, wmag * np.abs(t_speed), "wts"),
            peak_task(x, wmag * np.abs(t_full), "wtf"),
        ]
        tasks += bound_tasks
    solve(tasks, ev)
    margins = margins_of(lt)
    bandwidth = bw_task.freq_hz if bw_task is not None else math.nan

    poles = np.linalg.eigvals(closed_loop_matrix(cfg, used))
    max_radius = float(np.max(np.abs(poles)))

    reasons: list[str] = []
    if not max_radius < limits.pole_radius_max:
        reasons.append(
            f"closed-loop pole radius {max_radius:.5f} >= {limits.pole_radius_max:g}"
            + (" (unstable)" if max_radius >= 1.0 else "")
        )
    _margin_reasons(margins, limits, "", reasons)
    noise_cmd = np.abs((cv + f1) / d_on) if on else np.abs(cv / d_off)
    k_noise = int(np.argmax(noise_cmd))
    noise_cmd_db = float(20.0 * np.log10(noise_cmd[k_noise]))
    if not noise_cmd_db <= limits.noise_to_command_max_db:
        reasons.append(
            f"noise to command gain {noise_cmd_db:.1f} dB > {limits.noise_to_command_max_db:g} dB"
            f" (at {_fmt_hz(float(f[k_noise]))})"
        )

    sources: list[SourceResult] = []
    for m in plant.measured:
        model = _MeasuredModel(m, cfg)
        sources.append(_measured_source(cfg, dob, on, model, m.name, f, bk, limits, reasons))
    if bound is not None:
        sp, fp = bound_tasks
        dq = wmag * np.abs(f2d) if on else np.zeros_like(wmag)
        j = int(np.argmax(dq))
        sources.append(
            SourceResult(
                name=bound.name,
                kind="bound",
                small_gain_peak=sp.value,
                small_gain_freq_hz=sp.freq_hz,
                small_gain_full_peak=fp.value,
                small_gain_full_freq_hz=fp.freq_hz,
                delta_q_peak=float(dq[j]),
                delta_q_freq_hz=float(f[j]),
                base_loop_stable=True,
                full_loop_winding_ok=True,
                margins=None,
                inv_delta_db=readonly(-20.0 * np.log10(wmag)),
            )
        )
        for t, which in ((sp, "speed loop"), (fp, "with position loop")):
            if not t.value < limits.small_gain_max:
                reasons.append(
                    f"||W T|| ({which}) peaks at {t.value:.3g} at {_fmt_hz(t.freq_hz)} for bound "
                    f"{bound.name!r} >= {limits.small_gain_max:g}"
                )

    peaks = [s.small_gain_peak for s in sources] + [s.small_gain_full_peak for s in sources]
    peaks = [p for p in peaks if math.isfinite(p)]
    with np.errstate(divide="ignore"):
        rejection = 20.0 * np.log10(np.abs(d_on / (one_f2 * d_off)))
    return Analysis(
        config=cfg,
        tau_s=dob.tau_s,
        freq_hz=f,
        open_loop=readonly(loop),
        open_loop_mag_db=readonly(20.0 * np.log10(np.abs(loop))),
        open_loop_phase_deg=readonly(np.degrees(np.unwrap(np.angle(loop)))),
        closed_loop=readonly(gyw),
        closed_loop_dob=readonly(gyw_on),
        closed_loop_no_dob=readonly(gyw_off),
        disturbance_dob=readonly(pd * one_f2 / d_on),
        disturbance_no_dob=readonly(pd / d_off),
        noise_dob=readonly(g * (cv + f1) / d_on),
        noise_no_dob=readonly(gyw_off),
        q_mag_db=readonly(20.0 * np.log10(np.abs(f2d))),
        rejection_db=readonly(rejection),
        margins=margins,
        bandwidth_hz=bandwidth,
        poles=readonly(poles),
        max_pole_radius=max_radius,
        sources=tuple(sources),
        small_gain_peak=max(peaks) if peaks else math.nan,
        verdict="accept" if not reasons else "reject",
        reasons=tuple(reasons),
        noise_to_command_peak_db=noise_cmd_db,
    )


def _margin_reasons(m: Margins, limits: GateLimits, suffix: str, reasons: list[str]) -> None:
    if not m.phase_margin_deg >= limits.phase_margin_min_deg:
        reasons.append(
            f"phase margin {m.phase_margin_deg:.1f} deg < {limits.phase_margin_min_deg:g} deg"
            f" (at {_fmt_hz(m.gain_crossover_hz)}){suffix}"
        )
    if not abs(m.gain_margin_db) >= limits.gain_margin_min_db:
        reasons.append(
            f"gain margin {m.gain_margin_db:.1f} dB, |GM| < {limits.gain_margin_min_db:g} dB"
            f" (at {_fmt_hz(m.phase_crossover_hz)}){suffix}"
        )
    if not m.peak_sensitivity_db <= limits.peak_sensitivity_max_db:
        reasons.append(
            f"peak sensitivity {m.peak_sensitivity_db:.1f} dB > "
            f"{limits.peak_sensitivity_max_db:g} dB (at {_fmt_hz(m.peak_sensitivity_hz)}){suffix}"
        )


def _measured_source(
    cfg: LoopConfig,
    dob: DobFilters,
    on: bool,
    model: _MeasuredModel,
    name: str,
    f: FloatArray,
    bk: LoopBlocks,
    limits: GateLimits,
    reasons: list[str],
) -> SourceResult:
    x = np.log(f)
    gm, delta = model.discrete(f, bk.g)
    suffix = f" for response {name!r}"
    used = dob if on else None

    # The loops without DOB must be stable with this plant (base of the small-gain test).
    base_ok = winding_ok(1.0 + gm * bk.cv, _integrators(cfg, False)) and winding_ok(
        1.0 + gm * bk.ctot, _integrators(cfg, True)
    )
    if not base_ok:
        reasons.append(
            f"the loop without DOB is not proven stable{suffix} (argument principle on 1 + G C)"
        )

    d_full = 1.0 - bk.f2d + gm * (bk.ctot + bk.f1) if on else 1.0 + gm * bk.ctot
    full_ok = winding_ok(d_full, _integrators(cfg, True))

    def ev(ff: FloatArray) -> Outputs:
        b = loop_blocks(cfg, used, ff)
        g2 = model.discrete(ff, b.g)[0]
        num = g2 * b.f1 - b.f2d
        return {
            "L": g2 * (b.cv + b.f1) / (1.0 - b.f2d),
            "xs": num / (1.0 + g2 * b.cv),
            "xf": num / (1.0 + g2 * b.ctot),
        }

    loop = gm * (bk.cv + bk.f1) / (1.0 - bk.f2d) if on else gm * bk.cv
    lt = loop_tasks(x, loop, "L")
    tasks = lt.all()
    num = gm * bk.f1 - bk.f2d
    if on:
        sg = [
            peak_task(x, np.abs(num / (1.0 + gm * bk.cv)), "xs"),
            peak_task(x, np.abs(num / (1.0 + gm * bk.ctot)), "xf"),
        ]
        tasks += sg
    solve(tasks, ev)
    if on:
        sp, fp = sg
        dq = np.abs(delta * bk.f2d)
        j = int(np.argmax(dq))
        dq_peak, dq_f = float(dq[j]), float(f[j])
        for t, which in ((sp, ""), (fp, " (with position loop)")):
            if not t.value < limits.small_gain_max:
                reasons.append(
                    f"eq. 21{which} peaks at {t.value:.3g} at {_fmt_hz(t.freq_hz)}{suffix} "
                    f">= {limits.small_gain_max:g}"
                )
        peaks = (sp.value, sp.freq_hz, fp.value, fp.freq_hz)
    else:
        dq_peak = dq_f = math.nan
        peaks = (math.nan,) * 4
    margins = margins_of(lt)
    if limits.check_measured_margins:
        _margin_reasons(margins, limits, suffix, reasons)
    with np.errstate(divide="ignore"):
        inv_delta = -20.0 * np.log10(np.abs(delta))
    return SourceResult(
        name=name,
        kind="measured",
        small_gain_peak=peaks[0],
        small_gain_freq_hz=peaks[1],
        small_gain_full_peak=peaks[2],
        small_gain_full_freq_hz=peaks[3],
        delta_q_peak=dq_peak,
        delta_q_freq_hz=dq_f,
        base_loop_stable=base_ok,
        full_loop_winding_ok=full_ok,
        margins=margins,
        inv_delta_db=readonly(inv_delta),
    )


