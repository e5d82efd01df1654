"""The article's experiments (Yu et al., IEEE TIE 2022) on the simulated rig, beside its numbers.

One function per figure returns a `FigureResult`: what we ran, our numbers, the article's
(`ARTICLE`, the one table of reported values, from control.md; "not reported" where control.md
gives none), plot data, and a plain agreement statement whose verdict is computed from the
numbers (so it stays true when the rig or the loop changes). Pure: no I/O, no plotting.

Where control.md is silent we chose, and each result's `setup` says so: the split of Figs. 8
and 9, the trajectory of Fig. 10, the position-loop DOB's design, the disturbances' sizes.

The figures live by topic: `paper_common` (the article's values, the results' types),
`paper_speed` (Figs. 8-10), `paper_disturbances` (the disturbances' matrix), this module the
rest (Figs. 11, 14-17, eqs. 28-29) and the list of experiments.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from controller.core.arrays import FloatArray
from controller.core.trajectory import Trajectory, default_trajectory
from controller.sim.experiment import ExperimentResult, run_experiment
from controller.sim.linear_rig import LinearRig, PlantVariant
from controller.sim.paper_common import (
    ARTICLE,
    ARTICLE_RAMP_REDUCTION_PCT,
    FIXED_POINT,
    NOISE_LEVEL_DEG,
    ArticleValue,
    FigureResult,
    Options,
    Panel,
    Series,
    article_values,
    disturbance_note,
    fmt,
    pct_change,
    rig_run,
    thinned,
)
from controller.sim.paper_disturbances import disturbance_matrix
from controller.sim.paper_freq import (
    disturbance_responses,
    sensitivity_curves,
    suppression_curve,
)
from controller.sim.paper_speed import VARIANTS_40, fig10, figs_8_9, reversal_run, speed_step_run

__all__ = [
    "ARTICLE",
    "EXPERIMENTS",
    "VARIANTS_40",
    "ArticleValue",
    "FigureResult",
    "Options",
    "Panel",
    "Series",
    "command_noise_deg_s",
    "disturbance_matrix",
    "reversal_run",
    "run_paper",
    "speed_step_run",
]


# -- Fig. 11: disturbance responses, eqs. 16 and 18, and their ratio eq. 23 -----------------

#: Where the article's amplification "around 8 Hz" counts as reproduced: the speed loop's peak
#: of the disturbance response lies within this band.
FIG11_BAND_HZ = (5.0, 12.0)


def fig11(o: Options) -> FigureResult:
    cfg = o.cfg
    o.say("Fig. 11: disturbance responses (eqs. 16, 18) and suppression (eq. 23)")
    fc = cfg.q_cutoff_hz
    cases = (("q20", VARIANTS_40[0]), ("q31", VARIANTS_40[0]), ("q31", VARIANTS_40[1]))
    resp = [disturbance_responses(cfg, qt, fc, v) for qt, v in cases]
    supp = [suppression_curve(cfg, qt, fc, v) for qt, v in cases]
    rows = []
    for r, c in zip(resp, supp, strict=True):
        e1_db, e1_hz = r.peak("e1")
        e2_db, e2_hz = r.peak("e2")
        rows.append((f"{c.q_type.upper()} {c.cutoff_hz:g} Hz", c.plant, fmt(c.at(0.1), ".1f"),
                     fmt(c.crossover_hz, ".3g"), fmt(c.waterbed_db, ".2f"),
                     fmt(c.waterbed_hz, ".3g"), fmt(e2_db, ".2f"), fmt(e2_hz, ".3g"),
                     fmt(e1_db, ".2f"), fmt(e1_hz, ".3g")))
    nominal31 = resp[1]
    panels = (
        Panel("Disturbance response |Gdw|: E1 (eq. 18, no DOB) and E2 (eq. 16, DOB)",
              "frequency Hz", "dB", (
                  Series("E1: no DOB (eq. 18)", nominal31.freq_hz, nominal31.e1_db),
                  *(Series(f"E2: DOB {r.q_type.upper()} {fc:g} Hz, {r.plant} (eq. 16)",
                           r.freq_hz, r.e2_db) for r in resp)),
              logx=True, hlines=(("0 dB", 0.0),)),
        Panel("Disturbance suppression |E1/E2| (eq. 23; > 0 dB: the DOB rejects better)",
              "frequency Hz", "dB", tuple(
                  Series(f"{c.q_type.upper()} {c.cutoff_hz:g} Hz, {c.plant}", c.freq_hz,
                         c.gain_db) for c in supp), logx=True, hlines=(("0 dB", 0.0),)),
    )
    e2_db, e2_hz = nominal31.peak("e2")
    e1_db, e1_hz = nominal31.peak("e1")
    q31 = supp[1]
    lo, hi = FIG11_BAND_HZ
    ok = lo <= e2_hz <= hi
    size = ("above 0 dB: an amplification of the disturbance" if e2_db > 0.0 else
            "below 0 dB: a resonance of the disturbance response, not an amplification; its "
            "size depends on Cv, which the article does not give")
    reason = (
        f"The article shows the DOB's disturbance response (eq. 16) amplifying around 8 Hz. "
        f"Ours, Q31 at {fc:g} Hz on P = Pn: eq. 16 peaks at {e2_db:+.2f} dB at "
        f"{e2_hz:.3g} Hz ({size}); the plain loop's eq. 18 peaks at {e1_db:+.2f} dB at "
        f"{e1_hz:.3g} Hz. The peak belongs to the speed loop Cv M P (its sensitivity peak near "
        f"the {cfg.cv_kp:g} (1 + {cfg.cv_ki_per_s:g}/s) crossover), present with and without "
        "the DOB: "
        + (f"its frequency agrees with the article's ({lo:g}-{hi:g} Hz). " if ok else
           f"at {e2_hz:.3g} Hz it is outside {lo:g}-{hi:g} Hz, so it does not match the "
           "article's 8 Hz (the article's Cv is not given; the peak moves with Cv's "
           "crossover). ")
        + f"The DOB's own price is eq. 23: |E1/E2| = 1/|1 - Q| for P = Pn, above 0 dB (the "
        f"DOB rejects better) up to {q31.crossover_hz:.3g} Hz and down to "
        f"{q31.waterbed_db:+.2f} dB at {q31.waterbed_hz:.3g} Hz, near the cut-off (the "
        "waterbed); at 0.1 Hz it rejects "
        f"{q31.at(0.1):+.1f} dB better than the plain loop."
    )
    nums = {"e2_peak_hz": e2_hz, "e2_peak_db": e2_db, "e1_peak_hz": e1_hz, "e1_peak_db": e1_db,
            "q31_waterbed_hz": q31.waterbed_hz, "q31_waterbed_db": q31.waterbed_db,
            "q20_waterbed_db": supp[0].waterbed_db, "q31_at_0.1hz_db": q31.at(0.1),
            "q31_helps_below_hz": q31.crossover_hz}
    return FigureResult(
        "Fig. 11", "Disturbance responses (eqs. 16, 18) and suppression (eq. 23), Q20 and Q31",
        f"Continuous, Gdw with the DOB E2 = P (1 - Q)/D (eq. 16) and without E1 = P/(1 + Cv M "
        f"P) (eq. 18), D = 1 + Cv M P + (P Pn^-1 - 1) Q; their ratio E1/E2 is eq. 23. Cv = "
        f"{cfg.cv_kp:g} (1 + {cfg.cv_ki_per_s:g}/s), M = Mn, P = Pn and P = 1.4 Pn R (5 Hz "
        f"mode), cut-off {fc:g} Hz.",
        ("Q", "plant", "E1/E2 at 0.1 Hz dB", "E1/E2 falls to 0 dB at Hz", "waterbed dB",
         "waterbed Hz", "E2 peak dB", "E2 peak Hz", "E1 peak dB", "E1 peak Hz"), tuple(rows),
        panels, "agrees" if ok else "disagrees", reason, nums)


# -- Figs. 14-15: sine and step (the existing tests) ------------------------------------------

#: Command noise: the RMS of the speed command above this frequency (the DOB's price, eq. 17).
NOISE_BAND_HZ = 20.0


def command_noise_deg_s(r: ExperimentResult, band_hz: float = NOISE_BAND_HZ) -> float:
    """RMS of the command's spectrum above `band_hz` over the metrics window (deg/s)."""
    m = r.t_s >= r.metrics.window_s[0]
    u = r.command_deg_s[m]
    spec = np.fft.rfft(u - np.mean(u))
    f = np.fft.rfftfreq(len(u), r.t_s[1] - r.t_s[0])
    p = np.abs(spec[f >= band_hz]) ** 2
    # Parseval: sum over the one-sided bins (twice, except DC/Nyquist, ignored here) / n^2.
    return float(math.sqrt(2.0 * float(np.sum(p))) / len(u))


