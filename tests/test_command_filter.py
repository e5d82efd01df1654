"""The speed-command filter (controller.core.command_filter): configuration, its Tustin
biquad against scipy, and the tick against scipy's lfilter."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal as sig

from controller.core.command_filter import (
    CommandFilter,
    biquad,
    command_filter_response,
    continuous_tf,
)
from controller.core.config import LoopConfig, config_from_builtins, config_to_builtins
from controller.core.discrete import prewarped_fs
from controller.core.errors import ConfigError
from controller.core.loop import LoopCoefficients, ServoLoop

RATE = 1000.0


def test_off_by_default_and_round_trips() -> None:
    cfg = LoopConfig()
    assert cfg.command_filter.kind == "off"
    on = cfg.with_(command_filter=CommandFilter(kind="notch", notch_hz=31.0))
    assert config_from_builtins(config_to_builtins(on)) == on
    # Older configurations without the field decode to the filter off.
    data = config_to_builtins(cfg)
    del data["command_filter"]
    assert config_from_builtins(data) == cfg


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"kind": "bandstop"}, "command_filter.kind"),
        ({"kind": "notch", "notch_hz": 0.0}, "command_filter.notch_hz"),
        ({"kind": "notch", "notch_hz": -5.0}, "command_filter.notch_hz"),
        ({"kind": "notch", "notch_hz": 450.0}, "command_filter.notch_hz"),
        ({"kind": "notch", "notch_hz": 600.0}, "command_filter.notch_hz"),
        ({"kind": "lowpass", "lowpass_hz": 499.0}, "command_filter.lowpass_hz"),
        ({"kind": "notch", "notch_depth_db": 0.0}, "command_filter.notch_depth_db"),
        ({"kind": "notch", "notch_depth_db": 200.0}, "command_filter.notch_depth_db"),
        ({"kind": "notch", "notch_width": 0.0}, "command_filter.notch_width"),
        ({"kind": "lowpass", "lowpass_damping": 0.0}, "command_filter.lowpass_damping"),
        ({"kind": "notch", "notch_hz": float("nan")}, "command_filter.notch_hz"),
    ],
)
def test_bad_values_are_rejected_naming_the_field(data: dict[str, object], field: str) -> None:
    cfg = config_to_builtins(LoopConfig())
    cfg["command_filter"] = {**cfg["command_filter"], **data}
    with pytest.raises(ConfigError) as info:
        config_from_builtins(cfg)
    assert field in str(info.value)


def test_the_frequency_is_checked_against_the_loop_rate() -> None:
    LoopConfig(command_filter=CommandFilter(kind="notch", notch_hz=300.0))
    with pytest.raises(ConfigError, match=r"command_filter\.notch_hz"):
        LoopConfig(rate_hz=500.0, command_filter=CommandFilter(kind="notch", notch_hz=300.0))


FILTERS = [
    CommandFilter(kind="notch", notch_hz=31.0, notch_depth_db=20.0, notch_width=0.3),
    CommandFilter(kind="notch", notch_hz=120.0, notch_depth_db=40.0, notch_width=0.05),
    CommandFilter(kind="lowpass", lowpass_hz=80.0, lowpass_damping=0.707),
    CommandFilter(kind="lowpass", lowpass_hz=300.0, lowpass_damping=0.4),
]


@pytest.mark.parametrize("cf", FILTERS, ids=lambda c: c.describe())
def test_biquad_is_scipys_prewarped_bilinear(cf: CommandFilter) -> None:
    num, den = continuous_tf(cf)
    bz, az = sig.bilinear(num, den, fs=prewarped_fs(RATE, cf.frequency_hz))
    bz, az = np.atleast_1d(bz) / az[0], np.atleast_1d(az) / az[0]
    b0, b1, b2, a1, a2 = biquad(cf, RATE)
    np.testing.assert_allclose([b0, b1, b2], np.pad(bz, (3 - len(bz), 0)), rtol=1e-10,
                               atol=1e-13)
    np.testing.assert_allclose([1.0, a1, a2], az, rtol=1e-10, atol=1e-13)


@pytest.mark.parametrize("cf", FILTERS, ids=lambda c: c.describe())
def test_response_is_placed_where_asked(cf: CommandFilter) -> None:
    # Prewarped: the discrete response at f0 is the continuous one at f0 exactly.
    num, den = continuous_tf(cf)
    s = 2j * math.pi * cf.frequency_hz
    want = np.polyval(num, s) / np.polyval(den, s)
    got = command_filter_response(cf, np.array([cf.frequency_hz]), RATE)[0]
    assert abs(got - want) < 1e-9 * max(1.0, abs(want))
    assert abs(command_filter_response(cf, np.array([0.0]), RATE)[0] - 1.0) < 1e-12
    if cf.kind == "notch":
        assert 20 * math.log10(abs(got)) == pytest.approx(-cf.notch_depth_db, abs=1e-6)


def test_off_response_is_one() -> None:
    h = command_filter_response(CommandFilter(), np.geomspace(0.1, 400, 50), RATE)
    assert np.array_equal(h, np.ones(50, dtype=complex))


@pytest.mark.parametrize("cf", FILTERS[::2], ids=lambda c: c.describe())
def test_tick_filters_cvs_output_as_lfilter_does(cf: CommandFilter) -> None:
    # DOB off, no saturation: u is exactly N(z) applied to Cv's output sequence.
    cfg = LoopConfig(dob_on=False, command_limit_deg_s=1e4, command_filter=cf)
    plain = ServoLoop(LoopCoefficients.build(cfg.with_(command_filter=CommandFilter())))
    filt = ServoLoop(LoopCoefficients.build(cfg))
    rng = np.random.default_rng(7)
    refs = rng.normal(0.0, 10.0, 2000)
    speeds = rng.normal(0.0, 10.0, 2000)
    v = np.array([plain.tick_speed(r, w) for r, w in zip(refs, speeds, strict=True)])
    u = np.array([filt.tick_speed(r, w) for r, w in zip(refs, speeds, strict=True)])
    b0, b1, b2, a1, a2 = biquad(cf, RATE)
    want = sig.lfilter([b0, b1, b2], [1.0, a1, a2], v)
    np.testing.assert_allclose(u, want, rtol=1e-9, atol=1e-9 * float(np.max(np.abs(v))))
    assert not np.allclose(u, v)


def test_filter_off_is_the_plain_loop_bit_for_bit() -> None:
    # Off, the filter is no element of the tick: u is Cv's Tustin PI output, computed here
    # independently with the same float operations, equal bit for bit.
    cfg = LoopConfig(dob_on=False, command_limit_deg_s=1e4)
    loop = ServoLoop(LoopCoefficients.build(cfg))
    assert loop._cfn == 0 and loop._cfs == []
    kp = cfg.cv_kp
    half = cfg.cv_kp * cfg.cv_ki_per_s * cfg.period_s * 0.5
    rng = np.random.default_rng(3)
    integ = e_prev = 0.0
    for r, w in rng.normal(0.0, 20.0, (3000, 2)).tolist():
        e = r - w
        integ = integ + half * (e + e_prev)
        e_prev = e
        assert loop.tick_speed(r, w) == kp * e + integ


def test_switching_the_filter_on_is_bumpless() -> None:
    cfg = LoopConfig(command_limit_deg_s=1e4)
    loop = ServoLoop(LoopCoefficients.build(cfg))
    us = []
    for k in range(1500):
        us.append(loop.tick(2.0 * math.sin(k / 200), 0.0, 1.9 * math.sin(k / 200), 0.0))
    loop.request(LoopCoefficients.build(
        cfg.with_(command_filter=CommandFilter(kind="notch", notch_hz=31.0)), 1))
    k = 1500
    u_next = loop.tick(2.0 * math.sin(k / 200), 0.0, 1.9 * math.sin(k / 200), 0.0)
    step = abs(us[-1] - us[-2])
    assert abs(u_next - us[-1]) < 3 * step + 1e-9


# -- the gate sees the filter: margins and poles against python-control (tests/fuzz_truth.py,
# where the filter is discretised by control.c2d, not by this module)

GATE_CASES = [
    LoopConfig(command_filter=CommandFilter(kind="notch", notch_hz=12.0, notch_depth_db=20.0,
                                            notch_width=0.5)),
    LoopConfig(command_filter=CommandFilter(kind="lowpass", lowpass_hz=25.0)),
    LoopConfig(dob_on=False, command_filter=CommandFilter(kind="lowpass", lowpass_hz=40.0,
                                                          lowpass_damping=0.5)),
]


@pytest.mark.parametrize("cfg", GATE_CASES, ids=lambda c: c.command_filter.describe())
def test_gate_margins_and_poles_include_the_filter(cfg: LoopConfig) -> None:
    from fuzz_truth import TruePlant, truth

    from controller.gate.analysis import analyse

    t = truth(TruePlant(), cfg)
    a = analyse(cfg)
    plain = analyse(cfg.with_(command_filter=CommandFilter()))
    assert t.margins_speed is not None
    assert a.margins.gain_margin_db == pytest.approx(t.margins_speed.gain_margin_db, abs=0.1)
    assert a.margins.phase_margin_deg == pytest.approx(t.margins_speed.phase_margin_deg,
                                                       abs=0.5)
    assert a.max_pole_radius == pytest.approx(t.radius_full, abs=1e-4)
    # The filter costs phase at crossover: the gate's margins are not the unfiltered ones.
    assert a.margins.phase_margin_deg < plain.margins.phase_margin_deg - 1.0
