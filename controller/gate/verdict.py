"""The gate's one verdict: the analysis on all the plant knowledge, the recommended cut-off and
the nonlinear check, combined into accept / caution / reject with reasons that name their
evidence (`controller.core.verdict.Verdict`). The controller (its analysis worker) and
`dobtune check` call `judge`; the dashboard calls `verdict_of` on the one analysis it also
draws its charts from, so a verdict is the same wherever it is computed from the same
knowledge.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Protocol

from controller.core.config import LoopConfig, NominalModel
from controller.core.verdict import Verdict, VerdictKind, VerdictMargins
from controller.gate.analysis import Analysis, GateLimits, analyse
from controller.gate.knowledge import PlantKnowledge
from controller.gate.margins import Margins
from controller.gate.search import recommendation_search

__all__ = [
    "EXIT_CODES",
    "NonlinearCheck",
    "NonlinearFinding",
    "Verdict",
    "conditional_stability",
    "judge",
    "margins_of_analysis",
    "recommended_cutoff_hz",
    "verdict_of",
]

#: `dobtune check` exit codes per verdict (2 is bad input).
EXIT_CODES: dict[str, int] = {"accept": 0, "caution": 3, "reject": 1}

#: The recommended cut-off with responses at several positions (`controller.gate.search`).
_SPREAD_NOTE = ", held where |Delta Q| with the spread between the measured responses stays small"



class NonlinearFinding(Protocol):
    """One finding of a nonlinear check (`controller.sim.nonlinear_check.Finding`)."""

    @property
    def text(self) -> str: ...

    @property
    def sustained(self) -> bool:
        """An oscillation that does not decay: the candidate is rejected."""
        ...


NonlinearCheck = Callable[[LoopConfig, NominalModel], Sequence[NonlinearFinding]]
"""Runs a candidate on a nonlinear model of the rig with the knowledge's plant model; returns
the findings (empty: none). `controller.sim.nonlinear_check.findings` is the one in use."""


def recommended_cutoff_hz(
    cfg: LoopConfig, plant: PlantKnowledge, limits: GateLimits | None = None
) -> float | None:
    """`recommended_max_cutoff_hz` for cfg's Q type, cached per (configuration without the
    cut-off, plant knowledge object, limits): moving the cut-off slider costs one search."""
    return recommendation_search(cfg, plant, limits).value()


def conditional_stability(a: Analysis, limits: GateLimits) -> tuple[str, ...]:
    """The loops (plant model) that are conditionally stable, each with its gain-reduction
    margin: a phase crossover with |L| > 1 means the loop goes unstable when its gain falls by
    that much (a saturating command, a weaker drive). Margins within `gain_margin_min_db` are
    already cautions of the analysis and are not repeated."""
    out = []
    loops: tuple[tuple[str, Margins | None], ...] = (
        ("speed loop", a.margins), ("whole servo", a.margins_full))
    for which, m in loops:
        if (m is None or not m.conditionally_stable
                or m.gain_reduction_margin_db < limits.gain_margin_min_db):
            continue
        out.append(
            f"conditionally stable: a gain reduction of {m.gain_reduction_margin_db:.1f} dB"
            f" destabilises the {which} (gain-reduction margin"
            f" {m.gain_reduction_margin_db:.1f} dB down at"
            f" {m.gain_reduction_margin_hz:.3g} Hz, {_up_text(m)}, plant model): a saturating"
            f" command or a weaker drive lowers the loop gain that far"
        )
    return tuple(out)


def _up_text(m: Margins) -> str:
    if m.gain_margin_up_db == math.inf:
        return "gain margin unlimited up"
    return f"gain margin {m.gain_margin_up_db:.1f} dB up at {m.gain_margin_up_hz:.3g} Hz"


def margins_of_analysis(a: Analysis) -> VerdictMargins:
    """The verdict's figures from the analysis (the plant model's loops)."""
    return VerdictMargins(
        gain_margin_db=float(a.gain_margin_db),
        phase_margin_deg=float(a.phase_margin_deg),
        peak_sensitivity_db=float(a.peak_sensitivity_db),
        small_gain_peak=float(a.small_gain_peak),
        max_pole_radius=float(a.max_pole_radius),
        noise_to_command_peak_db=float(a.noise_to_command_peak_db),
        gain_margin_up_db=float(a.margins.gain_margin_up_db),
        gain_reduction_margin_db=float(a.margins.gain_reduction_margin_db),
    )


def judge(
    cfg: LoopConfig,
    plant: PlantKnowledge,
    limits: GateLimits | None = None,
    *,
    nonlinear: NonlinearCheck | None = None,
    recommendation: bool = True,
) -> Verdict:
    """The verdict on `cfg` against `plant`: `verdict_of` its analysis on the gate's grid."""
    return verdict_of(analyse(cfg, plant, limits), plant, limits, nonlinear=nonlinear,
                      recommendation=recommendation)