def fig14(o: Options) -> FigureResult:
    cfg = o.cfg
    dur = 10.0 if o.quick else 30.0
    traj = default_trajectory("sine")
    runs = {
        "no DOB": rig_run(o, cfg.with_(dob_on=False, ff_on=False), traj, dur, "Fig. 14: no DOB"),
        "DOB": rig_run(o, cfg.with_(dob_on=True, ff_on=False), traj, dur, "Fig. 14: DOB"),
        "DOB + FF": rig_run(o, cfg.with_(dob_on=True, ff_on=True), traj, dur,
                             "Fig. 14: DOB + FF"),
    }
    art = {(a.run, a.quantity.split(",")[0]): a for a in article_values("Fig. 14")}
    noise = {k: command_noise_deg_s(r) for k, r in runs.items()}
    rows = tuple(
        (k, fmt(r.peak_error_deg), fmt(r.rmse_deg), fmt(noise[k], ".4f"),
         art[(k, "peak |e|")].text, art[(k, "RMSE")].text)
        for k, r in runs.items()
    )
    panel = Panel("Position error, 5 sin(0.5 t) deg", "time s", "error deg", tuple(
        Series(k, thinned(r.t_s), thinned(r.error_deg)) for k, r in runs.items()))
    off, dob, ff = (runs[k].rmse_deg for k in ("no DOB", "DOB", "DOB + FF"))
    p_off, p_dob = runs["no DOB"].peak_error_deg, runs["DOB"].peak_error_deg
    o.say("Fig. 14: the reference response alone (linear nominal loop)")
    lag = run_experiment(cfg.with_(dob_on=False, ff_on=False), traj, dur,
                         rig=LinearRig(VARIANTS_40[0], cfg.nominal, rate_hz=cfg.rate_hz),
                         settle_s=None).rmse_deg
    dob_ok = dob < off and p_dob < p_off
    ff_ok = dob / ff >= 2.0
    agree = "agrees" if dob_ok and ff_ok else "partly agrees" if ff_ok else "disagrees"
    reason = (
        f"Article: the DOB lowers the RMSE {pct_change(0.0207, 0.0231):+.0f} % and the peak "
        f"{pct_change(0.05, 0.1):+.0f} %; feedforward then cuts the RMSE {0.0207 / 0.0052:.1f}x. "
        f"Ours: the DOB changes the RMSE {pct_change(dob, off):+.1f} % and the peak "
        f"{pct_change(p_dob, p_off):+.1f} %; feedforward cuts the RMSE {dob / ff:.1f}x. "
        + f"The linear nominal loop without any disturbance (the reference response alone) "
        f"already has RMSE {lag:.4f} deg: that part is the reference lag, and eq. 15 = eq. 18 "
        "(with P = Pn the DOB leaves Gyw = Cv M P / (1 + Cv M P) unchanged), so no DOB "
        "setting can remove it; feedforward can. The DOB can act only on the rest, the error "
        "the disturbances cause (the Disturbances section isolates it: run with minus run "
        "without, same seed), and there only where 1/|1 - Q| > 1 (Fig. 11). "
        + ("The DOB's gain is reproduced." if dob_ok else
           "The DOB's gain is not reproduced on this rig and loop.")
        + f" Its price: the command's RMS above {NOISE_BAND_HZ:g} Hz goes from "
        f"{noise['no DOB']:.4f} to {noise['DOB']:.4f} deg/s."
        + (" Feedforward's gain is reproduced." if ff_ok else " Feedforward's is not.")
    )
    return FigureResult(
        "Fig. 14", "Sine tracking 5 sin(0.5 t) deg: no DOB, DOB, DOB + feedforward",
        f"Simulated rig, {dur:g} s, metrics over 2 s-end, {cfg.q_type.upper()} at "
        f"{cfg.q_cutoff_hz:g} Hz, {disturbance_note(o)}.",
        ("run", "peak |e| deg", "RMSE deg", f"command > {NOISE_BAND_HZ:g} Hz RMS deg/s",
         "article peak", "article RMSE"), rows, (panel,),
        agree, reason, {"rmse_off": off, "rmse_dob": dob, "rmse_ff": ff, "peak_off": p_off,
                        "peak_dob": p_dob, "rmse_reference_lag": lag,
                        "noise_off": noise["no DOB"], "noise_dob": noise["DOB"]})


