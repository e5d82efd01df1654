"""Excitation signals for frequency-response identification (pure math, no I/O).

Two kinds, both sampled at the loop rate and expressed as a load-side speed in deg/s (the unit
of the speed command u):

* Stepped sine: one frequency at a time. Every frequency is snapped to ``fs / L`` with an
  integer period of ``L`` samples, so each measurement window (and each single period in it)
  holds whole periods and the single-bin DFT is exact. Per point: a linear amplitude ramp-in,
  settling, the measurement window, a ramp-out; all whole periods.
* Periodic multisine: whole periods of ``N`` samples, components on exact DFT bins
  ``k fs / N`` in ``[f_min, f_max]``, Schroeder phases for a low crest factor, ``P`` measured
  periods after ``transient_periods`` periods that the estimator discards.
* Odd random-phase multisine (Pintelon & Schoukens, *System Identification*, ch. 3-4): the
  same, with only odd bins excited (``harmonics="odd"``; log-spaced, the next free odd bin
  where the odd grid is coarser than the spacing asked for) and random phases, then the crest
  factor lowered by clipping. Every other bin is a detection line: even bins see the even-order
  nonlinear distortion, the non-excited odd bins the odd-order distortion, all of them the
  noise; the estimator takes the variance of each excited line from its non-excited neighbours
  (``spread_from="lines"``), so one period suffices and the spread includes the nonlinear
  distortion. Instead of whole transient periods a lead-in of ``lead_samples`` (the end of a
  period, faded in over its first half) precedes the measured periods: the plant settles in a
  fraction of a second, the lowest frequency's period is ten seconds. A faded tail follows.

Amplitude shaping (position window). A speed sine ``A sin(2 pi f t)`` moves the position by
``A / (2 pi f)`` deg (amplitude). With ``window_deg`` set, the stepped sine caps the speed
amplitude at ``window_deg * 2 pi f``; the generator then integrates the actual samples and, if
the ramps still push the excursion past the window, scales that point down so that
``max |position - start position| <= window_deg`` holds exactly for the sampled signal. The
multisine optionally gives components below ``position_knee_hz`` a speed amplitude proportional
to ``f`` (constant position amplitude), then scales the whole signal so that both the peak speed
``<= amplitude_deg_s`` and the peak excursion from the start ``<= window_deg`` hold.

Invalid specifications raise :class:`controller.core.errors.ConfigError` (a ``ValueError``) whose
message starts with the field name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np

from controller.core.arrays import FloatArray, IntArray
from controller.core.errors import ConfigError
from controller.core.validate import Check, check_fields, nonnegative, optional, positive

__all__ = [
    "HARMONICS",
    "PHASES",
    "SPREAD_FROM",
    "Harmonics",
    "Multisine",
    "MultisineSpec",
    "PhaseKind",
    "SpreadFrom",
    "SteppedSine",
    "SteppedSinePoint",
    "SteppedSineSpec",
    "cap_speed_amplitude",
    "crest_factor",
    "multisine",
    "schroeder_phases",
    "stepped_sine",
]


Harmonics = Literal["all", "odd"]
PhaseKind = Literal["schroeder", "random"]
SpreadFrom = Literal["periods", "lines"]
HARMONICS: tuple[Harmonics, ...] = ("all", "odd")
PHASES: tuple[PhaseKind, ...] = ("schroeder", "random")
SPREAD_FROM: tuple[SpreadFrom, ...] = ("periods", "lines")


# --------------------------------------------------------------------------- validation helpers


#: Bounds that keep a spec from asking for more points or samples than any measurement uses
#: (1e9 points per decade made a spec's construction build a billion frequencies).
MAX_POINTS_PER_DECADE = 1000
MAX_PERIOD_SAMPLES = 10_000_000


def _integer(value: object, name: str, minimum: int, maximum: int | None = None) -> int:
    """Whole numbers only: 3 and 3.0 pass, 2.5, NaN, True do not."""
    if isinstance(value, bool):
        raise ConfigError(name, f"must be an integer (got {value!r})")
    whole_float = (
        isinstance(value, (float, np.floating)) and math.isfinite(value) and value.is_integer()
    )
    if isinstance(value, (int, np.integer)) or whole_float:
        v = int(value)  # type: ignore[call-overload]
    else:
        raise ConfigError(name, f"must be an integer (got {value!r})")
    if v < minimum:
        raise ConfigError(name, f"must be >= {minimum} (got {v})")
    if maximum is not None and v > maximum:
        raise ConfigError(name, f"must be <= {maximum} (got {v})")
    return v


def _whole(minimum: int, maximum: int | None = None) -> Check:
    """A field's declared check: `_integer` from `minimum` on (up to `maximum`)."""

    def check(value: object, name: str) -> int:
        return _integer(value, name, minimum, maximum)

    return check


