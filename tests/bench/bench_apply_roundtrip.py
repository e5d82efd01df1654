"""Benchmark: apply round trip (a candidate sent to a real controller -> its reply), this tree
against an older commit in one run, and where an apply's time goes.

    .venv/bin/python tests/bench/bench_apply_roundtrip.py [--before main~3] [--n 60]
        [--busy 0] [--realtime]

Each controller (a fresh state directory) first adopts plant knowledge with three measured
responses (0.1-20 Hz, 24 points each, as identification hands them over); then, timed:

* first apply: the first apply after the controller answers (its analysis worker may still be
  loading);
* new gains: every candidate has new gains (cv_kp 0.35-0.8, pos_kp 3-12 /s) and a cut-off
  below its recommendation (0.3-1.0 x, where there is one), sent with confirm: the verdict,
  the recommended cut-off's search for the new gains, the nonlinear check, the filters, the
  save (fsync), the swap at a tick boundary and the change log;
* cut-off only: the same gains, the cut-off moves (0.3-1.0 x its recommendation);
* rejected: a candidate the analysis rejects; get: the active configuration.

Each accepted apply runs the gate in the controller's worker process. The candidates are the
same for both trees (made and judged beforehand in this process). The breakdown times the
parts of a new-gains apply in this process, on the same candidates (this tree's code): the
analysis, the recommended cut-off as the gate asks it (and the whole search, as before), the
nonlinear check, the filter design and the persistence; the Zenoh round trip is the GET's.
`--busy N` runs N busy loops beside the measurement; the load average is printed.
Target: apply p99 <= 50 ms.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "integration"))
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from bench_startup import busy_loops, export_tree  # noqa: E402
from plant_evidence import three_positions  # noqa: E402
from procs import Client, start_controller  # noqa: E402

from controller import protocol as proto  # noqa: E402
from controller.core.config import LoopConfig  # noqa: E402
from controller.core.loop import LoopCoefficients  # noqa: E402
from controller.gate.analysis import analyse  # noqa: E402
from controller.gate.knowledge import (  # noqa: E402
    KnowledgeRecord,
    PlantKnowledge,
)
from controller.gate.search import RecommendationSearch, recommendation_search  # noqa: E402
from controller.gate.verdict import judge  # noqa: E402
from controller.process.persistence import Change, StateStore  # noqa: E402
from controller.sim.nonlinear_check import findings, nonlinear_check  # noqa: E402


def candidates(plant: PlantKnowledge, n: int, seed: int) -> tuple[list[LoopConfig],
                                                                   list[LoopConfig]]:
    """(new gains, cut-off only): applicable candidates (accept or caution), judged here."""
    rng = np.random.default_rng(seed)
    new: list[LoopConfig] = []
    while len(new) < n:
        base = LoopConfig(cv_kp=float(rng.uniform(0.35, 0.8)),
                          pos_kp_per_s=float(rng.uniform(3.0, 12.0)))
        rec = recommendation_search(base, plant).value()
        fc = float(rng.uniform(0.05, 0.5)) if rec is None else rec * float(rng.uniform(0.3, 1.0))
        cfg = base.with_(q_cutoff_hz=fc)
        if judge(cfg, plant, nonlinear=findings).applicable:
            new.append(cfg)
    base = new[0]
    rec = recommendation_search(base, plant).value() or 0.5
    same = [base.with_(q_cutoff_hz=rec * float(u)) for u in np.linspace(0.3, 1.0, n)]
    rng.shuffle(same)  # type: ignore[arg-type]
    same = [c for c in same if judge(c, plant, nonlinear=findings).applicable]
    return new, same


def _timed(items: list[LoopConfig], fn: Callable[[LoopConfig], bool]) -> np.ndarray:
    out = np.zeros(len(items))
    for i, cfg in enumerate(items):
        t0 = time.perf_counter()
        ok = fn(cfg)
        out[i] = (time.perf_counter() - t0) * 1e3
        if not ok:
            raise SystemExit(f"unexpected reply on {cfg}")
    return out


def _stats(ms: list[float]) -> str:
    a = np.asarray(ms)
    return (f"p50 {np.percentile(a, 50):6.1f}  p99 {np.percentile(a, 99):6.1f}  "
            f"max {a.max():6.1f} ms (n={a.size})")


class Rig:
    """One controller (a tree's code) with its client, ready and on the bench's knowledge."""

    def __init__(self, name: str, tree: Path | None, state: Path, record: KnowledgeRecord,
                 extra: tuple[str, ...], stack: contextlib.ExitStack) -> None:
        self.name = name
        self.proc = start_controller(state, extra_args=extra, tree=tree)
        stack.callback(self.proc.stop)
        self.c = stack.enter_context(Client(self.proc.endpoint, self.proc.rig, timeout_s=60.0))
        self.c.wait_ready(self.proc)
        # The first apply after the controller answers (its worker may still be loading).
        self.first_ms = _timed([LoopConfig(q_cutoff_hz=0.45)], self.apply)
        req = proto.KnowledgeRequest(record=record, client="bench")
        reply = proto.decode(self.c.query_raw(proto.key_knowledge(self.c.rig), proto.encode(req),
                                              timeout_s=60.0), proto.KnowledgeReply)
        if not reply.ok:
            raise SystemExit(f"{name}: knowledge not adopted: {reply.message}")
        for _ in range(5):  # warm up both sides
            self.c.get_config()

    def apply(self, cfg: LoopConfig) -> bool:
        reply = self.c.config_raw(proto.encode(proto.ConfigRequest(
            candidate=cfg, client="bench", confirm=True)))
        return reply.accepted

    def rejected(self, cfg: LoopConfig) -> bool:
        return not self.c.apply(cfg).accepted

    def get(self, cfg: LoopConfig) -> bool:
        return self.c.get_config().accepted


def run(trees: dict[str, Path | None], record: KnowledgeRecord, new: list[LoopConfig],
        same: list[LoopConfig], extra: tuple[str, ...]) -> dict[str, dict[str, list[float]]]:
    """Every controller runs at once; each request goes to each in turn (the order swapped
    every time), so they see the same load."""
    out: dict[str, dict[str, list[float]]] = {name: {} for name in trees}
    with tempfile.TemporaryDirectory(prefix="dobtune-bench-") as d, \
            contextlib.ExitStack() as stack:
        rigs = [Rig(name, tree, Path(d) / f"state{i}", record, extra, stack)
                for i, (name, tree) in enumerate(trees.items())]
        for r in rigs:
            out[r.name]["first apply"] = list(r.first_ms)
        st0 = {r.name: r.c.fresh_status() for r in rigs}
        bad = LoopConfig(cv_kp=20.0)
        kinds: list[tuple[str, list[LoopConfig], str]] = [
            ("new gains", new, "apply"), ("cut-off only", same, "apply"),
            ("rejected", [bad] * 20, "rejected"), ("get", [bad] * 50, "get")]
        for kind, items, how in kinds:
            for i, cfg in enumerate(items):
                for r in (rigs if i % 2 == 0 else rigs[::-1]):
                    out[r.name].setdefault(kind, []).extend(_timed([cfg], getattr(r, how)))
        for r in rigs:
            st1 = r.c.fresh_status()
            d_ticks = st1.timing.ticks - st0[r.name].timing.ticks
            d_over = st1.timing.overruns - st0[r.name].timing.overruns
            print(f"  {r.name}: loop overruns during the run {d_over} / {d_ticks} ticks")
    return out


def breakdown(plant: PlantKnowledge, new: list[LoopConfig], get_ms: float) -> None:
    """The parts of a new-gains apply, timed here on the same candidates (fresh caches)."""
    parts: dict[str, list[float]] = {}
    cpu: dict[str, list[float]] = {}

    def t(name: str, fn: Callable[..., object], *args: object) -> None:
        t0, c0 = time.perf_counter(), time.process_time()
        fn(*args)
        parts.setdefault(name, []).append((time.perf_counter() - t0) * 1e3)
        cpu.setdefault(name, []).append((time.process_time() - c0) * 1e3)

    def gate_asks(cfg: LoopConfig) -> bool | None:
        return RecommendationSearch(cfg, plant).decide(lambda r: not cfg.q_cutoff_hz > r * 1.0001)

    def whole(cfg: LoopConfig) -> float | None:
        return RecommendationSearch(cfg, plant).value()

    with tempfile.TemporaryDirectory(prefix="dobtune-bench-") as d:
        store = StateStore(Path(d))
        verdict = judge(LoopConfig(), plant)  # what a line of the change log carries

        def persist(cfg: LoopConfig, v: int, prev: LoopConfig) -> None:
            store.save(cfg, v, Change(old=prev, old_version=v - 1, verdict=verdict,
                                      client="bench"))

        def persist_before(cfg: LoopConfig, v: int, prev: LoopConfig) -> None:
            store.save(cfg, v)  # then the line, its fsync after the directory's (before ec2f14f)
            store.append_change(old=prev, old_version=v - 1, new=cfg, version=v,
                                verdict=verdict, client="bench")

        prev = LoopConfig()
        for v, cfg in enumerate(new, start=2):
            t("analysis", analyse, cfg, plant)
            t("search (as the gate asks)", gate_asks, cfg)
            t("search (whole, as before)", whole, cfg)
            t("nonlinear check", nonlinear_check, cfg, plant.model)
            t("filter design", LoopCoefficients.build, cfg, v)
            # Each way first every other time: neither is always timed right after the
            # other's fsyncs.
            saves = [("persistence (save + log, fsyncs)", persist),
                     ("persistence (save, then log)", persist_before)]
            for name, fn in saves if v % 2 == 0 else saves[::-1]:
                t(name, fn, cfg, v, prev)
            prev = cfg
    print("  where a new-gains apply's time goes (this tree's code in this process, over the "
          "same candidates; CPU time is what the load does not stretch):")
    print(f"    {'':34s} {'wall p50 / p99 ms':>18s} {'CPU p50 / p99 ms':>18s}")
    for name, ms in parts.items():
        c = cpu[name]
        print(f"    {name:34s} {statistics.median(ms):8.1f} / {np.percentile(ms, 99):6.1f} "
              f"{statistics.median(c):8.1f} / {np.percentile(c, 99):6.1f}")
    print(f"    {'zenoh round trip (a GET)':34s} {get_ms:8.1f}")
    gate = ["analysis", "search (as the gate asks)", "nonlinear check", "filter design"]
    before = ["analysis", "search (whole, as before)", "nonlinear check", "filter design"]
    now, then = (np.sum([cpu[k] for k in keys], axis=0) for keys in (gate, before))
    print(f"    CPU of the gate's parts per candidate: p50 {np.percentile(now, 50):.1f} ms, p99 "
          f"{np.percentile(now, 99):.1f} ms (with the whole search, as before: p50 "
          f"{np.percentile(then, 50):.1f} ms, p99 {np.percentile(then, 99):.1f} ms)")

def _load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--n", type=int, default=60, help="candidates per kind (default 60)")
    p.add_argument("--before", default=None, help="also run this older commit (git rev)")
    p.add_argument("--busy", type=int, default=0, help="busy loops beside the measurement")
    p.add_argument("--realtime", action="store_true", help="controller with SCHED_FIFO")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--breakdown-only", action="store_true",
                   help="no controllers: only where the time goes, in this process")
    a = p.parse_args()
    extra = ("--realtime-priority",) if a.realtime else ()
    plant = three_positions(source="bench: 3 positions")
    record = KnowledgeRecord.of(plant)
    t0 = time.perf_counter()
    new, same = candidates(plant, a.n, a.seed)
    print(f"{len(new)} new-gains and {len(same)} cut-off-only candidates, judged here in "
          f"{time.perf_counter() - t0:.1f} s; {os.cpu_count()} CPUs, {a.busy} busy loops beside")
    if a.breakdown_only:
        print(_load())
        breakdown(plant, new, float("nan"))
        print(_load())
        return 0
    with tempfile.TemporaryDirectory(prefix="bench-apply-") as d:
        trees: dict[str, Path | None] = {}
        if a.before:
            trees[f"before ({a.before})"] = export_tree(a.before, Path(d))
        trees["after (this tree)"] = None
        with busy_loops(a.busy):
            print(f"{_load()} (at the start)")
            results = run(trees, record, new, same, extra)
            print(f"{_load()} (at the end)")
    kinds = ("first apply", "new gains", "cut-off only", "rejected", "get")
    for kind in kinds:
        print(f"{kind}:" + ("  (target p99 <= 50 ms)" if kind in ("new gains", "cut-off only")
                            else ""))
        for name, r in results.items():
            print(f"  {name:24s} {_stats(r[kind])}")
    after = results["after (this tree)"]
    breakdown(plant, new, float(np.median(after["get"])))
    print(f"{_load()} (after the breakdown)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
