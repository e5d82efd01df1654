"""The article's experiments (Yu et al., IEEE TIE 2022) on the simulated rig, beside its numbers.

One function per figure returns a `FigureResult`: what we ran, our numbers, the article's
(`ARTICLE`, the one table of reported values, from control.md; "not reported" where control.md
gives none), plot data, and a plain agreement statement whose verdict is computed from the
numbers (so it stays true when the rig or the loop changes). Pure: no I/O, no plotting.

Where control.md is silent we chose, and each result's `setup` says so: the split of Figs. 8
and 9, the trajectory of Fig. 10, the position-loop DOB's design, the disturbances' sizes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory, default_trajectory
from controller.sim.experiment import ExperimentResult, Loop, run_experiment
from controller.sim.linear_rig import LinearRig, PlantVariant
from controller.sim.paper_freq import (
    cutoff_for_waterbed_at,
    sensitivity_curves,
    suppression_curve,
)
from controller.sim.position_dob import PositionDobLoop
from controller.sim.rig_disturbances import ScheduledRig, build_rig, rig_setup
from controller.sim.sim_rig import RigFaults

__all__ = [
    "ARTICLE",
    "EXPERIMENTS",
    "ArticleValue",
    "FigureResult",
    "Options",
    "Panel",
    "Series",
    "run_paper",
]

FloatArray = npt.NDArray[np.float64]
Progress = Callable[[str], None]


@dataclass(frozen=True)
class ArticleValue:
    figure: str
    quantity: str
    run: str
    value: float | None
    """None: control.md reports no number for it."""
    unit: str = ""
    note: str = ""

    @property
    def text(self) -> str:
        if self.value is None:
            return "not reported" + (f" ({self.note})" if self.note else "")
        return f"{self.value:g} {self.unit}".strip() + (f" ({self.note})" if self.note else "")


#: Everything the article reports that we compare with (control.md, "The article's
#: experiments" and "Stability and robustness"). The figure of each value follows issue 15's
#: list (control.md's table names no figure).
ARTICLE: tuple[ArticleValue, ...] = (
    ArticleValue("Fig. 8", "rate response, 40 % error + 5 Hz mode, disturbance at 1 s", "all",
                 None),
    ArticleValue("Fig. 9", "rate response, 40 % error + 5 Hz mode, disturbance at 1 s", "all",
                 None),
    ArticleValue("Fig. 10", "error at the velocity reversal, 6-6.5 s", "all", None,
                 note="control.md: the reversal spike 'is what the DOB removes'"),
    ArticleValue("Fig. 11", "frequency of the waterbed (amplification) of eq. 23", "Q20, Q31",
                 8.0, "Hz", "'around 8 Hz'; its size and the cut-off used are not reported"),
    ArticleValue("Fig. 14", "peak |e|, 5 sin(0.5 t) deg", "no DOB", 0.1, "deg"),
    ArticleValue("Fig. 14", "peak |e|, 5 sin(0.5 t) deg", "DOB", 0.05, "deg"),
    ArticleValue("Fig. 14", "peak |e|, 5 sin(0.5 t) deg", "DOB + FF", None),
    ArticleValue("Fig. 14", "RMSE, 5 sin(0.5 t) deg", "no DOB", 0.0231, "deg"),
    ArticleValue("Fig. 14", "RMSE, 5 sin(0.5 t) deg", "DOB", 0.0207, "deg"),
    ArticleValue("Fig. 14", "RMSE, 5 sin(0.5 t) deg", "DOB + FF", 0.0052, "deg"),
    ArticleValue("Fig. 15", "step response", "DOB", None, note="'faster with DOB', no number"),
    ArticleValue("Fig. 16", "best Q31 cut-off among those tried", "DOB", 0.5, "Hz",
                 "the other cut-offs tried are not reported"),
    ArticleValue("Fig. 17", "static error at 40 deg, no DOB / DOB", "ratio", 2.0, "x",
                 "'about 2x smaller' with DOB"),
    ArticleValue("Fig. 17", "ramp 1.0 t deg error reduction with DOB", "DOB", None,
                 note="'5-25 % smaller at low/medium speed'"),
    ArticleValue("Eqs. 28-29", "|S_P'^W2| against |S_P'^W1|", "DOB", None,
                 note="'the DOB loop is less sensitive to P -> P''"),
)

#: The reported lower and upper bound of Fig. 17's ramp error reduction (5-25 %).
ARTICLE_RAMP_REDUCTION_PCT = (5.0, 25.0)


def article_values(figure: str) -> tuple[ArticleValue, ...]:
    return tuple(a for a in ARTICLE if a.figure == figure)


@dataclass(frozen=True)
class Series:
    label: str
    x: FloatArray
    y: FloatArray


@dataclass(frozen=True)
class Panel:
    title: str
    xlabel: str
    ylabel: str
    series: tuple[Series, ...]
    logx: bool = False
    hlines: tuple[tuple[str, float], ...] = ()
    vspan: tuple[float, float] | None = None
    xticks: tuple[str, ...] = ()
    """Category names for x = 0, 1, ... (empty: a numeric axis)."""


@dataclass(frozen=True)
class FigureResult:
    figure: str
    """'Fig. 8' ... 'Fig. 17', 'Eqs. 28-29', 'Disturbances'."""
    title: str
    setup: str
    columns: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    panels: tuple[Panel, ...]
    agreement: str
    """'agrees', 'disagrees', 'partly agrees' or 'no number to compare'."""
    reason: str
    numbers: dict[str, float] = field(default_factory=dict)

    @property
    def article(self) -> tuple[ArticleValue, ...]:
        return article_values(self.figure)


@dataclass(frozen=True)
class Options:
    cfg: LoopConfig = field(default_factory=LoopConfig)
    disturbances: tuple[str, ...] = ()
    quick: bool = False
    seed: int = 0
    progress: Progress | None = None

    def say(self, what: str) -> None:
        if self.progress is not None:
            self.progress(what)


def _f(v: float, spec: str = ".4f") -> str:
    return "-" if not math.isfinite(v) else format(v, spec)


def _pct(new: float, old: float) -> float:
    return 100.0 * (new - old) / old if old else math.nan


def _thin(x: FloatArray, n: int = 2000) -> FloatArray:
    step = max(1, len(x) // n)
    return np.asarray(x[::step], float)


def _rig_run(
    o: Options, cfg: LoopConfig, traj: Trajectory, duration_s: float, label: str,
    *, names: tuple[str, ...] | None = None, loop: Loop | None = None,
    settle_s: float | None = None,
) -> ExperimentResult:
    o.say(label)
    setup = rig_setup(o.disturbances if names is None else names)
    rig = build_rig(setup, rate_hz=cfg.rate_hz, seed=o.seed,
                    initial_position_deg=traj.at(0.0)[0])
    return run_experiment(cfg, traj, duration_s, seed=o.seed, disturbance_name=setup.label,
                          rig=rig, loop=loop, settle_s=settle_s)


def _dist_note(o: Options) -> str:
    return ("disturbances: " + ", ".join(o.disturbances)) if o.disturbances else (
        "no added disturbance (the reference rig's own tooth ripple, friction and backlash)")


# -- Figs. 8-9: the rate loop on uncertain linear plants --------------------------------------

#: The article's second uncertainty case (control.md): 40 % low-frequency error and an
#: unmodelled mode at 5 Hz; the pair of zeros (4 Hz) and the dampings (0.05) are our choice.
VARIANTS_40 = (
    PlantVariant("nominal P = Pn"),
    PlantVariant("P = 1.4 Pn R (5 Hz mode)", 1.4, 5.0, 0.05, 4.0, 0.05),
    PlantVariant("P = 0.6 Pn R (5 Hz mode)", 0.6, 5.0, 0.05, 4.0, 0.05),
)
SPEED_STEP_DEG_S = 10.0
DISTURBANCE_DEG_S = 5.0
DISTURBANCE_TIME_S = 1.0


#: A faster DOB next to the configured one, to show what the cut-off buys and costs.
FAST_CUTOFF_HZ = 4.0


@dataclass(frozen=True)
class SpeedRun:
    variant: str
    dob: str
    t_s: FloatArray
    ref_deg_s: FloatArray
    speed_deg_s: FloatArray

    @property
    def stable(self) -> bool:
        return bool(np.all(np.isfinite(self.speed_deg_s))) and float(
            np.max(np.abs(self.speed_deg_s))) < 1e3

    def overshoot_pct(self) -> float:
        m = self.t_s < DISTURBANCE_TIME_S
        return max(0.0, (float(np.max(self.speed_deg_s[m])) / SPEED_STEP_DEG_S - 1.0) * 100.0)

    def rise_s(self) -> float:
        y = self.speed_deg_s / SPEED_STEP_DEG_S
        i10, i90 = int(np.argmax(y >= 0.1)), int(np.argmax(y >= 0.9))
        return float(self.t_s[i90] - self.t_s[i10]) if y[i90] >= 0.9 else math.nan

    def after(self) -> FloatArray:
        m = self.t_s >= DISTURBANCE_TIME_S
        return np.asarray((self.ref_deg_s - self.speed_deg_s)[m], float)

    def peak_dev_deg_s(self) -> float:
        return float(np.max(np.abs(self.after())))

    def iae_deg(self) -> float:
        """Integral of |r - w| after the disturbance (deg): how much motion it disturbs."""
        return float(np.sum(np.abs(self.after())) * (self.t_s[1] - self.t_s[0]))

    def offset_deg(self) -> float:
        """Integral of r - w after the disturbance: the position offset it leaves (deg)."""
        return float(np.sum(self.after()) * (self.t_s[1] - self.t_s[0]))


def speed_step_run(
    cfg: LoopConfig, variant: PlantVariant, duration_s: float,
    *, disturbance_deg_s: float = DISTURBANCE_DEG_S,
) -> SpeedRun:
    """The rate loop (Cv, and the DOB when cfg.dob_on) on the linear plant `variant`: a speed
    reference step at 0 s and a rate disturbance step at 1 s (the runtime's `tick_speed`)."""
    rig = LinearRig(
        variant, cfg.nominal, rate_hz=cfg.rate_hz,
        speed_disturbance=lambda t: disturbance_deg_s if t >= DISTURBANCE_TIME_S else 0.0,
    )
    loop = ServoLoop(LoopCoefficients.build(cfg))
    n = round(duration_s * cfg.rate_hz)
    w = np.empty(n)
    for k in range(n):
        _, wk = rig.read()
        w[k] = wk
        if not abs(wk) < 1e6:
            w[k:] = math.nan
            break
        rig.step(loop.tick_speed(SPEED_STEP_DEG_S, wk))
    t = np.arange(n) / cfg.rate_hz
    dob = f"{cfg.q_type.upper()} {cfg.q_cutoff_hz:g} Hz" if cfg.dob_on else "off"
    return SpeedRun(variant.label, dob, t, np.full(n, SPEED_STEP_DEG_S), w)


def rig_uncertainty_runs(o: Options) -> dict[str, ExperimentResult]:
    """The same case on the nonlinear simulated rig: hold at 0 deg, the drive's gain 1.4 (the
    40 %), a 5 Hz mode (the rig's: a payload on a spring, poles only), 2 N m load step at 1 s
    (`big-step`); DOB off and on."""
    cfg = o.cfg
    dur = 3.0 if o.quick else 5.0
    traj = Trajectory(kind="hold", offset_deg=0.0)
    setup = rig_setup(("big-step",))
    out = {}
    for d in (False, True):
        o.say(f"Fig. 9: simulated rig, gain 1.4 + 5 Hz mode, DOB {'on' if d else 'off'}")
        rig = build_rig(setup, rate_hz=cfg.rate_hz, seed=o.seed, initial_position_deg=0.0)
        sim = rig.rig if isinstance(rig, ScheduledRig) else rig
        sim.set_faults(RigFaults(plant_gain=1.4, resonance_hz=5.0, resonance_damping=0.05))
        out["DOB on" if d else "DOB off"] = run_experiment(
            cfg.with_(dob_on=d), traj, dur, seed=o.seed, disturbance_name=setup.label, rig=rig,
            settle_s=DISTURBANCE_TIME_S)
    return out


def figs_8_9(o: Options) -> tuple[FigureResult, FigureResult]:
    cfg = o.cfg
    dur = 2.0 if o.quick else 3.0
    runs: list[SpeedRun] = []
    settings = (cfg.with_(dob_on=False), cfg.with_(dob_on=True),
                cfg.with_(dob_on=True, q_cutoff_hz=FAST_CUTOFF_HZ))
    for v in VARIANTS_40:
        for c in settings:
            o.say(f"Figs. 8-9: {v.label}, DOB {'off' if not c.dob_on else c.q_cutoff_hz}")
            runs.append(speed_step_run(c, v, dur))
    q = f"{cfg.q_type.upper()} at {cfg.q_cutoff_hz:g} Hz"
    setup = (
        f"Rate loop only (Cv and the DOB, the runtime's tick_speed), {q}, on linear plants "
        f"w = P (M u + d) sampled exactly at {cfg.rate_hz:g} Hz: P = Pn, and the article's "
        "second uncertainty case P = (1 +- 0.4) Pn R(s) with R a pair of conjugate poles at "
        "5 Hz and zeros at 4 Hz (damping 0.05 each; our choice). Speed reference step "
        f"{SPEED_STEP_DEG_S:g} deg/s at 0 s, rate disturbance d = {DISTURBANCE_DEG_S:g} deg/s "
        f"(half the reference: 'large') at {DISTURBANCE_TIME_S:g} s; the DOB off, at "
        f"{cfg.q_cutoff_hz:g} Hz and at {FAST_CUTOFF_HZ:g} Hz (what a faster Q buys). Fig. 8 "
        "is our view of the reference step (0-1 s), Fig. 9 of the disturbance (1 s on); "
        "control.md does not say how the article split them."
    )

    def label(r: SpeedRun) -> str:
        return f"{r.variant}, DOB {r.dob}"

    rows8 = tuple(
        (r.variant, r.dob, "yes" if r.stable else "NO",
         _f(r.rise_s() * 1e3, ".1f"), _f(r.overshoot_pct(), ".1f"))
        for r in runs
    )
    rows9 = tuple(
        (r.variant, r.dob, "yes" if r.stable else "NO",
         _f(r.peak_dev_deg_s(), ".3f"), _f(r.iae_deg(), ".4f"), _f(r.offset_deg(), ".4f"))
        for r in runs
    )
    t_thin = _thin(runs[0].t_s)
    panel8 = Panel("Rate step response", "time s", "load rate deg/s", tuple(
        Series(label(r), t_thin, _thin(r.speed_deg_s)) for r in runs), vspan=(0.0, 1.0))
    m = runs[0].t_s >= 0.9
    panel9 = Panel("Disturbance at 1 s", "time s", "rate error r - w deg/s", tuple(
        Series(label(r), runs[0].t_s[m][::2], (r.ref_deg_s - r.speed_deg_s)[m][::2])
        for r in runs))
    nl = rig_uncertainty_runs(o)
    m_nl = nl["DOB off"].t_s >= 0.9
    panel9_rig = Panel("Simulated rig (nonlinear), drive gain 1.4, 5 Hz mode, 2 N m at 1 s",
                       "time s", "position error deg", tuple(
                           Series(k, _thin(r.t_s[m_nl]), _thin(r.error_deg[m_nl]))
                           for k, r in nl.items()))
    nl_peak = {k: r.peak_error_deg for k, r in nl.items()}
    nl_rmse = {k: r.rmse_deg for k, r in nl.items()}
    nl_sat = {k: 100.0 * r.metrics.saturated_fraction for k, r in nl.items()}
    nl_text = (
        "On the nonlinear simulated rig (hold at 0 deg, drive gain 1.4, a 5 Hz mode, 2 N m load "
        "step at 1 s; second plot), position error after the step without / with the DOB: "
        f"peak {nl_peak['DOB off']:.4f} / {nl_peak['DOB on']:.4f} deg, RMSE "
        f"{nl_rmse['DOB off']:.4f} / {nl_rmse['DOB on']:.4f} deg, command at its limit "
        f"{nl_sat['DOB off']:.0f} / {nl_sat['DOB on']:.0f} % of the time."
    )
    if max(nl_sat.values()) > 1.0:
        nl_text += (
            " The step excites an oscillation at the command limit, with and without the "
            "DOB: the rig's mode (a payload on a spring, read by the encoder: poles only, "
            "non-collocated) at 5 Hz sits at the speed loop's 4.5 Hz crossover, a harder case "
            "than the article's pole-zero pair; the DOB cannot hold a loop Cv alone cannot.")
    all_stable = all(r.stable for r in runs)
    n_set = len(settings)
    trip = {v.label: runs[i * n_set : (i + 1) * n_set] for i, v in enumerate(VARIANTS_40)}
    iae = {k: tuple(r.iae_deg() for r in rs) for k, rs in trip.items()}
    peak = {k: tuple(r.peak_dev_deg_s() for r in rs) for k, rs in trip.items()}
    better = [k for k, v in iae.items() if v[1] < 0.95 * v[0]]
    ov = {k: (rs[0].overshoot_pct(), rs[1].overshoot_pct()) for k, rs in trip.items()}
    reason8 = (
        "control.md reports no number for Fig. 8. Ours: every loop is "
        f"{'stable' if all_stable else 'NOT stable'}; overshoot without / with the DOB: "
        + "; ".join(f"{k} {a:.1f} / {b:.1f} %" for k, (a, b) in ov.items())
        + ". The DOB leaves the reference response almost unchanged (eq. 15: with P = Pn, "
        "Gyw is the plain loop's)."
    )
    reason9 = (
        "control.md reports no number for Fig. 9. Ours, integral of |r - w| after the "
        f"disturbance (DOB off / {cfg.q_cutoff_hz:g} Hz / {FAST_CUTOFF_HZ:g} Hz): "
        + "; ".join(f"{k} {a:.4f} / {b:.4f} / {c:.4f} deg" for k, (a, b, c) in iae.items())
        + "; peak |r - w|: "
        + "; ".join(f"{k} {a:.2f} / {b:.2f} / {c:.2f} deg/s" for k, (a, b, c) in peak.items())
        + (f". At {cfg.q_cutoff_hz:g} Hz the DOB cuts the integral by 5 % or more for "
           f"{len(better)} of {len(iae)} plants" if better else
           f". At {cfg.q_cutoff_hz:g} Hz the DOB does not cut it by 5 % for any plant")
        + " (its rejection acts below about half the cut-off, where Cv's integral action is "
        "already strong; the DOB also removes the offset Cv's integrator leaves). "
        + ("Every loop stays stable on the perturbed plants." if all_stable else
           "Some loop is NOT stable on a perturbed plant (table).")
        + " " + nl_text
    )
    nums_rig = {"rig_peak_off": nl_peak["DOB off"], "rig_peak_on": nl_peak["DOB on"],
                "rig_rmse_off": nl_rmse["DOB off"], "rig_rmse_on": nl_rmse["DOB on"]}
    nums = {f"iae_{i}": r.iae_deg() for i, r in enumerate(runs)} | nums_rig
    cols8 = ("plant", "DOB", "stable", "rise 10-90 % ms", "overshoot %")
    cols9 = ("plant", "DOB", "stable", "peak |r - w| deg/s", "integral |r - w| deg",
             "offset deg")
    return (
        FigureResult("Fig. 8", "Model uncertainty (40 % + 5 Hz mode): reference step", setup,
                     cols8, rows8, (panel8,), "no number to compare", reason8,
                     {"all_stable": float(all_stable)}),
        FigureResult("Fig. 9", "Model uncertainty (40 % + 5 Hz mode): large disturbance at 1 s",
                     setup, cols9, rows9, (panel9, panel9_rig), "no number to compare", reason9,
                     nums),
    )


# -- Fig. 10: where the DOB sits, at a velocity reversal --------------------------------------

FIG10_TRAJECTORY = Trajectory(kind="sine", amplitude_deg=5.0, omega_rad_s=0.75)
FIG10_WINDOW_S = (6.0, 6.5)


def fig10(o: Options) -> FigureResult:
    cfg = o.cfg
    dur = 7.0 if o.quick else 12.0
    traj = FIG10_TRAJECTORY
    runs = {
        "dual loop, no DOB": _rig_run(o, cfg.with_(dob_on=False), traj, dur, "Fig. 10: no DOB"),
        "DOB in the rate loop": _rig_run(o, cfg.with_(dob_on=True), traj, dur,
                                         "Fig. 10: rate-loop DOB"),
        "DOB in the position loop": _rig_run(
            o, cfg.with_(dob_on=False), traj, dur, "Fig. 10: position-loop DOB",
            loop=PositionDobLoop(cfg)),
    }
    a, b = FIG10_WINDOW_S
    rows = []
    nums: dict[str, float] = {}
    for i, (label, r) in enumerate(runs.items()):
        m = (r.t_s >= a) & (r.t_s <= b)
        e = r.error_deg[m]
        peak, rms = float(np.max(np.abs(e))), float(np.sqrt(np.mean(e * e)))
        nums[f"peak_{i}"] = peak
        rows.append((label, _f(peak), _f(rms), _f(r.rmse_deg)))
    m = (runs["dual loop, no DOB"].t_s >= 5.0) & (runs["dual loop, no DOB"].t_s <= 7.0)
    panel = Panel("Position error around the reversal", "time s", "error deg", tuple(
        Series(k, r.t_s[m], r.error_deg[m]) for k, r in runs.items()), vspan=FIG10_WINDOW_S)
    p_plain, p_rate, p_pos = nums["peak_0"], nums["peak_1"], nums["peak_2"]
    best = min(("dual loop", p_plain), ("rate-loop DOB", p_rate), ("position-loop DOB", p_pos),
               key=lambda x: x[1])[0]
    cuts = p_rate < 0.8 * p_plain
    beats_pos = p_rate <= p_pos
    agree = "agrees" if cuts and beats_pos else "partly agrees" if cuts else "disagrees"
    reason = (
        f"control.md gives no number; its claim is that the DOB removes the reversal spike. "
        f"Ours, peak |e| in {a:g}-{b:g} s: dual loop {p_plain:.4f}, rate-loop DOB "
        f"{p_rate:.4f}, position-loop DOB {p_pos:.4f} deg (smallest: {best}). "
        + (f"The rate-loop DOB changes the spike {_pct(p_rate, p_plain):+.1f} % against the "
           f"dual loop ({'a cut of 20 % or more' if cuts else 'not the 20 % cut we ask for'}) "
           f"and {'beats' if beats_pos else 'does not beat'} the position-loop DOB "
           f"({_pct(p_pos, p_plain):+.1f} %). ")
        + ("" if cuts else
           "The spike is the friction and backlash at the reversal, over in a few hundred "
           "ms: its energy lies near and above the Q cut-off, where the DOB cannot reject "
           "(eq. 23: 1/|1 - Q| > 1 only below about half the cut-off, Fig. 11).")
    )
    setup = (
        f"Trajectory 5 sin(0.75 t) deg ({dur:g} s): control.md gives the window 6-6.5 s but not "
        "the trajectory, and the article's 5 sin(0.5 t) reverses at 3.14 and 9.42 s only; "
        "0.75 rad/s reverses at 2 pi s = 6.28 s. "
        f"{cfg.q_type.upper()} at {cfg.q_cutoff_hz:g} Hz for the rate-loop DOB; the "
        "position-loop DOB (simulation only, controller/sim/position_dob.py) corrects the "
        "speed reference with Q41 at the same cut-off and the nominal closed rate loop's "
        f"inverse. Simulated rig, {_dist_note(o)}."
    )
    return FigureResult("Fig. 10", "DOB in the rate loop, in the position loop, none: reversal",
                        setup, ("loop", "peak |e| 6-6.5 s deg", "RMS e 6-6.5 s deg",
                                "RMSE 2 s-end deg"),
                        tuple(rows), (panel,), agree, reason, nums)


# -- Fig. 11: disturbance suppression, eq. 23 --------------------------------------------------

def fig11(o: Options) -> FigureResult:
    cfg = o.cfg
    o.say("Fig. 11: suppression curves (eq. 23)")
    fc = cfg.q_cutoff_hz
    curves = [
        suppression_curve(cfg, "q20", fc),
        suppression_curve(cfg, "q31", fc),
        suppression_curve(cfg, "q31", fc, VARIANTS_40[1]),
    ]
    at8 = {qt: cutoff_for_waterbed_at(qt, 8.0, cfg) for qt in ("q20", "q31")}  # type: ignore[arg-type]
    rows = tuple(
        (f"{c.q_type.upper()} {c.cutoff_hz:g} Hz", c.plant, _f(c.at(0.1), ".1f"),
         _f(c.crossover_hz, ".3g"), _f(c.peak_db, ".2f"), _f(c.peak_hz, ".3g"))
        for c in curves
    )
    panel = Panel("Disturbance suppression |E1/E2| (eq. 23)", "frequency Hz", "dB", tuple(
        Series(f"{c.q_type.upper()} {c.cutoff_hz:g} Hz, {c.plant}", c.freq_hz, c.gain_db)
        for c in curves), logx=True, hlines=(("0 dB", 0.0),))
    q31 = curves[1]
    ok = 5.0 <= q31.peak_hz <= 12.0
    reason = (
        f"The article puts the waterbed near 8 Hz. Ours, Q31 at {fc:g} Hz: peak "
        f"{q31.peak_db:+.2f} dB at {q31.peak_hz:.3g} Hz; Q20: {curves[0].peak_db:+.2f} dB at "
        f"{curves[0].peak_hz:.3g} Hz. With P = Pn eq. 23 is exactly 1 - Q, whose peak scales "
        f"with the cut-off: it lies at 8 Hz for Q31 at {at8['q31']:.3g} Hz or Q20 at "
        f"{at8['q20']:.3g} Hz. "
        + ("Agrees." if ok else
           f"So at {fc:g} Hz the waterbed is not near 8 Hz; the article's 8 Hz fits a cut-off "
           f"near {at8['q31']:.2g} Hz (control.md does not say which cut-off Fig. 11 used).")
    )
    nums = {"q31_peak_hz": q31.peak_hz, "q31_peak_db": q31.peak_db,
            "q20_peak_hz": curves[0].peak_hz, "q20_peak_db": curves[0].peak_db,
            "q31_cutoff_for_8hz": at8["q31"], "q20_cutoff_for_8hz": at8["q20"],
            "q31_at_0.1hz_db": q31.at(0.1)}
    return FigureResult(
        "Fig. 11", "Disturbance suppression curves (eq. 23), Q20 and Q31",
        f"Continuous eq. 23, |E1/E2| = |(1 - Q)(1 + Cv M P)/D|, Cv = {cfg.cv_kp:g} (1 + "
        f"{cfg.cv_ki_per_s:g}/s), M = Mn, P = Pn and P = 1.4 Pn R (5 Hz mode), cut-off "
        f"{fc:g} Hz.",
        ("Q", "plant", "at 0.1 Hz dB", "0 dB crossing Hz", "peak dB", "peak Hz"), rows,
        (panel,), "agrees" if ok else "disagrees", reason, nums)


# -- Figs. 14-15: sine and step (the existing tests) ------------------------------------------

def fig14(o: Options) -> FigureResult:
    cfg = o.cfg
    dur = 10.0 if o.quick else 30.0
    traj = default_trajectory("sine")
    runs = {
        "no DOB": _rig_run(o, cfg.with_(dob_on=False, ff_on=False), traj, dur, "Fig. 14: no DOB"),
        "DOB": _rig_run(o, cfg.with_(dob_on=True, ff_on=False), traj, dur, "Fig. 14: DOB"),
        "DOB + FF": _rig_run(o, cfg.with_(dob_on=True, ff_on=True), traj, dur,
                             "Fig. 14: DOB + FF"),
    }
    art = {(a.run, a.quantity.split(",")[0]): a for a in article_values("Fig. 14")}
    rows = tuple(
        (k, _f(r.peak_error_deg), _f(r.rmse_deg), art[(k, "peak |e|")].text,
         art[(k, "RMSE")].text)
        for k, r in runs.items()
    )
    panel = Panel("Position error, 5 sin(0.5 t) deg", "time s", "error deg", tuple(
        Series(k, _thin(r.t_s), _thin(r.error_deg)) for k, r in runs.items()))
    off, dob, ff = (runs[k].rmse_deg for k in ("no DOB", "DOB", "DOB + FF"))
    p_off, p_dob = runs["no DOB"].peak_error_deg, runs["DOB"].peak_error_deg
    dob_ok = dob < off and p_dob < p_off
    ff_ok = dob / ff >= 2.0
    agree = "agrees" if dob_ok and ff_ok else "partly agrees" if ff_ok else "disagrees"
    reason = (
        f"Article: the DOB lowers the RMSE {_pct(0.0207, 0.0231):+.0f} % and the peak "
        f"{_pct(0.05, 0.1):+.0f} %; feedforward then cuts the RMSE {0.0207 / 0.0052:.1f}x. "
        f"Ours: the DOB changes the RMSE {_pct(dob, off):+.1f} % and the peak "
        f"{_pct(p_dob, p_off):+.1f} %; feedforward cuts the RMSE {dob / ff:.1f}x. "
        + ("The DOB's gain is reproduced." if dob_ok else
           "The DOB's gain is not reproduced: the sine's error on this rig is the reversal "
           "spike and the lag, whose energy lies near and above the cut-off where "
           "1/|1 - Q| <= 1 (the DOB rejects better only below ~0.26 Hz, Fig. 11); the slow "
           "disturbances it rejects are already rejected by the PI loops (Disturbances).")
        + (" Feedforward's gain is reproduced." if ff_ok else " Feedforward's is not.")
    )
    return FigureResult(
        "Fig. 14", "Sine tracking 5 sin(0.5 t) deg: no DOB, DOB, DOB + feedforward",
        f"Simulated rig, {dur:g} s, metrics over 2 s-end, {cfg.q_type.upper()} at "
        f"{cfg.q_cutoff_hz:g} Hz, {_dist_note(o)}.",
        ("run", "peak |e| deg", "RMSE deg", "article peak", "article RMSE"), rows, (panel,),
        agree, reason, {"rmse_off": off, "rmse_dob": dob, "rmse_ff": ff, "peak_off": p_off,
                        "peak_dob": p_dob})


def fig15(o: Options) -> FigureResult:
    cfg = o.cfg
    dur = 3.0 if o.quick else 5.0
    traj = default_trajectory("step")
    runs = {
        "no DOB": _rig_run(o, cfg.with_(dob_on=False), traj, dur, "Fig. 15: step, no DOB"),
        "DOB": _rig_run(o, cfg.with_(dob_on=True), traj, dur, "Fig. 15: step, DOB"),
    }
    rows = tuple(
        (k, _f(r.metrics.rise_time_s or math.nan, ".3f"),
         _f(r.metrics.overshoot_pct or 0.0, ".1f"), _f(r.metrics.static_error_deg or math.nan))
        for k, r in runs.items()
    )
    panel = Panel("5 deg step at 0.5 s", "time s", "position deg", tuple(
        Series(k, _thin(r.t_s), _thin(r.pos_deg)) for k, r in runs.items()))
    r_off = runs["no DOB"].metrics.rise_time_s or math.nan
    r_on = runs["DOB"].metrics.rise_time_s or math.nan
    faster = r_on < 0.97 * r_off
    reason = (
        f"Article: the step is faster with the DOB (no number). Ours: rise time 10-90 % "
        f"{r_off:.3f} s without, {r_on:.3f} s with the DOB ({_pct(r_on, r_off):+.1f} %). "
        + ("Faster with the DOB: agrees." if faster else
           "Not faster by 3 % or more: the rise is set by the position and rate loops; the "
           "DOB at this cut-off barely acts within the rise time.")
    )
    return FigureResult(
        "Fig. 15", "Step response (5 deg)",
        f"Simulated rig, {dur:g} s, {cfg.q_type.upper()} at {cfg.q_cutoff_hz:g} Hz, "
        f"{_dist_note(o)}.",
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
    off = _rig_run(o, cfg.with_(dob_on=False), traj, dur, "Fig. 16: DOB off")
    runs = [
        _rig_run(o, cfg.with_(dob_on=True, q_type="q31", q_cutoff_hz=fc), traj, dur,
                 f"Fig. 16: Q31 at {fc:g} Hz")
        for fc in grid
    ]
    rows = (("DOB off", _f(off.peak_error_deg), _f(off.rmse_deg)), *(
        (f"Q31 {fc:g} Hz", _f(r.peak_error_deg), _f(r.rmse_deg))
        for fc, r in zip(grid, runs, strict=True)))
    x = np.array(grid, float)
    panels = (
        Panel("RMSE against the Q31 cut-off", "cut-off Hz", "RMSE deg",
              (Series("DOB on", x, np.array([r.rmse_deg for r in runs])),), logx=True,
              hlines=(("DOB off", off.rmse_deg),)),
        Panel("Peak |e| against the Q31 cut-off", "cut-off Hz", "peak |e| deg",
              (Series("DOB on", x, np.array([r.peak_error_deg for r in runs])),), logx=True,
              hlines=(("DOB off", off.peak_error_deg),)),
    )
    i = int(np.argmin([r.rmse_deg for r in runs]))
    best_hz, best = grid[i], runs[i].rmse_deg
    near = 0.35 <= best_hz <= 0.7
    beats = best < off.rmse_deg
    agree = "agrees" if near and beats else "partly agrees" if near else "disagrees"
    reason = (
        f"Article: 0.5 Hz was the best Q31 cut-off tried. Ours: lowest RMSE at {best_hz:g} Hz "
        f"({best:.4f} deg) against {off.rmse_deg:.4f} deg with the DOB off. "
        + ("It also beats the DOB off." if beats else
           "No cut-off beats the DOB off on this trajectory: the best DOB is the weakest.")
        + (f" Larger cut-offs are worse: at {grid[-1]:g} Hz RMSE {runs[-1].rmse_deg:.4f} deg, "
           f"peak {runs[-1].peak_error_deg:.4f} deg (ringing after the reversals)."
           if runs[-1].rmse_deg > best else "")
    )
    nums = {"best_hz": best_hz, "best_rmse": best, "off_rmse": off.rmse_deg}
    return FigureResult(
        "Fig. 16", "Position error for several Q31 bandwidths",
        f"Sine 5 sin(0.5 t) deg, {dur:g} s on the simulated rig, {_dist_note(o)}.",
        ("run", "peak |e| deg", "RMSE deg"), rows, panels, agree, reason, nums)


# -- Fig. 17: fixed point 40 deg and ramps ------------------------------------------------------

RAMP_SLOPES = (0.2, 1.0, 5.0)
#: The fixed point: from 0 to 40 deg at 0.5 s (the command limit shapes the move), then hold.
FIXED_POINT = Trajectory(kind="step", amplitude_deg=40.0, step_time_s=0.5)
#: Below this RMS (deg) an error is at the encoder's noise and quantisation level (1e-5 deg
#: noise, 5e-6 deg per count): a relative change there says nothing.
NOISE_LEVEL_DEG = 1e-4


def fig17(o: Options) -> FigureResult:
    cfg = o.cfg
    hold_dur = 6.0 if o.quick else 20.0
    ramp_dur = 8.0 if o.quick else 30.0
    hold = FIXED_POINT
    h = {d: _rig_run(o, cfg.with_(dob_on=d), hold, hold_dur,
                     f"Fig. 17: to 40 deg and hold, DOB {'on' if d else 'off'}")
         for d in (False, True)}
    slopes = (1.0,) if o.quick else RAMP_SLOPES
    ramps = {
        (s, d): _rig_run(o, cfg.with_(dob_on=d), Trajectory(kind="ramp", slope_deg_s=s),
                         ramp_dur, f"Fig. 17: ramp {s:g} t deg, DOB {'on' if d else 'off'}")
        for s in slopes for d in (False, True)
    }
    s_off = h[False].metrics.static_error_deg or math.nan
    s_on = h[True].metrics.static_error_deg or math.nan
    rows: list[tuple[str, ...]] = [
        ("fixed point 40 deg: static error (mean |e|, last quarter)", _f(s_off, ".5f"),
         _f(s_on, ".5f"), _f(_pct(s_on, s_off), "+.1f"), "about 2x smaller with DOB"),
    ]
    red: dict[float, float] = {}
    measurable: list[float] = []
    for s in slopes:
        a, b = ramps[(s, False)].rmse_deg, ramps[(s, True)].rmse_deg
        red[s] = -_pct(b, a)
        if max(a, b) >= NOISE_LEVEL_DEG:
            measurable.append(s)
        rows.append((f"ramp {s:g} t deg: RMSE 2 s-end", _f(a, ".5f"), _f(b, ".5f"),
                     _f(_pct(b, a), "+.1f") if s in measurable else "both at noise level",
                     "5-25 % smaller (low/medium speed)"))
    def tail(r: ExperimentResult, from_s: float) -> tuple[FloatArray, FloatArray]:
        m = r.t_s >= from_s
        return _thin(r.t_s[m]), _thin(r.error_deg[m])

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
        f"{cfg.q_type.upper()} at {cfg.q_cutoff_hz:g} Hz, {_dist_note(o)}.",
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
        rows.append((c.plant, _f(s1, ".1f"), _f(s2, ".1f"), _f(s1b, ".1f"), _f(s2b, ".1f"),
                     _f(c.dob_less_sensitive_below_hz, ".3g"), _f(c.worst_excess_db, "+.2f")))
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


# -- Which disturbances make the DOB useful --------------------------------------------------

MATRIX_NAMES = ("none", "tooth-meshing", "cogging", "load-steps", "friction-change",
                "stick-slip", "sine-0.05hz", "sine-0.5hz")
MATRIX_NAMES_QUICK = ("none", "tooth-meshing", "load-steps")
HELPS_PCT = 5.0


def disturbance_matrix(o: Options) -> FigureResult:
    cfg = o.cfg
    names = MATRIX_NAMES_QUICK if o.quick else MATRIX_NAMES
    sine_dur, hold_dur = (8.0, 6.0) if o.quick else (30.0, 25.0)
    sine, hold = default_trajectory("sine"), default_trajectory("hold")
    rows = []
    nums: dict[str, float] = {}
    helps: list[str] = []
    hurts: list[str] = []
    changes = []
    for name in names:
        res = {}
        for kind, traj, dur in (("sine", sine, sine_dur), ("hold", hold, hold_dur)):
            for d in (False, True):
                res[(kind, d)] = _rig_run(
                    o, cfg.with_(dob_on=d), traj, dur,
                    f"disturbances: {name}, {kind}, DOB {'on' if d else 'off'}", names=(name,),
                    settle_s=2.0)
        cs = _pct(res[("sine", True)].rmse_deg, res[("sine", False)].rmse_deg)
        h_off, h_on = res[("hold", False)].rmse_deg, res[("hold", True)].rmse_deg
        ch = _pct(h_on, h_off)
        changes.append((name, cs, ch))
        # A baseline at the encoder's noise level makes a percentage meaningless: say what
        # happened instead.
        ch_text = _f(ch, "+.1f") if h_off >= NOISE_LEVEL_DEG else (
            "still -> hunts" if h_on >= NOISE_LEVEL_DEG else "both still")
        nums[f"{name}_sine_off"] = res[("sine", False)].rmse_deg
        nums[f"{name}_sine_on"] = res[("sine", True)].rmse_deg
        nums[f"{name}_hold_off"] = res[("hold", False)].rmse_deg
        nums[f"{name}_hold_on"] = res[("hold", True)].rmse_deg
        shown = "no added disturbance" if name == "none" else name
        for label, c in (("sine", cs), ("hold", ch)):
            what = f"{label} {c:+.0f} %"
            if label == "hold" and h_off < NOISE_LEVEL_DEG:
                what = f"hold {h_off:.1g} -> {h_on:.2g} deg"
                if h_on < NOISE_LEVEL_DEG:
                    continue
            if c <= -HELPS_PCT:
                helps.append(f"{shown} ({what})")
            elif c >= HELPS_PCT:
                hurts.append(f"{shown} ({what})")
        rows.append((name, _f(res[("sine", False)].rmse_deg), _f(res[("sine", True)].rmse_deg),
                     _f(cs, "+.1f"), _f(h_off, ".5f"), _f(h_on, ".5f"), ch_text))
    x = np.arange(len(names), dtype=float)
    panel = Panel("Sine: RMSE change with the DOB (negative: the DOB helps)", "disturbance",
                  "change %", (Series("sine", x, np.array([c[1] for c in changes])),),
                  hlines=((f"-{HELPS_PCT:g} %", -HELPS_PCT), (f"+{HELPS_PCT:g} %", HELPS_PCT)),
                  xticks=names)
    hold_panel = Panel("Hold at 40 deg from rest: RMSE", "disturbance", "RMSE deg", (
        Series("DOB off", x, np.array([nums[f"{n}_hold_off"] for n in names])),
        Series("DOB on", x, np.array([nums[f"{n}_hold_on"] for n in names]))), xticks=names)
    reason = (
        f"The DOB lowers the RMSE by {HELPS_PCT:g} % or more with: "
        + (", ".join(helps) if helps else "none of them")
        + f". It raises it by {HELPS_PCT:g} % or more with: "
        + (", ".join(hurts) if hurts else "none") + ". Elsewhere within +-5 %. "
        "At hold from rest the plain loop keeps the stuck turntable still (encoder noise "
        "dithers the integrators' input to zero mean) unless a disturbance moves it; the DOB "
        "(1/(1 - Q) adds a double integrator at DC for Q31) winds up on the noise alone and "
        "breaks the turntable away into the stick-slip limit cycle both loops end in once "
        "moved (Fig. 17's fixed point)."
    )
    return FigureResult(
        "Disturbances", "Where the DOB helps: named timing-belt disturbances",
        f"Sine 5 sin(0.5 t) {sine_dur:g} s and hold at 40 deg from rest {hold_dur:g} s on the "
        "simulated "
        f"rig, each disturbance alone (controller/sim/rig_disturbances.py), RMSE over 2 s-end, "
        f"{cfg.q_type.upper()} at {cfg.q_cutoff_hz:g} Hz against the DOB off.",
        ("disturbance", "sine off", "sine DOB", "change %", "hold off", "hold DOB", "change %"),
        tuple(rows), (panel, hold_panel), "agrees" if helps else "disagrees", reason, nums)


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