def fig15(o: Options) -> FigureResult:
    cfg = o.cfg
    dur = 3.0 if o.quick else 5.0
    traj = default_trajectory("step")
    runs = {
        "no DOB": rig_run(o, cfg.with_(dob_on=False), traj, dur, "Fig. 15: step, no DOB"),
        "DOB": rig_run(o, cfg.with_(dob_on=True), traj, dur, "Fig. 15: step, DOB"),
    }
    rows = tuple(
        (k, fmt(r.metrics.rise_time_s or math.nan, ".3f"),
         fmt(r.metrics.overshoot_pct or 0.0, ".1f"), fmt(r.metrics.static_error_deg or math.nan))
        for k, r in runs.items()
    )
    panel = Panel("5 deg step at 0.5 s", "time s", "position deg", tuple(
        Series(k, thinned(r.t_s), thinned(r.pos_deg)) for k, r in runs.items()))
    r_off = runs["no DOB"].metrics.rise_time_s or math.nan
    r_on = runs["DOB"].metrics.rise_time_s or math.nan
    faster = r_on < 0.97 * r_off
    reason = (
        f"Article: the step is faster with the DOB (no number). Ours: rise time 10-90 % "
        f"{r_off:.3f} s without, {r_on:.3f} s with the DOB ({pct_change(r_on, r_off):+.1f} %). "
        + ("Faster with the DOB: agrees." if faster else
           "Not faster by 3 % or more: the rise is set by the position and rate loops; the "
           "DOB at this cut-off barely acts within the rise time.")
    )
    return FigureResult(
        "Fig. 15", "Step response (5 deg)",
        f"Simulated rig, {dur:g} s, {cfg.q_type.upper()} at {cfg.q_cutoff_hz:g} Hz, "
        f"{disturbance_note(o)}.",
        ("run", "rise 10-90 % s", "overshoot %", "static error deg"), rows, (panel,),
        "agrees" if faster else "disagrees", reason, {"rise_off": r_off, "rise_on": r_on})


