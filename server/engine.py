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
from typing import Generic, TypeVar

import numpy as np
import numpy.typing as npt

from controller.core.arrays import FloatArray
from controller.core.config import LoopConfig, NominalModel
from controller.core.errors import ConfigError
from controller.core.trajectory import Trajectory
from controller.core.verdict import Verdict
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
from controller.gate.search import cached_recommendation, knowledge_spread
from controller.gate.verdict import recommended_cutoff_hz, verdict_of
from controller.sim.nonlinear_check import findings
from controller.sim.rig_disturbances import RigSetup, rig_setup
from controller.tune.plant import SimPlant
from server import charts
from server.charts import BodeCurves, NyquistLoop, PlantCurves

__all__ = [
    "CUTOFF_MAX_HZ",
    "CUTOFF_MIN_HZ",
    "Comparison",
    "ConfigError",
    "Evaluation",
    "PreviewComparison",
    "PreviewResult",
    "TuningEngine",
    "analysis_loop",
    "candidate_from_values",
    "chart_index",
    "curves_from_analysis",
    "freq_grid_hz",
    "plant_curves",
    "speed_loop",
]

#: Range of the Q cut-off the dashboard offers, Hz.
CUTOFF_MIN_HZ = 0.05
CUTOFF_MAX_HZ = 50.0


@dataclass(frozen=True)
class Evaluation:
    """One configuration's curves and verdict (both from its one analysis), and how long the
    evaluation took."""

    config: LoopConfig
    curves: BodeCurves
    verdict: Verdict
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
    plant_source: str = ""
    """What the run simulated: the rig's twin (from the measured responses) or the built-in
    model when nothing was measured (`controller.tune.plant.SimPlant.source`)."""


@dataclass(frozen=True)
class PreviewComparison:
    """The previews of the candidate, the same gains with the DOB off, and the active
    configuration, and the chart data."""

    candidate: PreviewResult
    active: PreviewResult
    chart_data: tuple[FloatArray, ...]
    no_dob: PreviewResult | None = None
    """The candidate's run with the DOB off (its price and value side by side)."""


#: The charts draw every CHART_STEP-th point of the gate's grid (and its last): the 500-point
#: grid the verdict is computed on, thinned to ~250 points for the browser.
CHART_STEP = 2


def chart_index(n: int) -> npt.NDArray[np.intp]:
    """The indices of the gate's n-point grid the charts draw."""
    idx = np.arange(0, n, CHART_STEP)
    return idx if idx[-1] == n - 1 else np.append(idx, n - 1)


def freq_grid_hz(rate_hz: float = 1000.0) -> FloatArray:
    """The Bode plots' grid: the gate's own grid (0.01 Hz to just under Nyquist), thinned
    (`chart_index`)."""
    f = default_grid(rate_hz)
    return np.asarray(f[chart_index(f.size)], dtype=np.float64)


def candidate_from_values(base: LoopConfig, values: dict[str, object]) -> LoopConfig:
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


def analysis_loop(a: Analysis, idx: npt.NDArray[np.intp]) -> NyquistLoop:
    """The speed loop of `a` (with the DOB as `a.config.dob_on` says) for the Nyquist view,
    straight from the analysis: its loop on the grid points `idx`, and the crossings and
    margins the analysis refined (the gate's own figures, not a second computation)."""
    c = a.crossings
    assert c is not None, "an Analysis from analyse() carries its crossings"
    return NyquistLoop(
        response=np.asarray(a.open_loop[idx], dtype=np.complex128),
        gain_crossover_hz=np.array(c.gain_crossover_hz, dtype=np.float64),
        gain_crossings=np.array(c.gain_crossings, dtype=np.complex128),
        phase_crossover_hz=np.array(c.phase_crossover_hz, dtype=np.float64),
        phase_crossings=np.array(c.phase_crossings, dtype=np.complex128),
        phase_margin_deg=a.margins.phase_margin_deg,
        gain_margin_db=a.margins.gain_margin_db,
    )


def thinned(loop: NyquistLoop, idx: npt.NDArray[np.intp]) -> NyquistLoop:
    """`loop` with its response at the grid points `idx` only (the crossings stay)."""
    return dataclasses.replace(loop, response=np.asarray(loop.response[idx]))


def plant_curves(plant: PlantKnowledge, freq_hz: FloatArray, rate_hz: float) -> PlantCurves:
    """The plant chart's curves: the knowledge's model M P (continuous) and its measured
    responses with their spread (`charts.spread_band_db`), on `freq_hz` merged with every
    measured frequency. With measured responses the grid starts at the lowest measured
    frequency (the chart shows where the plant was measured). Sampled responses (u[k] ->
    w[k]) are brought to the continuous basis by dividing out the gate's ZOH +
    backward-difference factor (`discrete_equivalent`)."""
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


