"""Frequency-response identification on the loop: measure -> fit -> recommend (no I/O).

`run_identification` drives a rig-like object (``read() -> (pos_deg, speed_deg_s)``,
``step(command_deg_s)``) tick by tick, exactly as the controller would, and returns the
measured responses, the second-order fit of Mn Pn, Delta per position and the gate's
recommended Q cut-offs. It never sleeps: against `SimRig` it runs faster than real time.

How the excitation is applied (and why):

* The turntable has stiction and a belt with backlash and compliance. Around a standstill every
  speed reversal loses a few tenths of a degree of motion, so a small sine about hold is very
  nonlinear (on the simulated rig, 1 deg/s about hold reads -6 dB / -38 deg at 1 Hz and is
  meaningless at 5 Hz). Moving one way the small-signal response is linear (within 0.3 dB of
  M(s)P(s) on the simulated rig at 1-20 deg/s). So each excitation segment rides on a constant
  speed offset ``v0 = offset_ratio * a`` (``a`` the excitation amplitude), which the load never
  reverses: ramp the offset up, measure, ramp it down.
* The position window (``+-window_deg`` about each measurement position) bounds the travel.
  Segments alternate direction so the load sweeps back and forth inside the window; each
  segment's exact position excursion (integral of the planned command) is planned beforehand
  and its amplitude (and so the offset) is reduced until the segment fits in
  ``travel_fraction`` of the window. When a segment does not fit from where the load is, the
  position loop first moves it to the edge of the window it starts from. The low frequencies,
  which take longest, therefore get the smallest amplitudes.
* Stepped sine: one segment per frequency (whole periods, settling then measurement).
  Multisine: one segment per position (transient period + measured periods).
* Open mode: the command sent is ``u = +-v0 + x`` (no controller in the loop); the estimate is
  H1 from u to w. Closed mode: the speed loop (Cv and the DOB of `cfg`) tracks ``r = +-v0`` and
  the excitation is added after it, ``u = sat(loop.tick_speed(r, w) + x)``; the DOB is fed the
  command actually sent (``loop.u_prev = u``), as it must be, so it does not cancel the
  excitation as if it were a disturbance. The estimate is ``S_xw / S_xu``, unbiased under the
  feedback.
* Responses are measured sample by sample, u[k] -> w[k]; the zero-order hold and the
  backward-difference rate add about one tick of delay
  (`controller.gate.analysis.discrete_equivalent`).
  The estimates reported, written to CSV and used for the fit and the gate are the
  continuous-equivalent responses (that factor divided out), the form `dobtune check --frd`
  expects; the raw sampled estimates are kept too.

Limits: the excitation amplitude (``|x| <= amplitude_deg_s`` by construction; offset plus
amplitude must stay below the command limit), the position window (checked every tick, during
excitation and repositioning) and the maximum duration (checked before the start against the
plan and every tick). A limit hit stops the motor (command 0 for `stop_s`), then holds the
position with the position loop for `hold_s`, keeps all data recorded so far (marked incomplete)
and raises `IdentifyAborted` carrying the partial result.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from controller.core.config import LoopConfig, NominalModel
from controller.core.errors import ConfigError
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.validate import number, positive
from controller.gate.analysis import (
    MeasuredResponse,
    PlantKnowledge,
    analyse,
    discrete_equivalent,
    recommended_max_cutoff_hz,
)
from controller.ident.estimate import (
    Agreement,
    FrdEstimate,
    agreement,
    estimate_multisine,
    estimate_stepped_sine,
)
from controller.ident.excitation import (
    Multisine,
    MultisineSpec,
    SteppedSine,
    SteppedSineSpec,
    multisine,
    stepped_sine,
)
from controller.ident.model_fit import (
    ModelUncertainty,
    SecondOrderFit,
    fit_second_order,
    frd_weights,
    uncertainty_bound,
)
from controller.process.runtime import ExcitationProgram

__all__ = [
    "MODES",
    "PHASE_ABORT",
    "PHASE_EXCITE",
    "PHASE_MOVE",
    "SIGNALS",
    "GateCheck",
    "IdentifyAborted",
    "IdentifyResult",
    "IdentifySpec",
    "PositionRecord",
    "ProgramPlan",
    "ProgressFn",
    "RawRecord",
    "RigLike",
    "fitted_nominal",
    "plan_program",
    "result_from_program",
    "run_identification",
    "to_program",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Mode = Literal["open", "closed"]
SignalKind = Literal["sine", "multisine"]
MODES: tuple[str, ...] = ("open", "closed")
SIGNALS: tuple[str, ...] = ("sine", "multisine")

#: Values of `RawRecord.phase`.
PHASE_MOVE, PHASE_EXCITE, PHASE_ABORT = 0, 1, 2

ProgressFn = Callable[[float, str], None]

_RAMP_S = 0.3  # offset ramp up / down (raised cosine)
_STEADY_S = 0.2  # constant offset before the excitation starts
_STILL_S = 0.1  # command 0 (open) or r = 0 (closed) after a segment
_MIN_MOVE_S = 0.3


class RigLike(Protocol):
    """What identification needs from a rig (SimRig, CanRig, ...)."""

    def read(self) -> tuple[float, float]: ...

    def step(self, command_deg_s: float) -> None: ...


# --------------------------------------------------------------------------------- the spec


def _integer(value: object, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(name, f"must be an integer (got {value!r})")
    v = int(value)
    if not lo <= v <= hi:
        raise ConfigError(name, f"must be in [{lo}, {hi}] (got {v})")
    return v


@dataclass(frozen=True, slots=True)
class IdentifySpec:
    """What to measure and within which limits; validated on construction.

    Invalid values raise `ConfigError` whose message starts with the field name.
    """

    mode: str = "open"
    """``open`` (u = offset + x, no controller) or ``closed`` (speed loop active, x added)."""
    signal: str = "sine"
    """``sine`` (stepped sine) or ``multisine`` (periodic, Schroeder phases)."""
    f_min_hz: float = 0.1
    f_max_hz: float = 20.0
    points_per_decade: int = 10
    positions: int = 3
    """Measurement positions, evenly spread: ``first_position_deg + span_deg * k / positions``."""
    span_deg: float = 360.0
    """Spread of the positions (360: a full turn, so 3 positions are 0, 120, 240 deg)."""
    first_position_deg: float = 0.0
    amplitude_deg_s: float = 10.0
    """Largest excitation amplitude (speed, load side); lowered where the window needs it."""
    window_deg: float = 60.0
    """Half-width of the position window about each measurement position (hard limit)."""
    max_duration_s: float = 3600.0
    """Largest simulated/real duration of the whole run (hard limit)."""
    seed: int = 0
    """Seed of the default simulated rig."""
    offset_ratio: float = 2.0
    """Speed offset = this x the excitation amplitude (> 1: the load never reverses)."""
    min_offset_deg_s: float = 0.5
    """Smallest useful offset (well above the Stribeck speed); below it the window is too
    small for the lowest frequency."""
    travel_fraction: float = 0.8
    """Share of the window the plan may use (the rest absorbs belt stretch and lag)."""
    min_periods: int = 2
    """Stepped sine: measured periods per frequency (>= 2 for a variance)."""
    min_measure_s: float = 2.0
    """Stepped sine: at least this long a measurement window per frequency."""
    multisine_periods: int = 3
    """Multisine: measured periods (one more transient period is discarded)."""
    fit_f_lo_hz: float | None = None
    """Fit band, low end (None: the lowest measured frequency)."""
    fit_f_hi_hz: float | None = 10.0
    """Fit band, high end (None: the highest measured). Default 10 Hz: about 1.5x the natural
    frequency of the article's Mn Pn; above it unmodelled dynamics pull a second order off."""
    fit_error_floor: float = 0.01
    """Relative model error added to each point's variance in the fit weights (1 %)."""
    periodic_pitch_deg: float | None = 12.0
    """Position period of the strongest position-periodic disturbance (one tooth of the
    article's 30-tooth pulley: 12 deg). The measured travel of each segment is made a whole
    number of pitches so that disturbance does not leak into the estimate. None: off."""
    agreement_tol_db: float = 1.0
    agreement_tol_deg: float = 10.0
    move_speed_deg_s: float = 30.0
    """Peak speed of position-loop moves between positions and to a segment's start."""
    settle_s: float = 0.5
    """Hold after each move before exciting."""
    stop_s: float = 0.1
    """On abort: command 0 for this long, then the position loop holds."""
    hold_s: float = 1.0
    """On abort: position-loop hold recorded after the stop (offline runs end there)."""

    def __post_init__(self) -> None:
        def put(name: str, v: object) -> None:
            object.__setattr__(self, name, v)

        if self.mode not in MODES:
            raise ConfigError("mode", f"must be one of {', '.join(MODES)} (got {self.mode!r})")
        if self.signal not in SIGNALS:
            raise ConfigError(
                "signal", f"must be one of {', '.join(SIGNALS)} (got {self.signal!r})"
            )
        f_lo = positive(self.f_min_hz, "f_min_hz")
        f_hi = positive(self.f_max_hz, "f_max_hz")
        if f_lo >= f_hi:
            raise ConfigError("f_min_hz", f"must be < f_max_hz (got {f_lo} >= {f_hi})")
        put("f_min_hz", f_lo)
        put("f_max_hz", f_hi)
        put("points_per_decade", _integer(self.points_per_decade, "points_per_decade", 1, 200))
        put("positions", _integer(self.positions, "positions", 1, 36))
        put("span_deg", positive(self.span_deg, "span_deg"))
        put("first_position_deg", number(self.first_position_deg, "first_position_deg"))
        put("amplitude_deg_s", positive(self.amplitude_deg_s, "amplitude_deg_s"))
        put("window_deg", positive(self.window_deg, "window_deg"))
        put("max_duration_s", positive(self.max_duration_s, "max_duration_s"))
        put("seed", _integer(self.seed, "seed", 0, 2**63 - 1))
        ratio = number(self.offset_ratio, "offset_ratio")
        if ratio < 1.2:
            raise ConfigError("offset_ratio", f"must be >= 1.2 (got {ratio})")
        put("offset_ratio", ratio)
        put("min_offset_deg_s", positive(self.min_offset_deg_s, "min_offset_deg_s"))
        frac = number(self.travel_fraction, "travel_fraction")
        if not 0.1 <= frac <= 1.0:
            raise ConfigError("travel_fraction", f"must be in [0.1, 1] (got {frac})")
        put("travel_fraction", frac)
        put("min_periods", _integer(self.min_periods, "min_periods", 2, 1000))
        put("min_measure_s", number(self.min_measure_s, "min_measure_s"))
        if self.min_measure_s < 0:
            raise ConfigError("min_measure_s", f"must be >= 0 (got {self.min_measure_s})")
        put("multisine_periods", _integer(self.multisine_periods, "multisine_periods", 2, 1000))
        for name in ("fit_f_lo_hz", "fit_f_hi_hz"):
            if getattr(self, name) is not None:
                put(name, positive(getattr(self, name), name))
        if (
            self.fit_f_lo_hz is not None
            and self.fit_f_hi_hz is not None
            and self.fit_f_lo_hz >= self.fit_f_hi_hz
        ):
            raise ConfigError("fit_f_lo_hz", "must be < fit_f_hi_hz")
        put("fit_error_floor", positive(self.fit_error_floor, "fit_error_floor"))
        if self.periodic_pitch_deg is not None:
            put("periodic_pitch_deg", positive(self.periodic_pitch_deg, "periodic_pitch_deg"))
        put("agreement_tol_db", positive(self.agreement_tol_db, "agreement_tol_db"))
        put("agreement_tol_deg", positive(self.agreement_tol_deg, "agreement_tol_deg"))
        put("move_speed_deg_s", positive(self.move_speed_deg_s, "move_speed_deg_s"))
        for name in ("settle_s", "stop_s", "hold_s"):
            v = number(getattr(self, name), name)
            if v < 0:
                raise ConfigError(name, f"must be >= 0 (got {v})")
            put(name, v)

    @property
    def centers_deg(self) -> tuple[float, ...]:
        """The measurement positions."""
        n = self.positions
        return tuple(self.first_position_deg + self.span_deg * k / n for k in range(n))

    def with_(self, **changes: object) -> IdentifySpec:
        """A copy with some fields changed, validated again."""
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ result types