def _bins(value: object, name: str) -> tuple[int, ...]:
    return tuple(_integer(k, name, 1) for k in value)  # type: ignore[attr-defined]


def _choice(choices: tuple[str, ...]) -> Check:
    """A field's declared check: one of `choices`."""

    def check(value: object, name: str) -> object:
        if value not in choices:
            raise ConfigError(name, f"must be one of {', '.join(choices)} (got {value!r})")
        return value

    return check


def _check_band(spec: SteppedSineSpec | MultisineSpec) -> None:
    fs, f_min, f_max = spec.sample_rate_hz, spec.f_min_hz, spec.f_max_hz
    if f_min >= f_max:
        raise ConfigError("f_min_hz", f"must be < f_max_hz (got {f_min} >= {f_max})")
    if f_max >= fs / 2.0:
        raise ConfigError("f_max_hz", f"must be below Nyquist {fs / 2.0} Hz (got {f_max})")


# ----------------------------------------------------------------------------- shared helpers


def cap_speed_amplitude(
    amplitude_deg_s: float | FloatArray, freq_hz: float | FloatArray, window_deg: float | None
) -> FloatArray:
    """Speed amplitude capped so that a sine at ``freq_hz`` moves at most ``window_deg``.

    The position amplitude of ``A sin(2 pi f t)`` deg/s is ``A / (2 pi f)`` deg, hence the cap
    ``A <= window_deg * 2 pi f``. ``window_deg=None`` means no cap.
    """
    a = np.asarray(amplitude_deg_s, dtype=np.float64)
    f = np.asarray(freq_hz, dtype=np.float64)
    if window_deg is None:
        return np.broadcast_to(a, np.broadcast(a, f).shape).astype(np.float64)
    return np.minimum(a, window_deg * 2.0 * np.pi * f)


def crest_factor(signal: FloatArray) -> float:
    """Peak over RMS of a signal (sqrt 2 for a single sine)."""
    x = np.asarray(signal, dtype=np.float64)
    rms = float(np.sqrt(np.mean(x * x)))
    return float(np.max(np.abs(x)) / rms) if rms > 0.0 else math.inf


def schroeder_phases(bins: IntArray | FloatArray, amplitudes: FloatArray) -> FloatArray:
    """Schroeder phases (rad) for harmonics ``bins`` of one period, any amplitudes.

    The signal behaves like a chirp that visits harmonic ``k`` at the fraction of the period
    equal to the power below it: ``phi_k = phi_{k-1} - 2 pi (k - k_prev) C_{k-1}`` with ``C``
    the cumulative power fraction. For consecutive harmonics with equal amplitudes this is the
    classical ``phi_k = -pi k (k - 1) / K``; it also works for sparse (log-spaced) bins.
    """
    k = np.asarray(bins, dtype=np.float64)
    p = np.asarray(amplitudes, dtype=np.float64) ** 2
    phases = np.zeros_like(k)
    if k.size > 1:
        cum = np.cumsum(p) / np.sum(p)
        phases[1:] = -2.0 * np.pi * np.cumsum(np.diff(k) * cum[:-1])
    return np.mod(phases, 2.0 * np.pi)


# ------------------------------------------------------------------------------- stepped sine


