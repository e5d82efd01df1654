"""The identification plan: excitation segments per position, and the whole run as per-tick
columns for the controller's loop (`ProgramPlan` -> `controller.ident.program.ExcitationProgram`).

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
  Multisine: one segment per position: an odd random-phase multisine (odd bins of the lowest
  frequency, log-spaced, crest factor lowered), a lead-in of `LEAD_S` (the end of a period,
  faded in: the plant settles in a fraction of a second, far less than the 10 s period of
  0.1 Hz), ``multisine_periods`` measured periods, a faded tail of `TAIL_S`. The spread of each
  line comes from its non-excited neighbours, so one period is enough
  (`controller.ident.estimate.estimate_multisine_lines`; docs/identification.md has the
  trade-off against the stepped sine). The belt tooth's line is kept on an odd, non-excited
  bin (one odd bin is left out of the excitation for it if needed), where its intermodulation
  with the excitation falls on even lines (`_tooth_clear`), and in open mode the lines below
  `POSITION_KNEE_HZ` have equal position amplitudes.

Every planning error is a `ConfigError` naming the spec field, raised before anything moves.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from array import array
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeAlias

import numpy as np
from numpy.typing import NDArray

from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from controller.ident.excitation import (
    FloatArray,
    IntArray,
    Multisine,
    MultisineSpec,
    SteppedSine,
    SteppedSineSpec,
    multisine,
    stepped_sine,
)
from controller.ident.program import ExcitationProgram
from controller.ident.spec import IdentifySpec

__all__ = [
    "LEAD_CLOSED_S",
    "LEAD_S",
    "MULTISINE_SEED",
    "POSITION_KNEE_HZ",
    "TAIL_S",
    "Excitation",
    "ProgramPlan",
    "Segment",
    "check_duration",
    "check_rate",
    "excitation_text",
    "move_label",
    "move_profile",
    "move_ticks",
    "plan_program",
    "plan_segments",
    "plan_text",
    "planned_ticks",
    "segment_label",
    "segments_done",
    "to_program",
]

Excitation: TypeAlias = SteppedSine | Multisine

_RAMP_S = 0.3  # offset ramp up / down (raised cosine)
_STEADY_S = 0.2  # constant offset before the excitation starts
_STILL_S = 0.1  # command 0 (open) or r = 0 (closed) after a segment
_MIN_MOVE_S = 0.3
#: Multisine lead-in before the measured periods (open mode; closed mode: `LEAD_CLOSED_S`).
LEAD_S = 1.0
LEAD_CLOSED_S = 2.0
#: Multisine faded tail after the measured periods.
TAIL_S = 0.2
#: Seed of the multisine's random phases (fixed: the plan is the same every time).
MULTISINE_SEED = 0
#: Open mode: multisine lines below this frequency have equal position (not speed)
#: amplitudes. A disturbance periodic in position (a belt tooth) is phase modulated by the
#: excitation's position, and the low lines' position amplitude (speed / 2 pi f) sets the
#: modulation index: on the simulated rig 2 Hz takes the per-point error from 0.22 % rms
#: (0.63 % max) to 0.04 % (0.12 %). Closed mode keeps equal speed amplitudes: the loop rejects
#: the disturbance, and the low lines' response is small behind its gain.
POSITION_KNEE_HZ = 2.0


@dataclass(frozen=True, slots=True)
class Segment:
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


# ------------------------------------------------------------------------------ moves


def move_ticks(distance_deg: float, spec: IdentifySpec, rate_hz: float) -> tuple[int, int]:
    """(move, hold) ticks of a position-loop move over `distance_deg`, then ``settle_s``."""
    t = max(_MIN_MOVE_S, math.pi * abs(distance_deg) / (2.0 * spec.move_speed_deg_s))
    return round(t * rate_hz), round(spec.settle_s * rate_hz)


def move_profile(
    distance_deg: float, spec: IdentifySpec, rate_hz: float
) -> tuple[FloatArray, FloatArray]:
    """A smooth (raised-cosine) move then the hold, normalised: (shape, slope) with the
    reference ``start + distance * shape`` and its rate ``distance * slope``."""
    n_move, n_hold = move_ticks(distance_deg, spec, rate_hz)
    q = np.arange(1, n_move + 1) / n_move
    shape = np.concatenate([0.5 - 0.5 * np.cos(np.pi * q), np.ones(n_hold)])
    ts = 1.0 / rate_hz
    slope = np.concatenate([np.pi / (2.0 * n_move * ts) * np.sin(np.pi * q), np.zeros(n_hold)])
    return shape, slope


# ------------------------------------------------------------------------------- segments


def _ramp(n: int) -> FloatArray:
    """Raised cosine from 0 (exclusive) to 1 (inclusive) over n samples."""
    k = np.arange(1, n + 1)
    return 0.5 - 0.5 * np.cos(np.pi * k / n)


def check_rate(spec: IdentifySpec, rate_hz: float) -> None:
    """ConfigError unless the spec's band fits the loop rate."""
    if spec.f_max_hz >= 0.5 * rate_hz:
        raise ConfigError("f_max_hz", f"must be below Nyquist {0.5 * rate_hz} Hz")


