"""The one identification spec (`controller.ident.spec`): validation naming the field, the
wire message it is (`identify_start`), and the metadata the CLI and the dashboard use."""

from __future__ import annotations

import math
import re
from pathlib import Path

import msgspec
import pytest

from controller import protocol as proto
from controller.core.errors import ConfigError
from controller.ident.spec import IDENTIFY_FIELDS, OFFLINE_FIELDS, IdentifySpec, OfflineOptions

ROOT = Path(__file__).resolve().parents[1]

#: The wire's identify_start spec as docs/protocol.md lists it: names, order and defaults.
WIRE_DEFAULTS = {
    "mode": "open",
    "signal": "multisine",
    "f_min_hz": 0.1,
    "f_max_hz": 20.0,
    "points_per_decade": 10,
    "positions": 3,
    "span_deg": 360.0,
    "first_position_deg": 0.0,
    "amplitude_deg_s": 10.0,
    "window_deg": 60.0,
    "max_duration_s": 3600.0,
    "offset_ratio": 2.0,
    "min_offset_deg_s": 0.5,
    "travel_fraction": 0.8,
    "min_periods": 2,
    "min_measure_s": 2.0,
    "multisine_periods": 1,
    "fit_f_lo_hz": None,
    "fit_f_hi_hz": 10.0,
    "fit_error_floor": 0.01,
    "periodic_pitch_deg": 12.0,
    "agreement_tol_db": 1.0,
    "agreement_tol_deg": 10.0,
    "move_speed_deg_s": 30.0,
    "settle_s": 0.5,
    "resolution_hz": None,
}


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("mode", "sideways"),
        ("signal", "chirp"),
        ("f_min_hz", -1.0),
        ("f_max_hz", math.nan),
        ("positions", 0),
        ("positions", 2.5),
        ("amplitude_deg_s", 0.0),
        ("window_deg", "wide"),
        ("offset_ratio", 1.0),
        ("max_duration_s", -5.0),
        ("resolution_hz", 0.0),
    ],
)
def test_spec_validation_names_the_field(field: str, value: object) -> None:
    with pytest.raises(ConfigError, match=rf"^{field}:"):
        IdentifySpec(**{field: value})  # type: ignore[arg-type]


def test_spec_positions_are_evenly_spread() -> None:
    assert IdentifySpec().centers_deg == (0.0, 120.0, 240.0)
    assert IdentifySpec(positions=4, span_deg=90.0, first_position_deg=10.0).centers_deg == (
        10.0,
        32.5,
        55.0,
        77.5,
    )
    with pytest.raises(ConfigError, match=r"^f_min_hz"):
        IdentifySpec(f_min_hz=5.0, f_max_hz=1.0)




@pytest.mark.parametrize(
    ("field", "value"),
    [("seed", -1), ("seed", 1.5), ("stop_s", -0.1), ("hold_s", math.inf), ("hold_s", "long")],
)
def test_offline_options_validation_names_the_field(field: str, value: object) -> None:
    with pytest.raises(ConfigError, match=rf"^{field}:"):
        OfflineOptions(**{field: value})  # type: ignore[arg-type]


def test_values_are_normalised_and_copies_validated_again() -> None:
    spec = IdentifySpec(f_min_hz=1, positions=2)
    assert type(spec.f_min_hz) is float and type(spec.positions) is int
    assert spec.with_(positions=4).positions == 4
    with pytest.raises(ConfigError, match=r"^positions:"):
        spec.with_(positions=0)
    with pytest.raises(ConfigError, match=r"^fit_f_lo_hz:"):
        IdentifySpec(fit_f_lo_hz=20.0)  # above fit_f_hi_hz


def test_the_spec_is_the_wire_message_documented() -> None:
    """Same field names, order, types and defaults as the protocol has always carried (and as
    docs/protocol.md lists); the offline-only options are not on the wire."""
    assert msgspec.to_builtins(IdentifySpec()) == WIRE_DEFAULTS
    assert list(msgspec.to_builtins(IdentifySpec())) == list(WIRE_DEFAULTS)
    assert not {f.name for f in OFFLINE_FIELDS} & set(WIRE_DEFAULTS)
    doc = (ROOT / "docs" / "protocol.md").read_text()
    section = doc[doc.index("`IdentifySpec` (no `v`") :].split("\n\n", 1)[0]
    names = [n for n in re.findall(r"`([a-z_]+)`", section) if n != "v"]
    assert names[: len(WIRE_DEFAULTS)] == list(WIRE_DEFAULTS)
    cmd = proto.Command(body=proto.IdentifyStart(spec=IdentifySpec(positions=1)), client="t")
    assert proto.decode(proto.encode(cmd), proto.Command) == cmd


@pytest.mark.parametrize(
    ("spec", "field"),
    [
        ({"bogus": 1}, "body.spec.bogus"),
        ({"seed": 3}, "body.spec.seed"),  # offline only: not a wire field
        ({"f_min_hz": "low"}, "body.spec.f_min_hz"),
        ({"f_min_hz": -1.0}, "body.spec.f_min_hz"),
        ({"positions": 2.5}, "body.spec.positions"),
        ({"mode": "sideways"}, "body.spec.mode"),
        ({"f_min_hz": 5.0, "f_max_hz": 2.0}, "body.spec.f_min_hz"),
    ],
)
def test_identify_start_rejects_bad_and_unknown_fields_naming_them(
    spec: dict[str, object], field: str
) -> None:
    payload = msgspec.msgpack.encode(
        {"v": proto.PROTOCOL_VERSION, "body": {"type": "identify_start", "spec": spec}})
    with pytest.raises(proto.ProtocolError) as info:
        proto.decode(payload, proto.Command)
    assert info.value.field == field and str(info.value).startswith(f"{field}: ")


def test_every_field_has_help_and_consistent_metadata() -> None:
    for f in (*IDENTIFY_FIELDS, *OFFLINE_FIELDS):
        p = f.param
        assert p.help, f.name
        assert f.check(f.default) == f.default, f.name  # the default is valid
        assert not p.choices or f.default in p.choices, f.name
        if p.label:
            assert p.choices or f.limits[0] <= f.default <= f.limits[1], f.name
    flags = {f.name: f.param.flag for f in IDENTIFY_FIELDS if f.param.flag}
    assert flags == {
        "mode": "--mode",
        "signal": "--signal",
        "f_min_hz": "--f-min",
        "f_max_hz": "--f-max",
        "positions": "--positions",
        "amplitude_deg_s": "--amplitude",
    }
