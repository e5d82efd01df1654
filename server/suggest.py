"""The dashboard's "Suggest" (issue 15 item 3): the cut-off autotune run for one browser's
candidate, drawn as the curve it searched and put into that candidate (never applied).

Pure (no viser): the search is `controller.tune.autotune.autotune` on the dashboard's copy of
the controller's plant knowledge, on the nonlinear simulated rig, with the controller's
present trajectory; here are the settings, the chart and the text.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from controller.core.arrays import FloatArray
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import PlantKnowledge
from controller.sim.rig_disturbances import RigSetup
from controller.tune.autotune import SIGNIFICANT_REL, TuneResult, autotune
from server.charts import ChartSpec
from server.escape import esc

__all__ = ["SUGGEST_CHART", "SuggestSettings", "suggest", "suggest_data", "suggest_html",
           "suggested_config"]

#: The Q types in the curve's series order.
Q_TYPES = ("q31", "q20")


@dataclass(frozen=True)
class SuggestSettings:
    """How the dashboard's Suggest searches (shorter runs than the CLI's default: the user
    waits for it)."""

    duration_s: float = 8.0
    points: int = 8
    refine: int = 3
    lowest_hz: float = 0.1
    highest_hz: float = 20.0
    objective: str = "rmse"


def suggest(base: LoopConfig, plant: PlantKnowledge, trajectory: Trajectory,
            settings: SuggestSettings = SuggestSettings(),
            progress: Callable[[float], None] | None = None,
            setup: RigSetup | None = None) -> TuneResult:
    """The autotune of `base`'s Q type and cut-off (its gains kept) on `trajectory`, on the
    simulated rig with `setup`'s named disturbances (the preview's)."""
    from controller.sim.nonlinear_check import findings

    return autotune(base, plant, trajectory, duration_s=settings.duration_s, setup=setup,
                    objective=settings.objective, points=settings.points,
                    refine=settings.refine, lowest_hz=settings.lowest_hz,
                    highest_hz=settings.highest_hz, nonlinear=findings, q_types=Q_TYPES,
                    progress=progress)


def suggested_config(base: LoopConfig, result: TuneResult) -> LoopConfig:
    """What Suggest puts into the candidate: the best accepted DOB setting when it beats the
    DOB off, else the DOB off (the same gains)."""
    if result.dob_helps and result.best is not None:
        p = result.best
        return base.with_(dob_on=True, q_type=p.q_type, q_cutoff_hz=p.q_cutoff_hz)
    return base.with_(dob_on=False)


SUGGEST_CHART = ChartSpec(
    key="suggest",
    title=("Suggest: score (tracking error + command-noise price) against the Q cut-off "
           "(simulated rig); hollow: the gate's caution, not counted"),
    series=(
        {"label": "f (Hz)"},
        {"label": "Q31 score (deg)", "stroke": "#1f77b4", "width": 1.5, "scale": "y",
         "points": {"show": True, "size": 6}, "spanGaps": True},
        {"label": "Q20 score (deg)", "stroke": "#2ca02c", "width": 1.5, "scale": "y",
         "points": {"show": True, "size": 6}, "spanGaps": True},
        {"label": "caution, not counted (deg)", "stroke": "#9467bd", "width": 0, "scale": "y",
         "points": {"show": True, "size": 9, "stroke": "#9467bd", "fill": "#ffffff",
                    "width": 2}},
        {"label": "DOB off (deg)", "stroke": "#e8871e", "width": 1.5, "scale": "y",
         "dash": (4, 3)},
        {"label": f"DOB off -{SIGNIFICANT_REL:.0%}: a win below (deg)", "stroke": "#e8871e",
         "width": 1, "scale": "y", "dash": (1, 3)},
        {"label": "suggested", "stroke": "#d62728", "width": 0, "scale": "y",
         "points": {"show": True, "size": 12, "stroke": "#d62728", "fill": "#d62728"}},
    ),
    scales={"x": {"time": False, "distr": 3, "log": 10}, "y": {"auto": True}},
    axes=({"label": "Hz", "scale": "x"}, {"label": "score deg", "scale": "y"}),
    height=220,
)


def suggest_data(result: TuneResult | None) -> tuple[FloatArray, ...]:
    """The chart's columns: the cut-offs tried (both Q types, sorted); each type's score
    (what the search ranks: the objective plus the command-noise price) where it was run and
    counts (NaN where it was not, or the gate rejected it); the points run but not counted
    (the gate's caution) in a column of their own, drawn hollow; the DOB-off level and the
    level a DOB setting must be below to win (`SIGNIFICANT_REL`); the suggested point (only
    when a DOB setting wins). Without a result: a placeholder that draws nothing. NaN stays
    NaN: the chart's y scale is fixed by `charts.ranged_scales` (a stand-in first value drew
    a fake "suggested" dot)."""
    if result is None or not result.curve:
        x = np.array([0.1, 20.0])
        return (x, *(np.full(2, math.nan) for _ in range(len(SUGGEST_CHART.series) - 1)))
    x = np.array(sorted({p.q_cutoff_hz for p in result.curve}), dtype=np.float64)
    index = {f: i for i, f in enumerate(x)}
    cols = {q: np.full(len(x), math.nan) for q in Q_TYPES}
    caution = np.full(len(x), math.nan)
    for p in result.curve:
        if p.verdict == "reject":
            continue
        if p.verdict in result.counted and p.q_type in cols:
            cols[p.q_type][index[p.q_cutoff_hz]] = p.score
        elif p.verdict not in result.counted:
            i = index[p.q_cutoff_hz]
            caution[i] = p.score if math.isnan(caution[i]) else min(caution[i], p.score)
    base = np.full(len(x), result.baseline.score)
    bar = base * (1.0 - SIGNIFICANT_REL)
    best = np.full(len(x), math.nan)
    if result.dob_helps and result.best is not None:
        best[index[result.best.q_cutoff_hz]] = result.best.score
    return (x, *(cols[q] for q in Q_TYPES), caution, base, bar, best)


def suggest_html(result: TuneResult, trajectory: Trajectory, elapsed_s: float | None) -> str:
    """What the search found, in words (the numbers are the simulated rig's). `elapsed_s`
    None: the candidate has changed since Suggest put its setting in (said so instead)."""
    tried = len(result.curve)
    rejected = sum(1 for p in result.curve if p.verdict == "reject")
    if elapsed_s is None:
        what = ("The candidate has been changed since (Suggest's setting is no longer in "
                "it).")
        took = ""
    else:
        what = ("The candidate now has this setting (not applied: the verdict and Apply are "
                "yours)." if result.dob_helps else
                "The candidate now has the <b>DOB off</b> (not applied).")
        took = f", {elapsed_s:.1f} s"
    return (f"<div class='dt-suggest dt-suggest-done' style='font-size:12px'><b>Suggest</b> "
            f"({esc(trajectory.kind)}, {tried} cut-offs tried, {rejected} rejected by the "
            f"gate{took}): {esc(result.summary())}. {what}</div>")