@dataclass(frozen=True, eq=False)
class RawRecord:
    """Every tick recorded at one position (moves, excitation and an abort's stop and hold)."""

    t_s: FloatArray
    """Time since the start of the run."""
    u_deg_s: FloatArray
    """Speed command actually sent (after saturation)."""
    w_deg_s: FloatArray
    """Measured load rate."""
    x_deg_s: FloatArray
    """Excitation part of the command (0 outside the excitation)."""
    pos_deg: FloatArray
    """Measured load position."""
    offset_deg_s: FloatArray
    """Speed offset (open mode: part of u; closed mode: the speed reference r)."""
    phase: NDArray[np.int8]
    """PHASE_MOVE (position loop), PHASE_EXCITE or PHASE_ABORT (stop, then hold)."""
    exc_index: IntArray
    """Sample index into the excitation signal, -1 where the excitation is not running."""

    def aligned(self, name: str, length: int) -> FloatArray:
        """Signal ``name`` (e.g. ``"u_deg_s"``) laid out on the excitation's sample grid."""
        out = np.zeros(length)
        m = self.exc_index >= 0
        out[self.exc_index[m]] = getattr(self, name)[m]
        return out

    def as_arrays(self) -> dict[str, NDArray[np.generic]]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass(frozen=True, eq=False)
