"""The identification spec: one typed definition of what to measure and within which limits.

`IdentifySpec` is at once the domain type (validated on construction and on decode, errors
name the field), the wire message of the ``identify_start`` command (`controller.protocol`
carries it as is: its field names and types are the wire's, unknown fields are rejected) and
the source of the ``dobtune identify`` options and of the dashboard's Identify fields, which
are generated from each field's `Param` (default, range or choices, unit, help text).

The controller uses every field of `IdentifySpec` (planning, the limits it checks every tick,
the estimates, the fit and the gate). What only an offline run on a rig object uses (the
simulated rig's seed, the stop and hold recorded after an abort: the controller holds the
position by itself) is `OfflineOptions`, which is never sent.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from typing import Annotated, Any, get_args, get_type_hints

import msgspec

from controller.core.errors import ConfigError
from controller.core.validate import number

__all__ = [
    "IDENTIFY_FIELDS",
    "MODES",
    "OFFLINE_FIELDS",
    "SIGNALS",
    "IdentifySpec",
    "OfflineOptions",
    "Param",
    "SpecField",
]

MODES: tuple[str, ...] = ("open", "closed")
SIGNALS: tuple[str, ...] = ("sine", "multisine")


@dataclass(frozen=True, slots=True)
class Param:
    """What a spec field means and allows, beyond its type and default."""

    help: str
    unit: str = ""
    """As shown to people ("Hz", "deg/s"); the field name carries it too."""
    gt: float | None = None
    ge: float | None = None
    le: float | None = None
    choices: tuple[str, ...] = ()
    flag: str = ""
    """The ``dobtune identify`` option ("" : not on the command line)."""
    label: str = ""
    """The dashboard field's label without the unit ("" : not on the dashboard)."""
    widget: tuple[float, float, float] | None = None
    """Dashboard number input (min, max, step) where the valid range is open-ended."""


@dataclass(frozen=True, slots=True)
class SpecField:
    """One field of a spec as the command line and the dashboard see it."""

    name: str
    type: type
    """float, int or str (without the None of an optional field)."""
    optional: bool
    default: Any
    param: Param

    @property
    def title(self) -> str:
        """Label with its unit: "f min (Hz)"."""
        p = self.param
        return f"{p.label} ({p.unit})" if p.unit else p.label

    @property
    def metavar(self) -> str:
        """Command-line placeholder: the choices, the unit ("HZ", "DEG_S") or N."""
        p = self.param
        if p.choices:
            return "|".join(p.choices)
        if self.type is int:
            return "N"
        return p.unit.upper().replace("/", "_") or "X"

    @property
    def limits(self) -> tuple[float, float, float]:
        """Dashboard number input (min, max, step)."""
        p = self.param
        if p.widget is not None:
            return p.widget
        if p.ge is None or p.le is None:
            raise ValueError(f"{self.name}: a dashboard field needs a range or a widget range")
        return (p.ge, p.le, 1.0 if self.type is int else 0.01)

    def check(self, value: object) -> object:
        """The value, normalised (int or float); ConfigError naming the field if invalid."""
        if value is None and self.optional:
            return None
        name, p = self.name, self.param
        if p.choices:
            if value not in p.choices:
                raise ConfigError(name, f"must be one of {', '.join(p.choices)} (got {value!r})")
            return value
        if self.type is int:
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ConfigError(name, f"must be an integer (got {value!r})")
            v: float = int(value)
        else:
            v = number(value, name)
        if p.gt is not None and not v > p.gt:
            raise ConfigError(name, f"must be > {_num(p.gt)}, got {v}")
        if p.ge is not None and p.le is not None and not p.ge <= v <= p.le:
            raise ConfigError(name, f"must be in [{_num(p.ge)}, {_num(p.le)}] (got {v})")
        if p.ge is not None and not v >= p.ge:
            raise ConfigError(name, f"must be >= {_num(p.ge)} (got {v})")
        return v


def _num(x: float) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}"