@dataclass(frozen=True, slots=True)
class SteppedSineSpec:
    """What to measure with a stepped sine; validated on construction."""

    f_min_hz: Annotated[float, positive] = 0.1
    """Lowest frequency (before snapping to ``fs / L``)."""
    f_max_hz: Annotated[float, positive] = 20.0
    """Highest frequency; below Nyquist."""
    points_per_decade: Annotated[int, _whole(1, MAX_POINTS_PER_DECADE)] = 10
    """Log spacing of the grid; points that snap to the same period are merged."""
    amplitude_deg_s: Annotated[float, positive] = 10.0
    """Speed amplitude (load side) before the window cap."""
    window_deg: Annotated[float | None, optional(positive)] = None
    """Largest allowed position excursion from the start of each point, or None."""
    min_periods: Annotated[int, _whole(1)] = 3
    """At least this many whole periods in each measurement window (>= 2 for a variance)."""
    min_measure_s: Annotated[float, nonnegative] = 2.0
    """At least this long a measurement window (more periods at high frequency)."""
    settle_periods: Annotated[int, _whole(0)] = 2
    """At least this many whole periods of settling before measuring (ramp-in included)."""
    settle_s: Annotated[float, nonnegative] = 1.0
    """At least this long a settling time."""
    ramp_periods: Annotated[int, _whole(0)] = 1
    """Linear amplitude ramp-in and ramp-out, in periods (0: abrupt start and stop)."""
    sample_rate_hz: Annotated[float, positive] = 1000.0
    """Loop rate."""

    def __post_init__(self) -> None:
        check_fields(self, store=True)
        _check_band(self)


@dataclass(frozen=True, slots=True)
class SteppedSinePoint:
    """One frequency of a stepped sine; indices refer to :attr:`SteppedSine.signal`."""

    freq_hz: float
    """Snapped frequency ``sample_rate_hz / period_samples``."""
    amplitude_deg_s: float
    """Speed amplitude actually used (after the window cap)."""
    period_samples: int
    """Samples per period ``L``."""
    start: int
    """First sample of this point (ramp-in starts here, at phase 0)."""
    settle_periods: int
    """Whole periods before the measurement window (ramp-in included)."""
    n_periods: int
    """Whole periods in the measurement window."""
    ramp_periods: int
    """Ramp-out periods after the window (equal to the ramp-in)."""
    max_excursion_deg: float
    """Largest position excursion from the start of the point, for the sampled signal."""

    @property
    def measure_start(self) -> int:
        """First sample of the measurement window."""
        return self.start + self.settle_periods * self.period_samples

    @property
    def measure_len(self) -> int:
        """Samples in the measurement window (whole periods)."""
        return self.n_periods * self.period_samples

    @property
    def stop(self) -> int:
        """One past the last sample of this point."""
        return self.measure_start + (self.n_periods + self.ramp_periods) * self.period_samples


@dataclass(frozen=True, eq=False)
class SteppedSine:
    """A generated stepped sine: the points and the concatenated command samples."""

    spec: SteppedSineSpec
    points: tuple[SteppedSinePoint, ...]
    signal: FloatArray = field(repr=False)
    """Speed excitation in deg/s, one sample per loop tick."""

    @property
    def freq_hz(self) -> FloatArray:
        return np.array([p.freq_hz for p in self.points])

    @property
    def duration_s(self) -> float:
        return self.signal.size / self.spec.sample_rate_hz


def _envelope(total: int, ramp: int) -> FloatArray:
    """Linear ramp in and out over whole periods, symmetric: env[n] == env[total - n].

    A linear ramp has a constant derivative, whose integral against cos(omega t) over whole
    periods is zero: the position oscillates about the start point with no offset (a
    raised-cosine ramp over one period would offset it by a third of the amplitude).
    """
    env = np.ones(total)
    if ramp > 0:
        rise = np.arange(ramp) / ramp
        env[:ramp] = rise
        # env[total - n] = rise[n] for n = 1 .. ramp-1 keeps the zero-drift symmetry
        env[total - ramp + 1 :] = rise[1:][::-1]
    return env


