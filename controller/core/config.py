"""Loop configuration: the one immutable description of what the controller runs.

Units: positions in load-side degrees, speeds in load-side deg/s, the speed command u is a
load-side speed (the drive adapter converts to motor units). Gains follow control.md:
Cv(s) = cv_kp (1 + cv_ki_per_s / s), Cp(s) = pos_kp_per_s (1 + pos_ki_per_s / s),
r = Cp e_pos + ff_gain * d(theta_ref)/dt (feedforward only when ff_on).
"""

from __future__ import annotations

import math
from typing import Any

import msgspec

from controller.core.command_filter import CommandFilter
from controller.core.errors import ConfigError
from controller.core.qfilter import Q_TYPES
from controller.core.validate import in_range, number, split_msgspec_error

Poly2 = tuple[float, float, float]

#: Article eqs. (33)-(34): M = 1/mn_den, P = pn_num/pn_den, coefficients of s^2, s, 1.
ARTICLE_MN_DEN: Poly2 = (1.013e-05, 0.004501, 1.0)
ARTICLE_PN_NUM: Poly2 = (1.013e-05, 0.004501, 1.0)
ARTICLE_PN_DEN: Poly2 = (0.0005169, 0.03215, 1.0)


def _poly_degree(p: Poly2) -> int:
    return 2 if p[0] != 0.0 else (1 if p[1] != 0.0 else 0)


#: Bounds on the nominal model's polynomials: each coefficient, the constant term, and the
#: magnitude of the roots (rad/s).
POLY_COEFF_MAX = 1e9
POLY_CONST_MIN = 1e-9
ROOT_RAD_S_RANGE = (1e-6, 1e7)


def _check_poly(p: Any, field: str) -> None:
    if not isinstance(p, tuple) or len(p) != 3:
        raise ConfigError(field, "expected 3 coefficients (s^2, s, 1)")
    a2, a1, a0 = (number(c, f"{field}[{i}]") for i, c in enumerate(p))
    if a0 <= 0.0:
        raise ConfigError(f"{field}[2]", f"constant term must be > 0, got {a0}")
    if a2 < 0.0 or a1 < 0.0:
        raise ConfigError(field, f"coefficients must be >= 0 (stable, minimum phase), got {p}")
    if a2 > 0.0 and a1 == 0.0:
        raise ConfigError(f"{field}[1]", "an undamped second-order factor is not allowed")
    for i, c in enumerate((a2, a1, a0)):
        if c > POLY_COEFF_MAX:
            raise ConfigError(f"{field}[{i}]", f"{c:g} is above the limit {POLY_COEFF_MAX:g}")
    if a0 < POLY_CONST_MIN:
        raise ConfigError(f"{field}[2]", f"{a0:g} is below the limit {POLY_CONST_MIN:g}")
    # The roots (poles or zeros) must lie where the gate's frequency grid and the filter
    # design can represent them; a model of 1e300 or 1e-300 would only give non-finite numbers.
    roots: tuple[float, ...]
    if a2 > 0.0:
        disc = a1 * a1 - 4.0 * a2 * a0
        if disc < 0.0:
            roots = (math.sqrt(a0 / a2),)
        else:
            q = 0.5 * (a1 + math.sqrt(disc))
            roots = (q / a2, a0 / q)
    else:
        roots = (a0 / a1,) if a1 > 0.0 else ()
    lo, hi = ROOT_RAD_S_RANGE
    for w in roots:
        if not lo <= w <= hi:
            raise ConfigError(
                field, f"a root at {w:.3g} rad/s is outside [{lo:g}, {hi:g}] rad/s (units?)"
            )


