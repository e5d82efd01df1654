"""Benchmark: where an apply's round trip goes, stage by stage, in a real controller.

    PYTHONPATH=$PWD .venv/bin/python tests/bench/bench_apply_stages.py [--n 40] [--reps 1]

One controller (this tree) on the plant knowledge of `bench_apply_roundtrip` (three measured
responses) gets its new-gains and cut-off-only candidates, `--reps` times over (a repeat may
find the worker's verdict or the gains' search cached: `--reps 1` for fresh ones only). The
controller runs with `apply_stages_probe/sitecustomize.py` (on its PYTHONPATH only), which
time-stamps each apply's stages in the controller and the analysis worker (one clock for
every process). Per kind of candidate, for each stage: wall p50 / p90 / p99 / max and its
mean over the slowest 5 % of round trips (what the tail is made of):

* client -> node: the request's way to the controller's Zenoh callback;
* queue: the callback's hand-off to the config worker thread;
* read: payload, decoding and the lease up to the apply;
* worker hand-off: the call to the analysis worker process minus the gate's own wall time
  there (pickling, the pool's threads, the pipes);
* gate (worker): `gate_and_build` in the worker, wall and its process CPU;
* save: the configuration and its change-log line, fsynced;
* tick: the swap's ticket (the next tick boundary) and the wait for the version;
* reply: the rest of the apply, the audit record and encoding, `query.reply`;
* reply -> client: the reply's way back;
* controller thread CPU: the config worker thread's CPU for the whole request.

Then every garbage collection (generation 1-2, or longer than 0.3 ms) in the client, the
controller and the worker that fell inside a timed request. The load average is printed.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import glob
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_apply_roundtrip import Rig, _load, candidates, three_positions  # noqa: E402

from controller.gate.knowledge import KnowledgeRecord  # noqa: E402

PROBE_DIR = HERE / "apply_stages_probe"


def _span(stages: dict[str, tuple[str, float, float, float]], name: str) -> float:
    _, t0, t1, _ = stages[name]
    return t1 - t0


def _row(kind: str, t0: float, t1: float, rec: dict[str, Any], gate: dict[str, Any] | None,
         ) -> dict[str, Any]:
    st = {s[0]: s for s in rec["stages"]}
    reply1 = rec["reply"][1]
    gate_wall = gate["gate"][1] - gate["gate"][0] if gate else 0.0
    arrived = rec["arrived"] if rec["arrived"] is not None else rec["taken"]
    return {
        "kind": kind,
        "round trip": t1 - t0,
        "client -> node": arrived - t0,
        "queue": rec["taken"] - arrived,
        "read": st["apply"][1] - rec["taken"],
        "worker hand-off": _span(st, "worker") - gate_wall,
        "gate (worker)": gate_wall if gate else float("nan"),
        "gate CPU (worker)": gate["gate_cpu"] if gate else float("nan"),
        "save": _span(st, "save"),
        "tick": _span(st, "ticket") + _span(st, "wait_version"),
        "reply": reply1 - st["wait_version"][2],
        "reply -> client": t1 - reply1,
        "controller thread CPU": rec["cpu"],
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--n", type=int, default=40, help="candidates per kind (default 40)")
    p.add_argument("--reps", type=int, default=1,
                   help="times each candidate is sent (default 1; repeats may be cached)")
    p.add_argument("--seed", type=int, default=1)
    a = p.parse_args()
    plant = three_positions(source="bench: 3 positions")
    record = KnowledgeRecord.of(plant)
    new, same = candidates(plant, a.n, a.seed)
    client_gc: list[tuple[int, float, float]] = []
    gc_start = [0.0]

    def on_gc(phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            gc_start[0] = time.perf_counter()
        else:
            client_gc.append((info["generation"], gc_start[0], time.perf_counter()))

    calls: list[tuple[str, float, float]] = []
    # (The worker, ended by its parent's death, may write a last line while this is removed.)
    with tempfile.TemporaryDirectory(prefix="bench-stages-", ignore_cleanup_errors=True) as d, \
            contextlib.ExitStack() as stack:
        prefix = str(Path(d) / "probe")
        os.environ["DOBTUNE_APPLY_PROBE"] = prefix
        os.environ["PYTHONPATH"] = os.pathsep.join(
            [str(PROBE_DIR), *filter(None, [os.environ.get("PYTHONPATH")])])
        rig = Rig("this tree", None, Path(d) / "state", record, (), stack)
        del os.environ["DOBTUNE_APPLY_PROBE"]
        print(f"{_load()} (at the start)")
        gc.callbacks.append(on_gc)
        for _ in range(a.reps):
            for kind, items in (("new gains", new), ("cut-off only", same)):
                for cfg in items:
                    t0 = time.perf_counter()
                    ok = rig.apply(cfg)
                    t1 = time.perf_counter()
                    if not ok:
                        raise SystemExit(f"unexpected reply on {cfg}")
                    calls.append((kind, t0, t1))
        gc.callbacks.remove(on_gc)
        print(f"{_load()} (at the end)")
        controller_pid = rig.proc.proc.pid
        stack.close()  # the controller stops: its files are complete
        applies: list[dict[str, Any]] = []
        gates: list[dict[str, Any]] = []
        pauses: dict[int, list[tuple[int, float, float]]] = {os.getpid(): client_gc}
        names = {os.getpid(): "client", controller_pid: "controller"}
        for path in glob.glob(prefix + ".*"):
            pid = int(path.rsplit(".", 1)[1])
            lines = [json.loads(x) for x in Path(path).read_text().splitlines() if x]
            if ".gc." in path:
                pauses[pid] = [tuple(x) for x in lines]  # type: ignore[misc]
            else:
                for x in lines:
                    (gates if "gate" in x else applies).append(x)
                if any("gate" in x for x in lines):
                    names[pid] = "analysis worker"
    rows = []
    for kind, t0, t1 in calls:
        rec = [x for x in applies if t0 <= x["taken"] <= t1]
        if len(rec) != 1:
            continue
        st = {s[0]: s for s in rec[0]["stages"]}
        w0, w1 = st["worker"][1:3]
        gate = [g for g in gates if w0 <= g["gate"][0] <= w1]
        rows.append(_row(kind, t0, t1, rec[0], gate[0] if gate else None))
    for kind in ("new gains", "cut-off only"):
        rs = [r for r in rows if r["kind"] == kind]
        n_calls = sum(1 for c in calls if c[0] == kind)
        print(f"{kind}: {len(rs)} of {n_calls} applies matched (ms)")
        if not rs:
            continue
        total = np.array([r["round trip"] for r in rs])
        slow = np.argsort(total)[-max(1, len(rs) // 20):]
        print(f"  {'stage':24s} {'p50':>7s} {'p90':>7s} {'p99':>7s} {'max':>7s}  slowest 5 %")
        for name in rs[0]:
            if name == "kind":
                continue
            v = np.array([r[name] for r in rs]) * 1e3
            print(f"  {name:24s} {np.nanpercentile(v, 50):7.2f} {np.nanpercentile(v, 90):7.2f} "
                  f"{np.nanpercentile(v, 99):7.2f} {np.nanmax(v):7.2f}  {np.nanmean(v[slow]):7.2f}")
    print("garbage collections inside timed requests (generation: count, longest ms):")
    for pid, gcs in pauses.items():
        inside = [g for g in gcs if any(g[1] < t1 and g[2] > t0 for _, t0, t1 in calls)]
        by_gen = {gen: [g[2] - g[1] for g in inside if g[0] == gen] for gen in (0, 1, 2)}
        print(f"  {names.get(pid, f'other ({pid})'):16s} " + ", ".join(
            f"gen {gen}: {len(v)}, {1e3 * max(v, default=0.0):.1f}" for gen, v in by_gen.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