def curves_from_analysis(
    a: Analysis,
    plant: PlantKnowledge,
    *,
    other_loop: NyquistLoop | None = None,
    plant_chart: PlantCurves | None = None,
) -> BodeCurves:
    """Adapter: the gate's Analysis (of `a.config` on `plant`, on the gate's grid) -> what the
    charts draw, on every `CHART_STEP`-th point of that grid. The Nyquist view's loop in the
    configured DOB state is the analysis's own; `other_loop` (the other DOB state, on the
    analysis grid) and `plant_chart` (the plant chart's curves on the charts' grid) are
    computed here when not given (the engine caches what does not depend on the cut-off)."""
    idx = chart_index(a.freq_hz.size)
    f = np.asarray(a.freq_hz[idx], dtype=np.float64)
    if other_loop is None:
        other_loop = speed_loop(a.config, plant.model, a.freq_hz, dob=not a.config.dob_on)
    own, other = analysis_loop(a, idx), thinned(other_loop, idx)
    bound = [src.inv_delta_db[idx] for src in a.sources if src.kind == "bound"]
    measured = [src.inv_delta_db[idx] for src in a.sources if src.kind == "measured"]
    loop = a.open_loop[idx]
    loop_full = None if a.open_loop_full is None else a.open_loop_full[idx]
    return BodeCurves(
        freq_hz=f,
        open_loop_db=a.open_loop_mag_db[idx],
        open_loop_phase_deg=_wrap_start(a.open_loop_phase_deg[idx]),
        closed_dob_db=charts.db(a.closed_loop_dob[idx]),
        closed_nodob_db=charts.db(a.closed_loop_no_dob[idx]),
        dist_dob_db=charts.db(a.disturbance_dob[idx]),
        dist_nodob_db=charts.db(a.disturbance_no_dob[idx]),
        noise_dob_db=charts.db(a.noise_dob[idx]),
        noise_nodob_db=charts.db(a.noise_no_dob[idx]),
        q_db=a.q_mag_db[idx],
        rejection_db=a.rejection_db[idx],
        inv_delta_db=bound[0] if bound else None,
        # The worst measured response at each frequency (smallest 1/|Delta|).
        inv_delta_measured_db=np.min(np.stack(measured), axis=0) if measured else None,
        s_db=charts.db(1.0 / (1.0 + loop)),
        t_db=charts.db(loop / (1.0 + loop)),
        s_full_db=None if loop_full is None else charts.db(1.0 / (1.0 + loop_full)),
        t_full_db=None if loop_full is None else charts.db(loop_full / (1.0 + loop_full)),
        nyquist_dob=own if a.config.dob_on else other,
        nyquist_nodob=other if a.config.dob_on else own,
        dob_on=a.config.dob_on,
        plant=plant_chart if plant_chart is not None else plant_curves(
            plant, f, a.config.rate_hz),
    )


def _wrap_start(phase_deg: FloatArray) -> FloatArray:
    """Shift an unwrapped phase by whole turns so that it starts in (-270, 90] deg."""
    if len(phase_deg) == 0:
        return phase_deg
    turns = math.floor((phase_deg[0] + 270.0) / 360.0)
    return np.asarray(phase_deg - 360.0 * turns, dtype=np.float64)


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