def stepped_sine(spec: SteppedSineSpec) -> SteppedSine:
    """Generate the stepped sine described by ``spec``.

    Each point is ``a[n] sin(2 pi n / L)`` with a symmetric envelope over whole periods, so the
    speed is continuous (zero at every boundary) and the net position drift of a point is zero
    (the summand is antisymmetric about the middle of the point).
    """
    fs = spec.sample_rate_hz
    decades = math.log10(spec.f_max_hz / spec.f_min_hz)
    n_target = max(2, round(spec.points_per_decade * decades) + 1)
    targets = np.logspace(math.log10(spec.f_min_hz), math.log10(spec.f_max_hz), n_target)
    periods: list[int] = []
    for f in targets:
        period = max(3, round(fs / f))
        if not periods or period != periods[-1]:
            periods.append(period)
    points: list[SteppedSinePoint] = []
    chunks: list[FloatArray] = []
    start = 0
    for period in periods:
        f = fs / period
        n_meas = max(spec.min_periods, math.ceil(spec.min_measure_s * f - 1e-9))
        n_settle = max(spec.settle_periods, spec.ramp_periods, math.ceil(spec.settle_s * f - 1e-9))
        n_total = n_settle + n_meas + spec.ramp_periods
        total = n_total * period
        env = _envelope(total, spec.ramp_periods * period)
        unit = env * np.sin(2.0 * np.pi * np.arange(total) / period)
        amp = float(cap_speed_amplitude(spec.amplitude_deg_s, f, spec.window_deg))
        # the excursion the loop will see: position integrated from the command samples
        excursion = float(np.max(np.abs(np.cumsum(unit)))) / fs
        if spec.window_deg is not None and amp * excursion > spec.window_deg:
            amp = spec.window_deg / excursion
        chunks.append(amp * unit)
        points.append(
            SteppedSinePoint(
                freq_hz=f,
                amplitude_deg_s=amp,
                period_samples=period,
                start=start,
                settle_periods=n_settle,
                n_periods=n_meas,
                ramp_periods=spec.ramp_periods,
                max_excursion_deg=amp * excursion,
            )
        )
        start += total
    signal = np.concatenate(chunks) if chunks else np.zeros(0)
    return SteppedSine(spec=spec, points=tuple(points), signal=signal)


# ---------------------------------------------------------------------------------- multisine


