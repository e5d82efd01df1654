"""The tuning engine: a candidate configuration -> Bode chart data, margins, verdict, and the
time-domain preview. Pure computation (no viser): the panels display what it returns.

It evaluates a candidate with the shared stability check (`controller.gate.analysis`), the
same function the controller runs before it applies anything, and runs the offline experiment
for the preview. Results are cached per configuration; the engine is thread-safe.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np
import numpy.typing as npt

from controller.core.config import LoopConfig, NominalModel
from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory
from controller.gate.analysis import Analysis, analyse
from controller.gate.knowledge import (
    COMMISSIONING_BOUND,
    KnowledgeRecord,
    MeasuredResponse,
    PlantKnowledge,
    PositionSpread,
)
from controller.gate.loop_model import (
    default_grid,
    discrete_equivalent,
    dob_filters,
    loop_blocks,
    nominal_continuous_response,
)
from controller.gate.margins import loop_tasks, margins_of, solve
from controller.gate.search import knowledge_spread
from controller.gate.verdict import judge, recommended_cutoff_hz
from controller.sim.nonlinear_check import findings
from controller.sim.rig_disturbances import RigSetup, rig_setup
from server import charts
from server.charts import BodeCurves, FloatArray, NyquistLoop, PlantCurves

__all__ = [
    "CUTOFF_MAX_HZ",
    "CUTOFF_MIN_HZ",
    "Comparison",
    "ConfigError",
    "Evaluation",
    "GateView",
    "PreviewComparison",
    "PreviewResult",
    "TuningEngine",
    "candidate_from_values",
    "curves_from_analysis",
    "freq_grid_hz",
    "measured_from_csv",
    "plant_curves",
    "speed_loop",
]

#: Range of the Q cut-off the dashboard offers, Hz.
CUTOFF_MIN_HZ = 0.05
CUTOFF_MAX_HZ = 50.0


@dataclass(frozen=True)
class GateView:
    """What the stability check says about one configuration, ready to display."""

    verdict: str  # "accept" | "caution" | "reject"
    reasons: tuple[str, ...]
    margins: dict[str, float]
    recommended_max_cutoff_hz: float | None = None
    knowledge: str = ""  # the plant knowledge the verdict was judged on

    @property
    def accepted(self) -> bool:
        return self.verdict == "accept"

    @property
    def applicable(self) -> bool:
        """accept, or caution (applied only after the user confirms the reasons)."""
        return self.verdict != "reject"


@dataclass(frozen=True)
class Evaluation:
    """One configuration's curves and verdict, and how long the check took."""

    config: LoopConfig
    curves: BodeCurves
    gate: GateView
    elapsed_s: float


@dataclass(frozen=True)
class Comparison:
    """A candidate against the active configuration, with the data of every Bode chart."""

    candidate: Evaluation
    active: Evaluation
    #: Bode chart key -> its uPlot data tuple (candidate and active curves).
    chart_data: dict[str, tuple[FloatArray, ...]]


@dataclass(frozen=True)
class PreviewResult:
    """The offline experiment of one configuration on one trajectory."""

    config: LoopConfig
    trajectory: Trajectory
    t_s: FloatArray
    error_deg: FloatArray
    peak_error_deg: float
    rmse_deg: float
    elapsed_s: float
    command_noise_deg_s: float = math.nan
    """RMS of the speed command above 20 Hz (`controller.tune.autotune.command_noise_deg_s`):
    what the DOB costs in the drive."""
    disturbances: str = "none"
    """The simulated rig's named disturbances in the run."""


@dataclass(frozen=True)
class PreviewComparison:
    """The previews of the candidate, the same gains with the DOB off, and the active
    configuration, and the chart data."""

    candidate: PreviewResult
    active: PreviewResult
    chart_data: tuple[FloatArray, ...]
    no_dob: PreviewResult | None = None
    """The candidate's run with the DOB off (its price and value side by side)."""


def freq_grid_hz(rate_hz: float = 1000.0, n: int = 240) -> FloatArray:
    """Log grid of the Bode plots: 0.01 Hz to just under Nyquist (the gate's own grid)."""
    return np.asarray(default_grid(rate_hz, n), dtype=np.float64)


def candidate_from_values(base: LoopConfig, values: dict[str, Any]) -> LoopConfig:
    """A validated candidate: `base` with the control values; raises ConfigError."""
    return base.with_(**values)


