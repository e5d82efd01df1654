"""The gate as the controller runs it: verdicts, the rig's limit, a worker process that hangs."""

from __future__ import annotations

import concurrent.futures
import gc
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import spawn
from old_loop import OLD_LOOP

from controller.core.config import LoopConfig
from controller.gate.knowledge import COMMISSIONING_BOUND, KnowledgeRecord, PlantKnowledge
from controller.process.analysis_worker import (
    AnalysisWorker,
    clear_caches,
    gate,
    gate_and_build,
    judged,
)

K = KnowledgeRecord.of(PlantKnowledge(bound=COMMISSIONING_BOUND, version=3, source="test"))


def test_gate_accepts_the_default_and_rejects_an_unstable_candidate() -> None:
    ok = gate(LoopConfig(), K)
    assert ok.applicable and ok.reasons == () and ok.margins.phase_margin_deg > 30.0
    assert ok.verdict == "accept" and ok.knowledge_version == 3
    bad = gate(LoopConfig(cv_kp=20.0), K)
    assert not bad.applicable and bad.reasons
    assert gate_and_build(LoopConfig(cv_kp=20.0), 7, K)[1] is None
    assert bad.verdict == "reject"
    built, coefficients = gate_and_build(LoopConfig(q_cutoff_hz=1.0), 7, K)
    assert built.applicable and coefficients is not None and coefficients.version == 7


def test_a_caution_may_be_applied_and_says_why() -> None:
    # Thin whole-servo margins, calm on the nonlinear rig (the earlier loop at 5 Hz chatters at
    # standstill without decaying: rejected, and the verdict says so).
    v = gate(LoopConfig(cv_kp=2.0, cv_ki_per_s=10.8, pos_kp_per_s=9.0, pos_ki_per_s=3.5,
                        q_type="q31", q_cutoff_hz=5.0), K)
    assert v.applicable and v.verdict == "caution", v.reasons
    assert any("whole servo" in r for r in v.reasons)
    chatter = gate(OLD_LOOP.with_(q_cutoff_hz=5.0), K)
    assert not chatter.applicable and chatter.verdict == "reject"
    assert any(r.startswith("nonlinear check: chatter at standstill") for r in chatter.reasons)


def test_the_rigs_command_limit_is_checked_first() -> None:
    runner = AnalysisWorker(subprocess=False, command_limit_max_deg_s=30.0)
    verdict = runner.check(LoopConfig(command_limit_deg_s=40.0), K)
    assert not verdict.applicable and "rig's limit" in verdict.reasons[0]
    assert math.isnan(verdict.margins.gain_margin_db)


@pytest.mark.slow
def test_a_hanging_worker_is_killed_and_the_next_call_gets_a_fresh_one() -> None:
    runner = AnalysisWorker(subprocess=True)
    try:
        assert runner.check(LoopConfig(), K).applicable  # (a fresh worker's first job may be slow)
        with pytest.raises(concurrent.futures.TimeoutError):
            runner.call(time.sleep, 30.0, timeout_s=0.5)
        verdict, coefficients = runner.check_and_build(LoopConfig(), 3, K)
        assert verdict.applicable and coefficients is not None
    finally:
        runner.close()


@pytest.mark.slow
def test_the_worker_judges_the_running_configuration_once_loaded() -> None:
    """`prime` (the controller's start-up): the worker judges the running configuration on
    its knowledge by itself, so the first apply finds it done."""
    cfg = LoopConfig(q_cutoff_hz=0.6)
    runner = AnalysisWorker(subprocess=True)
    try:
        runner.start()
        runner.prime(cfg, K)
        assert runner.call(judged, cfg, K)  # (queued behind the prime job: done by now)
        assert not runner.call(judged, cfg.with_(q_cutoff_hz=0.61), K)
        assert runner.check(cfg, K) == gate(cfg, K)
        # What the warm-up loaded is out of the collector's reach (a full collection of it
        # was ~40 ms of CPU inside an apply): ~110 000 objects, at least the analysis's.
        assert runner.call(gc.get_freeze_count) > 50_000
    finally:
        runner.close()


@pytest.mark.slow
def test_a_slow_start_of_the_worker_is_not_a_rejection() -> None:
    """A fresh worker's first job gets the start-up time (a loaded machine), later jobs only
    their own timeout."""
    runner = AnalysisWorker(subprocess=True, timeout_s=1.5, start_timeout_s=30.0)
    try:
        runner.call(time.sleep, 2.0, timeout_s=1.5)  # the first job: slow, still served
        assert runner.check(LoopConfig(), K).applicable  # a verdict takes ~0.1 s (1.5 s here)
        with pytest.raises(concurrent.futures.TimeoutError):
            runner.call(time.sleep, 2.0, timeout_s=1.5)
    finally:
        runner.close()


def test_analysis_failures_carry_no_internal_text(monkeypatch: pytest.MonkeyPatch) -> None:
    import controller.gate.verdict as verdict_module

    def broken(*_args: object, **_kw: object) -> None:
        raise np.linalg.LinAlgError("Array must not contain infs or NaNs")

    monkeypatch.setattr(verdict_module, "analyse", broken)
    clear_caches()  # (the default was judged by the tests before, with the real analysis)
    verdict = gate(LoopConfig(), K)
    assert not verdict.applicable
    assert verdict.reasons[0].startswith("candidate: ")
    assert "LinAlgError" not in verdict.reasons[0] and "NaN" not in verdict.reasons[0]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (ended, not yet reaped by whoever adopted it) counts as ended
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.slow
def test_the_worker_ends_when_the_controller_is_killed(tmp_path: Path) -> None:
    code = (
        "import os, sys, time\n"
        "from controller.process.analysis_worker import AnalysisWorker\n"
        "r = AnalysisWorker(subprocess=True)\n"
        "print(r.call(os.getpid), flush=True)\n"
        "time.sleep(60)\n"
    )
    proc = spawn(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, cwd=Path(__file__).parents[1]
    )
    try:
        assert proc.stdout is not None
        worker = int(proc.stdout.readline())
        assert _alive(worker)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10.0)
        deadline = time.monotonic() + 10.0
        while _alive(worker) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not _alive(worker), "the analysis worker outlived the killed controller"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10.0)
