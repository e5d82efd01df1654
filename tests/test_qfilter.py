"""Q-filter design: eq. (35) coefficients, the -3 dB mapping, and input validation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import optimize, signal

from controller.core.config import LoopConfig
from controller.core.discrete import sos_response
from controller.core.dob import design_dob
from controller.core.errors import ConfigError
from controller.core.qfilter import (
    CUTOFF_TAU_PRODUCT,
    HALF_POWER_OMEGA_TAU,
    design_q,
    tau_from_cutoff,
)


def test_q31_at_article_tau_equals_eq35() -> None:
    num, den = design_q("q31", tau_s=0.5133).tf()
    # eq. (35): (1.54 s + 1) / (0.1353 s^3 + 0.7907 s^2 + 1.54 s + 1)
    np.testing.assert_allclose(num, [1.54, 1.0], rtol=1e-3)
    np.testing.assert_allclose(den, [0.1353, 0.7907, 1.54, 1.0], rtol=1e-3)


def test_half_power_constants_match_control_md() -> None:
    # control.md gives omega*tau = 1.642474; the root of |Q31(jx)|^2 = 1/2 is 1.6424677
    # (checked independently with brentq below); the constant k = 0.26141 agrees to 5 digits.
    root = optimize.brentq(lambda x: abs((3j * x + 1) / (1j * x + 1) ** 3) ** 2 - 0.5, 1, 3)
    assert HALF_POWER_OMEGA_TAU["q31"] == pytest.approx(root, abs=1e-9)
    assert HALF_POWER_OMEGA_TAU["q31"] == pytest.approx(1.642474, abs=1e-5)
    assert HALF_POWER_OMEGA_TAU["q20"] == pytest.approx(0.643594, abs=1e-6)
    assert CUTOFF_TAU_PRODUCT["q31"] == pytest.approx(0.26141, abs=1e-5)
    assert CUTOFF_TAU_PRODUCT["q20"] == pytest.approx(0.10243, abs=1e-5)


def _minus3db_hz(num: list[float], den: list[float], guess_hz: float) -> float:
    def f(log_f: float) -> float:
        _, h = signal.freqs(num, den, worN=[2 * math.pi * math.exp(log_f)])
        return float(20 * np.log10(abs(h[0])) + 10 * math.log10(2))

    # Q31 peaks (+2.27 dB) below the cut-off: bracket above the peak.
    lo, hi = math.log(guess_hz / 3), math.log(guess_hz * 3)
    return math.exp(optimize.brentq(f, lo, hi))


@pytest.mark.parametrize("q_type", ["q20", "q31"])
@pytest.mark.parametrize("cutoff_hz", [0.05, 0.5, 2.0, 15.0])
def test_minus_3db_frequency_equals_requested_cutoff(q_type: str, cutoff_hz: float) -> None:
    q = design_q(q_type, cutoff_hz=cutoff_hz)  # type: ignore[arg-type]
    num, den = q.tf()
    assert _minus3db_hz(num, den, cutoff_hz) == pytest.approx(cutoff_hz, rel=0.01)
    # The implemented (Tustin, prewarped at the cut-off) F2 = Q is -3 dB there too.
    dob = design_dob(LoopConfig(q_type=q_type, q_cutoff_hz=cutoff_hz))
    h = sos_response(dob.f2_sos, np.array([cutoff_hz]), 1000.0)[0]
    assert 20 * math.log10(abs(h)) == pytest.approx(-10 * math.log10(2), abs=0.01)


def test_q31_peak_and_tau_mapping() -> None:
    q = design_q("q31", cutoff_hz=0.5)
    assert q.tau_s == pytest.approx(0.26141 / 0.5, rel=1e-4)
    num, den = q.tf()
    w = 1 / (math.sqrt(3) * q.tau_s)
    _, h = signal.freqs(num, den, worN=[w])
    assert 20 * math.log10(abs(h[0])) == pytest.approx(2.27, abs=0.01)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"q_cutoff_hz": -1.0}, "q_cutoff_hz"),
        ({"q_cutoff_hz": 0.0}, "q_cutoff_hz"),
        ({"q_cutoff_hz": float("nan")}, "q_cutoff_hz"),
        ({"q_cutoff_hz": float("inf")}, "q_cutoff_hz"),
        ({"q_cutoff_hz": 500.0}, "q_cutoff_hz"),
        ({"q_cutoff_hz": 800.0}, "q_cutoff_hz"),
        ({"q_type": "q42"}, "q_type"),
        ({"cv_kp": -0.5}, "cv_kp"),
        ({"cv_kp": "0.5"}, "cv_kp"),
        ({"rate_hz": 0.0}, "rate_hz"),
        ({"command_limit_deg_s": float("nan")}, "command_limit_deg_s"),
    ],
)
def test_bad_inputs_name_the_parameter(kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(ConfigError) as info:
        LoopConfig(**kwargs)  # type: ignore[arg-type]
    assert info.value.field == field
    assert field in str(info.value)


@pytest.mark.parametrize("bad", [-1.0, 0.0, float("nan"), float("-inf")])
def test_tau_from_cutoff_rejects(bad: float) -> None:
    with pytest.raises(ConfigError, match="cutoff_hz"):
        tau_from_cutoff("q31", bad)
    with pytest.raises(ConfigError, match="q_type"):
        design_q("q99", cutoff_hz=1.0)  # type: ignore[arg-type]