class NominalModel(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Nominal Mn(s) = 1/mn_den(s) and Pn(s) = pn_num(s)/pn_den(s) (control.md eqs. 12-13)."""

    mn_den: Poly2 = ARTICLE_MN_DEN
    pn_num: Poly2 = ARTICLE_PN_NUM
    pn_den: Poly2 = ARTICLE_PN_DEN

    def __post_init__(self) -> None:
        for name in ("mn_den", "pn_num", "pn_den"):
            _check_poly(getattr(self, name), f"nominal.{name}")
        excess = _poly_degree(self.mn_den) + _poly_degree(self.pn_den) - _poly_degree(self.pn_num)
        if excess > 2:
            raise ConfigError(
                "nominal.pn_num",
                f"Mn*Pn has relative degree {excess} > 2: Q (Mn Pn)^-1 would be improper",
            )

    @property
    def dc_gain(self) -> float:
        return self.pn_num[2] / (self.mn_den[2] * self.pn_den[2])


class LoopConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Everything the three-loop servo needs; validated on construction and on decode."""

    rate_hz: float = 1000.0
    nominal: NominalModel = msgspec.field(default_factory=NominalModel)
    # The starting speed PI (controller.tune.starting_loop, docs/starting_loop.md): crossover
    # placed for a phase margin on Mn Pn with one tick of delay (60 deg, raised until the
    # article's uncertainty case leaves ||W T|| <= 0.7: 75 deg), integral corner at a quarter
    # of it. The article gives no Cv; the older guess 0.5 (1 + 55/s) is
    # examples/loop_cv_0.5_55.json.
    cv_kp: float = 1.35
    cv_ki_per_s: float = 10.8
    pos_kp_per_s: float = 9.0
    pos_ki_per_s: float = 3.5
    ff_on: bool = False
    ff_gain: float = 1.0
    dob_on: bool = True
    q_type: str = "q31"
    q_cutoff_hz: float = 0.5
    command_limit_deg_s: float = 100.0
    # The optional notch or low-pass on Cv's output (controller.core.command_filter); off by
    # default, and off it is no element of the tick.
    command_filter: CommandFilter = msgspec.field(default_factory=CommandFilter)

    def __post_init__(self) -> None:
        rate = in_range(self.rate_hz, "rate_hz", 50.0, 20000.0)
        in_range(self.cv_kp, "cv_kp", 0.0, 1e3, lo_open=True)
        in_range(self.cv_ki_per_s, "cv_ki_per_s", 0.0, rate / 2)
        in_range(self.pos_kp_per_s, "pos_kp_per_s", 0.0, rate / 2, lo_open=True)
        in_range(self.pos_ki_per_s, "pos_ki_per_s", 0.0, rate / 2)
        for name in ("ff_on", "dob_on"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(name, f"expected true/false, got {getattr(self, name)!r}")
        in_range(self.ff_gain, "ff_gain", 0.0, 2.0)
        if self.q_type not in Q_TYPES:
            raise ConfigError(
                "q_type", f"unknown Q type {self.q_type!r}; expected one of {', '.join(Q_TYPES)}"
            )
        cut = number(self.q_cutoff_hz, "q_cutoff_hz")
        if cut <= 0.0:
            raise ConfigError("q_cutoff_hz", f"must be > 0, got {cut}")
        if cut >= rate / 2:
            raise ConfigError(
                "q_cutoff_hz", f"{cut} Hz is at or above the Nyquist limit {rate / 2} Hz"
            )
        in_range(self.command_limit_deg_s, "command_limit_deg_s", 0.0, 1e4, lo_open=True)
        if not isinstance(self.nominal, NominalModel):
            raise ConfigError("nominal", "expected a NominalModel")
        if not isinstance(self.command_filter, CommandFilter):
            raise ConfigError("command_filter", "expected a CommandFilter")
        self.command_filter.check_rate(rate)

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    def with_(self, **changes: Any) -> LoopConfig:
        """A copy with some fields changed, validated again."""
        return msgspec.structs.replace(self, **changes)


def config_to_builtins(cfg: LoopConfig) -> dict[str, Any]:
    out: dict[str, Any] = msgspec.to_builtins(cfg)
    return out


def config_from_builtins(data: Any) -> LoopConfig:
    """Decode and validate; raises ConfigError naming the field."""
    try:
        return msgspec.convert(data, LoopConfig, strict=True)
    except msgspec.ValidationError as exc:
        raise ConfigError(*split_msgspec_error(str(exc))) from exc