class TuningEngine:
    """Evaluates candidates; caches the evaluation of configurations seen before."""

    def __init__(self, preview_duration_s: float = 12.6,
                 sim_disturbances: tuple[str, ...] = ()):
        #: The charts' grid (the gate's grid, thinned: `freq_grid_hz`).
        self.freq_hz = freq_grid_hz(1000.0)
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
        #: What does not depend on the cut-off: the Nyquist view's loop in the other DOB state
        #: when the DOB is on (G Cv: the gains and the plant), and the plant chart's curves.
        self._loops_without_dob: _Cache[tuple[int, LoopConfig], NyquistLoop] = _Cache(64)
        self._plant_charts: _Cache[tuple[int, float], PlantCurves] = _Cache(4)
        self._previews: _Cache[tuple[int, LoopConfig, Trajectory], PreviewResult] = _Cache(16)
        #: What the previews run on, per plant generation (the twin's fit takes a while).
        self._sim_plants: _Cache[int, SimPlant] = _Cache(2)
        self._steps: _Cache[tuple[LoopConfig, NominalModel],
                            tuple[FloatArray, FloatArray, FloatArray]] = (
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
            self._loops_without_dob.clear()
            self._plant_charts.clear()

    def _current(self) -> tuple[int, PlantKnowledge]:
        with self._plant_lock:
            return self._generation, self.plant

    def with_measured(self, *ms: MeasuredResponse) -> KnowledgeRecord:
        """The present knowledge plus `ms` (same name replaces), as a record to send to the
        controller for adoption (only the controller's knowledge is ever judged on)."""
        p = self.plant
        names = {m.name for m in ms}
        kept = tuple(x for x in p.measured if x.name not in names)
        return KnowledgeRecord.of(PlantKnowledge(
            (*kept, *ms), p.bound, p.model, p.version,
            f"{p.source} + {' + '.join(m.name for m in ms)}"))

    def position_spread(self) -> PositionSpread | None:
        """The spread between the knowledge's measured responses (None with fewer than two;
        a few ms: computed on each call)."""
        _, plant = self._current()
        return knowledge_spread(plant, LoopConfig().rate_hz)

    def cached_recommendation(self, cfg: LoopConfig) -> tuple[bool, float | None]:
        """(known, value) without computing (the gate's one cache, `recommended_cutoff_hz`)."""
        _, plant = self._current()
        return cached_recommendation(cfg, plant)

    def recommended_max_cutoff_hz(self, cfg: LoopConfig) -> float | None:
        """The gate's largest accepted Q cut-off for this candidate's other settings (cached;
        ~0.1 s, so call it off the slider path)."""
        _, plant = self._current()
        return recommended_cutoff_hz(cfg, plant)

    def evaluate(self, cfg: LoopConfig) -> Evaluation:
        """The gate's verdict and curves for `cfg` (cached)."""
        gen, plant = self._current()
        return self._evaluations.get((gen, cfg), lambda: self._evaluate(cfg, gen, plant))

    def _evaluate(self, cfg: LoopConfig, gen: int, plant: PlantKnowledge) -> Evaluation:
        """One analysis on the gate's grid (the controller's own, `analyse` with its
        defaults): the verdict (`verdict_of`, the controller's function on the controller's
        knowledge: both sides say the same) and every chart come from it."""
        t0 = time.perf_counter()
        a = analyse(cfg, plant)
        # The verdict alone, as the controller's gate judges (the recommendation is searched
        # only as far as the verdict needs); the whole search runs off the slider path
        # (`recommended_max_cutoff_hz`, the same cache).
        verdict = verdict_of(a, plant, nonlinear=findings, recommendation=False)
        other = None
        if cfg.dob_on:  # G Cv: the same for every cut-off
            other = self._loops_without_dob.get(
                (gen, _without_dob(cfg)),
                lambda: speed_loop(cfg, plant.model, a.freq_hz, dob=False))
        f = self.freq_hz if cfg.rate_hz == 1000.0 else freq_grid_hz(cfg.rate_hz)
        plant_chart = self._plant_charts.get(
            (gen, cfg.rate_hz), lambda: plant_curves(plant, f, cfg.rate_hz))
        curves = curves_from_analysis(a, plant, other_loop=other, plant_chart=plant_chart)
        return Evaluation(cfg, curves, verdict, time.perf_counter() - t0)

    def compare(self, candidate: LoopConfig, active: LoopConfig) -> Comparison:
        """Candidate and active evaluated, and the data of every Bode chart."""
        cand, act = self.evaluate(candidate), self.evaluate(active)
        data = {spec.key: charts.bode_data(spec.key, cand.curves, act.curves)
                for spec in charts.BODE_CHARTS}
        return Comparison(cand, act, data)

    def preview(self, cfg: LoopConfig, trajectory: Trajectory) -> PreviewResult:
        """The offline experiment over one sine period (12.6 s) or `preview_duration_s`, on
        the plant `sim_plant` names."""
        gen, plant = self._current()
        return self._previews.get((gen, cfg, trajectory),
                                  lambda: self._preview(cfg, trajectory, gen, plant))

    def sim_plant(self) -> SimPlant:
        """What predictions run on, as Suggest and `dobtune autotune` do (`plant_for`): the
        rig's twin fitted to the knowledge's measured responses with the demo's named
        disturbances on top; the built-in model when nothing was measured (its `source` says
        so). ValueError when the twin cannot be fitted (said, never a silent fall back)."""
        gen, plant = self._current()
        return self._sim_plants.get(gen, lambda: self._plant_for(plant))

    def _plant_for(self, plant: PlantKnowledge) -> SimPlant:
        from controller.tune.plant import plant_for

        return plant_for(plant, self.sim_setup or rig_setup(()))

    def preview_run_s(self, trajectory: Trajectory) -> float:
        """How long a preview runs: one period of a periodic trajectory, else
        `preview_duration_s`, at most 30 s (Suggest runs as long, so its numbers are the
        preview's)."""
        return min(trajectory.period_s or self.preview_duration_s, 30.0)

    def _preview(self, cfg: LoopConfig, trajectory: Trajectory, gen: int,
                 plant: PlantKnowledge) -> PreviewResult:
        from controller.tune.autotune import command_noise_deg_s, run_point

        t0 = time.perf_counter()
        sim = self._sim_plants.get(gen, lambda: self._plant_for(plant))
        res = run_point(cfg, trajectory, self.preview_run_s(trajectory), plant=sim)
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
            plant_source=sim.source,
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
