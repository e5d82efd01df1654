"""The analysis worker: the stability gate, the filter design and identification estimates, run
off the loop in a niced worker process.

`gate` is the one adapter to `controller.gate.analysis`; `AnalysisWorker` runs it (and any other
heavy computation: identification estimates) in a worker process of its own, so the
analysis (NumPy + Python, ~10 ms) never competes with the loop's thread for this
interpreter's lock: run in a thread of the controller it made the loop overrun on a busy
machine. A worker that hangs is killed after its timeout; the next call starts a fresh one.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import logging
import os
import threading
from collections.abc import Callable
from typing import Any

import msgspec

from controller.core.config import LoopConfig
from controller.core.heap import freeze_startup_heap
from controller.core.loop import LoopCoefficients
from controller.core.verdict import Verdict
from controller.gate.knowledge import KnowledgeRecord
from controller.process.worker_start import worker_init

__all__ = ["AnalysisWorker", "WorkerStopped", "clear_caches", "gate", "gate_and_build", "judged"]

log = logging.getLogger(__name__)


#: The worker's converted plant knowledge (one record at a time) and its verdicts: the caches
#: of the analysis (the recommended cut-off's search, `gate`'s verdicts) are keyed on the
#: knowledge object, so it stays the same while the record is equal, every field of it (not
#: only its version and source: a record is judged on its evidence, whatever it is named).
_knowledge: list[tuple[KnowledgeRecord, Any]] = []
#: The gate's verdicts by (candidate, knowledge object): a candidate sent again (a
#: confirmation after a caution, a re-apply) is not analysed again. Everything a verdict
#: depends on is in the key: the whole configuration (gains, filters, limits, rate), the
#: knowledge (its evidence and version); the gate's limits are the defaults, the rig's
#: command limit is checked before (`AnalysisWorker`).
_verdicts: dict[tuple[LoopConfig, Any], Verdict] = {}
_VERDICTS_MAX = 64
_cache_lock = threading.Lock()


def _plant(record: KnowledgeRecord) -> Any:
    with _cache_lock:
        if _knowledge and _knowledge[0][0] == record:
            return _knowledge[0][1]
    k = record.to_knowledge()
    with _cache_lock:
        _knowledge[:] = [(record, k)]
        _verdicts.clear()
    return k


def clear_caches() -> None:
    """Forget the converted knowledge and the verdicts (for tests that change the code the
    gate runs; the caches' keys hold every input)."""
    with _cache_lock:
        _knowledge.clear()
        _verdicts.clear()


def judged(cfg: LoopConfig, record: KnowledgeRecord) -> bool:
    """The gate's verdict on `cfg` against `record` is cached here (this process)."""
    with _cache_lock:
        if not (_knowledge and _knowledge[0][0] == record):
            return False
        return (cfg, _knowledge[0][1]) in _verdicts


def gate(cfg: LoopConfig, record: KnowledgeRecord) -> Verdict:
    """The gate's verdict (`controller.gate.verdict.judge`) on `cfg` against the plant
    knowledge `record`. Never raises."""
    try:
        plant = _plant(record)
    except Exception as exc:
        log.warning("plant knowledge v%d failed to convert: %s: %s", record.version,
                    type(exc).__name__, exc)
        reason = "knowledge: the plant knowledge cannot be used"
        return Verdict.refused(reason, record.version)
    key = (cfg, plant)
    with _cache_lock:
        verdict = _verdicts.get(key)
    if verdict is None:
        from controller.gate.verdict import judge
        from controller.sim.nonlinear_check import findings

        try:
            verdict = judge(cfg, plant, nonlinear=findings, recommendation=False)
        except Exception as exc:  # the details go to the log, never to the client
            log.warning("analysis failed on %r: %s: %s", cfg, type(exc).__name__, exc)
            reason = "candidate: the stability analysis cannot evaluate this configuration"
            return Verdict.refused(reason, record.version)
        if verdict.verdict == "reject" and not verdict.reasons:
            verdict = msgspec.structs.replace(
                verdict, rejections=("rejected by the stability analysis",))
        verdict = msgspec.structs.replace(verdict, knowledge_version=record.version)
        with _cache_lock:
            if len(_verdicts) >= _VERDICTS_MAX:
                del _verdicts[next(iter(_verdicts))]
            _verdicts[key] = verdict
    return verdict


def gate_and_build(
    cfg: LoopConfig, version: int, record: KnowledgeRecord
) -> tuple[Verdict, LoopCoefficients | None]:
    """`gate`, then (if it may be applied) the loop's filters for `version`. Never raises."""
    verdict = gate(cfg, record)
    if not verdict.applicable:
        return verdict, None
    try:
        return verdict, LoopCoefficients.build(cfg, version)
    except Exception as exc:
        reason = f"candidate: filters could not be built: {exc}"
        return msgspec.structs.replace(
            verdict, verdict="reject", rejections=(reason,), cautions=()), None


def _warm_up() -> None:
    """A new worker's first job: load the analysis code (seconds on a busy machine)."""
    import controller.gate.verdict  # noqa: F401
    from controller.core.config import LoopConfig
    from controller.sim.nonlinear_check import nonlinear_check

    nonlinear_check(LoopConfig())  # compiles the simulated rig's kernel (numba) once
    # What is loaded now (~110 000 objects: the analysis's modules, numba's kernel) is never
    # scanned by the collector again, as in the controller: a full collection of it cost
    # ~40 ms of CPU, and one came inside an apply every few dozen.
    freeze_startup_heap()


class WorkerStopped(RuntimeError):
    """The job was cut short because its worker was stopped (`close(wait=False)`: the
    controller stops): not a failure of the job or of the worker."""


class AnalysisWorker:
    """Runs the gate and other heavy work in a worker process (default) or in the caller."""

    def __init__(
        self,
        *,
        subprocess: bool = True,
        timeout_s: float = 10.0,
        start_timeout_s: float = 60.0,
        command_limit_max_deg_s: float | None = None,
    ) -> None:
        self._subprocess = subprocess
        #: A new worker (the first call, or the next one after a worker was killed) gets this
        #: long to start and load the analysis; the work itself gets the call's timeout.
        self._start_timeout_s = start_timeout_s
        #: The rig's own command limit (CAN rig file): a config may not exceed it, or the drive
        #: would clamp commands the DOB believes were sent.
        self.command_limit_max_deg_s = command_limit_max_deg_s
        self._timeout_s = timeout_s
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        #: The worker has not finished a job yet: its first job also gets the start-up time
        #: (a slow start on a loaded machine is not a rejection).
        self._fresh = True
        #: A new worker's warm-up (imports, the rig kernel), waited for by the first call.
        self._warming: concurrent.futures.Future[None] | None = None
        #: The worker has been given its first job (`prime` is worth it only before).
        self._primed = False
        self._lock = threading.Lock()
        #: `close(wait=False)` killed the worker: a job it cut short raises WorkerStopped.
        self._stopped = False

    def _executor(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            import multiprocessing

            self._pool = concurrent.futures.ProcessPoolExecutor(
                max_workers=1,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=worker_init,
                initargs=(os.getpid(), threading.current_thread() is threading.main_thread()),
            )
            self._fresh = True
            self._primed = False
            self._warming = self._pool.submit(_warm_up)
        return self._pool

    def start(self) -> None:
        """Start the worker process now and let it load the analysis while the caller goes on
        (the controller's start-up); the first `call` waits for it. Nothing without a worker."""
        if self._subprocess:
            with self._lock:
                self._executor()

    def prime(self, cfg: LoopConfig, record: KnowledgeRecord) -> None:
        """Let the worker judge `cfg` (the running configuration) on `record` as soon as it
        has loaded, while the caller goes on: it converts the knowledge and fills what the
        first apply would otherwise wait for (the analysis's first run, the verdict, the
        recommended cut-off's search for these gains). Nothing without a worker."""
        if self._subprocess:
            with self._lock:
                pool = self._executor()
                if not self._primed:  # (a new worker's first job after its warm-up)
                    self._primed = True
                    pool.submit(gate, cfg, record)

    def check(self, cfg: LoopConfig, record: KnowledgeRecord) -> Verdict:
        """The gate's verdict on `cfg` against the plant knowledge (no filters built)."""
        return self.check_and_build(cfg, 0, record, build=False)[0]

    def check_here(self, cfg: LoopConfig, record: KnowledgeRecord) -> Verdict:
        """`check` in this process (the same gate and rig limit): for the controller's
        start-up, before its loop runs, when the worker is still loading and a niced worker
        would wait behind a busy machine."""
        refused = self._over_rig_limit(cfg)
        return refused if refused is not None else gate(cfg, record)

    def _over_rig_limit(self, cfg: LoopConfig) -> Verdict | None:
        rig_max = self.command_limit_max_deg_s
        if rig_max is not None and cfg.command_limit_deg_s > rig_max:
            reason = (
                f"command_limit_deg_s {cfg.command_limit_deg_s:g} deg/s > the rig's limit "
                f"{rig_max:g} deg/s (rig file limits.command_limit_deg_s): the drive would "
                "clamp commands the DOB believes were sent"
            )
            return Verdict.refused(reason)
        return None

    def check_and_build(
        self, cfg: LoopConfig, version: int, record: KnowledgeRecord, *, build: bool = True
    ) -> tuple[Verdict, LoopCoefficients | None]:
        """The gate's verdict and, if it may be applied and `build`, the coefficients (None
        otherwise)."""
        refused = self._over_rig_limit(cfg)
        if refused is not None:
            return refused, None
        try:
            if build:
                built: tuple[Verdict, LoopCoefficients | None] = self.call(
                    gate_and_build, cfg, version, record, timeout_s=self._timeout_s
                )
                return built
            return self.call(gate, cfg, record, timeout_s=self._timeout_s), None
        except concurrent.futures.TimeoutError:
            reason = f"analysis: no verdict within {self._timeout_s:g} s"
        except Exception as exc:  # a dead worker (BrokenProcessPool), pickling, ...
            reason = f"analysis worker failed: {type(exc).__name__}: {exc}"
        return Verdict.refused(reason), None

    def call(self, fn: Callable[..., Any], *args: Any, timeout_s: float = 120.0) -> Any:
        """Run `fn(*args)` in the worker process (or here without one); raises on failure.
        A worker that fails or does not answer within `timeout_s` is killed."""
        if not self._subprocess:
            return fn(*args)
        with self._lock:
            try:
                pool = self._executor()
                warming, self._warming = self._warming, None
                if warming is not None:
                    warming.result(timeout=self._start_timeout_s)
                if self._fresh:
                    # The first real job pays for the imports and caches the warm-up did not
                    # touch: it gets the start-up time too, not just the job's timeout.
                    timeout_s = max(timeout_s, self._start_timeout_s)
                self._primed = True
                result = pool.submit(fn, *args).result(timeout=timeout_s)
                self._fresh = False
                return result
            except Exception as exc:
                if self._stopped:
                    log.info("analysis worker: %s stopped with the controller",
                             getattr(fn, "__name__", fn))
                    raise WorkerStopped(
                        f"{getattr(fn, '__name__', fn)}: stopped with the controller") from exc
                log.warning(
                    "analysis worker: %s failed (%s: %s); worker killed",
                    getattr(fn, "__name__", fn),
                    type(exc).__name__,
                    exc,
                )
                self._kill()
                raise

    def _kill(self) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        for proc in list(getattr(pool, "_processes", {}).values()):
            with contextlib.suppress(Exception):
                proc.kill()
        with contextlib.suppress(Exception):
            pool.shutdown(wait=False, cancel_futures=True)

    def close(self, *, wait: bool = True) -> None:
        """Stop the worker. `wait`: let a job in progress finish first (a gate check: seconds);
        without it the worker is killed at once (the twin's fit: minutes on a busy machine,
        of no use to a controller that stops; its caller gets the worker's failure)."""
        if not wait:
            self._stopped = True
            self._warming = None
            self._kill()
            return
        warming = self._warming
        if warming is not None and not warming.done():
            # Still loading (a stop right after the start, on a busy machine: the niced worker
            # may need many seconds more): nothing to finish, do not wait for it.
            with self._lock:
                self._warming = None
                self._kill()
            return
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