def _build_excitation(spec: IdentifySpec, rate_hz: float) -> Excitation:
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
        n = math.ceil(rate_hz / (spec.resolution_hz or spec.f_min_hz) - 1e-9)
        lead = round((LEAD_CLOSED_S if spec.closed else LEAD_S) * rate_hz)
        return multisine(
            MultisineSpec(
                f_min_hz=max(rate_hz / n, spec.f_min_hz if spec.resolution_hz else 0.0),
                f_max_hz=spec.f_max_hz,
                period_samples=n,
                n_periods=spec.multisine_periods,
                transient_periods=max(0, math.ceil(lead / n) - 1),
                amplitude_deg_s=1.0,
                window_deg=None,
                points_per_decade=spec.points_per_decade,
                sample_rate_hz=rate_hz,
                harmonics="odd",
                phases="random",
                seed=MULTISINE_SEED,
                lead_samples=min(lead, n),
                tail_samples=min(round(TAIL_S * rate_hz), n),
                spread_from="lines",
                position_knee_hz=None if spec.closed else POSITION_KNEE_HZ,
            )
        )
    except ConfigError as exc:
        # excitation fields map onto ours except the sample rate, which is the loop's
        field_name = "f_max_hz" if exc.field == "sample_rate_hz" else exc.field
        raise ConfigError(field_name, str(exc).split(": ", 1)[-1]) from exc


def _unit_slices(exc: Excitation) -> list[tuple[int, int, float]]:
    """(start, stop, lowest frequency) of each segment's slice of the unit excitation."""
    if isinstance(exc, SteppedSine):
        return [(p.start, p.stop, p.freq_hz) for p in exc.points]
    return [(0, exc.signal.size, float(exc.freq_hz[0]))]


def _tooth_clear(j: int, periods: int, bins: set[int], odd: bool) -> bool:
    """Whether a disturbance at bin `j` of a multisine record of `periods` periods keeps
    itself and its first intermodulation products with the excitation off the excited lines.

    The excitation moves the position, so a disturbance periodic in position is phase
    modulated: lines at ``j`` and ``j +- k P`` for every excited bin ``k``. Off the period grid
    (``j`` not a multiple of ``P``) none of them is a multiple of ``P``. On it, at period bin
    ``m``: ``m`` must not be excited, and with only odd bins excited ``m`` odd puts every
    ``m +- k`` on an even, non-excited line.
    """
    if j % periods:
        return True
    m = j // periods
    if m in bins:
        return False
    if odd:
        return m % 2 == 1
    return not any(m + k in bins or abs(m - k) in bins for k in bins)


def _tooth_bin(spec: IdentifySpec, exc: Excitation, i: int, amp: float) -> tuple[int, float]:
    """(j0, t_meas): the most whole pitches the measured record of segment `i` can travel at
    amplitude `amp`, and the record's length."""
    pitch = spec.periodic_pitch_deg
    assert pitch is not None
    fs = exc.spec.sample_rate_hz
    if isinstance(exc, SteppedSine):
        t_meas = exc.points[i].measure_len / fs
    else:
        t_meas = exc.spec.n_periods * exc.spec.period_samples / fs
    return math.floor(spec.offset_ratio * amp * t_meas / pitch + 1e-9), t_meas


