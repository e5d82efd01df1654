"""The recommended maximum Q cut-off: the top of the accepted region from the lowest cut-off,
and, with responses measured at several turntable positions, below where they diverge.

The second limit is the article's argument (Fig. 13): the responses measured at different
positions agree only at low frequency, so a single model of the plant is trusted only there,
and Q must roll off before the responses part. The spread between them (`PositionSpread`,
relative: |H_i / H_ref - 1|) is a multiplicative plant error Delta that the DOB's model must
allow wherever the turntable stands; the DOB's small-gain figure with it, max_f |Delta(f)|
|Q(f)|, must stay at or below 1 / `SPREAD_MARGIN` (the agreement level, 1 dB). (The figure
alone is not sufficient for stability, control.md: the gate's own analysis is the other
limit, and the smaller wins.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, TypedDict, Unpack

import numpy as np

from controller.core.arrays import ComplexArray
from controller.core.config import LoopConfig
from controller.core.qfilter import Q_TYPES, QType, check_q_type, design_q
from controller.gate.analysis import GateLimits, accepted, accepted_cutoffs
from controller.gate.knowledge import (
    DIVERGENCE_FRACTION,
    MeasuredResponse,
    PlantKnowledge,
    PositionSpread,
    position_spread,
)
from controller.gate.loop_model import TWO_PI, discrete_equivalent

__all__ = [
    "SPREAD_MARGIN",
    "Recommendation",
    "RecommendationSearch",
    "SearchOptions",
    "TopSearch",
    "cached_recommendation",
    "knowledge_spread",
    "recommend",
    "recommendation_key",
    "recommendation_search",
    "recommended_max_cutoff_hz",
    "spread_figure",
    "spread_limited_cutoff_hz",
]

#: The position spread's figure max |Delta Q| is held at or below 1 / SPREAD_MARGIN =
#: `DIVERGENCE_FRACTION` (1 dB): Q passes no more model error than the level at which the
#: responses still count as agreeing, so it rolls off where they diverge (the article's
#: argument). That is 18 dB from the small-gain limit |Delta Q| = 1: the spread at a few
#: positions is a sample of the plant's variation, not its bound.
SPREAD_MARGIN = 1.0 / DIVERGENCE_FRACTION


@dataclass(frozen=True)
class Recommendation:
    """The recommended maximum cut-off for one Q type and what limits it."""

    q_type: str
    recommended_hz: float | None
    """min(gate_hz, spread_hz); None when the gate accepts not even the lowest cut-off."""
    gate_hz: float | None
    """The top of the gate's accepted region from the lowest cut-off."""
    spread_hz: float | None
    """The largest cut-off with max |Delta Q| <= 1 / margin (None: no spread evidence, or even
    the lowest cut-off exceeds it)."""
    spread: PositionSpread | None
    margin: float

    @property
    def limited_by_spread(self) -> bool:
        return (
            self.spread is not None
            and self.gate_hz is not None
            and self.recommended_hz is not None
            and self.recommended_hz < self.gate_hz
        )

    def describe(self) -> str:
        """One line: the recommendation and its limits."""
        def hz(v: float | None) -> str:
            return "none" if v is None else f"{v:.3g} Hz"

        if self.spread is None:
            return f"{self.q_type}: {hz(self.recommended_hz)} (gate; no position spread)"
        div = self.spread.divergence_hz
        where = (
            f"the {len(self.spread.names)} responses diverge above {div:.3g} Hz"
            if div is not None
            else f"the {len(self.spread.names)} responses agree on their whole band"
        )
        return (
            f"{self.q_type}: {hz(self.recommended_hz)} (gate alone {hz(self.gate_hz)}; "
            f"position spread |Delta Q| <= {1.0 / self.margin:.3g}: {hz(self.spread_hz)}; {where})"
        )


