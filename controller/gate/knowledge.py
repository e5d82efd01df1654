"""What the gate knows about the plant: measured responses and uncertainty bounds.

Plain data, validated on construction; the stability analysis (`controller.gate.analysis`)
judges a candidate against a `PlantKnowledge`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import msgspec
import numpy as np
from numpy.typing import ArrayLike

from controller.core.arrays import ComplexArray, FloatArray
from controller.core.config import NominalModel
from controller.core.validate import finite_nonzero, frequency_grid

TWO_PI = 2.0 * math.pi

__all__ = [
    "COMMISSIONING_BOUND",
    "DIVERGENCE_FRACTION",
    "MIN_ALLOWANCE",
    "UNCERTAINTY_SIGMAS",
    "BoundRecord",
    "KnowledgeRecord",
    "MeasuredRecord",
    "MeasuredResponse",
    "PlantKnowledge",
    "PositionSpread",
    "SampledBound",
    "UncertaintyBound",
    "WeightBound",
    "measured_modes_hz",
    "position_spread",
    "readonly",
]


def readonly(a: np.ndarray) -> np.ndarray:
    """Mark an array read-only (the records are shared between threads)."""
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class MeasuredResponse:
    """A measured (or model-variant) plant response from speed command u to load rate.

    `response` is continuous, G_c(j 2 pi f), unless `sampled` is true: then it is already the
    response of the sampled loop u[k] -> w[k] (what an FRF test run by the loop itself gives).
    """

    name: str
    freq_hz: FloatArray
    response: ComplexArray
    sampled: bool = False
    spread: FloatArray | None = None
    """Relative spread per point (|dH| / |H|: repeats, positions, noise), or None: then the
    gate allows `MIN_ALLOWANCE` at every point."""

    def __post_init__(self) -> None:
        f = np.array(self.freq_hz, dtype=np.float64)
        h = np.array(self.response, dtype=np.complex128)
        if self.spread is not None:
            sp = np.array(self.spread, dtype=np.float64)
            if sp.shape != f.shape or not np.all(np.isfinite(sp)) or np.any(sp < 0):
                raise ValueError(
                    f"measured response {self.name!r}: spread must be finite, >= 0, one per point"
                )
            object.__setattr__(self, "spread", readonly(sp))
        if not isinstance(self.name, str) or not self.name:
            raise ValueError("measured response: a non-empty name is required")
        if f.ndim != 1 or f.size < 2 or h.shape != f.shape:
            raise ValueError(f"measured response {self.name!r}: need >= 2 points, equal sizes")
        frequency_grid(f, f"measured response {self.name!r}: freq_hz")
        finite_nonzero(h, f"measured response {self.name!r}: response")
        object.__setattr__(self, "freq_hz", readonly(f))
        object.__setattr__(self, "response", readonly(h))


@dataclass(frozen=True, eq=False)
class WeightBound:
    """Multiplicative uncertainty bound |Delta(jw)| <= |W(jw)|, W first order plus a mode.

    W1(s) = (tau s + r0) / (tau s / r_inf + 1): r0 = `low_freq_fraction` at DC, |W1| = 1 at
    `unity_freq_hz`, r_inf = `high_freq_fraction` at high frequency. An optional unmodelled
    mode (a resonance at `mode_hz` with damping `mode_damping` missing from the model) adds
    its relative error |s^2 + 2 z wm s| / |s^2 + 2 z wm s + wm^2| to |W1|.
    """

    low_freq_fraction: float
    unity_freq_hz: float
    high_freq_fraction: float = 2.0
    mode_hz: float | None = None
    mode_damping: float = 0.05
    name: str = "bound"

    def __post_init__(self) -> None:
        r0, rinf = self.low_freq_fraction, self.high_freq_fraction
        if not (0.0 <= r0 < 1.0):
            raise ValueError(f"low_freq_fraction must be in [0, 1), got {r0}")
        if not (rinf > 1.0 and math.isfinite(rinf)):
            raise ValueError(f"high_freq_fraction must be > 1, got {rinf}")
        if not (self.unity_freq_hz > 0 and math.isfinite(self.unity_freq_hz)):
            raise ValueError(f"unity_freq_hz must be > 0, got {self.unity_freq_hz}")
        if self.mode_hz is not None and not (self.mode_hz > 0 and math.isfinite(self.mode_hz)):
            raise ValueError(f"mode_hz must be > 0, got {self.mode_hz}")
        if not (0.0 < self.mode_damping < 1.0):
            raise ValueError(f"mode_damping must be in (0, 1), got {self.mode_damping}")

    @property
    def tau_s(self) -> float:
        r0, rinf = self.low_freq_fraction, self.high_freq_fraction
        w1 = TWO_PI * self.unity_freq_hz
        return math.sqrt((1.0 - r0 * r0) / (1.0 - 1.0 / (rinf * rinf))) / w1

    def transfer_function(self) -> tuple[list[float], list[float]]:
        """(num, den) of W1(s), highest power first."""
        tau = self.tau_s
        return [tau, self.low_freq_fraction], [tau / self.high_freq_fraction, 1.0]

    def magnitude(self, freq_hz: ArrayLike) -> FloatArray:
        s = 1j * TWO_PI * np.asarray(freq_hz, dtype=np.float64)
        tau = self.tau_s
        mag = np.abs((tau * s + self.low_freq_fraction) / (tau / self.high_freq_fraction * s + 1))
        if self.mode_hz is not None:
            wm = TWO_PI * self.mode_hz
            a = s * s + 2.0 * self.mode_damping * wm * s
            mag = mag + np.abs(a / (a + wm * wm))
        return np.asarray(mag, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class SampledBound:
    """|W| given at frequencies (interpolated log-log; held constant outside the range)."""

    freq_hz: FloatArray
    mag: FloatArray
    name: str = "bound"

    def __post_init__(self) -> None:
        f = np.array(self.freq_hz, dtype=np.float64)
        m = np.array(self.mag, dtype=np.float64)
        if f.ndim != 1 or f.size < 1 or m.shape != f.shape:
            raise ValueError("sampled bound: freq_hz and mag must be 1-D of equal size")
        frequency_grid(f, "sampled bound: freq_hz")
        if not (np.all(np.isfinite(m)) and np.all(m > 0)):
            raise ValueError("sampled bound: mag must be finite and > 0")
        object.__setattr__(self, "freq_hz", readonly(f))
        object.__setattr__(self, "mag", readonly(m))

    def magnitude(self, freq_hz: ArrayLike) -> FloatArray:
        x = np.log(np.asarray(freq_hz, dtype=np.float64))
        return np.exp(np.interp(x, np.log(self.freq_hz), np.log(self.mag)))


UncertaintyBound = WeightBound | SampledBound


#: The smallest relative error the gate allows at a measured point (noise, drift, the
#: response's own estimation error), whatever spread the measurement states.
MIN_ALLOWANCE = 0.05

#: The commissioning model's stated uncertainty when a rig states none: 20 % at low
#: frequency (within 1.6 dB), 100 % at 40 Hz, up to 300 % above (the belt's unmodelled modes).
COMMISSIONING_BOUND = WeightBound(
    low_freq_fraction=0.2, unity_freq_hz=40.0, high_freq_fraction=4.0, name="commissioning bound"
)


@dataclass(frozen=True, eq=False)
class PlantKnowledge:
    """What is known of the real plant: the evidence every candidate is judged against.

    `model` is the plant model M(s) P(s) from speed command to load rate (the rig's
    commissioning model; never a candidate's `nominal`, which is only the DOB's internal
    model); `bound` its stated uncertainty |Delta| <= |W| (None: the model is taken as exact,
    for analyses of a model alone); `measured` the responses measured on the rig (one per
    position), trusted inside their band with an allowance between the points; beyond the
    band the plant is known only as the response at the band's edge within `bound`.
    `version` and `source` name the record (the controller's state directory keeps it).
    """

    measured: tuple[MeasuredResponse, ...] = ()
    bound: UncertaintyBound | None = None
    model: NominalModel = field(default_factory=NominalModel)
    version: int = 0
    source: str = "model"

    def __post_init__(self) -> None:
        names = [m.name for m in self.measured]
        if len(set(names)) != len(names):
            raise ValueError(f"measured responses need distinct names, got {names}")
        if not isinstance(self.model, NominalModel):
            raise ValueError("plant knowledge: model must be a NominalModel")

    @property
    def band_hz(self) -> tuple[float, float] | None:
        """The measured band (lowest, highest measured frequency), None without measurements."""
        if not self.measured:
            return None
        return (
            min(float(m.freq_hz[0]) for m in self.measured),
            max(float(m.freq_hz[-1]) for m in self.measured),
        )

    def describe(self) -> str:
        """One line: version, source, band (for reasons and status)."""
        band = self.band_hz
        measured = (
            f"{len(self.measured)} measured response(s) {band[0]:.3g}-{band[1]:.3g} Hz"
            if band
            else "no measured response"
        )
        bound = self.bound.name if self.bound is not None else "no bound"
        return f"plant knowledge v{self.version} ({self.source}: model, {bound}, {measured})"


# --------------------------------------------------------------------------- position spread

#: Responses "agree" at a frequency while they differ from their common centre by at most this
#: fraction (|H_i / H_ref - 1|): 1 dB in magnitude alone (10^(1/20) - 1), 7 deg in phase alone.
DIVERGENCE_FRACTION = 10.0 ** (1.0 / 20.0) - 1.0
#: A difference between positions within this many standard uncertainties of the responses
#: (their `spread`) is not taken as a difference of the plant.
UNCERTAINTY_SIGMAS = 2.0


@dataclass(frozen=True, eq=False)
class PositionSpread:
    """How far the measured responses (one per turntable position) differ from one another:
    the article's Fig. 13 as evidence. On the band all of them cover, at every measured
    frequency of any of them (each interpolated in log magnitude and unwrapped phase, linear
    in log f, as the gate interpolates a response):

        H_ref = exp(mean_i ln H_i)           (geometric mean: mean dB, mean phase)
        relative(f) = max_i |H_i / H_ref - 1|

    Judged against the measurement's own uncertainty: each response's `spread` (its relative
    standard uncertainty per point, from the noise lines or coherence; 0 where None) is
    `UNCERTAINTY_SIGMAS` times taken off its difference, so a point the measurement cannot
    resolve (a low-coherence point, friction at a low frequency) is not a divergence of the
    plant. `measured` is the difference before that (max_i |H_i / H_ref - 1|), `uncertainty`
    what was taken off (max_i of k u_i).

    `relative` (max_i max(0, |H_i / H_ref - 1| - k u_i)) is a multiplicative plant error Delta
    that a single model of the plant must allow wherever the turntable stands: the small-gain
    figure of the DOB, ||Delta Q||, uses it (`controller.gate.search`; the gate still judges
    every measured response on its own). `divergence_hz` is the lowest frequency where
    `relative` exceeds `DIVERGENCE_FRACTION` (interpolated in log f; None if the responses
    agree on the whole band): the model is trusted below it.
    """

    names: tuple[str, ...]
    freq_hz: FloatArray
    relative: FloatArray
    mag_db: FloatArray
    """max - min of the magnitudes in dB."""
    phase_deg: FloatArray
    """max - min of the phases in deg."""
    divergence_hz: float | None
    measured: FloatArray | None = None
    """max_i |H_i / H_ref - 1| before the uncertainty is taken off (None: as `relative`)."""
    uncertainty: FloatArray | None = None
    """max_i k u_i: the part of a difference the measurement cannot resolve."""

    def at(self, freq_hz: ArrayLike) -> FloatArray:
        """`relative` at any frequency: linear in log f inside the band, held at the band's
        edge values outside it."""
        x = np.log(np.asarray(freq_hz, dtype=np.float64))
        return np.asarray(np.interp(x, np.log(self.freq_hz), self.relative), dtype=np.float64)


def position_spread(
    measured: Sequence[MeasuredResponse],
    to_continuous: Callable[[MeasuredResponse], ComplexArray] | None = None,
) -> PositionSpread | None:
    """The spread across `measured` (see `PositionSpread`); None with fewer than two.

    `to_continuous(m)`: m's response on the continuous basis; needed only when the responses
    mix sampled and continuous forms (the sampling factor cancels in the ratio otherwise).
    None too when the responses share no band of at least two frequencies (the spread
    between them is then not measured).
    """
    if len(measured) < 2:
        return None
    mixed = len({m.sampled for m in measured}) > 1
    if mixed and to_continuous is None:
        raise ValueError("position spread: the responses mix sampled and continuous forms")
    lo = max(float(m.freq_hz[0]) for m in measured)
    hi = min(float(m.freq_hz[-1]) for m in measured)
    f = np.unique(np.concatenate([m.freq_hz for m in measured]))
    f = f[(f >= lo) & (f <= hi)]
    if f.size < 2:  # nothing to compare: no evidence of spread either way
        return None
    x = np.log(f)
    logs = []
    for m in measured:
        h = to_continuous(m) if mixed and to_continuous is not None else m.response
        ph = np.unwrap(np.angle(h))
        logs.append(
            np.interp(x, np.log(m.freq_hz), np.log(np.abs(h)))
            + 1j * np.interp(x, np.log(m.freq_hz), ph)
        )
    ln = np.array(logs)
    unc = np.array([
        np.zeros(f.size) if m.spread is None
        else UNCERTAINTY_SIGMAS * np.interp(x, np.log(m.freq_hz), m.spread)
        for m in measured])
    # Whole turns between responses are not a difference of the plant: align each phase to
    # the first response's at the lowest common frequency.
    turns = np.round((ln[:, 0].imag - ln[0, 0].imag) / TWO_PI)
    ln = ln - 1j * TWO_PI * turns[:, None]
    ref = ln.mean(axis=0)
    diff = np.abs(np.exp(ln - ref[None, :]) - 1.0)
    rel = np.max(np.maximum(0.0, diff - unc), axis=0)
    mag_db = 20.0 / math.log(10.0) * (ln.real.max(axis=0) - ln.real.min(axis=0))
    phase_deg = np.degrees(ln.imag.max(axis=0) - ln.imag.min(axis=0))
    return PositionSpread(
        names=tuple(m.name for m in measured),
        freq_hz=readonly(f),
        relative=readonly(rel),
        mag_db=readonly(mag_db),
        phase_deg=readonly(phase_deg),
        divergence_hz=_first_crossing(f, rel, DIVERGENCE_FRACTION),
        measured=readonly(np.max(diff, axis=0)),
        uncertainty=readonly(np.max(unc, axis=0)),
    )


def measured_modes_hz(knowledge: PlantKnowledge) -> tuple[tuple[float, float], ...]:
    """Per measured response (one per position) its first resonance: the lowest frequency
    above 2 Hz where the response peaks by >= 3 dB over the lowest magnitude below it, with
    the relative uncertainty of that frequency (half the measured grid's step there: the peak
    lies between the neighbouring points). Responses that show none are left out."""
    found: list[tuple[float, float]] = []
    for m in knowledge.measured:
        mag = 20.0 * np.log10(np.abs(m.response))
        f = m.freq_hz
        for i in range(1, len(f) - 1):
            if f[i] < 2.0 or not (mag[i] >= mag[i - 1] and mag[i] > mag[i + 1]):
                continue
            if mag[i] - float(np.min(mag[: i + 1])) >= 3.0:
                step = max(f[i + 1] / f[i], f[i] / f[i - 1])
                found.append((float(f[i]), 0.5 * (float(step) - 1.0)))
                break
    return tuple(found)


def _first_crossing(f: FloatArray, y: FloatArray, level: float) -> float | None:
    """The lowest frequency where y rises above `level` (linear in log f between points; the
    lowest frequency itself when y starts above it; None if it never does)."""
    above = np.flatnonzero(y > level)
    if above.size == 0:
        return None
    i = int(above[0])
    if i == 0:
        return float(f[0])
    x0, x1 = math.log(f[i - 1]), math.log(f[i])
    t = (level - y[i - 1]) / (y[i] - y[i - 1])
    return float(math.exp(x0 + t * (x1 - x0)))


# --------------------------------------------------------------------------- wire/persisted form


class _Rec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    pass


class MeasuredRecord(_Rec, frozen=True, kw_only=True):
    name: str
    freq_hz: list[float]
    re: list[float]
    im: list[float]
    sampled: bool = False
    spread: list[float] | None = None


class BoundRecord(_Rec, frozen=True, kw_only=True):
    """Either a weight (low_freq_fraction, unity_freq_hz, high_freq_fraction, mode) or
    sampled magnitudes (freq_hz, mag)."""

    name: str = "bound"
    low_freq_fraction: float | None = None
    unity_freq_hz: float | None = None
    high_freq_fraction: float = 2.0
    mode_hz: float | None = None
    mode_damping: float = 0.05
    freq_hz: list[float] | None = None
    mag: list[float] | None = None


class KnowledgeRecord(_Rec, frozen=True, kw_only=True):
    """`PlantKnowledge` as plain data (persisted in the state directory, sent on the wire)."""

    version: int = 0
    source: str = "model"
    model: NominalModel = msgspec.field(default_factory=NominalModel)
    bound: BoundRecord | None = None
    measured: list[MeasuredRecord] = []

    def to_knowledge(self) -> PlantKnowledge:
        """Raises ValueError naming the offending part."""
        bound: UncertaintyBound | None = None
        b = self.bound
        if b is not None:
            if b.freq_hz is not None or b.mag is not None:
                if b.freq_hz is None or b.mag is None:
                    raise ValueError("bound: freq_hz and mag go together")
                bound = SampledBound(np.array(b.freq_hz), np.array(b.mag), name=b.name)
            else:
                if b.low_freq_fraction is None or b.unity_freq_hz is None:
                    raise ValueError("bound: low_freq_fraction and unity_freq_hz are required")
                bound = WeightBound(
                    b.low_freq_fraction, b.unity_freq_hz, b.high_freq_fraction,
                    b.mode_hz, b.mode_damping, b.name,
                )
        measured = []
        for i, m in enumerate(self.measured):
            if not (len(m.freq_hz) == len(m.re) == len(m.im)):
                raise ValueError(f"measured[{i}]: freq_hz, re and im need equal lengths")
            try:
                measured.append(
                    MeasuredResponse(
                        m.name, np.array(m.freq_hz), np.array(m.re) + 1j * np.array(m.im),
                        m.sampled, None if m.spread is None else np.array(m.spread),
                    )
                )
            except ValueError as exc:
                raise ValueError(f"measured[{i}]: {exc}") from None
        return PlantKnowledge(tuple(measured), bound, self.model, self.version, self.source)

    @classmethod
    def of(cls, k: PlantKnowledge) -> KnowledgeRecord:
        b = k.bound
        bound: BoundRecord | None
        if b is None:
            bound = None
        elif isinstance(b, WeightBound):
            bound = BoundRecord(
                name=b.name, low_freq_fraction=b.low_freq_fraction,
                unity_freq_hz=b.unity_freq_hz, high_freq_fraction=b.high_freq_fraction,
                mode_hz=b.mode_hz, mode_damping=b.mode_damping,
            )
        else:
            bound = BoundRecord(name=b.name, freq_hz=b.freq_hz.tolist(), mag=b.mag.tolist())
        measured = [
            MeasuredRecord(
                name=m.name, freq_hz=m.freq_hz.tolist(), re=m.response.real.tolist(),
                im=m.response.imag.tolist(), sampled=m.sampled,
                spread=None if m.spread is None else m.spread.tolist(),
            )
            for m in k.measured
        ]
        return cls(version=k.version, source=k.source, model=k.model, bound=bound,
                   measured=measured)


