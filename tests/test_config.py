"""LoopConfig: defaults are the article's, every bad value is rejected naming the field."""

from __future__ import annotations

import msgspec
import pytest

from controller.core.config import (
    LoopConfig,
    NominalModel,
    config_from_builtins,
    config_to_builtins,
)
from controller.core.errors import ConfigError


def test_defaults_are_the_article_rig_and_starting_controller() -> None:
    c = LoopConfig()
    # Cv: docs/starting_loop.md's procedure (tests/test_starting_loop.py checks the numbers).
    assert (c.rate_hz, c.cv_kp, c.cv_ki_per_s, c.pos_kp_per_s, c.pos_ki_per_s) == (
        1000.0,
        1.35,
        10.8,
        9.0,
        3.5,
    )
    assert (c.q_type, c.q_cutoff_hz, c.dob_on, c.ff_on) == ("q31", 0.5, True, False)
    # M(s)P(s) = 1/(5.169e-4 s^2 + 0.03215 s + 1): unit DC gain
    assert c.nominal.dc_gain == 1.0


def test_round_trip_through_builtins_and_msgpack() -> None:
    c = LoopConfig(q_type="q20", q_cutoff_hz=1.5, ff_on=True)
    assert config_from_builtins(config_to_builtins(c)) == c
    assert msgspec.msgpack.decode(msgspec.msgpack.encode(c), type=LoopConfig) == c


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"cv_kp": "0.5"}, "cv_kp"),
        ({"cv_kp": -1}, "cv_kp"),
        ({"cv_ki_per_s": 1e9}, "cv_ki_per_s"),
        ({"pos_kp_per_s": 0}, "pos_kp_per_s"),
        ({"dob_on": 1}, "dob_on"),
        ({"ff_gain": 3.0}, "ff_gain"),
        ({"q_type": "Q31"}, "q_type"),
        ({"q_cutoff_hz": 500.0}, "q_cutoff_hz"),
        ({"rate_hz": 1e6}, "rate_hz"),
        ({"command_limit_deg_s": 0}, "command_limit_deg_s"),
        ({"nominal": {"mn_den": [1.0, 2.0]}}, "nominal.mn_den"),
        ({"nominal": {"pn_den": [1.0, -2.0, 1.0]}}, "nominal.pn_den"),
        ({"nominal": {"pn_num": [0.0, 0.0, 0.0]}}, "nominal.pn_num[2]"),
        ({"nominal": {"pn_num": [0.0, 0.0, 1.0]}}, "nominal.pn_num"),  # rel. degree 4 > 2
        ({"unknown_gain": 1.0}, "unknown_gain"),
    ],
)
def test_bad_values_name_the_field(data: dict[str, object], field: str) -> None:
    with pytest.raises(ConfigError) as info:
        config_from_builtins(data)
    assert info.value.field == field, str(info.value)


def test_nominal_model_validation_direct() -> None:
    with pytest.raises(ConfigError, match=r"nominal.mn_den\[1\]"):
        NominalModel(mn_den=(1.0, 0.0, 1.0))
    with pytest.raises(ConfigError, match=r"nominal\.pn_den"):
        NominalModel(pn_den=(1.0, float("nan"), 1.0))


def test_with_revalidates() -> None:
    with pytest.raises(ConfigError, match="q_cutoff_hz"):
        LoopConfig().with_(q_cutoff_hz=-3.0)