# -- Fig. 16: the Q31 bandwidth sweep -----------------------------------------------------------

SWEEP_HZ = (0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 2.0, 4.0)
SWEEP_HZ_QUICK = (0.2, 0.5, 2.0)


def fig16(o: Options) -> FigureResult:
    cfg = o.cfg
    dur = 8.0 if o.quick else 30.0
    traj = default_trajectory("sine")
    grid = SWEEP_HZ_QUICK if o.quick else SWEEP_HZ
    off: dict[bool, ExperimentResult] = {}
    sweeps: dict[bool, list[ExperimentResult]] = {}
    for ff in (False, True):
        tag = " + FF" if ff else ""
        off[ff] = rig_run(o, cfg.with_(dob_on=False, ff_on=ff), traj, dur,
                           f"Fig. 16: DOB off{tag}")
        sweeps[ff] = [
            rig_run(o, cfg.with_(dob_on=True, ff_on=ff, q_type="q31", q_cutoff_hz=fc), traj,
                     dur, f"Fig. 16: Q31 at {fc:g} Hz{tag}")
            for fc in grid
        ]
    rows = tuple(
        (label, fmt(off[False].peak_error_deg if r is None else r[0].peak_error_deg),
         fmt(off[False].rmse_deg if r is None else r[0].rmse_deg),
         fmt(off[True].peak_error_deg if r is None else r[1].peak_error_deg),
         fmt(off[True].rmse_deg if r is None else r[1].rmse_deg))
        for label, r in (("DOB off", None), *(
            (f"Q31 {fc:g} Hz", (a, b))
            for fc, a, b in zip(grid, sweeps[False], sweeps[True], strict=True))))
    x = np.array(grid, float)
    panels = tuple(
        Panel(f"{name} against the Q31 cut-off", "cut-off Hz", unit, (
            Series("DOB on", x, np.array([get(r) for r in sweeps[False]])),
            Series("DOB on + FF", x, np.array([get(r) for r in sweeps[True]]))), logx=True,
            hlines=(("DOB off", get(off[False])), ("DOB off + FF", get(off[True]))))
        for name, unit, get in (
            ("RMSE", "RMSE deg", lambda r: r.rmse_deg),
            ("Peak |e|", "peak |e| deg", lambda r: r.peak_error_deg)))
    best: dict[bool, tuple[float, float]] = {}
    for ff in (False, True):
        i = int(np.argmin([r.rmse_deg for r in sweeps[ff]]))
        best[ff] = (grid[i], sweeps[ff][i].rmse_deg)
    best_hz, best_rmse = best[False]
    near = 0.35 <= best_hz <= 0.7
    beats = best_rmse < off[False].rmse_deg
    agree = "agrees" if near and beats else "partly agrees" if near else "disagrees"
    ff_hz, ff_rmse = best[True]

    def verdict(ff: bool) -> str:
        hz, r = best[ff]
        o_r = off[ff].rmse_deg
        return (f"lowest RMSE at {hz:g} Hz ({r:.4f} deg, {pct_change(r, o_r):+.1f} % against "
                f"{o_r:.4f} deg with the DOB off)")

    reason = (
        f"Article: 0.5 Hz was the best Q31 cut-off tried. Ours without feedforward: "
        f"{verdict(False)}; with feedforward: {verdict(True)}. "
        + ("Without feedforward the best DOB beats the DOB off. " if beats else
           "Without feedforward no cut-off beats the DOB off: the error is mostly the "
           "reference lag, which no DOB changes (eq. 15 = eq. 18). ")
        + ("With feedforward the lag is gone and the error left is what disturbances cause, "
           "where the DOB can act; " if ff_rmse < off[True].rmse_deg else
           "With feedforward too no cut-off beats the DOB off; ")
        + f"larger cut-offs cost: at {grid[-1]:g} Hz RMSE {sweeps[False][-1].rmse_deg:.4f} / "
        f"{sweeps[True][-1].rmse_deg:.4f} deg (without / with feedforward)."
    )
    nums = {"best_hz": best_hz, "best_rmse": best_rmse, "off_rmse": off[False].rmse_deg,
            "ff_best_hz": ff_hz, "ff_best_rmse": ff_rmse, "ff_off_rmse": off[True].rmse_deg}
    return FigureResult(
        "Fig. 16", "Position error for several Q31 bandwidths, without and with feedforward",
        f"Sine 5 sin(0.5 t) deg, {dur:g} s on the simulated rig, {disturbance_note(o)}.",
        ("run", "peak |e| deg", "RMSE deg", "peak |e| + FF deg", "RMSE + FF deg"), rows,
        panels, agree, reason, nums)