# -- the analysis adapter -------------------------------------------------------------------------


def speed_loop(cfg: LoopConfig, model: NominalModel, freq_hz: FloatArray, *, dob: bool,
               ) -> NyquistLoop:
    """The speed loop broken at the plant input, with the DOB (G (Cv + F1) / (1 - F2 z^-1))
    or without it (G Cv), whatever `cfg.dob_on`: the gate's own blocks (`loop_blocks`, the
    implemented discrete loop on the plant `model`) and its own margin refinement
    (`loop_tasks`, `solve`, `margins_of`: python-control's selection rules)."""
    filters = dob_filters(cfg) if dob else None

    def loop_at(f: FloatArray) -> npt.NDArray[np.complex128]:
        b = loop_blocks(cfg, filters, f, model)
        return np.asarray(b.g * (b.cv + b.f1) / (1.0 - b.f2d), dtype=np.complex128)

    f = np.asarray(freq_hz, dtype=np.float64)
    response = loop_at(f)
    tasks = loop_tasks(np.log(f), response, "L")
    solve(tasks.all(), lambda ff: {"L": loop_at(ff)})
    m = margins_of(tasks)
    phase = [t for t in tasks.phase if t.out.real <= 0.0]  # margins_of's own filter
    return NyquistLoop(
        response=response,
        gain_crossover_hz=np.array([t.freq_hz for t in tasks.gain], dtype=np.float64),
        gain_crossings=np.array([t.out for t in tasks.gain], dtype=np.complex128),
        phase_crossover_hz=np.array([t.freq_hz for t in phase], dtype=np.float64),
        phase_crossings=np.array([t.out for t in phase], dtype=np.complex128),
        phase_margin_deg=m.phase_margin_deg,
        gain_margin_db=m.gain_margin_db,
    )


def plant_curves(plant: PlantKnowledge, freq_hz: FloatArray, rate_hz: float) -> PlantCurves:
    """The plant chart's curves: the knowledge's model M P (continuous) and its measured
    responses with their spread (`charts.spread_band_db`), on `freq_hz` merged with every
    measured frequency. With measured responses the grid starts at the lowest measured
    frequency, so that every measured column starts with a real point (uPlot's first-value
    rule, `charts.uplot_column`, would otherwise join a stand-in point to the first
    measurement). Sampled responses (u[k] -> w[k]) are brought to the continuous basis by
    dividing out the gate's ZOH + backward-difference factor (`discrete_equivalent`)."""
    grid = np.asarray(freq_hz, dtype=np.float64)
    measured = plant.measured
    if measured:
        lowest = min(float(m.freq_hz[0]) for m in measured)
        grid = np.union1d(grid[grid > lowest], np.concatenate([m.freq_hz for m in measured]))
    model = nominal_continuous_response(plant.model, grid)
    model_phase = _wrap_start(np.degrees(np.unwrap(np.angle(model))))
    n = grid.size
    mag_sum, phase_sum, count = np.zeros(n), np.zeros(n), np.zeros(n)
    upper, lower = np.full(n, -np.inf), np.full(n, np.inf)
    for m in measured:
        h = _continuous(m, rate_hz)
        idx = np.searchsorted(grid, m.freq_hz)
        ph = np.degrees(np.unwrap(np.angle(h)))
        ph = ph - 360.0 * np.round((ph[0] - model_phase[idx[0]]) / 360.0)  # near the model
        spread = m.spread if m.spread is not None else np.zeros(h.shape)
        hi, lo = charts.spread_band_db(h, spread)
        mag_sum[idx] += charts.db(h)
        phase_sum[idx] += ph
        count[idx] += 1.0
        upper[idx] = np.maximum(upper[idx], hi)
        lower[idx] = np.minimum(lower[idx], lo)
    have = count > 0
    positions = []
    for m in measured[: charts.PLANT_POSITIONS]:
        col = np.full(n, np.nan)
        col[np.searchsorted(grid, m.freq_hz)] = charts.db(_continuous(m, rate_hz))
        positions.append(col)
    between = knowledge_spread(plant, rate_hz)
    spread_db = None
    if between is not None:
        spread_db = np.full(n, np.nan)
        spread_db[np.searchsorted(grid, between.freq_hz)] = between.mag_db
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_db = np.where(have, mag_sum / count, np.nan)
        mean_phase = np.where(have, phase_sum / count, np.nan)
    return PlantCurves(
        freq_hz=grid,
        model_db=charts.db(model),
        model_phase_deg=model_phase,
        measured_db=mean_db,
        measured_phase_deg=mean_phase,
        upper_db=np.where(have, upper, np.nan),
        lower_db=np.where(have, lower, np.nan),
        n_measured=len(measured),
        positions_db=tuple(positions),
        spread_db=spread_db,
        divergence_hz=None if between is None else between.divergence_hz,
    )