def knowledge_spread(plant: PlantKnowledge, rate_hz: float) -> PositionSpread | None:
    """The spread across the knowledge's measured responses (None with fewer than two)."""

    def continuous(m: MeasuredResponse) -> ComplexArray:
        if not m.sampled:
            return m.response
        return m.response / discrete_equivalent(np.ones(m.freq_hz.size), m.freq_hz, rate_hz)

    return position_spread(plant.measured, continuous)


def _q_mag(q_type: QType, cutoff_hz: float, freq_hz: np.ndarray) -> np.ndarray:
    num, den = design_q(q_type, cutoff_hz=cutoff_hz).tf()
    s = 1j * TWO_PI * freq_hz
    return np.asarray(np.abs(np.polyval(num, s) / np.polyval(den, s)), dtype=np.float64)


def _spread_grid(spread: PositionSpread) -> np.ndarray:
    """The spread's own points, a dense log grid over its band and a decade above it (the
    spread held at the edge there)."""
    lo, hi = float(spread.freq_hz[0]), float(spread.freq_hz[-1])
    return np.union1d(spread.freq_hz, np.geomspace(lo, 10.0 * hi, 1200))


def spread_figure(q_type: str, cutoff_hz: float, spread: PositionSpread) -> float:
    """max_f |Delta(f)| |Q(f)| with Delta the position spread (continuous Q)."""
    qt = check_q_type(q_type)
    f = _spread_grid(spread)
    return float(np.max(spread.at(f) * _q_mag(qt, cutoff_hz, f)))


def spread_limited_cutoff_hz(
    q_type: str,
    spread: PositionSpread,
    margin: float = SPREAD_MARGIN,
    *,
    lowest_hz: float = 0.01,
    highest_hz: float = 100.0,
    rel_tol: float = 1e-3,
) -> float | None:
    """The largest cut-off whose `spread_figure` stays <= 1 / margin, searched from
    `lowest_hz` up (the first crossing, bisected in log cut-off to `rel_tol`); `highest_hz`
    if it never crosses; None if `lowest_hz` already exceeds it."""
    if not (margin >= 1.0 and math.isfinite(margin)):
        raise ValueError(f"margin: {margin!r} must be >= 1")
    limit = 1.0 / margin

    def ok(fc: float) -> bool:
        return spread_figure(q_type, fc, spread) <= limit

    return _top_of(ok, np.geomspace(lowest_hz, highest_hz, 60), rel_tol)


class SearchOptions(TypedDict, total=False):
    """How the recommendation is searched (`RecommendationSearch`'s keyword arguments, with
    its defaults): `spread_margin` (None: the gate alone), the cut-offs scanned from
    `lowest_hz` to `highest_hz` (None: a tenth of the loop rate) on `coarse_points`, bisected
    to `rel_tol`."""

    spread_margin: float | None
    lowest_hz: float
    highest_hz: float | None
    coarse_points: int
    rel_tol: float


def recommend(
    cfg: LoopConfig,
    plant: PlantKnowledge | None = None,
    limits: GateLimits | None = None,
    q_type: str | None = None,
    **options: Unpack[SearchOptions],
) -> Recommendation:
    """The gate's top cut-off and, with two or more measured responses, the position spread's
    limit (`spread_margin` None: the gate alone)."""
    return RecommendationSearch(cfg, plant, limits, q_type, **options).recommendation()


