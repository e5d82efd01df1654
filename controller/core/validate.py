"""Field validation shared by every config and message: clear errors naming the field."""

from __future__ import annotations

import math
import re

import numpy as np

from controller.core.errors import ConfigError

_NUMBER_TYPES = (int, float, np.integer, np.floating)


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