def _continuous(m: MeasuredResponse, rate_hz: float) -> npt.NDArray[np.complex128]:
    """A response in the continuous basis (a sampled one with the ZOH + backward-difference
    factor divided out)."""
    h = np.asarray(m.response, dtype=np.complex128)
    if m.sampled:
        h = h / discrete_equivalent(np.ones_like(h), m.freq_hz, rate_hz)
    return h


def curves_from_analysis(a: Analysis, plant: PlantKnowledge) -> tuple[BodeCurves, GateView]:
    """Adapter: the gate's Analysis (of `a.config` on `plant`) -> what the charts draw and
    the verdict box shows."""
    bound = [src.inv_delta_db for src in a.sources if src.kind == "bound"]
    measured = [src.inv_delta_db for src in a.sources if src.kind == "measured"]
    curves = BodeCurves(
        freq_hz=a.freq_hz,
        open_loop_db=a.open_loop_mag_db,
        open_loop_phase_deg=_wrap_start(a.open_loop_phase_deg),
        closed_dob_db=charts.db(a.closed_loop_dob),
        closed_nodob_db=charts.db(a.closed_loop_no_dob),
        dist_dob_db=charts.db(a.disturbance_dob),
        dist_nodob_db=charts.db(a.disturbance_no_dob),
        noise_dob_db=charts.db(a.noise_dob),
        noise_nodob_db=charts.db(a.noise_no_dob),
        q_db=a.q_mag_db,
        rejection_db=a.rejection_db,
        inv_delta_db=bound[0] if bound else None,
        # The worst measured response at each frequency (smallest 1/|Delta|).
        inv_delta_measured_db=np.min(np.stack(measured), axis=0) if measured else None,
        s_db=charts.db(1.0 / (1.0 + a.open_loop)),
        t_db=charts.db(a.open_loop / (1.0 + a.open_loop)),
        s_full_db=None if a.open_loop_full is None else charts.db(1.0 / (1.0 + a.open_loop_full)),
        t_full_db=None if a.open_loop_full is None else charts.db(
            a.open_loop_full / (1.0 + a.open_loop_full)),
        nyquist_dob=speed_loop(a.config, plant.model, a.freq_hz, dob=True),
        nyquist_nodob=speed_loop(a.config, plant.model, a.freq_hz, dob=False),
        plant=plant_curves(plant, a.freq_hz, a.config.rate_hz),
    )
    margins = {
        "gain_margin_db": a.gain_margin_db,
        "phase_margin_deg": a.phase_margin_deg,
        "peak_sensitivity_db": a.peak_sensitivity_db,
        "small_gain_peak": a.small_gain_peak,
        "max_pole_radius": a.max_pole_radius,
        "noise_to_command_peak_db": a.noise_to_command_peak_db,
    }
    return curves, GateView(a.verdict, tuple(a.reasons), margins)


def _wrap_start(phase_deg: FloatArray) -> FloatArray:
    """Shift an unwrapped phase by whole turns so that it starts in (-270, 90] deg."""
    if len(phase_deg) == 0:
        return phase_deg
    turns = math.floor((phase_deg[0] + 270.0) / 360.0)
    return np.asarray(phase_deg - 360.0 * turns, dtype=np.float64)


def measured_from_csv(name: str, data: Any) -> MeasuredResponse:
    """A CSV response (FrdData) as the gate's plant knowledge: a continuous response u -> w."""
    return MeasuredResponse(name=name, freq_hz=data.freq_hz, response=data.response)


# -- the engine ---------------------------------------------------------------------------------

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")