class RecommendationSearch:
    """`recommend` for one configuration's gains and one plant knowledge, searched only as far
    as each question needs (`decide`: is a cut-off above the recommendation?) and completed
    on demand (`recommendation`, `value`); what was evaluated is kept for the next question.

    The answers are the whole search's, exactly: the gate's accepted region is searched by a
    `TopSearch` (the same evaluations, in the same order, as the whole search) and the
    position spread's limit, which does not depend on the gains, is computed once per plant
    knowledge and Q type (`_spread_limit`)."""

    def __init__(
        self,
        cfg: LoopConfig,
        plant: PlantKnowledge | None = None,
        limits: GateLimits | None = None,
        q_type: str | None = None,
        *,
        spread_margin: float | None = SPREAD_MARGIN,
        lowest_hz: float = 0.02,
        highest_hz: float | None = None,
        coarse_points: int = 16,
        rel_tol: float = 0.01,
    ) -> None:
        qt: QType = check_q_type(q_type if q_type is not None else cfg.q_type)
        self.q_type = qt
        self.gate = _gate_search(cfg, plant, limits, qt, lowest_hz, highest_hz, coarse_points,
                                 rel_tol)
        self.spread: PositionSpread | None = None
        self.spread_hz: float | None = None
        self.margin = spread_margin if spread_margin is not None else math.nan
        if spread_margin is not None and plant is not None:
            self.spread, self.spread_hz = _spread_limit(plant, cfg.rate_hz, qt, spread_margin)

    def none(self) -> bool:
        """No recommendation: the gate accepts not even the lowest cut-off, or the position
        spread allows none (one evaluation at most)."""
        if self.spread is not None and self.spread_hz is None:
            return True
        return self.gate.none()

    def decide(self, holds: Callable[[float], bool]) -> bool | None:
        """`holds(recommended_hz)` (None when there is no recommendation) for a `holds` that
        is monotone non-decreasing in the cut-off (once true, true for every larger one),
        evaluating the gate's region only until the answer is certain."""
        if self.spread is not None and (self.spread_hz is None or not holds(self.spread_hz)):
            # No recommendation, or min(gate, spread) <= spread: False unless the gate has
            # none either.
            return None if self.none() else False
        if self.gate.none():  # (the first point alone: often all that a rejection needs)
            return None
        self.gate.prefetch(holds)
        return self.gate.decide(holds)

    @property
    def complete(self) -> bool:
        """The search has run to its end (`value` evaluates nothing more)."""
        return self.gate.done

    def value(self) -> float | None:
        """The recommended maximum cut-off (the whole search)."""
        gate_hz = self.gate.value()
        if gate_hz is None or self.spread is None:
            return gate_hz
        return None if self.spread_hz is None else min(gate_hz, self.spread_hz)

    def recommendation(self) -> Recommendation:
        return Recommendation(self.q_type, self.value(), self.gate.value(), self.spread_hz,
                              self.spread, self.margin)


#: Recommendation searches by (configuration without its cut-off and DOB switch, plant
#: knowledge object, limits): everything the recommendation depends on (the knowledge object
#: stands for its evidence: a new record is a new object). Bounded.
_SEARCHES: dict[tuple[LoopConfig, PlantKnowledge, GateLimits], RecommendationSearch] = {}
_SEARCHES_MAX = 64


def recommendation_search(
    cfg: LoopConfig, plant: PlantKnowledge, limits: GateLimits | None = None
) -> RecommendationSearch:
    """The `RecommendationSearch` for cfg's Q type, gains and limits on `plant`, shared by
    every configuration that differs from cfg only in the cut-off or the DOB switch: moving
    the cut-off costs at most the rest of one search; new gains, knowledge or limits start a
    new one."""
    limits = limits if limits is not None else GateLimits()
    key = (recommendation_key(cfg), plant, limits)
    found = _SEARCHES.get(key)
    if found is None:
        # (Two threads may both start one: each is right; one is kept.)
        found = RecommendationSearch(key[0], plant, limits)
        if len(_SEARCHES) >= _SEARCHES_MAX:
            _SEARCHES.clear()  # what a tuning session revisits is recent: it comes back
        _SEARCHES[key] = found
    return found


def recommendation_key(cfg: LoopConfig) -> LoopConfig:
    """What the recommendation depends on in a configuration: all but the cut-off and the
    DOB switch."""
    return cfg.with_(q_cutoff_hz=1.0, dob_on=True)