def _pitch_lock(spec: IdentifySpec, exc: Excitation, i: int, amp: float) -> float:
    """Lower ``amp`` (so the offset) until the travel over the measured periods is a whole
    number ``j`` of `periodic_pitch_deg`.

    A disturbance periodic in position (a belt tooth) then runs ``j`` whole cycles over the
    record, which is orthogonal to every DFT bin but bin ``j``; ``j`` (and ``2 j`` if possible)
    are kept off the excited bins, for a multisine its intermodulation with the excitation too
    (`_tooth_clear`). Returns ``amp`` unchanged when no such ``j >= 1`` exists.
    """
    pitch = spec.periodic_pitch_deg
    if pitch is None:
        return amp
    j0, t_meas = _tooth_bin(spec, exc, i, amp)
    tiers: list[Callable[[int], bool]] = []
    if isinstance(exc, SteppedSine):
        excited = {exc.points[i].n_periods}
    else:
        p = exc.spec.n_periods
        excited = {int(k) * p for k in exc.bins}
        bins = {int(k) for k in exc.bins}
        odd = exc.spec.harmonics == "odd"
        tiers += [
            lambda j: _tooth_clear(j, p, bins, odd) and _tooth_clear(2 * j, p, bins, odd),
            lambda j: _tooth_clear(j, p, bins, odd),
        ]
    tiers += [  # keep the second harmonic off too if possible
        lambda j: j not in excited and 2 * j not in excited,
        lambda j: j not in excited,
    ]
    for ok in tiers:
        for j in range(j0, 0, -1):
            if ok(j):
                return j * pitch / t_meas / spec.offset_ratio
    return amp


def _clear_tooth_line(spec: IdentifySpec, exc: Multisine, amp: float) -> Multisine:
    """An odd multisine measured over one period has no bin off the period grid: when no
    odd, non-excited bin lies within the pitches the record can travel, leave the highest odd
    bin that does out of the excitation so the tooth can sit there (`_tooth_clear`)."""
    if spec.periodic_pitch_deg is None or exc.spec.harmonics != "odd":
        return exc
    j0, _ = _tooth_bin(spec, exc, 0, amp)
    p = exc.spec.n_periods
    bins = {int(k) for k in exc.bins}
    if any(_tooth_clear(j, p, bins, True) for j in range(1, j0 + 1)):
        return exc
    m = (j0 // p) - (1 - (j0 // p) % 2)  # the highest odd period bin within reach
    if m <= int(exc.bins[0]):  # never the lowest frequency
        return exc
    skip = (*exc.spec.skip_bins, m)
    return multisine(dataclasses.replace(exc.spec, skip_bins=skip))


@dataclass(frozen=True, slots=True)
class _Shape:
    """Sample counts of a segment's parts (ramp, steady, still) at the loop rate."""

    ramp: int
    steady: int
    still: int

    def samples(self, unit: FloatArray, amp: float, v0: float) -> tuple[FloatArray, FloatArray]:
        """(offset, x) of a segment with excitation ``amp * unit`` on the offset ``v0``."""
        ramp = _ramp(self.ramp)
        offset = np.concatenate(
            [ramp, np.ones(self.steady + unit.size), ramp[::-1][1:], np.zeros(1 + self.still)]
        )
        x = np.concatenate(
            [np.zeros(self.ramp + self.steady), amp * unit, np.zeros(self.ramp + self.still)]
        )
        return v0 * offset, x


def _excursion(offset: FloatArray, x: FloatArray, ts: float) -> tuple[FloatArray, float, float]:
    """The planned path of a segment and its extremes (including the start, 0)."""
    path = np.cumsum(offset + x) * ts
    return path, min(0.0, float(path.min())), max(0.0, float(path.max()))


def _fit_amplitude(
    spec: IdentifySpec, unit: FloatArray, shape: _Shape, direction: float, ts: float
) -> float:
    """The largest amplitude (at most the spec's) whose segment, offset included, travels
    within ``travel_fraction`` of the window."""
    half = spec.travel_fraction * spec.window_deg
    ratio = spec.offset_ratio
    t_eff = (shape.ramp + shape.steady + unit.size + shape.still) * ts
    amp = min(spec.amplitude_deg_s, 2.0 * half / (t_eff * ratio))
    for _ in range(20):  # shrink until the exact excursion fits in the window
        _, lo, hi = _excursion(*shape.samples(unit, amp, direction * ratio * amp), ts)
        if hi - lo <= 2.0 * half:
            break
        amp *= 0.98 * 2.0 * half / (hi - lo)
    return amp


def plan_segments(spec: IdentifySpec, cfg: LoopConfig) -> tuple[Excitation, list[Segment]]:
    """The unit excitation and the segments of one position (the same at every position: each
    starts from the centre). ConfigError (naming the spec field) if it cannot be planned."""
    if not isinstance(spec, IdentifySpec):
        raise ConfigError("spec", f"must be an IdentifySpec (got {type(spec).__name__})")
    rate_hz = cfg.rate_hz
    check_rate(spec, rate_hz)
    exc = _build_excitation(spec, rate_hz)
    command_limit = cfg.command_limit_deg_s
    ts = 1.0 / rate_hz
    shape = _Shape(
        ramp=max(1, round(_RAMP_S * rate_hz)),
        steady=round(_STEADY_S * rate_hz),
        still=round(_STILL_S * rate_hz),
    )
    half = spec.travel_fraction * spec.window_deg
    ratio = spec.offset_ratio
    if spec.amplitude_deg_s * (1.0 + ratio) > command_limit:
        raise ConfigError(
            "amplitude_deg_s",
            f"{spec.amplitude_deg_s} deg/s with its offset ({ratio:g}x) exceeds the command limit "
            f"{command_limit} deg/s: at most {command_limit / (1.0 + ratio):.3g}",
        )
    if isinstance(exc, Multisine):
        exc = _clear_tooth_line(spec, exc, _fit_amplitude(spec, exc.signal, shape, 1.0, ts))
    segments: list[Segment] = []
    p = 0.0  # planned position relative to the centre
    for i, (start, stop, f_lo) in enumerate(_unit_slices(exc)):
        unit = exc.signal[start:stop]
        t_eff = (shape.ramp + shape.steady + unit.size + shape.still) * ts
        direction = 1.0 if p <= 0.0 else -1.0
        amp = _fit_amplitude(spec, unit, shape, direction, ts)
        amp = _pitch_lock(spec, exc, i, amp)
        offset, x = shape.samples(unit, amp, direction * ratio * amp)
        path, lo, hi = _excursion(offset, x, ts)
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
            Segment(
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
                        np.full(shape.ramp + shape.steady, -1),
                        np.arange(start, stop),
                        np.full(shape.ramp + shape.still, -1),
                    ]
                ).astype(np.int64),
                travel_deg=float(path[-1]),
            )
        )
    return exc, segments