class PositionRecord:
    """The measurement at one position."""

    index: int
    center_deg: float
    raw: RawRecord
    estimate: FrdEstimate | None
    """Continuous-equivalent response u -> w (sampling factor removed); None if nothing was
    measured. For an interrupted stepped sine: the frequencies completed."""
    sampled: FrdEstimate | None
    """The same as measured sample by sample, u[k] -> w[k]."""
    points_done: int
    points_total: int

    @property
    def complete(self) -> bool:
        return self.points_done == self.points_total

    @property
    def name(self) -> str:
        return f"pos{self.index}_{self.center_deg:g}deg"


@dataclass(frozen=True)
class GateCheck:
    """The gate's verdict on one Q cut-off with the fitted nominal and the measured plants."""

    q_type: str
    cutoff_hz: float
    accepted: bool
    small_gain_peak: float
    reasons: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class IdentifyResult:
    """Everything measured and derived; partial (complete False) after an abort."""

    spec: IdentifySpec
    config: LoopConfig
    """The loop configuration the run used (its nominal is the one before the fit)."""
    excitation: SteppedSine | Multisine = field(repr=False)
    """Unit-amplitude excitation; segments scale it (see each raw record's x)."""
    positions: tuple[PositionRecord, ...]
    complete: bool
    abort_reason: str | None
    simulated_s: float
    """Time the run took on the rig (simulated seconds offline)."""
    agreement: Agreement | None = None
    """Across positions (None with fewer than two complete positions)."""
    fit: SecondOrderFit | None = None
    """Mn Pn = 1 / (a2 s^2 + a1 s + 1) fitted to all complete positions together."""
    uncertainty: ModelUncertainty | None = None
    """Delta of every complete position against the fit."""
    nominal: NominalModel | None = None
    """The fit as a NominalModel (article form: Mn from the config, Pn = Mn_den / fit_den)."""
    recommended_cutoff_hz: dict[str, float | None] = field(default_factory=dict)
    """Gate's largest accepted cut-off per Q type, fitted nominal + measured responses (None:
    even the lowest is rejected; the search stops at a tenth of the loop rate)."""
    recommended_cutoff_hz_config: dict[str, float | None] = field(default_factory=dict)
    """The same with the configuration's own nominal model (if the fit is not adopted)."""
    gate_checks: tuple[GateCheck, ...] = ()
    """Q31 at the recommended cut-off and at 1.5x it (fitted nominal)."""
    notes: tuple[str, ...] = ()
    """What could not be done as asked (fit band widened, no usable fit, ...)."""

    @property
    def fitted_config(self) -> LoopConfig | None:
        """The run's configuration with the fitted nominal model (what "use as nominal" means)."""
        return None if self.nominal is None else self.config.with_(nominal=self.nominal)

    def measured_responses(self) -> tuple[MeasuredResponse, ...]:
        """The complete positions' responses as the gate's plant knowledge."""
        return tuple(
            MeasuredResponse(name=p.name, freq_hz=p.estimate.freq_hz, response=p.estimate.response)
            for p in self.positions
            if p.complete and p.estimate is not None and p.estimate.freq_hz.size >= 2
        )


class IdentifyAborted(RuntimeError):
    """A limit stopped the run; `result` holds the partial data (complete False)."""

    def __init__(self, reason: str, limit: str, result: IdentifyResult) -> None:
        super().__init__(reason)
        self.reason = reason
        self.limit = limit
        """``window`` or ``duration``."""
        self.result = result


# ------------------------------------------------------------------------------ the plan


@dataclass(frozen=True, slots=True)
class _Segment:
    """One excitation segment: offset ramp-up, steady, excitation, ramp-down, still."""

    point: int
    """Stepped-sine point index (0 for the multisine)."""
    exc_start: int
    exc_stop: int
    amplitude: float
    """Scale of the unit excitation (deg/s)."""
    offset_deg_s: float
    """Signed offset (direction included)."""
    start_rel_deg: float
    """Planned start position relative to the measurement position."""
    reposition: bool
    """Whether the position loop moves the load to the start first."""
    offset: FloatArray = field(repr=False)
    """Offset samples of the whole segment (signed)."""
    x: FloatArray = field(repr=False)
    """Excitation samples of the whole segment."""
    exc_index: IntArray = field(repr=False)
    travel_deg: float = 0.0
    """Planned net travel over the segment."""


def _move_ticks(distance_deg: float, spec: IdentifySpec, rate_hz: float) -> int:
    t = max(_MIN_MOVE_S, math.pi * abs(distance_deg) / (2.0 * spec.move_speed_deg_s))
    return round(t * rate_hz) + round(spec.settle_s * rate_hz)


def _ramp(n: int) -> FloatArray:
    """Raised cosine from 0 (exclusive) to 1 (inclusive) over n samples."""
    k = np.arange(1, n + 1)
    return 0.5 - 0.5 * np.cos(np.pi * k / n)


def _build_excitation(spec: IdentifySpec, rate_hz: float) -> SteppedSine | Multisine:
    try:
        if spec.signal == "sine":
            return stepped_sine(
                SteppedSineSpec(
                    f_min_hz=spec.f_min_hz,
                    f_max_hz=spec.f_max_hz,
                    points_per_decade=spec.points_per_decade,
                    amplitude_deg_s=1.0,
                    window_deg=None,
                    min_periods=spec.min_periods,
                    min_measure_s=spec.min_measure_s,
                    settle_periods=1,
                    settle_s=0.5,
                    ramp_periods=0,
                    sample_rate_hz=rate_hz,
                )
            )
        n = math.ceil(rate_hz / spec.f_min_hz - 1e-9)
        return multisine(
            MultisineSpec(
                f_min_hz=rate_hz / n,
                f_max_hz=spec.f_max_hz,
                period_samples=n,
                n_periods=spec.multisine_periods,
                transient_periods=1,
                amplitude_deg_s=1.0,
                window_deg=None,
                points_per_decade=spec.points_per_decade,
                sample_rate_hz=rate_hz,
            )
        )
    except ConfigError as exc:
        # excitation fields map onto ours except the sample rate, which is the loop's
        field_name = "f_max_hz" if exc.field == "sample_rate_hz" else exc.field
        raise ConfigError(field_name, str(exc).split(": ", 1)[-1]) from exc


