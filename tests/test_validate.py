"""controller.core.validate: the checks declared in a field's annotation (`check_fields`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import msgspec
import numpy as np
import pytest

from controller.core.errors import ConfigError
from controller.core.validate import (
    check_fields,
    nonnegative,
    one_of,
    optional,
    positive,
    within,
)


@dataclass(frozen=True)
class _Plain:
    gain: Annotated[float, positive] = 1.0
    offset: float = 0.0
    damping: Annotated[float, within(0.0, 1.0, lo_open=True)] = 0.5
    kind: Annotated[str, one_of(("a", "b"), "kind of thing")] = "a"

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class _Stored:
    gain: Annotated[float, positive] = 1.0
    window: Annotated[float | None, optional(nonnegative)] = None

    def __post_init__(self) -> None:
        check_fields(self, store=True)


class _Struct(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    gain: Annotated[float, positive] = 1.0
    damping: Annotated[float, within(0.0, 1.0, lo_open=True)] = 0.5

    def __post_init__(self) -> None:
        check_fields(self)


def _error(make: object) -> str:
    with pytest.raises(ConfigError) as info:
        make()  # type: ignore[operator]
    return str(info.value)


def test_each_declared_check_names_its_field() -> None:
    assert _error(lambda: _Plain(gain=0.0)) == "gain: must be > 0, got 0.0"
    assert _error(lambda: _Plain(damping=0.0)) == "damping: 0.0 is out of range (0.0, 1.0]"
    assert _error(lambda: _Plain(damping=1.5)) == "damping: 1.5 is out of range (0.0, 1.0]"
    assert _error(lambda: _Plain(kind="c")) == (
        "kind: unknown kind of thing 'c'; expected one of a, b")
    assert _error(lambda: _Plain(gain=float("nan"))) == "gain: must be finite, got nan"
    assert _error(lambda: _Plain(gain="1")) == "gain: expected a number, got str '1'"  # type: ignore[arg-type]


def test_the_checks_run_in_field_order_and_skip_undeclared_fields() -> None:
    assert _error(lambda: _Plain(kind="c", gain=-1.0)).startswith("gain:")
    assert _Plain(offset=-1e300).offset == -1e300  # no check declared: taken as given
    assert _Plain(damping=1.0).damping == 1.0


def test_values_are_kept_as_given_unless_stored() -> None:
    plain = _Plain(gain=2)
    assert plain.gain == 2 and type(plain.gain) is int
    stored = _Stored(gain=np.float32(2.5), window=3)
    assert type(stored.gain) is float and stored.gain == 2.5
    assert type(stored.window) is float and stored.window == 3.0


def test_optional_lets_none_through_and_checks_the_rest() -> None:
    assert _Stored(window=None).window is None
    assert _error(lambda: _Stored(window=-1.0)) == "window: must be >= 0, got -1.0"


def test_a_struct_runs_its_checks_on_construction_and_on_decode() -> None:
    assert _error(lambda: _Struct(gain=-1.0)) == "gain: must be > 0, got -1.0"
    with pytest.raises(msgspec.ValidationError, match=r"damping: 2.0 is out of range"):
        msgspec.json.decode(b'{"damping": 2.0}', type=_Struct)
    assert msgspec.json.decode(b'{"gain": 3.0}', type=_Struct) == _Struct(gain=3.0)