def verdict_of(
    a: Analysis,
    plant: PlantKnowledge,
    limits: GateLimits | None = None,
    *,
    nonlinear: NonlinearCheck | None = None,
    recommendation: bool = True,
) -> Verdict:
    """The verdict on `a.config` from its analysis `a` against `plant` (one analysis serves
    the verdict and, in the dashboard, the charts): reject on any rejection of the analysis
    or a sustained oscillation in the nonlinear check (chatter that does not decay: the loop
    watchdog would roll it back); else caution for any caution of the analysis, a Q cut-off
    above the recommended maximum (the top of the continuous accepted region from the lowest
    cut-off) or another finding of the nonlinear check (ringing that decays, hunting); else
    accept. A verdict other than accept also names every conditionally stable loop with its
    gain-reduction margin (`conditional_stability`).

    The recommended cut-off is searched only as far as the verdict needs (for a cut-off
    below it, the coarse scan up to the cut-off; `RecommendationSearch`), and to the end for
    the result's `recommended_max_cutoff_hz` unless `recommendation` is False (the
    controller's gate: the verdict alone)."""
    limits = limits if limits is not None else GateLimits()
    cfg = a.config
    judged = {"margins": margins_of_analysis(a), "knowledge": a.knowledge,
              "knowledge_version": plant.version}
    if a.verdict == "reject":
        cond = conditional_stability(a, limits)
        return Verdict(verdict="reject", rejections=a.rejections, cautions=a.cautions + cond,
                       **judged)  # type: ignore[arg-type]
    rejections: list[str] = []
    cautions = list(a.cautions)
    search = recommendation_search(cfg, plant, limits)
    if cfg.dob_on:
        # Searched only as far as the answer needs (a cut-off well below the recommendation
        # needs the coarse scan up to it), to the end only for a caution's text.
        fits = search.decide(lambda r: not cfg.q_cutoff_hz > r * 1.0001)
        if fits is None:
            cautions.append(
                f"Q cut-off {cfg.q_cutoff_hz:g} Hz: no {cfg.q_type} cut-off is accepted without "
                f"reservation on {plant.describe()}"
            )
        elif not fits:
            rec = search.value()
            assert rec is not None
            cautions.append(
                f"Q cut-off {cfg.q_cutoff_hz:g} Hz is above the recommended maximum "
                f"{rec:.3g} Hz for {cfg.q_type} (the top of the accepted region from the lowest "
                f"cut-off{_SPREAD_NOTE if len(plant.measured) >= 2 else ''}, {plant.describe()})"
            )
    if nonlinear is not None:
        for finding in nonlinear(cfg, plant.model):
            (rejections if finding.sustained else cautions).append(
                f"nonlinear check: {finding.text}"
            )
    verdict: VerdictKind = "reject" if rejections else "caution" if cautions else "accept"
    if verdict != "accept":
        cautions += conditional_stability(a, limits)
    rec = search.value() if recommendation else None
    return Verdict(verdict=verdict, rejections=tuple(rejections), cautions=tuple(cautions),
                   recommended_max_cutoff_hz=rec, **judged)  # type: ignore[arg-type]