def _unit_slices(exc: SteppedSine | Multisine) -> list[tuple[int, int, float]]:
    """(start, stop, lowest frequency) of each segment's slice of the unit excitation."""
    if isinstance(exc, SteppedSine):
        return [(p.start, p.stop, p.freq_hz) for p in exc.points]
    return [(0, exc.signal.size, float(exc.freq_hz[0]))]


def _pitch_lock(spec: IdentifySpec, exc: SteppedSine | Multisine, i: int, amp: float) -> float:
    """Lower ``amp`` (so the offset) until the travel over the measured periods is a whole
    number ``j`` of `periodic_pitch_deg`.

    A disturbance periodic in position (a belt tooth) then runs ``j`` whole cycles over the
    record, which is orthogonal to every DFT bin but bin ``j``; ``j`` (and ``2 j`` if possible)
    are kept off the excited bins. Returns ``amp`` unchanged when no such ``j >= 1`` exists.
    """
    pitch = spec.periodic_pitch_deg
    if pitch is None:
        return amp
    fs = exc.spec.sample_rate_hz
    if isinstance(exc, SteppedSine):
        pt = exc.points[i]
        t_meas = pt.measure_len / fs
        excited = {pt.n_periods}
    else:
        p = exc.spec.n_periods
        t_meas = p * exc.spec.period_samples / fs
        excited = {int(k) * p for k in exc.bins}
    j0 = math.floor(spec.offset_ratio * amp * t_meas / pitch + 1e-9)
    for harmonics in ((1, 2), (1,)):  # keep the second harmonic off too if possible
        for j in range(j0, 0, -1):
            if all(h * j not in excited for h in harmonics):
                return j * pitch / t_meas / spec.offset_ratio
    return amp


def _segment_samples(
    unit: FloatArray, amp: float, v0: float, n_ramp: int, n_steady: int, n_still: int
) -> tuple[FloatArray, FloatArray]:
    ramp = _ramp(n_ramp)
    n_exc = unit.size
    offset = np.concatenate(
        [ramp, np.ones(n_steady + n_exc), ramp[::-1][1:], np.zeros(1 + n_still)]
    )
    x = np.concatenate([np.zeros(n_ramp + n_steady), amp * unit, np.zeros(n_ramp + n_still)])
    return v0 * offset, x


def _plan(
    spec: IdentifySpec, exc: SteppedSine | Multisine, rate_hz: float, command_limit: float
) -> list[_Segment]:
    """Segments for one position (the same at every position: each starts from the centre)."""
    ts = 1.0 / rate_hz
    n_ramp = max(1, round(_RAMP_S * rate_hz))
    n_steady = round(_STEADY_S * rate_hz)
    n_still = round(_STILL_S * rate_hz)
    half = spec.travel_fraction * spec.window_deg
    ratio = spec.offset_ratio
    if spec.amplitude_deg_s * (1.0 + ratio) > command_limit:
        raise ConfigError(
            "amplitude_deg_s",
            f"{spec.amplitude_deg_s} deg/s with its offset ({ratio:g}x) exceeds the command limit "
            f"{command_limit} deg/s: at most {command_limit / (1.0 + ratio):.3g}",
        )
    segments: list[_Segment] = []
    p = 0.0  # planned position relative to the centre
    for i, (start, stop, f_lo) in enumerate(_unit_slices(exc)):
        unit = exc.signal[start:stop]
        t_eff = (n_ramp + n_steady + unit.size + n_still) * ts
        amp = min(spec.amplitude_deg_s, 2.0 * half / (t_eff * ratio))
        direction = 1.0 if p <= 0.0 else -1.0
        for _ in range(20):  # shrink until the exact excursion fits in the window
            offset, x = _segment_samples(
                unit, amp, direction * ratio * amp, n_ramp, n_steady, n_still
            )
            path = np.cumsum(offset + x) * ts
            lo, hi = min(0.0, float(path.min())), max(0.0, float(path.max()))
            if hi - lo <= 2.0 * half:
                break
            amp *= 0.98 * 2.0 * half / (hi - lo)
        amp = _pitch_lock(spec, exc, i, amp)
        offset, x = _segment_samples(unit, amp, direction * ratio * amp, n_ramp, n_steady, n_still)
        path = np.cumsum(offset + x) * ts
        lo, hi = min(0.0, float(path.min())), max(0.0, float(path.max()))
        if ratio * amp < spec.min_offset_deg_s:
            need = spec.min_offset_deg_s * t_eff / (2.0 * spec.travel_fraction)
            raise ConfigError(
                "window_deg",
                f"{spec.window_deg} deg is too small for {f_lo:.3g} Hz: its segment lasts "
                f"{t_eff:.1f} s and needs a window of at least {need:.3g} deg "
                f"(or raise f_min_hz)",
            )
        reposition = p + lo < -half - 1e-9 or p + hi > half + 1e-9
        if reposition:
            p = -half - lo if direction > 0 else half - hi
        start_rel = p
        p += float(path[-1])
        segments.append(
            _Segment(
                point=i,
                exc_start=start,
                exc_stop=stop,
                amplitude=amp,
                offset_deg_s=direction * ratio * amp,
                start_rel_deg=start_rel,
                reposition=reposition,
                offset=offset,
                x=x,
                exc_index=np.concatenate(
                    [
                        np.full(n_ramp + n_steady, -1),
                        np.arange(start, stop),
                        np.full(n_ramp + n_still, -1),
                    ]
                ).astype(np.int64),
                travel_deg=float(path[-1]),
            )
        )
    return segments


def _planned_ticks(
    spec: IdentifySpec, segments: list[_Segment], start_deg: float, rate_hz: float
) -> int:
    """Ticks of the whole run if the load follows the plan."""
    total = 0
    here = start_deg
    for c in spec.centers_deg:
        for seg in segments:
            target = c + seg.start_rel_deg
            if seg is segments[0] or seg.reposition:
                total += _move_ticks(target - here, spec, rate_hz)
                here = target
            total += seg.offset.size
            here += seg.travel_deg
    return total


# ------------------------------------------------------------------------------- running


class _LimitHit(Exception):
    def __init__(self, reason: str, limit: str) -> None:
        super().__init__(reason)
        self.reason = reason
        self.limit = limit