class _Cache(Generic[K, V]):
    """A small thread-safe memo, emptied when it grows past `size` (the keys seen recently are
    what a slider revisits). Two threads may compute the same key once each: harmless."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._items: dict[K, V] = {}
        self._lock = threading.Lock()

    def lookup(self, key: K) -> tuple[bool, V | None]:
        with self._lock:
            if key in self._items:
                return True, self._items[key]
        return False, None

    def get(self, key: K, compute: Callable[[], V]) -> V:
        with self._lock:
            if key in self._items:
                return self._items[key]
        value = compute()
        with self._lock:
            if len(self._items) > self.size:
                self._items.clear()
            self._items[key] = value
        return value

    def clear(self) -> None:
        with self._lock:
            self._items.clear()


def _without_dob(cfg: LoopConfig) -> LoopConfig:
    """`cfg` with the DOB off and its Q settings at the defaults (unused with the DOB off: one
    run, and one cache entry, for every cut-off)."""
    d = LoopConfig()
    return cfg.with_(dob_on=False, q_type=d.q_type, q_cutoff_hz=d.q_cutoff_hz)


def _recommendation_key(cfg: LoopConfig) -> LoopConfig:
    """The recommendation depends on everything but the cut-off and the DOB switch."""
    return cfg.with_(q_cutoff_hz=1.0, dob_on=True)


class TuningEngine:
    """Evaluates candidates; caches the evaluation of configurations seen before."""

    def __init__(self, n_freq: int = 240, preview_duration_s: float = 12.6,
                 sim_disturbances: tuple[str, ...] = ()):
        self.n_freq = n_freq
        self.freq_hz = freq_grid_hz(1000.0, n_freq)
        self.preview_duration_s = preview_duration_s
        #: The simulated rig's named disturbances for the previews and Suggest (the demo's:
        #: those its controller's simulated rig runs with). ConfigError for an unknown name.
        self.sim_setup: RigSetup | None = (
            rig_setup(list(sim_disturbances)) if sim_disturbances else None)
        #: The controller's plant knowledge (`set_knowledge`), the same record its gate
        #: judges on; until it is fetched, the simulated rig's model with the commissioning
        #: bound (what a fresh controller starts with).
        self.plant = PlantKnowledge(bound=COMMISSIONING_BOUND, source="not yet fetched")
        self._plant_lock = threading.Lock()
        #: Bumped with every new plant: cache keys carry it, so that a result computed on the
        #: old plant while the new one arrived is never served for the new one.
        self._generation = 0
        self._evaluations: _Cache[tuple[int, LoopConfig], Evaluation] = _Cache(64)
        self._recommendations: _Cache[tuple[int, LoopConfig], float | None] = _Cache(64)
        self._previews: _Cache[tuple[LoopConfig, Trajectory], PreviewResult] = _Cache(16)
        self._steps: _Cache[tuple[LoopConfig, Any], tuple[FloatArray, FloatArray, FloatArray]] = (
            _Cache(32))

    @property
    def measured(self) -> tuple[MeasuredResponse, ...]:
        return self.plant.measured

    def set_knowledge(self, record: KnowledgeRecord) -> None:
        """Judge on `record` (the controller's plant knowledge); invalidates cached verdicts.
        Raises ValueError for a record that does not validate."""
        plant = record.to_knowledge()
        with self._plant_lock:
            self.plant = plant
            self._generation += 1
            self._evaluations.clear()
            self._recommendations.clear()

    def _current(self) -> tuple[int, PlantKnowledge]:
        with self._plant_lock:
            return self._generation, self.plant

    def with_measured(self, m: MeasuredResponse) -> KnowledgeRecord:
        """The present knowledge plus `m` (same name replaces), as a record to send to the
        controller for adoption (only the controller's knowledge is ever judged on)."""
        p = self.plant
        kept = tuple(x for x in p.measured if x.name != m.name)
        return KnowledgeRecord.of(
            PlantKnowledge((*kept, m), p.bound, p.model, p.version, f"{p.source} + {m.name}")
        )

    def position_spread(self) -> PositionSpread | None:
        """The spread between the knowledge's measured responses (None with fewer than two;
        a few ms: computed on each call)."""
        _, plant = self._current()
        return knowledge_spread(plant, LoopConfig().rate_hz)

    def cached_recommendation(self, cfg: LoopConfig) -> tuple[bool, float | None]:
        """(known, value) without computing."""
        gen, _ = self._current()
        return self._recommendations.lookup((gen, _recommendation_key(cfg)))

    def recommended_max_cutoff_hz(self, cfg: LoopConfig) -> float | None:
        """The gate's largest accepted Q cut-off for this candidate's other settings (cached;
        ~0.1 s, so call it off the slider path)."""
        key = _recommendation_key(cfg)
        gen, plant = self._current()
        return self._recommendations.get((gen, key), lambda: recommended_cutoff_hz(key, plant))

    def evaluate(self, cfg: LoopConfig) -> Evaluation:
        """The gate's verdict and curves for `cfg` (cached)."""
        gen, plant = self._current()
        return self._evaluations.get((gen, cfg), lambda: self._evaluate(cfg, plant))

    def _evaluate(self, cfg: LoopConfig, plant: PlantKnowledge) -> Evaluation:
        t0 = time.perf_counter()
        grid = freq_grid_hz(cfg.rate_hz, self.n_freq)
        curves, view = curves_from_analysis(analyse(cfg, plant, freq_hz=grid), plant)
        # The verdict: the controller's own function on the controller's knowledge (its
        # default grid, not the charts'), so both sides say the same.
        j = judge(cfg, plant, nonlinear=findings)
        gate = dataclasses.replace(
            view, verdict=j.verdict, reasons=j.reasons,
            recommended_max_cutoff_hz=j.recommended_max_cutoff_hz,
            knowledge=j.analysis.knowledge,
        )
        return Evaluation(cfg, curves, gate, time.perf_counter() - t0)

    def compare(self, candidate: LoopConfig, active: LoopConfig) -> Comparison:
        """Candidate and active evaluated, and the data of every Bode chart."""
        cand, act = self.evaluate(candidate), self.evaluate(active)
        data = {spec.key: charts.bode_data(spec.key, cand.curves, act.curves)
                for spec in charts.BODE_CHARTS}
        return Comparison(cand, act, data)

    def preview(self, cfg: LoopConfig, trajectory: Trajectory) -> PreviewResult:
        """The offline experiment over one sine period (12.6 s) or `preview_duration_s`."""
        return self._previews.get((cfg, trajectory), lambda: self._preview(cfg, trajectory))

    def preview_run_s(self, trajectory: Trajectory) -> float:
        """How long a preview runs: one period of a periodic trajectory, else
        `preview_duration_s`, at most 30 s (Suggest runs as long, so its numbers are the
        preview's)."""
        return min(trajectory.period_s or self.preview_duration_s, 30.0)

    def _preview(self, cfg: LoopConfig, trajectory: Trajectory) -> PreviewResult:
        from controller.tune.autotune import command_noise_deg_s, run_point

        t0 = time.perf_counter()
        res = run_point(cfg, trajectory, self.preview_run_s(trajectory), setup=self.sim_setup)
        return PreviewResult(
            config=cfg,
            trajectory=trajectory,
            t_s=np.asarray(res.t_s, dtype=np.float64),
            error_deg=np.asarray(res.error_deg, dtype=np.float64),
            peak_error_deg=float(res.peak_error_deg),
            rmse_deg=float(res.rmse_deg),
            elapsed_s=time.perf_counter() - t0,
            command_noise_deg_s=command_noise_deg_s(res.command_deg_s, cfg.rate_hz),
            disturbances="none" if self.sim_setup is None else self.sim_setup.label,
        )

    def steps(self, cfg: LoopConfig) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Reference and load-disturbance step responses on the plant knowledge's linear model
        (cached; ~25 ms, so off the slider path)."""
        from controller.tune.steps import step_responses

        model = self.plant.model
        return self._steps.get((cfg, model), lambda: step_responses(cfg, model))

    def steps_data(self, candidate: LoopConfig, active: LoopConfig) -> tuple[FloatArray, ...]:
        t, rc, dc = self.steps(candidate)
        _, ra, da = self.steps(active)
        return (t, rc, ra, dc, da)

    def compare_preview(
        self, candidate: LoopConfig, active: LoopConfig, trajectory: Trajectory
    ) -> PreviewComparison:
        """The previews of both configurations and of the candidate with the DOB off (its Q
        settings are not used then: the run is cached whatever the cut-off), and the preview
        chart's data."""
        pc, pa = self.preview(candidate, trajectory), self.preview(active, trajectory)
        pn = self.preview(_without_dob(candidate), trajectory)
        return PreviewComparison(
            pc, pa, charts.preview_data(pc.t_s, pc.error_deg, pa.error_deg, pn.error_deg), pn)
