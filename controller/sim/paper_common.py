"""What every experiment of the article shares (`controller.sim.paper`): the article's
reported values (`ARTICLE`), the results' plain data (series, panels, a figure's result), the
options and the figures' small helpers.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from controller.core.arrays import FloatArray
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.sim.experiment import ExperimentResult, Loop, run_experiment
from controller.sim.rig_disturbances import build_rig, rig_setup

__all__ = [
    "ARTICLE",
    "ARTICLE_RAMP_REDUCTION_PCT",
    "FIXED_POINT",
    "NOISE_LEVEL_DEG",
    "ArticleValue",
    "FigureResult",
    "Options",
    "Panel",
    "Progress",
    "Series",
    "article_values",
    "disturbance_note",
    "fmt",
    "pct_change",
    "rig_run",
    "thinned",
]


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
    ArticleValue("Fig. 8", "rate response with reversals, backlash, disturbance at 1 s", "all",
                 None),
    ArticleValue("Fig. 9", "the same with 40 % error and a 5 Hz pole-zero pair", "all",
                 None),
    ArticleValue("Fig. 10", "error at the velocity reversal, 6-6.5 s", "all", None,
                 note="control.md: the reversal spike 'is what the DOB removes'"),
    ArticleValue("Fig. 11", "frequency of the amplification of the disturbance response",
                 "Q20, Q31", 8.0, "Hz",
                 "'around 8 Hz'; its size, the cut-off and Cv are not reported"),
    ArticleValue("Fig. 13", "responses at three positions overlap below", "all", 1.0, "Hz",
                 "'overlap well only below about 1 Hz'"),
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


def fmt(v: float, spec: str = ".4f") -> str:
    return "-" if not math.isfinite(v) else format(v, spec)


def pct_change(new: float, old: float) -> float:
    return 100.0 * (new - old) / old if old else math.nan


def thinned(x: FloatArray, n: int = 2000) -> FloatArray:
    step = max(1, len(x) // n)
    return np.asarray(x[::step], float)


def rig_run(
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


def disturbance_note(o: Options) -> str:
    return ("disturbances: " + ", ".join(o.disturbances)) if o.disturbances else (
        "no added disturbance (the reference rig's own tooth ripple, friction and backlash)")


#: The fixed point: from 0 to 40 deg at 0.5 s (the command limit shapes the move), then hold.
FIXED_POINT = Trajectory(kind="step", amplitude_deg=40.0, step_time_s=0.5)
#: Below this RMS (deg) an error is at the encoder's noise and quantisation level (1e-5 deg
#: noise, 5e-6 deg per count): a relative change there says nothing.
NOISE_LEVEL_DEG = 1e-4
