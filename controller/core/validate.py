"""Field validation shared by every config and message: clear errors naming the field.

A field's own check can be declared with the field, in its annotation, and run by
`check_fields` from the class's ``__post_init__`` (a frozen dataclass or a msgspec Struct)::

    gain: Annotated[float, positive] = 1.0
    damping: Annotated[float, within(0.0, 1.0, lo_open=True)] = 0.05

A check is any ``check(value, field)`` that raises `ConfigError` naming the field and returns
the value (`number`, `positive`, `nonnegative`, `within(...)`, `one_of(...)`, `optional(...)`);
checks that involve several fields stay in ``__post_init__``, after `check_fields`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from typing import Annotated, get_origin, get_type_hints

import numpy as np

from controller.core.errors import ConfigError

_NUMBER_TYPES = (int, float, np.integer, np.floating)

#: A field's declared check: raises ConfigError naming `field`, else returns the value.
Check = Callable[[object, str], object]


def number(value: object, field: str) -> float:
    """A finite real number (bool is not a number here)."""
    if isinstance(value, bool) or not isinstance(value, _NUMBER_TYPES):
        raise ConfigError(field, f"expected a number, got {type(value).__name__} {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(field, f"must be finite, got {v}")
    return v


def positive(value: object, field: str) -> float:
    v = number(value, field)
    if v <= 0.0:
        raise ConfigError(field, f"must be > 0, got {v}")
    return v


def nonnegative(value: object, field: str) -> float:
    v = number(value, field)
    if v < 0.0:
        raise ConfigError(field, f"must be >= 0, got {v}")
    return v


def in_range(value: object, field: str, lo: float, hi: float, *, lo_open: bool = False) -> float:
    """lo <= value <= hi (lo < value with lo_open)."""
    v = number(value, field)
    if (v <= lo if lo_open else v < lo) or v > hi:
        bracket = "(" if lo_open else "["
        raise ConfigError(field, f"{v} is out of range {bracket}{lo}, {hi}]")
    return v


def within(lo: float, hi: float, *, lo_open: bool = False) -> Callable[[object, str], float]:
    """`in_range` as a field's declared check."""

    def check(value: object, field: str) -> float:
        return in_range(value, field, lo, hi, lo_open=lo_open)

    return check


def one_of(choices: tuple[str, ...], what: str) -> Check:
    """A field's declared check: one of `choices` ("unknown <what> 'x'; expected one of ...")."""

    def check(value: object, field: str) -> object:
        if value not in choices:
            raise ConfigError(
                field, f"unknown {what} {value!r}; expected one of {', '.join(choices)}"
            )
        return value

    return check


def optional(check: Check) -> Check:
    """A field's declared check that lets None through and gives any other value to `check`."""

    def check_unless_none(value: object, field: str) -> object:
        return None if value is None else check(value, field)

    return check_unless_none


def check_fields(obj: object, *, store: bool = False) -> None:
    """Run the checks declared in the annotations of `obj`'s fields, in field order (see the
    module docstring), each on the value as given; the first failing one raises. With `store`,
    each field is set to what its last check returns (a float for a number, ...: a frozen
    dataclass's normal form)."""
    cls = type(obj)
    declared = _DECLARED.get(cls)
    if declared is None:
        hints = get_type_hints(cls, include_extras=True)
        declared = _DECLARED[cls] = tuple(
            (name, tuple(hint.__metadata__))
            for name, hint in hints.items()
            if get_origin(hint) is Annotated
        )
    for name, checks in declared:
        value = getattr(obj, name)
        for check in checks:
            checked = check(value, name)
        if store:
            object.__setattr__(obj, name, checked)


#: Per class: (field name, its declared checks) in field order, read once from the annotations.
_DECLARED: dict[type, tuple[tuple[str, tuple[Check, ...]], ...]] = {}


def frequency_grid(freq_hz: np.ndarray, field: str) -> None:
    """Every frequency finite, > 0 and above the one before it."""
    f = freq_hz
    if not (np.all(np.isfinite(f)) and np.all(f > 0) and np.all(np.diff(f) > 0)):
        raise ConfigError(field, "must be finite, > 0 and strictly increasing")


def finite_nonzero(values: np.ndarray, field: str) -> None:
    """Every value finite and != 0 (a response one divides by or takes the log of)."""
    if not np.all(np.isfinite(values)) or np.any(values == 0):
        raise ConfigError(field, "must be finite and non-zero")


_FIELD_RE = re.compile(r"^([A-Za-z_][\w.\[\]]*): (.*)$", re.S)
_MISSING_OR_UNKNOWN = (
    ("Object contains unknown field `", "unknown field"),
    ("Object missing required field `", "missing required field"),
)


def split_msgspec_error(text: str) -> tuple[str, str]:
    """(field path, message) from a msgspec ValidationError text.

    msgspec's own errors read "Expected `float`, got `str` - at `$.candidate.cv_kp`"; errors
    raised by our validators inside nested structs read "cv_kp: must be > 0 - at `$.candidate`"
    (or repeat the struct's own name: "nominal.pn_den: ... - at `$.candidate.nominal`").
    All become a dotted path from the message root: "candidate.cv_kp".
    """
    msg, path = text, ""
    if " - at `$" in text:
        msg, at = text.rsplit(" - at `$", 1)
        path = at.rstrip("`").lstrip(".")
    for marker, what in _MISSING_OR_UNKNOWN:
        if msg.startswith(marker):
            name = msg[len(marker) :].split("`", 1)[0]
            return (f"{path}.{name}" if path else name), what
    m = _FIELD_RE.match(msg)
    if m is not None:
        name, why = m.group(1), m.group(2)
        last = path.rsplit(".", 1)[-1]
        if last and (name == last or name.startswith((f"{last}.", f"{last}["))):
            path = path[: -len(last)].rstrip(".")
        return (f"{path}.{name}" if path else name), why
    return (path or "payload"), msg