@dataclass(frozen=True, slots=True)
class MultisineSpec:
    """A periodic multisine; validated on construction."""

    f_min_hz: Annotated[float, positive] = 0.1
    """Lowest component; must be at least the resolution ``sample_rate_hz / period_samples``."""
    f_max_hz: Annotated[float, positive] = 20.0
    """Highest component; below Nyquist."""
    period_samples: Annotated[int, _whole(4, MAX_PERIOD_SAMPLES)] = 10000
    """Period ``N`` in samples; the frequency resolution is ``sample_rate_hz / N``."""
    n_periods: Annotated[int, _whole(1)] = 4
    """Measured periods ``P`` (>= 2 for the spread between periods; 1 is enough with
    ``spread_from="lines"``)."""
    transient_periods: Annotated[int, _whole(0)] = 1
    """Leading periods that the estimator discards (settling)."""
    amplitude_deg_s: Annotated[float, positive] = 10.0
    """Peak speed of the whole signal."""
    window_deg: Annotated[float | None, optional(positive)] = None
    """Largest allowed position excursion from the start, or None."""
    points_per_decade: Annotated[int | None, optional(_whole(1, MAX_POINTS_PER_DECADE))] = None
    """Log-spaced subset of the bins; None uses every bin in the band."""
    position_knee_hz: Annotated[float | None, optional(positive)] = None
    """Below this frequency component speed amplitudes fall as f (constant position)."""
    crest_iterations: Annotated[int, _whole(0)] = 100
    """Clip-and-restore iterations after the initial phases (0: the initial phases as they are)."""
    sample_rate_hz: Annotated[float, positive] = 1000.0
    """Loop rate."""
    harmonics: Annotated[Harmonics, _choice(HARMONICS)] = "all"
    """``odd``: only odd bins are excited (the rest are detection lines)."""
    phases: Annotated[PhaseKind, _choice(PHASES)] = "schroeder"
    """Initial phases: Schroeder's, or uniformly random (``seed``)."""
    seed: Annotated[int, _whole(0)] = 0
    """Seed of the random phases (the same seed gives the same signal)."""
    lead_samples: Annotated[int, _whole(0)] = 0
    """Samples of the end of a period played before the transient and measured periods,
    faded in over its first half (the signal is periodic: the measured periods start in
    steady state once the plant has settled in the second half)."""
    tail_samples: Annotated[int, _whole(0)] = 0
    """Samples of the start of a period played, faded out, after the measured periods."""
    spread_from: Annotated[SpreadFrom, _choice(SPREAD_FROM)] = "periods"
    """How the estimator gets each line's variance: between the measured periods (>= 2
    needed), or from the non-excited lines next to it (noise and nonlinear distortion)."""
    skip_bins: Annotated[tuple[int, ...], _bins] = ()
    """Bins left out of the excitation (detection lines kept free for a known periodic
    disturbance, see `controller.ident.plan`)."""

    def __post_init__(self) -> None:
        check_fields(self, store=True)
        for name in ("lead_samples", "tail_samples"):
            if getattr(self, name) > self.period_samples:
                raise ConfigError(
                    name,
                    f"must be <= period_samples {self.period_samples} "
                    f"(got {getattr(self, name)})",
                )
        _check_band(self)
        resolution = self.sample_rate_hz / self.period_samples
        if self.f_min_hz < resolution * (1.0 - 1e-9):
            raise ConfigError(
                "f_min_hz",
                f"below the frequency resolution sample_rate_hz / period_samples = {resolution}"
                f" Hz (got {self.f_min_hz})",
            )
        if self.bins().size == 0:
            raise ConfigError("f_min_hz", "no DFT bin between f_min_hz and f_max_hz")
        if self.spread_from == "lines" and self.noise_bins().size == 0:
            raise ConfigError("spread_from", "no non-excited line to take the spread from")

    def bins(self) -> IntArray:
        """The excited DFT bins ``k`` (frequency ``k * sample_rate_hz / period_samples``)."""
        res = self.sample_rate_hz / self.period_samples
        k_lo = math.ceil(self.f_min_hz / res - 1e-9)
        k_hi = math.floor(self.f_max_hz / res + 1e-9)
        odd = self.harmonics == "odd"
        if odd:
            k_lo += 1 - k_lo % 2
            k_hi -= 1 - k_hi % 2
        if k_hi < k_lo:
            return np.zeros(0, dtype=np.int64)
        if self.points_per_decade is None:
            every = np.arange(k_lo, k_hi + 1, 2 if odd else 1, dtype=np.int64)
            return np.setdiff1d(every, np.asarray(self.skip_bins, dtype=np.int64))
        decades = math.log10(k_hi / k_lo) if k_hi > k_lo else 0.0
        n = max(1, round(self.points_per_decade * decades) + 1)
        targets = np.logspace(math.log10(k_lo), math.log10(k_hi), n)
        if odd:  # the nearest odd bin, or the next free one where the odd grid is too coarse
            nearest = (2 * np.floor(targets / 2.0) + 1).astype(np.int64)  # within 1 of it
            ks = np.maximum.accumulate(nearest - 2 * np.arange(n)) + 2 * np.arange(n)
            ks = ks[ks <= k_hi]
        else:
            ks = np.round(targets).astype(np.int64)
        return np.setdiff1d(np.unique(ks), np.asarray(self.skip_bins, dtype=np.int64))

    def detection_bins(self) -> IntArray:
        """The non-excited bins from 1 to twice the highest excited one (below Nyquist): where
        the noise and the nonlinear distortion show without the linear response."""
        k_top = min(2 * int(self.bins()[-1]) + 1, (self.period_samples - 1) // 2)
        every = np.arange(1, k_top + 1, dtype=np.int64)
        return np.setdiff1d(every, self.bins())

    def noise_bins(self) -> IntArray:
        """The detection bins that give the excited lines' variance: with only odd bins
        excited the odd ones (even-order distortion never reaches an odd line), else all."""
        det = self.detection_bins()
        return det[det % 2 == 1] if self.harmonics == "odd" else det


@dataclass(frozen=True, eq=False)
class Multisine:
    """A generated periodic multisine."""

    spec: MultisineSpec
    bins: IntArray
    """Excited DFT bins of one period."""
    amplitudes_deg_s: FloatArray
    """Speed amplitude of each component."""
    phases_rad: FloatArray
    """Phase of each component: ``a cos(2 pi k n / N + phi)``."""
    period: FloatArray = field(repr=False)
    """One period, ``N`` samples (deg/s)."""
    signal: FloatArray = field(repr=False)
    """The faded lead-in, ``transient_periods + n_periods`` periods back to back and the faded
    tail (deg/s)."""
    crest_factor: float
    """Peak / RMS of the speed signal."""
    peak_speed_deg_s: float
    """Largest |speed| in the signal."""
    max_excursion_deg: float
    """Largest position excursion from the start (exact periodic integral)."""

    @property
    def freq_hz(self) -> FloatArray:
        return self.bins.astype(np.float64) * (self.spec.sample_rate_hz / self.spec.period_samples)

    @property
    def duration_s(self) -> float:
        return self.signal.size / self.spec.sample_rate_hz

    @property
    def measure_start(self) -> int:
        """First sample of the measured periods in :attr:`signal`."""
        return self.spec.lead_samples + self.spec.transient_periods * self.spec.period_samples

    @property
    def measure_len(self) -> int:
        """Samples in the measured periods."""
        return self.spec.n_periods * self.spec.period_samples


def _fade(n: int) -> FloatArray:
    """Raised cosine from 0 (exclusive) to 1 (exclusive) over n samples."""
    k = np.arange(1, n + 1)
    return 0.5 - 0.5 * np.cos(np.pi * k / (n + 1))


def _synth(n: int, bins: IntArray, amps: FloatArray, phases: FloatArray) -> FloatArray:
    spectrum = np.zeros(n // 2 + 1, dtype=np.complex128)
    spectrum[bins] = amps * np.exp(1j * phases) * (n / 2.0)
    return np.fft.irfft(spectrum, n)


def multisine(spec: MultisineSpec) -> Multisine:
    """Generate the periodic multisine described by ``spec`` (see the module docstring)."""
    n = spec.period_samples
    fs = spec.sample_rate_hz
    bins = spec.bins()
    freq = bins * (fs / n)
    shape = np.ones(bins.size)
    if spec.position_knee_hz is not None:
        shape = np.minimum(1.0, freq / spec.position_knee_hz)
    if spec.phases == "random":
        phases = np.random.default_rng(spec.seed).uniform(0.0, 2.0 * np.pi, bins.size)
    else:
        phases = schroeder_phases(bins, shape)
    period = _synth(n, bins, shape, phases)
    best = crest_factor(period)
    trial = period
    for _ in range(spec.crest_iterations):
        # clip the peaks, keep the new phases of the excited bins, restore their amplitudes;
        # keep the best period seen (the iteration is not monotonic)
        limit = 0.85 * np.max(np.abs(trial))
        trial_phases = np.angle(np.fft.rfft(np.clip(trial, -limit, limit))[bins])
        trial = _synth(n, bins, shape, trial_phases)
        cf = crest_factor(trial)
        if cf < best:
            best, period, phases = cf, trial, trial_phases
    # exact periodic position (zero mean) of the continuous-time components, sampled
    t = np.arange(n) / fs
    omega = 2.0 * np.pi * freq
    position = np.sum(
        (shape / omega)[:, None] * np.sin(omega[:, None] * t[None, :] + phases[:, None]), axis=0
    )
    excursion = float(np.max(np.abs(position - position[0])))
    scale = spec.amplitude_deg_s / float(np.max(np.abs(period)))
    if spec.window_deg is not None:
        scale = min(scale, spec.window_deg / excursion)
    period = period * scale
    lead = spec.lead_samples
    tail = spec.tail_samples
    fade_in = np.concatenate([_fade(lead // 2), np.ones(lead - lead // 2)])
    signal = np.concatenate(
        [
            period[n - lead :] * fade_in,
            np.tile(period, spec.transient_periods + spec.n_periods),
            period[:tail] * _fade(tail)[::-1],
        ]
    )
    return Multisine(
        spec=spec,
        bins=bins,
        amplitudes_deg_s=shape * scale,
        phases_rad=phases,
        period=period,
        signal=signal,
        crest_factor=crest_factor(period),
        peak_speed_deg_s=float(np.max(np.abs(period))),
        max_excursion_deg=excursion * scale,
    )