class _Recorder:
    """Per-position tick records in Python lists (cheap appends on the hot path)."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.u: list[float] = []
        self.w: list[float] = []
        self.x: list[float] = []
        self.pos: list[float] = []
        self.offset: list[float] = []
        self.phase: list[int] = []
        self.exc_index: list[int] = []

    def freeze(self) -> RawRecord:
        return RawRecord(
            t_s=np.asarray(self.t, dtype=np.float64),
            u_deg_s=np.asarray(self.u, dtype=np.float64),
            w_deg_s=np.asarray(self.w, dtype=np.float64),
            x_deg_s=np.asarray(self.x, dtype=np.float64),
            pos_deg=np.asarray(self.pos, dtype=np.float64),
            offset_deg_s=np.asarray(self.offset, dtype=np.float64),
            phase=np.asarray(self.phase, dtype=np.int8),
            exc_index=np.asarray(self.exc_index, dtype=np.int64),
        )


class _Runner:
    """Drives the rig tick by tick and enforces the limits."""

    def __init__(
        self,
        spec: IdentifySpec,
        cfg: LoopConfig,
        rig: RigLike,
        planned_ticks: int,
        progress: ProgressFn | None,
    ) -> None:
        self.spec = spec
        self.cfg = cfg
        self.rig = rig
        self.rate = cfg.rate_hz
        self.ts = 1.0 / cfg.rate_hz
        self.limit = cfg.command_limit_deg_s
        self.loop = ServoLoop(LoopCoefficients.build(cfg))
        self.tick = 0
        self.max_ticks = math.floor(spec.max_duration_s * cfg.rate_hz)
        self.planned = max(1, planned_ticks)
        self.progress = progress
        self.label = ""
        self.rec = _Recorder()
        self.center = 0.0
        self.window_on = False

    def report(self) -> None:
        if self.progress is not None:
            self.progress(min(0.99, self.tick / self.planned), self.label)

    def _window_check(self, pos: float) -> None:
        if abs(pos - self.center) > self.spec.window_deg:
            raise _LimitHit(
                f"position window: {pos:.3f} deg is outside {self.center:g} +- "
                f"{self.spec.window_deg:g} deg",
                "window",
            )

    def _duration_check(self) -> None:
        if self.tick >= self.max_ticks:
            raise _LimitHit(f"maximum duration {self.spec.max_duration_s:g} s reached", "duration")

    def position_phase(
        self, ref: FloatArray, ref_rate: FloatArray, phase: int = PHASE_MOVE, check: bool = True
    ) -> None:
        """Position loop following (ref, ref_rate); starts from fresh loop states."""
        self.loop.reset()
        tick = self.loop.tick
        read, step = self.rig.read, self.rig.step
        rec = self.rec
        ts = self.ts
        n0 = self.tick
        chunk = max(1, round(self.rate))
        window = self.window_on and check
        for k, (r, rr) in enumerate(zip(ref.tolist(), ref_rate.tolist(), strict=True)):
            if check:
                self._duration_check()
            pos, w = read()
            if window:
                self._window_check(pos)
            u = tick(r, rr, pos, w)
            step(u)
            rec.t.append((n0 + k) * ts)
            rec.u.append(u)
            rec.w.append(w)
            rec.x.append(0.0)
            rec.pos.append(pos)
            rec.offset.append(0.0)
            rec.phase.append(phase)
            rec.exc_index.append(-1)
            self.tick += 1
            if k % chunk == 0:
                self.report()

    def move_to(self, target_deg: float) -> None:
        """Smooth (raised-cosine) move with the position loop, then hold for settle_s."""
        start = self.rig.read()[0]
        dist = target_deg - start
        n_move = round(
            max(_MIN_MOVE_S, math.pi * abs(dist) / (2.0 * self.spec.move_speed_deg_s)) * self.rate
        )
        n_hold = round(self.spec.settle_s * self.rate)
        k = np.arange(1, n_move + 1) / n_move
        ref = np.concatenate(
            [start + dist * (0.5 - 0.5 * np.cos(np.pi * k)), np.full(n_hold, target_deg)]
        )
        rate = np.concatenate(
            [dist * np.pi / (2.0 * n_move * self.ts) * np.sin(np.pi * k), np.zeros(n_hold)]
        )
        self.position_phase(ref, rate)

    def excite(self, seg: _Segment, closed: bool) -> None:
        read, step = self.rig.read, self.rig.step
        rec = self.rec
        ts = self.ts
        lim = self.limit
        n0 = self.tick
        chunk = max(1, round(self.rate))
        loop = self.loop
        tick_speed = loop.tick_speed
        offs = seg.offset.tolist()
        xs = seg.x.tolist()
        idx = seg.exc_index.tolist()
        for k in range(len(offs)):
            self._duration_check()
            pos, w = read()
            self._window_check(pos)
            off = offs[k]
            x = xs[k]
            u = (tick_speed(off, w) if closed else off) + x
            if u > lim:
                u = lim
            elif u < -lim:
                u = -lim
            if closed:
                loop.u_prev = u  # the DOB must see the command actually sent
            step(u)
            rec.t.append((n0 + k) * ts)
            rec.u.append(u)
            rec.w.append(w)
            rec.x.append(x)
            rec.pos.append(pos)
            rec.offset.append(off)
            rec.phase.append(PHASE_EXCITE)
            rec.exc_index.append(idx[k])
            self.tick += 1
            if k % chunk == 0:
                self.report()

    def stop_and_hold(self) -> None:
        """Abort path: command 0, then hold where the load stopped with the position loop."""
        read, step = self.rig.read, self.rig.step
        rec = self.rec
        for _ in range(round(self.spec.stop_s * self.rate)):
            pos, w = read()
            step(0.0)
            rec.t.append(self.tick * self.ts)
            rec.u.append(0.0)
            rec.w.append(w)
            rec.x.append(0.0)
            rec.pos.append(pos)
            rec.offset.append(0.0)
            rec.phase.append(PHASE_ABORT)
            rec.exc_index.append(-1)
            self.tick += 1
        n_hold = round(self.spec.hold_s * self.rate)
        here = read()[0]
        self.position_phase(np.full(n_hold, here), np.zeros(n_hold), phase=PHASE_ABORT, check=False)


# ------------------------------------------------------------------------------ estimation


def _continuous(est: FrdEstimate, rate_hz: float) -> FrdEstimate:
    """Divide out the ZOH + backward-difference factor of the sampled measurement."""
    factor = discrete_equivalent(np.ones(est.freq_hz.size), est.freq_hz, rate_hz)
    return dataclasses.replace(est, response=est.response / factor)


def _estimate(
    exc: SteppedSine | Multisine,
    raw: RawRecord,
    points_done: int,
    closed: bool,
    rate_hz: float,
) -> tuple[FrdEstimate | None, FrdEstimate | None]:
    if points_done == 0:
        return None, None
    n = exc.signal.size
    u = raw.aligned("u_deg_s", n)
    w = raw.aligned("w_deg_s", n)
    x = raw.aligned("x_deg_s", n) if closed else None
    if isinstance(exc, SteppedSine):
        sub = dataclasses.replace(exc, points=exc.points[:points_done])
        sampled = estimate_stepped_sine(sub, u, w, x)
    else:
        sampled = estimate_multisine(exc, u, w, x)
    return _continuous(sampled, rate_hz), sampled


def _fit(spec: IdentifySpec, estimates: list[FrdEstimate], notes: list[str]) -> SecondOrderFit:
    """Unit-DC second order on all positions together, inverse-variance weights with a floor.

    The weights are ``1 / (var + floor^2)``: the between-period variance of each point plus
    `fit_error_floor` squared, because a second order is never exact and a nearly noise-free
    point would otherwise decide the fit on its own.
    """
    var = np.concatenate([1.0 / frd_weights(e) for e in estimates])
    weights = 1.0 / (np.nan_to_num(var, nan=0.0, posinf=1e12) + spec.fit_error_floor**2)
    f = np.concatenate([e.freq_hz for e in estimates])
    lo, hi = spec.fit_f_lo_hz, spec.fit_f_hi_hz
    in_band = np.unique(f[(f >= (lo or 0.0)) & (f <= (hi or math.inf))])
    if in_band.size < 3:
        notes.append(
            f"only {in_band.size} measured frequencies in the fit band "
            f"[{lo or 'min'}, {hi or 'max'}] Hz: fitted over the whole measured band instead"
        )
        lo = hi = None
    return fit_second_order(
        f,
        np.concatenate([e.response for e in estimates]),
        model="unit_dc",
        f_lo_hz=lo,
        f_hi_hz=hi,
        weights=weights,
    )


def fitted_nominal(fit: SecondOrderFit, base: NominalModel) -> NominalModel:
    """The fitted Mn Pn = 1/(a2 s^2 + a1 s + 1) in the article's form: Mn kept from `base`,
    Pn = mn_den / fit_den, so the product is exactly the fit."""
    a2, a1 = fit.params["a2"], fit.params["a1"]
    return NominalModel(mn_den=base.mn_den, pn_num=base.mn_den, pn_den=(a2, a1, 1.0))


def _analyse_result(spec: IdentifySpec, cfg: LoopConfig, result: IdentifyResult) -> IdentifyResult:
    done = [p for p in result.positions if p.complete and p.estimate is not None]
    if not done:
        return result
    estimates = [p.estimate for p in done if p.estimate is not None]
    agree = (
        agreement(estimates, spec.agreement_tol_db, spec.agreement_tol_deg)
        if len(estimates) >= 2
        else None
    )
    notes: list[str] = []
    fit: SecondOrderFit | None = None
    unc: ModelUncertainty | None = None
    nominal: NominalModel | None = None
    try:
        fit = _fit(spec, estimates, notes)
    except ValueError as exc:
        notes.append(f"no fit: {exc}")
    if fit is not None:
        unc = uncertainty_bound(fit, estimates)
        try:
            nominal = fitted_nominal(fit, cfg.nominal)
        except ConfigError as exc:  # not a stable, damped second order
            notes.append(f"the fit is not a usable nominal model ({exc})")
    rec: dict[str, float | None] = {}
    rec_config: dict[str, float | None] = {}
    checks: list[GateCheck] = []
    measured = result.measured_responses()
    try:
        if measured:
            plant = PlantKnowledge(measured=measured)
            for qt in ("q31", "q20"):
                rec_config[qt] = recommended_max_cutoff_hz(cfg, plant, q_type=qt)
        if nominal is not None and measured:
            gate_cfg = cfg.with_(nominal=nominal, dob_on=True)
            for qt in ("q31", "q20"):
                rec[qt] = recommended_max_cutoff_hz(gate_cfg, plant, q_type=qt)
            r31 = rec["q31"]
            if r31 is not None:
                for fc in (r31, 1.5 * r31):
                    if fc >= 0.5 * cfg.rate_hz:
                        continue
                    a = analyse(gate_cfg.with_(q_type="q31", q_cutoff_hz=fc), plant)
                    checks.append(GateCheck("q31", fc, a.accepted, a.small_gain_peak, a.reasons))
    except ValueError as exc:
        notes.append(f"the gate could not use the measured responses: {exc}")
    return dataclasses.replace(
        result,
        agreement=agree,
        fit=fit,
        uncertainty=unc,
        nominal=nominal,
        recommended_cutoff_hz=rec,
        recommended_cutoff_hz_config=rec_config,
        gate_checks=tuple(checks),
        notes=tuple(notes),
    )


# ------------------------------------------------------------------------------ entry point


def _default_rig(spec: IdentifySpec, cfg: LoopConfig) -> RigLike:
    from controller.sim.sim_rig import SimRig

    return SimRig(rate_hz=cfg.rate_hz, seed=spec.seed)


def run_identification(
    spec: IdentifySpec,
    cfg: LoopConfig,
    rig_factory: Callable[[], RigLike] | None = None,
    progress: ProgressFn | None = None,
) -> IdentifyResult:
    """Measure at every position, estimate, fit, compute Delta and ask the gate.

    ``rig_factory`` builds the rig (default: the simulated rig at ``cfg.rate_hz`` with
    ``spec.seed``). ``progress(fraction, text)`` is called about once per simulated second.
    Raises `ConfigError` (naming the field) before anything moves if the spec cannot be
    planned, and `IdentifyAborted` (with the partial result) when a limit is hit.
    """
    if not isinstance(spec, IdentifySpec):
        raise ConfigError("spec", f"must be an IdentifySpec (got {type(spec).__name__})")
    if spec.f_max_hz >= 0.5 * cfg.rate_hz:
        raise ConfigError("f_max_hz", f"must be below Nyquist {0.5 * cfg.rate_hz} Hz")
    exc = _build_excitation(spec, cfg.rate_hz)
    segments = _plan(spec, exc, cfg.rate_hz, cfg.command_limit_deg_s)
    rig = rig_factory() if rig_factory is not None else _default_rig(spec, cfg)
    start_deg = rig.read()[0]
    planned = _planned_ticks(spec, segments, start_deg, cfg.rate_hz)
    if planned > spec.max_duration_s * cfg.rate_hz:
        raise ConfigError(
            "max_duration_s",
            f"the plan takes {planned / cfg.rate_hz:.0f} s, more than {spec.max_duration_s:g} s",
        )
    closed = spec.mode == "closed"
    run = _Runner(spec, cfg, rig, planned, progress)
    records: list[PositionRecord] = []
    n_pos = len(spec.centers_deg)
    tol = max(0.5, 0.02 * spec.window_deg)
    abort: _LimitHit | None = None
    for i, c in enumerate(spec.centers_deg):
        run.rec = _Recorder()
        run.center = c
        done = 0
        try:
            for k, seg in enumerate(segments):
                target = c + seg.start_rel_deg
                if k == 0:  # the move between positions: no window yet
                    run.window_on = False
                    run.label = f"position {i + 1}/{n_pos}: moving to {c:g} deg"
                    run.move_to(target)
                    run.window_on = True
                elif seg.reposition or abs(rig.read()[0] - target) > tol:
                    run.label = f"position {i + 1}/{n_pos}: repositioning"
                    run.move_to(target)
                run.label = _segment_label(exc, seg, i, n_pos, len(segments))
                run.excite(seg, closed)
                done += 1
        except _LimitHit as hit:
            abort = hit
            run.label = f"aborted: {hit.reason}"
            run.stop_and_hold()
        raw = run.rec.freeze()
        cont, sampled = _estimate(exc, raw, done, closed, cfg.rate_hz)
        records.append(PositionRecord(i, c, raw, cont, sampled, done, len(segments)))
        if abort is not None:
            break
    result = IdentifyResult(
        spec=spec,
        config=cfg,
        excitation=exc,
        positions=tuple(records),
        complete=abort is None,
        abort_reason=None if abort is None else abort.reason,
        simulated_s=run.tick / cfg.rate_hz,
    )
    if abort is not None:
        raise IdentifyAborted(abort.reason, abort.limit, result)
    if progress is not None:
        progress(0.99, "fitting and checking")
    result = _analyse_result(spec, cfg, result)
    if progress is not None:
        progress(1.0, "done")
    return result


def _segment_label(
    exc: SteppedSine | Multisine, seg: _Segment, i: int, n_pos: int, n_seg: int
) -> str:
    if isinstance(exc, SteppedSine):
        f = exc.points[seg.point].freq_hz
        what = f"{f:.3g} Hz ({seg.point + 1}/{n_seg})"
    else:
        what = f"multisine {exc.freq_hz[0]:.3g}-{exc.freq_hz[-1]:.3g} Hz"
    return f"position {i + 1}/{n_pos}: {what}, {seg.amplitude:.2g} deg/s"


# ------------------------------------------------------------------- inside the controller


@dataclass(frozen=True, eq=False)
class ProgramPlan:
    """A whole identification as per-tick columns for `runtime.ExcitationProgram`.

    Unlike `run_identification` (which repositions only when the load drifted), every segment
    is preceded by a planned position-loop move to its start (then ``settle_s``): the program
    is fixed before it starts, so drift is corrected unconditionally.
    """

    spec: IdentifySpec
    config: LoopConfig
    excitation: SteppedSine | Multisine = field(repr=False)
    n_segments: int
    seg_end: list[int] = field(repr=False)
    """Tick (exclusive) at which each segment ends, position by position."""
    labels: list[tuple[int, str]] = field(repr=False)
    """(first tick, text) of each section, for progress reports."""
    # Per-tick columns as array.array (see ExcitationProgram): no Python object per element,
    # so building, pickling and holding a long plan never loads the controller's GC.
    kind: array[int] = field(repr=False)
    a: array[float] = field(repr=False)
    b: array[float] = field(repr=False)
    target: array[float] = field(repr=False)
    first: array[int] = field(repr=False)
    center: array[float] = field(repr=False)
    window: array[int] = field(repr=False)
    pos_index: array[int] = field(repr=False)
    exc_index: array[int] = field(repr=False)

    @property
    def n_ticks(self) -> int:
        return len(self.kind)

    def label_at(self, tick: int) -> str:
        text = ""
        for k, t in self.labels:
            if k > tick:
                break
            text = t
        return text


#: ProgramPlan's per-tick columns and their array typecodes.
_PLAN_COLUMNS: dict[str, str] = {
    "kind": "b",
    "a": "d",
    "b": "d",
    "target": "d",
    "first": "b",
    "center": "d",
    "window": "b",
    "pos_index": "q",
    "exc_index": "q",
}


def _as_array(x: NDArray[np.generic], code: str) -> array[Any]:
    out: array[Any] = array(code)
    out.frombytes(np.ascontiguousarray(x, dtype=np.dtype(code)).tobytes())
    return out


def plan_program(spec: IdentifySpec, cfg: LoopConfig, start_deg: float) -> ProgramPlan:
    """Plan every tick of a run that starts with the load at `start_deg`.

    Raises `ConfigError` (naming the spec field) if it cannot be planned within the limits.
    """
    if not isinstance(spec, IdentifySpec):
        raise ConfigError("spec", f"must be an IdentifySpec (got {type(spec).__name__})")
    rate = cfg.rate_hz
    ts = 1.0 / rate
    if spec.f_max_hz >= 0.5 * rate:
        raise ConfigError("f_max_hz", f"must be below Nyquist {0.5 * rate} Hz")
    exc = _build_excitation(spec, rate)
    segments = _plan(spec, exc, rate, cfg.command_limit_deg_s)
    cols: dict[str, list[NDArray[np.generic]]] = {name: [] for name in _PLAN_COLUMNS}

    def put(n: int, **values: NDArray[np.generic] | float) -> None:
        for name, v in values.items():
            cols[name].append(np.broadcast_to(np.asarray(v), (n,)))

    seg_end: list[int] = []
    labels: list[tuple[int, str]] = []
    total = 0
    here = start_deg
    n_pos = len(spec.centers_deg)
    n_hold = round(spec.settle_s * rate)
    for i, c in enumerate(spec.centers_deg):
        for k, seg in enumerate(segments):
            goal = c + seg.start_rel_deg
            dist = goal - here
            n_move = round(
                max(_MIN_MOVE_S, math.pi * abs(dist) / (2.0 * spec.move_speed_deg_s)) * rate
            )
            q = np.arange(1, n_move + 1) / n_move
            shape = np.concatenate([0.5 - 0.5 * np.cos(np.pi * q), np.ones(n_hold)])
            slope = np.concatenate(
                [np.pi / (2.0 * n_move * ts) * np.sin(np.pi * q), np.zeros(n_hold)]
            )
            n = shape.size
            labels.append(
                (
                    total,
                    f"position {i + 1}/{n_pos}: "
                    + (f"moving to {c:g} deg" if k == 0 else "repositioning"),
                )
            )
            first = np.zeros(n, dtype=np.int8)
            first[0] = 1
            put(n, kind=0, a=shape, b=slope, target=goal, first=first, center=c)
            put(n, window=int(k > 0), pos_index=i, exc_index=-1)
            total += n
            labels.append((total, _segment_label(exc, seg, i, n_pos, len(segments))))
            m = seg.offset.size
            put(m, kind=1, a=seg.offset, b=seg.x, target=0.0, first=0, center=c)
            put(m, window=1, pos_index=i, exc_index=seg.exc_index)
            total += m
            seg_end.append(total)
            here = goal + seg.travel_deg
    if total > spec.max_duration_s * rate:
        raise ConfigError(
            "max_duration_s",
            f"the plan takes {total / rate:.0f} s, more than {spec.max_duration_s:g} s",
        )
    arrays = {
        name: _as_array(np.concatenate(chunks), code)
        for (name, code), chunks in zip(_PLAN_COLUMNS.items(), cols.values(), strict=True)
    }
    return ProgramPlan(
        spec=spec,
        config=cfg,
        excitation=exc,
        n_segments=len(segments),
        seg_end=seg_end,
        labels=labels,
        **arrays,  # type: ignore[arg-type]
    )


def to_program(plan: ProgramPlan) -> ExcitationProgram:
    """The runtime object that executes `plan` inside the tick."""
    spec = plan.spec
    return ExcitationProgram(
        plan.kind,
        plan.a,
        plan.b,
        plan.target,
        plan.first,
        plan.center,
        plan.window,
        closed=spec.mode == "closed",
        window_deg=spec.window_deg,
        amplitude_limit=spec.amplitude_deg_s * (1.0 + 1e-9),
        max_duration_s=spec.max_duration_s,
        command_limit=plan.config.command_limit_deg_s,
    )


def result_from_program(
    plan: ProgramPlan,
    u: Sequence[float],
    w: Sequence[float],
    pos: Sequence[float],
    n_done: int,
    abort_reason: str | None,
    analyse_result: bool = True,
) -> IdentifyResult:
    """Estimate (and, for a complete run, fit and check) from the records of a program.

    `u`, `w`, `pos` hold at least `n_done` executed ticks. After an abort the positions
    reached are kept, the last one incomplete; nothing is fitted.
    """
    spec, cfg, exc = plan.spec, plan.config, plan.excitation
    rate = cfg.rate_hz
    closed = spec.mode == "closed"
    kind = np.frombuffer(plan.kind, dtype=np.int8)[:n_done].copy()
    pidx = np.frombuffer(plan.pos_index, dtype=np.int64)[:n_done]
    a = np.frombuffer(plan.a, dtype=np.float64)[:n_done]
    bx = np.frombuffer(plan.b, dtype=np.float64)[:n_done]
    exc_i = np.frombuffer(plan.exc_index, dtype=np.int64)[:n_done].copy()
    t = np.arange(n_done) * (1.0 / rate)
    uu = np.array(u[:n_done], dtype=np.float64)
    ww = np.array(w[:n_done], dtype=np.float64)
    pp = np.array(pos[:n_done], dtype=np.float64)
    excite = kind == PHASE_EXCITE
    records: list[PositionRecord] = []
    n_seg = plan.n_segments
    for i, c in enumerate(plan.spec.centers_deg):
        m = pidx == i
        if not m.any():
            break
        ends = plan.seg_end[i * n_seg : (i + 1) * n_seg]
        done = sum(1 for e in ends if e <= n_done)
        raw = RawRecord(
            t_s=t[m],
            u_deg_s=uu[m],
            w_deg_s=ww[m],
            x_deg_s=np.where(excite, bx, 0.0)[m],
            pos_deg=pp[m],
            offset_deg_s=np.where(excite, a, 0.0)[m],
            phase=kind[m],
            exc_index=exc_i[m],
        )
        cont, sampled = _estimate(exc, raw, done, closed, rate)
        records.append(PositionRecord(i, c, raw, cont, sampled, done, n_seg))
    result = IdentifyResult(
        spec=spec,
        config=cfg,
        excitation=exc,
        positions=tuple(records),
        complete=abort_reason is None,
        abort_reason=abort_reason,
        simulated_s=n_done / rate,
    )
    if abort_reason is None and analyse_result:
        result = _analyse_result(spec, cfg, result)
    return result


# ------------------------------------------------- live results of a program (off the loop)


@dataclass(frozen=True, eq=False)
class SegmentData:
    """One finished excitation segment of a program run, cut out of the records so it can be
    estimated off the loop: only this segment's excitation ticks (small to pickle).

    For a stepped sine `excitation` holds the segment's single point with indices relative to
    its first sample (and no signal); a multisine segment is the whole excitation."""

    excitation: SteppedSine | Multisine = field(repr=False)
    closed: bool
    rate_hz: float
    position: int
    point: int
    exc_index: IntArray = field(repr=False)
    """Excitation-sample index of each excitation tick (relative, see above)."""
    u: FloatArray = field(repr=False)
    w: FloatArray = field(repr=False)
    x: FloatArray = field(repr=False)


def segments_done(plan: ProgramPlan, n_done: int) -> int:
    """How many segments (over all positions, in order) ended within the first `n_done` ticks."""
    return bisect.bisect_right(plan.seg_end, n_done)


def segment_data(
    plan: ProgramPlan, k: int, u: Sequence[float] | array[float], w: Sequence[float] | array[float]
) -> SegmentData:
    """Segment `k` (over all positions) of `plan`, from the program's records `u`, `w` (which
    must hold at least ``plan.seg_end[k]`` executed ticks). Only slices: cheap."""
    n_seg = plan.n_segments
    lo = plan.seg_end[k - 1] if k > 0 else 0
    hi = plan.seg_end[k]
    ei = np.frombuffer(plan.exc_index, dtype=np.int64)[lo:hi]
    m = ei >= 0
    exc = plan.excitation
    base = 0
    part: SteppedSine | Multisine = exc
    if isinstance(exc, SteppedSine):
        p = exc.points[k % n_seg]
        base = p.start
        part = SteppedSine(
            spec=exc.spec, points=(dataclasses.replace(p, start=0),), signal=np.zeros(0)
        )
    return SegmentData(
        excitation=part,
        closed=plan.spec.mode == "closed",
        rate_hz=plan.config.rate_hz,
        position=k // n_seg,
        point=k % n_seg,
        exc_index=ei[m] - base,
        u=np.asarray(u[lo:hi], dtype=np.float64)[m],
        w=np.asarray(w[lo:hi], dtype=np.float64)[m],
        x=np.frombuffer(plan.b, dtype=np.float64)[lo:hi][m],
    )


def estimate_segment(seg: SegmentData) -> FrdEstimate:
    """The continuous-equivalent response of one finished segment: the same numbers as
    `result_from_program` gives for its frequencies (each point is estimated on its own)."""
    exc = seg.excitation
    n = exc.points[0].stop if isinstance(exc, SteppedSine) else exc.signal.size

    def aligned(v: FloatArray) -> FloatArray:
        out = np.zeros(n)
        out[seg.exc_index] = v
        return out

    x = aligned(seg.x) if seg.closed else None
    if isinstance(exc, SteppedSine):
        sampled = estimate_stepped_sine(exc, aligned(seg.u), aligned(seg.w), x)
    else:
        sampled = estimate_multisine(exc, aligned(seg.u), aligned(seg.w), x)
    return _continuous(sampled, seg.rate_hz)
