"""Stage timings of a controller's apply path, for `tests/bench/bench_apply_stages.py`.

Imported by every Python process started with this directory on PYTHONPATH; it does nothing
unless DOBTUNE_APPLY_PROBE names an output prefix. Then, in the controller, it wraps the
config worker's queue loop and the apply's parts (the worker call, the save, the tick
boundary's ticket, the wait for the version) and writes one JSON line per apply to
`<prefix>.<pid>`; in the analysis worker, it times `gate_and_build` (wall and process CPU);
in both, every garbage collection of generation 1 or 2, or longer than 0.3 ms, goes to
`<prefix>.gc.<pid>`. Times are `time.perf_counter` (CLOCK_MONOTONIC: one clock for every
process of the machine). A benchmark's instrument, never loaded by the product.
"""

from __future__ import annotations

import os

_OUT = os.environ.get("DOBTUNE_APPLY_PROBE")

if _OUT:
    import contextlib
    import functools
    import gc
    import importlib.abc
    import json
    import sys
    import threading
    import time
    from typing import Any

    pc, thread_cpu, process_cpu = time.perf_counter, time.thread_time, time.process_time
    _cur = threading.local()
    _lock = threading.Lock()
    _gc_start = [0.0]

    def _write(suffix: str, record: object) -> None:
        with _lock, open(f"{_OUT}.{suffix}{os.getpid()}", "a") as f:
            f.write(json.dumps(record) + "\n")

    def _on_gc(phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            _gc_start[0] = pc()
            return
        t1 = pc()
        if info["generation"] > 0 or t1 - _gc_start[0] > 0.0003:
            _write("gc.", (info["generation"], _gc_start[0], t1))

    gc.callbacks.append(_on_gc)

    def _stage(name: str, fn: Any) -> Any:
        @functools.wraps(fn)
        def timed(*a: Any, **k: Any) -> Any:
            rec = getattr(_cur, "rec", None)
            t0, c0 = pc(), thread_cpu()
            try:
                return fn(*a, **k)
            finally:
                if rec is not None:
                    rec.setdefault("stages", []).append((name, t0, pc(), thread_cpu() - c0))
        return timed

    def _install_controller() -> None:
        from controller.process import analysis_worker, node, persistence, runtime, service

        arrived: dict[int, float] = {}
        enqueue = node.ZenohNode._enqueue

        def _enqueue(self: Any, q: Any) -> Any:
            put = enqueue(self, q)

            def stamped(query: Any) -> None:
                arrived[id(query)] = pc()
                put(query)
            return stamped

        node.ZenohNode._enqueue = _enqueue
        analysis_worker.AnalysisWorker.check_and_build = _stage(
            "worker", analysis_worker.AnalysisWorker.check_and_build)
        persistence.StateStore.save = _stage("save", persistence.StateStore.save)
        runtime.Ticket.wait = _stage("ticket", runtime.Ticket.wait)
        service.ControllerService._wait_version = _stage(
            "wait_version", service.ControllerService._wait_version)
        service.ControllerService.apply = _stage("apply", service.ControllerService.apply)

        def serve_queue(self: Any, q: Any, handle: Any) -> None:
            # node.ZenohNode.serve_queue with time stamps (keep the two alike).
            rt = self.rt
            while True:
                item = q.get()
                if item is node.SHUTDOWN:
                    return
                query, arrival = item
                rec: dict[str, Any] = {"arrived": arrived.pop(id(query), None), "taken": pc()}
                c0 = thread_cpu()
                try:
                    payload = query.payload
                    data = b"" if payload is None else payload.to_bytes()
                    who = self.access.who(query.key_expr)
                    _cur.rec = rec
                    with rt.arrival_scope(arrival):
                        t0 = pc()
                        reply = handle(data, who)
                        rec["handle"] = (t0, pc())
                    _cur.rec = None
                    t0 = pc()
                    query.reply(query.key_expr, reply, encoding=self._reply_encoding.get(id(q)))
                    rec["reply"] = (t0, pc())
                except Exception as exc:
                    self.service.warn(f"query handler error: {type(exc).__name__}: {exc}")
                    with contextlib.suppress(Exception):
                        query.reply_err(b"internal error: the request was not served")
                finally:
                    _cur.rec = None
                    with contextlib.suppress(Exception):
                        query.drop()
                    rec["cpu"] = thread_cpu() - c0
                    if "reply" in rec and any(s[0] == "apply" for s in rec.get("stages", ())):
                        _write("", rec)

        node.ZenohNode.serve_queue = serve_queue

    def _install_worker() -> None:
        from controller.process import analysis_worker

        inner = analysis_worker.gate_and_build

        def gate_and_build(*a: Any) -> Any:
            t0, c0 = pc(), process_cpu()
            try:
                return inner(*a)
            finally:
                _write("", {"gate": (t0, pc()), "gate_cpu": process_cpu() - c0})

        # Pickled by name: the worker runs the module's attribute, this one.
        gate_and_build.__qualname__ = gate_and_build.__name__ = "gate_and_build"
        gate_and_build.__module__ = analysis_worker.__name__
        analysis_worker.gate_and_build = gate_and_build

    _hooks = {"controller.process.node": _install_controller,
              "controller.process.analysis_worker": _install_worker}

    class _Loader(importlib.abc.Loader):
        def __init__(self, inner: Any, hook: Any) -> None:
            self.inner, self.hook = inner, hook

        def create_module(self, spec: Any) -> Any:
            return self.inner.create_module(spec)

        def exec_module(self, module: Any) -> None:
            self.inner.exec_module(module)
            self.hook()

    class _Finder(importlib.abc.MetaPathFinder):
        """Runs a hook right after its module has been executed (once)."""

        def find_spec(self, name: str, path: Any, target: Any = None) -> Any:
            hook = _hooks.pop(name, None)
            if hook is None:
                return None
            for finder in sys.meta_path:
                if finder is not self and hasattr(finder, "find_spec"):
                    spec = finder.find_spec(name, path, target)
                    if spec is not None:
                        spec.loader = _Loader(spec.loader, hook)
                        return spec
            return None

    sys.meta_path.insert(0, _Finder())