def cached_recommendation(
    cfg: LoopConfig, plant: PlantKnowledge, limits: GateLimits | None = None
) -> tuple[bool, float | None]:
    """(known, value) of the recommended cut-off from the one cache, without evaluating
    anything: known once a search for cfg's gains on `plant` has run to its end."""
    limits = limits if limits is not None else GateLimits()
    found = _SEARCHES.get((recommendation_key(cfg), plant, limits))
    if found is None or not found.complete:
        return False, None
    return True, found.value()


_SPREADS: dict[tuple[PlantKnowledge, float, str, float],
               tuple[PositionSpread | None, float | None]] = {}
_SPREADS_MAX = 16


def _spread_limit(
    plant: PlantKnowledge, rate_hz: float, q_type: QType, margin: float
) -> tuple[PositionSpread | None, float | None]:
    """(knowledge_spread, spread_limited_cutoff_hz) per (plant knowledge object, rate, Q type,
    margin): the gains do not enter it."""
    key = (plant, rate_hz, q_type, margin)
    got = _SPREADS.get(key)
    if got is None:
        spread = knowledge_spread(plant, rate_hz)
        got = (spread, None if spread is None else spread_limited_cutoff_hz(q_type, spread,
                                                                              margin))
        if len(_SPREADS) >= _SPREADS_MAX:
            _SPREADS.clear()
        _SPREADS[key] = got
    return got


def recommended_max_cutoff_hz(
    cfg: LoopConfig,
    plant: PlantKnowledge | None = None,
    limits: GateLimits | None = None,
    q_type: str | None = None,
    **options: Unpack[SearchOptions],
) -> float | None:
    """Largest Q cut-off (Hz) recommended for `q_type` (default cfg.q_type), DOB on: the top of
    the gate's accepted region, and below the position spread's limit when the knowledge
    holds responses measured at two or more positions (`recommend`)."""
    return recommend(cfg, plant, limits, q_type, **options).recommended_hz


def _gate_search(
    cfg: LoopConfig, plant: PlantKnowledge | None, limits: GateLimits | None, qt: QType,
    lowest_hz: float, highest_hz: float | None, coarse_points: int, rel_tol: float,
) -> TopSearch:
    """The search for the largest Q cut-off (Hz) the gate accepts, DOB on.

    Acceptance is assumed to hold on an interval from low cut-offs up to a limit (robustness
    and margins degrade as the Q bandwidth grows), though not strictly monotone. Guard: scan
    `coarse_points` log-spaced cut-offs from `lowest_hz` to `highest_hz` (default: a tenth of
    the loop rate), take the first accept -> reject transition from below, then bisect it in
    log cut-off to `rel_tol`. None if `lowest_hz` is already rejected.
    """
    assert qt in Q_TYPES
    top = highest_hz if highest_hz is not None else 0.1 * cfg.rate_hz
    top = min(top, 0.45 * cfg.rate_hz)
    base = cfg.with_(dob_on=True, q_type=qt)

    def ok(fc: float) -> bool:
        return accepted(base.with_(q_cutoff_hz=fc), plant, limits)

    def ok_many(fcs: list[float]) -> list[bool]:
        return accepted_cutoffs(base, fcs, plant, limits)

    return TopSearch(ok, np.geomspace(lowest_hz, top, coarse_points), rel_tol, ok_many)


def _top_of(ok: Callable[[float], bool], grid: np.ndarray, rel_tol: float) -> float | None:
    """The first ok -> not ok transition on `grid` from below, bisected in log to `rel_tol`
    (the grid's top if there is none; None if its first point is not ok)."""
    return TopSearch(ok, grid, rel_tol).value()


class _TopState(NamedTuple):
    """Where a `TopSearch` stands (immutable: a step makes a new one)."""

    next: int
    """Coarse points evaluated."""
    lo: float | None
    """The largest point known ok on the way (the answer is at least this)."""
    hi: float | None
    """The transition's upper end (not ok), once the coarse scan found it."""
    done: bool
    value: float | None