# -- Fig. 17: fixed point 40 deg and ramps ------------------------------------------------------

RAMP_SLOPES = (0.2, 1.0, 5.0)


def fig17(o: Options) -> FigureResult:
    cfg = o.cfg
    hold_dur = 6.0 if o.quick else 20.0
    ramp_dur = 8.0 if o.quick else 30.0
    hold = FIXED_POINT
    h = {d: rig_run(o, cfg.with_(dob_on=d), hold, hold_dur,
                     f"Fig. 17: to 40 deg and hold, DOB {'on' if d else 'off'}")
         for d in (False, True)}
    slopes = (1.0,) if o.quick else RAMP_SLOPES
    ramps = {
        (s, d): rig_run(o, cfg.with_(dob_on=d), Trajectory(kind="ramp", slope_deg_s=s),
                         ramp_dur, f"Fig. 17: ramp {s:g} t deg, DOB {'on' if d else 'off'}")
        for s in slopes for d in (False, True)
    }
    s_off = h[False].metrics.static_error_deg or math.nan
    s_on = h[True].metrics.static_error_deg or math.nan
    rows: list[tuple[str, ...]] = [
        ("fixed point 40 deg: static error (mean |e|, last quarter)", fmt(s_off, ".5f"),
         fmt(s_on, ".5f"), fmt(pct_change(s_on, s_off), "+.1f"), "about 2x smaller with DOB"),
    ]
    red: dict[float, float] = {}
    measurable: list[float] = []
    for s in slopes:
        a, b = ramps[(s, False)].rmse_deg, ramps[(s, True)].rmse_deg
        red[s] = -pct_change(b, a)
        if max(a, b) >= NOISE_LEVEL_DEG:
            measurable.append(s)
        rows.append((f"ramp {s:g} t deg: RMSE 2 s-end", fmt(a, ".5f"), fmt(b, ".5f"),
                     fmt(pct_change(b, a), "+.1f") if s in measurable else "both at noise level",
                     "5-25 % smaller (low/medium speed)"))
    def tail(r: ExperimentResult, from_s: float) -> tuple[FloatArray, FloatArray]:
        m = r.t_s >= from_s
        return thinned(r.t_s[m]), thinned(r.error_deg[m])

    panels = (
        Panel("At the fixed point 40 deg (after the move)", "time s", "error deg", tuple(
            Series(f"DOB {'on' if d else 'off'}", *tail(r, 2.5)) for d, r in h.items())),
        *(Panel(f"Ramp {s:g} t deg", "time s", "error deg", tuple(
            Series(f"DOB {'on' if d else 'off'}", *tail(ramps[(s, d)], 2.0))
            for d in (False, True))) for s in slopes),
    )
    ratio = s_off / s_on if s_on > 0 else math.inf
    static_ok = ratio >= 1.5
    lo, _hi = ARTICLE_RAMP_REDUCTION_PCT
    ramp_ok = any(red[s] >= lo for s in measurable)
    ramp_noise = 1.0 not in measurable
    agree = ("agrees" if static_ok and ramp_ok else
             "partly agrees" if static_ok or ramp_ok else "disagrees")
    reason = (
        f"Article: static error about 2x smaller with the DOB; ramp error 5-25 % smaller. "
        f"Ours: static error {s_off:.5f} -> {s_on:.5f} deg ({ratio:.2f}x); ramp RMSE "
        "change with the DOB: "
        + ", ".join(f"{s:g} t {-red[s]:+.1f} %" if s in measurable else
                    f"{s:g} t none measurable" for s in slopes) + ". "
        + ("" if static_ok else
           "At standstill the error is a stick-slip limit cycle of the position PI against "
           "static friction, with and without the DOB; the DOB does not halve it. ")
        + (f"On the 1.0 t ramp both errors are below {NOISE_LEVEL_DEG:g} deg RMS, at the "
           "encoder's noise level: at constant speed friction is a constant the integrators "
           "remove, and the tooth ripple is slow; there is nothing left for the DOB. "
           if ramp_noise else "")
        + (f"At {max(slopes):g} deg/s the error is the rig's tooth ripple at 30 per rev = "
           f"{max(slopes) / 12.0:.2f} Hz, near the Q cut-off, where the DOB amplifies "
           f"({-red[max(slopes)]:+.0f} %: the waterbed of Fig. 11). "
           if max(slopes) in measurable and red[max(slopes)] < 0 and max(slopes) >= 4.0 else "")
        + ("" if ramp_ok else
           "At no ramp speed with a measurable error does the DOB cut it by 5 %"
           + (" (at 0.2 deg/s the error is stick-slip creep)." if 0.2 in measurable else "."))
    )
    nums = {"static_off": s_off, "static_on": s_on, "ramp1_reduction_pct": red[1.0]}
    return FigureResult(
        "Fig. 17", "Fixed point 40 deg and ramp 1.0 t deg",
        f"Simulated rig: from 0 to 40 deg at 0.5 s and hold, {hold_dur:g} s (static error: "
        f"mean |e| over the last quarter), ramps {ramp_dur:g} s, "
        f"{cfg.q_type.upper()} at {cfg.q_cutoff_hz:g} Hz, {disturbance_note(o)}.",
        ("test", "no DOB", "DOB", "change %", "article"), tuple(rows), panels, agree, reason,
        nums)