def check_duration(spec: IdentifySpec, ticks: int, rate_hz: float) -> None:
    """ConfigError if a plan of `ticks` is longer than ``max_duration_s``."""
    if ticks > spec.max_duration_s * rate_hz:
        raise ConfigError(
            "max_duration_s",
            f"the plan takes {ticks / rate_hz:.0f} s, more than {spec.max_duration_s:g} s",
        )


def planned_ticks(
    spec: IdentifySpec, segments: list[Segment], start_deg: float, rate_hz: float
) -> int:
    """Ticks of a whole offline run if the load follows the plan (moves only where needed)."""
    total = 0
    here = start_deg
    for c in spec.centers_deg:
        for seg in segments:
            target = c + seg.start_rel_deg
            if seg is segments[0] or seg.reposition:
                total += sum(move_ticks(target - here, spec, rate_hz))
                here = target
            total += seg.offset.size
            here += seg.travel_deg
    return total


def segment_label(exc: Excitation, seg: Segment, i: int, n_pos: int, n_seg: int) -> str:
    """The progress text while segment `seg` runs at position `i`."""
    if isinstance(exc, SteppedSine):
        f = exc.points[seg.point].freq_hz
        what = f"{f:.3g} Hz ({seg.point + 1}/{n_seg})"
    else:
        what = excitation_text(exc)
    return f"position {i + 1}/{n_pos}: {what}, {seg.amplitude:.2g} deg/s"


def excitation_text(exc: Excitation) -> str:
    """The excitation's band as the progress text names it (`segment_label`)."""
    if isinstance(exc, SteppedSine):
        f = [pt.freq_hz for pt in exc.points]
        return f"stepped sine {min(f):.3g}-{max(f):.3g} Hz ({len(f)} frequencies)"
    return f"multisine {exc.freq_hz[0]:.3g}-{exc.freq_hz[-1]:.3g} Hz"