class TopSearch:
    """`_top_of` one evaluation at a time: ok() is evaluated only as far as a question needs,
    each point once, in the order of the whole search (so every answer is the whole search's:
    the coarse scan from below up to the first point that is not ok, then the bisection of
    that transition in log to `rel_tol`).

    Safe to share between threads without a lock (this package runs none): a step is a pure
    function of the state it starts from and ok() (deterministic), so two threads stepping
    from the same state make the same next state, and a thread that stepped from an older
    one sets a state the search has passed through (its work is redone, never wrong)."""

    def __init__(self, ok: Callable[[float], bool], grid: np.ndarray, rel_tol: float,
                 ok_many: Callable[[list[float]], list[bool]] | None = None) -> None:
        self._ok = ok
        self._ok_many = ok_many
        self._grid = tuple(float(g) for g in grid)
        self._rel_tol = rel_tol
        self._state = _TopState(0, None, None, False, None)
        self._seen: dict[float, bool] = {}

    @property
    def done(self) -> bool:
        """The search has run to its end."""
        return self._state.done

    @property
    def evaluations(self) -> int:
        """Points evaluated so far."""
        return len(self._seen)

    def _good(self, fc: float) -> bool:
        good = self._seen.get(fc)
        if good is None:
            good = self._seen[fc] = bool(self._ok(fc))
        return good

    def prefetch(self, holds: Callable[[float], bool]) -> None:
        """Evaluate together (`ok_many`: one refinement for all) the coarse points `decide`
        (holds) evaluates if they are all ok: from where the scan stands up to the first
        point at which `holds` is true. Only what is evaluated changes, never the order of
        the search's steps: a point after one that is not ok is evaluated for nothing."""
        st = self._state
        if self._ok_many is None or st.done or st.hi is not None:
            return
        grid = self._grid
        if not holds(grid[-1]):
            return  # (decide answers at the first ok point)
        end = next(k for k in range(st.next, len(grid)) if holds(grid[k]))
        todo = [fc for fc in grid[st.next : end + 1] if fc not in self._seen]
        if len(todo) > 1:
            self._seen.update(zip(todo, (bool(v) for v in self._ok_many(todo)), strict=True))

    def _step(self, st: _TopState) -> _TopState:
        """The state after one more evaluation (`st` not done)."""
        if st.hi is None:  # the coarse scan
            fc = self._grid[st.next]
            n = st.next + 1
            if self._good(fc):
                done = n == len(self._grid)
                return _TopState(n, fc, None, done, fc if done else None)
            if st.lo is None:
                return _TopState(n, None, None, True, None)
            lo, hi = st.lo, fc
        else:  # the bisection
            assert st.lo is not None
            n, lo, hi = st.next, st.lo, st.hi
            mid = math.sqrt(lo * hi)
            if self._good(mid):
                lo = mid
            else:
                hi = mid
        if not hi / lo > 1.0 + self._rel_tol:
            return _TopState(n, lo, hi, True, lo)
        return _TopState(n, lo, hi, False, None)

    def _advance(self, st: _TopState) -> _TopState:
        new = self._step(st)
        if self._state is st:
            self._state = new
        return new

    def none(self) -> bool:
        """The first point is not ok (no top)."""
        st = self._state
        while not st.done and st.lo is None:
            st = self._advance(st)
        return st.done and st.value is None

    def decide(self, holds: Callable[[float], bool]) -> bool | None:
        """`holds(value)` (None if there is no top) for a `holds` monotone non-decreasing in
        the cut-off, from the bracket known so far where it settles the answer: the value is
        at least the largest ok point and at most the transition's upper end (the grid's top
        during the coarse scan)."""
        st = self._state
        while not st.done:
            if st.lo is not None:
                if holds(st.lo):
                    return True
                if not holds(st.hi if st.hi is not None else self._grid[-1]):
                    return False
            st = self._advance(st)
        return None if st.value is None else holds(st.value)

    def value(self) -> float | None:
        st = self._state
        while not st.done:
            st = self._advance(st)
        return st.value