def _fields(cls: type[msgspec.Struct]) -> tuple[SpecField, ...]:
    """The fields of a spec struct with their `Param`, in declaration order."""
    hints = get_type_hints(cls, include_extras=True)
    out = []
    for name, default in zip(cls.__struct_fields__, cls.__struct_defaults__, strict=True):
        base, param = get_args(hints[name])
        members = get_args(base) or (base,)  # float | None -> (float, NoneType)
        kinds = [t for t in members if t is not type(None)]
        out.append(SpecField(name, kinds[0], len(kinds) < len(members), default, param))
    return tuple(out)


def _validate(spec: msgspec.Struct, fields: tuple[SpecField, ...]) -> None:
    for f in fields:
        msgspec.structs.force_setattr(spec, f.name, f.check(getattr(spec, f.name)))


def _ordered(spec: msgspec.Struct, lo: str, hi: str) -> None:
    a, b = getattr(spec, lo), getattr(spec, hi)
    if a is not None and b is not None and a >= b:
        raise ConfigError(lo, f"must be < {hi} (got {a} >= {b})")



class IdentifySpec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What to measure and within which limits (see the module docstring); validated on
    construction and on decode: `ConfigError` (a ValueError) whose message starts with the
    field name."""

    mode: Annotated[str, Param(
        "open: u = offset + x, no controller; closed: the speed loop is active and x is added "
        "to its command", choices=MODES, flag="--mode", label="Mode")] = "open"
    signal: Annotated[str, Param(
        "multisine: odd random-phase multisine, one period per position (about 45 s for the "
        "default band); sine: stepped sine, one frequency at a time (about 11 min)",
        choices=SIGNALS, flag="--signal", label="Signal")] = "multisine"
    f_min_hz: Annotated[float, Param(
        "lowest frequency", unit="Hz", gt=0.0, flag="--f-min", label="f min",
        widget=(0.01, 200.0, 0.01))] = 0.1
    f_max_hz: Annotated[float, Param(
        "highest frequency (below the loop's Nyquist frequency)", unit="Hz", gt=0.0,
        flag="--f-max", label="f max", widget=(0.02, 400.0, 0.01))] = 20.0
    points_per_decade: Annotated[int, Param(
        "frequencies per decade", ge=1, le=200, label="Points per decade")] = 10
    positions: Annotated[int, Param(
        "measurement positions, evenly spread: first_position_deg + span_deg k / positions",
        ge=1, le=36, flag="--positions", label="Positions")] = 3
    span_deg: Annotated[float, Param(
        "spread of the positions (360: a full turn, 3 positions are 0, 120, 240 deg)",
        unit="deg", gt=0.0)] = 360.0
    first_position_deg: Annotated[float, Param("the first position", unit="deg")] = 0.0
    amplitude_deg_s: Annotated[float, Param(
        "largest excitation amplitude (load speed); lowered where the window needs it",
        unit="deg/s", gt=0.0, flag="--amplitude", label="Amplitude",
        widget=(0.1, 100.0, 0.1))] = 10.0
    window_deg: Annotated[float, Param(
        "half-width of the position window about each position (hard limit)", unit="deg",
        gt=0.0)] = 60.0
    max_duration_s: Annotated[float, Param(
        "largest duration of the whole run (hard limit)", unit="s", gt=0.0)] = 3600.0
    offset_ratio: Annotated[float, Param(
        "speed offset = this x the excitation amplitude (> 1: the load never reverses)",
        ge=1.2)] = 2.0
    min_offset_deg_s: Annotated[float, Param(
        "smallest useful offset (well above the Stribeck speed); below it the window is too "
        "small for the lowest frequency", unit="deg/s", gt=0.0)] = 0.5
    travel_fraction: Annotated[float, Param(
        "share of the window the plan may use (the rest absorbs belt stretch and lag)",
        ge=0.1, le=1.0)] = 0.8
    min_periods: Annotated[int, Param(
        "stepped sine: measured periods per frequency (>= 2 for a variance)",
        ge=2, le=1000)] = 2
    min_measure_s: Annotated[float, Param(
        "stepped sine: at least this long a measurement window per frequency", unit="s",
        ge=0.0)] = 2.0
    multisine_periods: Annotated[int, Param(
        "multisine: measured periods after a lead-in of 1 s (2 s closed); the spread of each "
        "line comes from the non-excited lines next to it, so one is enough",
        ge=1, le=1000)] = 1
    fit_f_lo_hz: Annotated[float | None, Param(
        "fit band, low end (none: the lowest measured frequency)", unit="Hz",
        gt=0.0)] = None
    fit_f_hi_hz: Annotated[float | None, Param(
        "fit band, high end (none: the highest measured). 10 Hz: about 1.5x the natural "
        "frequency of the article's Mn Pn; above it unmodelled dynamics pull a second order "
        "off", unit="Hz", gt=0.0)] = 10.0
    fit_error_floor: Annotated[float, Param(
        "relative model error added to each point's variance in the fit weights",
        gt=0.0)] = 0.01
    periodic_pitch_deg: Annotated[float | None, Param(
        "position period of the strongest position-periodic disturbance (one tooth of the "
        "article's 30-tooth pulley); each segment's measured travel is a whole number of "
        "pitches so it does not leak into the estimate (none: off)", unit="deg",
        gt=0.0)] = 12.0
    agreement_tol_db: Annotated[float, Param(
        "positions agree within this magnitude difference", unit="dB", gt=0.0)] = 1.0
    agreement_tol_deg: Annotated[float, Param(
        "positions agree within this phase difference", unit="deg", gt=0.0)] = 10.0
    move_speed_deg_s: Annotated[float, Param(
        "peak speed of the position-loop moves between positions and to a segment's start",
        unit="deg/s", gt=0.0)] = 30.0
    settle_s: Annotated[float, Param(
        "hold after each move before exciting", unit="s", ge=0.0)] = 0.5
    resolution_hz: Annotated[float | None, Param(
        "multisine: frequency resolution, the inverse of the period (none: f min); a zoomed "
        "pass about a measured mode takes a finer one than its band's low end", unit="Hz",
        gt=0.0)] = None

    def __post_init__(self) -> None:
        _validate(self, IDENTIFY_FIELDS)
        _ordered(self, "f_min_hz", "f_max_hz")
        _ordered(self, "fit_f_lo_hz", "fit_f_hi_hz")
        r = self.resolution_hz
        if r is not None and r > self.f_min_hz:
            raise ConfigError("resolution_hz", f"must be <= f_min_hz (got {r} > {self.f_min_hz})")

    @property
    def centers_deg(self) -> tuple[float, ...]:
        """The measurement positions."""
        n = self.positions
        return tuple(self.first_position_deg + self.span_deg * k / n for k in range(n))

    @property
    def closed(self) -> bool:
        return self.mode == "closed"

    def with_(self, **changes: Any) -> IdentifySpec:
        """A copy with some fields changed, validated again."""
        return msgspec.structs.replace(self, **changes)


class OfflineOptions(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What only an offline run (`controller.ident.engine.run_identification`) uses."""

    seed: Annotated[int, Param(
        "seed of the default simulated rig", ge=0, le=2**63 - 1)] = 0
    stop_s: Annotated[float, Param(
        "on abort: command 0 for this long, then the position loop holds", unit="s",
        ge=0.0)] = 0.1
    hold_s: Annotated[float, Param(
        "on abort: position-loop hold recorded after the stop (the run ends there)", unit="s",
        ge=0.0)] = 1.0

    def __post_init__(self) -> None:
        _validate(self, OFFLINE_FIELDS)


#: The fields of IdentifySpec and OfflineOptions with their metadata, in order.
IDENTIFY_FIELDS: tuple[SpecField, ...] = _fields(IdentifySpec)
OFFLINE_FIELDS: tuple[SpecField, ...] = _fields(OfflineOptions)