def plan_text(spec: IdentifySpec, cfg: LoopConfig, start_deg: float) -> str:
    """What a run will do, in the words and numbers its progress text will use: the band,
    the amplitude planned (lower than the spec's when each segment must stay within the
    position window: then both), the positions and the planned duration from `start_deg`.
    ConfigError (naming the spec field) if it cannot be planned."""
    plan = plan_program(spec, cfg, start_deg)
    _, segments = plan_segments(spec, cfg)
    amps = [seg.amplitude for seg in segments]
    lo, hi = f"{min(amps):.2g}", f"{max(amps):.2g}"
    amp = f"{lo} deg/s" if lo == hi else f"{lo}-{hi} deg/s"
    if max(amps) < spec.amplitude_deg_s * (1.0 - 1e-9):
        pitch = (f" and keeps the {spec.periodic_pitch_deg:g} deg tooth pitch"
                 if spec.periodic_pitch_deg else "")
        amp += (f" ({spec.amplitude_deg_s:g} deg/s asked: lowered so that each segment's "
                f"travel stays within the {spec.window_deg:g} deg position window{pitch})")
    n_pos = len(spec.centers_deg)
    duration_s = plan.seg_end[-1] / cfg.rate_hz
    return (f"{excitation_text(plan.excitation)}, {amp}, at {n_pos} position(s), about "
            f"{duration_s:.0f} s (moves included, from {start_deg:.3g} deg)")


def move_label(i: int, n_pos: int, center_deg: float, first: bool) -> str:
    """The progress text of the move to a position (`first`) or to a segment's start."""
    what = f"moving to {center_deg:g} deg" if first else "repositioning"
    return f"position {i + 1}/{n_pos}: {what}"


# ------------------------------------------------------------------- inside the controller


@dataclass(frozen=True, eq=False)
class ProgramPlan:
    """A whole identification as per-tick columns for `ExcitationProgram`.

    Unlike the offline run (`controller.ident.engine.run_identification`, which repositions
    only when the load drifted), every segment is preceded by a planned position-loop move to
    its start (then ``settle_s``): the program is fixed before it starts, so drift is corrected
    unconditionally.
    """

    spec: IdentifySpec
    config: LoopConfig
    excitation: Excitation = field(repr=False)
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

    def column(self, name: str, n: int | None = None) -> NDArray[Any]:
        """The first `n` ticks (all: None) of a per-tick column as a numpy view."""
        return np.frombuffer(getattr(self, name), dtype=np.dtype(_PLAN_COLUMNS[name]))[:n]


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
    exc, segments = plan_segments(spec, cfg)
    rate = cfg.rate_hz
    cols: dict[str, list[NDArray[np.generic]]] = {name: [] for name in _PLAN_COLUMNS}

    def put(n: int, **values: NDArray[np.generic] | float) -> None:
        for name, v in values.items():
            cols[name].append(np.broadcast_to(np.asarray(v), (n,)))

    seg_end: list[int] = []
    labels: list[tuple[int, str]] = []
    total = 0
    here = start_deg
    n_pos = len(spec.centers_deg)
    for i, c in enumerate(spec.centers_deg):
        for k, seg in enumerate(segments):
            goal = c + seg.start_rel_deg
            shape, slope = move_profile(goal - here, spec, rate)
            n = shape.size
            labels.append((total, move_label(i, n_pos, c, k == 0)))
            first = np.zeros(n, dtype=np.int8)
            first[0] = 1
            put(n, kind=0, a=shape, b=slope, target=goal, first=first, center=c)
            put(n, window=int(k > 0), pos_index=i, exc_index=-1)
            total += n
            labels.append((total, segment_label(exc, seg, i, n_pos, len(segments))))
            m = seg.offset.size
            put(m, kind=1, a=seg.offset, b=seg.x, target=0.0, first=0, center=c)
            put(m, window=1, pos_index=i, exc_index=seg.exc_index)
            total += m
            seg_end.append(total)
            here = goal + seg.travel_deg
    check_duration(spec, total, rate)
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
        closed=spec.closed,
        window_deg=spec.window_deg,
        amplitude_limit=spec.amplitude_deg_s * (1.0 + 1e-9),
        max_duration_s=spec.max_duration_s,
        command_limit=plan.config.command_limit_deg_s,
    )


def segments_done(plan: ProgramPlan, n_done: int) -> int:
    """How many segments (over all positions, in order) ended within the first `n_done` ticks."""
    return bisect.bisect_right(plan.seg_end, n_done)
