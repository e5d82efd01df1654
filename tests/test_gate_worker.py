"""The gate as the controller runs it: verdicts, the rig's limit, a worker process that hangs."""

from __future__ import annotations

import concurrent.futures
import math
import time

import pytest

from controller.core.config import LoopConfig
from controller.process.gate_worker import GateRunner, gate, gate_and_build


def test_gate_accepts_the_default_and_rejects_an_unstable_candidate() -> None:
    ok = gate(LoopConfig())
    assert ok.accepted and ok.reasons == () and ok.margins.phase_margin_deg > 30.0
    bad = gate(LoopConfig(cv_kp=20.0))
    assert not bad.accepted and bad.reasons and bad.coefficients is None
    built = gate_and_build(LoopConfig(q_cutoff_hz=1.0), 7)
    assert built.coefficients is not None and built.coefficients.version == 7


def test_the_rigs_command_limit_is_checked_first() -> None:
    runner = GateRunner(subprocess=False, command_limit_max_deg_s=30.0)
    verdict = runner.check(LoopConfig(command_limit_deg_s=40.0))
    assert not verdict.accepted and "rig's limit" in verdict.reasons[0]
    assert math.isnan(verdict.margins.gain_margin_db)


def test_a_hanging_worker_is_killed_and_the_next_call_gets_a_fresh_one() -> None:
    runner = GateRunner(subprocess=True)
    try:
        with pytest.raises(concurrent.futures.TimeoutError):
            runner.call(time.sleep, 30.0, timeout_s=0.5)
        verdict = runner.check_and_build(LoopConfig(), 3)
        assert verdict.accepted and verdict.coefficients is not None
    finally:
        runner.close()