# -- Eqs. 28-29: parameter sensitivity ---------------------------------------------------------

SENSITIVITY_VARIANTS = (
    *VARIANTS_40,
    PlantVariant("P = 1.2 Pn R (15 Hz mode)", 1.2, 15.0, 0.05, 12.0, 0.05),
    PlantVariant("P = 0.8 Pn R (15 Hz mode)", 0.8, 15.0, 0.05, 12.0, 0.05),
)


def sensitivity(o: Options) -> FigureResult:
    cfg = o.cfg.with_(dob_on=True)
    o.say("Eqs. 28-29: parameter sensitivity")
    curves = [sensitivity_curves(cfg, v) for v in SENSITIVITY_VARIANTS]
    rows = []
    for c in curves:
        s1, s2 = c.at(0.1)
        s1b, s2b = c.at(1.0)
        rows.append((c.plant, fmt(s1, ".1f"), fmt(s2, ".1f"), fmt(s1b, ".1f"), fmt(s2b, ".1f"),
                     fmt(c.dob_less_sensitive_below_hz, ".3g"), fmt(c.worst_excess_db, "+.2f")))
    panels = tuple(
        Panel(f"Sensitivity to P, {c.plant}", "frequency Hz", "dB", (
            Series("|S_P'^W1| (no DOB)", c.freq_hz, c.s1_db),
            Series("|S_P'^W2| (DOB)", c.freq_hz, c.s2_db)), logx=True)
        for c in (curves[0], curves[1])
    )
    low = all(c.at(0.1)[1] < c.at(0.1)[0] for c in curves)
    worst = max(c.worst_excess_db for c in curves)
    below = min(c.dob_less_sensitive_below_hz for c in curves)
    reason = (
        "Article: the DOB loop is less sensitive to P -> P'. Ours: "
        + ("at 0.1 Hz |S_P'^W2| < |S_P'^W1| for every plant" if low else
           "NOT less sensitive at 0.1 Hz for every plant")
        + f"; the advantage holds up to {below:.3g} Hz for all of them, above which the DOB "
        f"loop is up to {worst:.2f} dB more sensitive (the waterbed of 1 - Q)."
    )
    nums = {"worst_excess_db": worst, "less_sensitive_below_hz": below}
    for i, c in enumerate(curves):
        nums[f"s1_0.1hz_{i}"], nums[f"s2_0.1hz_{i}"] = c.at(0.1)
    return FigureResult(
        "Eqs. 28-29", "Parameter sensitivity |S_P'^W2| against |S_P'^W1|",
        f"Continuous, at perturbed plants P' (40 % + 5 Hz mode, 20 % + 15 Hz mode: control.md's "
        f"two cases; zeros at 0.8x the mode, damping 0.05), {cfg.q_type.upper()} at "
        f"{cfg.q_cutoff_hz:g} Hz: S1 = 1/(1 + Cv M P'), S2 = (1 - Q)/D(P').",
        ("plant", "S1 0.1 Hz dB", "S2 0.1 Hz dB", "S1 1 Hz dB", "S2 1 Hz dB",
         "S2 <= S1 below Hz", "worst S2 - S1 dB"), tuple(rows), panels,
        "agrees" if low else "disagrees", reason, nums)


def _f89(o: Options) -> tuple[FigureResult, ...]:
    return figs_8_9(o)


#: `dobtune experiment NAME`: name -> function returning the figure results.
EXPERIMENTS: dict[str, Callable[[Options], tuple[FigureResult, ...]]] = {
    "fig8": _f89,
    "fig9": _f89,
    "fig10": lambda o: (fig10(o),),
    "fig11": lambda o: (fig11(o),),
    "fig14": lambda o: (fig14(o),),
    "fig15": lambda o: (fig15(o),),
    "fig16": lambda o: (fig16(o),),
    "fig17": lambda o: (fig17(o),),
    "sensitivity": lambda o: (sensitivity(o),),
    "disturbances": lambda o: (disturbance_matrix(o),),
}


def run_paper(o: Options) -> tuple[FigureResult, ...]:
    """Every experiment, in the article's order."""
    out = list(figs_8_9(o))
    for f in (fig10, fig11, fig14, fig15, fig16, fig17, sensitivity, disturbance_matrix):
        out.append(f(o))
    return tuple(out)
