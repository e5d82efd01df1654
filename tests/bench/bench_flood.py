"""Benchmark: the loop and the e-stop under a client's request flood (issue 31 item 1).

    .venv/bin/python tests/bench/bench_flood.py [--seconds 20] [--tree DIR] [--budget N]
        [--runs none,viewer,operator] [--repeat N]

One controller with authentication (`--auth`, users op1 operator, view viewer, watch viewer),
`--realtime-priority` as on a rig. Each run lasts `--seconds`: `none` (no flood), `viewer` (a
viewer floods what it may ask: config, history of 1000, knowledge, lease, identify, and a
candidate it may not apply) and `operator` (the lease holder floods applies of two accepted
candidates, alternating); `estop` (a viewer puts e-stops as fast as it can: no request,
no budget: each reaches the loop's process). The flood comes from another process at nice
19 (it stands for another machine) with 4 threads, each sending its next request as soon as
the previous one is answered or refused: the fastest a client can send and still learn the
outcome.

Meanwhile an e-stop is put (by `watch`, on its own scope) every 0.3 s. The loop stays latched
in e-stop; each e-stop is a new one (`estop_seq`, the tick that saw it), so its latency is the
wall time of that tick (the state stream: epoch_s + t_s, the tick's own clock) minus the put's.
Printed per run: e-stop put -> tick p50/p99/max, ticks, skipped ticks (% of the ticks), worst
period, the flood's answers and refusals (a refusal naming the request budget, a refused
change, a query that got no answer), the machine's load (1 min) at the run's start and its
CPU steal over the run (/proc/stat: time a virtual machine's CPUs waited for the host).

`--repeat N` runs the `--runs` list N times, interleaved (none, viewer, operator, none, ...),
so the machine's drift falls on every role alike, and then prints per role: the median of
its runs' skipped %, the e-stop p50/p99/max pooled over all its runs, and each beside the
no-flood runs' (the difference: the target is skipped within 1 % of the run without flood
and p99 <= 5 ms).

`--budget N` gives the controller `--request-budget N`. `--tree DIR` runs the controller of
another source tree (e.g. a clone of an older commit); the clients are this tree's.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: helpers, for procs
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))

from procs import StateCollector, start_controller, wait_until

from controller import protocol as proto
from controller.auth import init_auth_dir, new_users
from controller.client import ClientOptions, ControllerClient, ControllerUnavailable
from controller.core.config import LoopConfig

RIG = "bench-flood"
THREADS = 4


def _client(endpoint: str, auth: Path, user: str, timeout_s: float = 2.0) -> ControllerClient:
    return ControllerClient(ClientOptions(
        connect=(endpoint,), rig_name=RIG, auth=auth, user=user, client_name=user,
        query_timeout_s=timeout_s, apply_timeout_s=timeout_s, connect_timeout_s=30.0))


# -- the flooding process ------------------------------------------------------------------------


def flood(role: str, endpoint: str, auth: Path, seconds: float) -> dict[str, int]:
    """Flood for `seconds` from THREADS threads (one session); counts by outcome."""
    os.nice(19)
    counts = {"answered": 0, "refused_budget": 0, "refused": 0, "no_answer": 0, "other_error": 0}
    lock = threading.Lock()
    user = "op1" if role == "operator" else "view"
    with _client(endpoint, auth, user) as c:
        if role == "operator":
            assert c.lease("takeover", 600.0).ok
        a, b = LoopConfig(q_cutoff_hz=0.5), LoopConfig(q_cutoff_hz=0.6)
        viewer_asks = [
            lambda i: c.get_config(),
            lambda i: c.history(1000),
            lambda i: c.knowledge(),
            lambda i: c.lease("status"),
            lambda i: c.identify_status(),
            lambda i: c.apply(a),
        ]
        started = threading.Event()
        stop_at = [0.0]

        def work(t: int) -> None:
            started.wait()
            i = t
            while time.monotonic() < stop_at[0]:
                i += 1
                try:
                    if role == "estop":  # puts: no reply to wait for
                        c.put_estop()
                        with lock:
                            counts["answered"] += 1
                        continue
                    if role == "operator":
                        r: Any = c.apply(a if i % 2 else b)
                    else:
                        r = viewer_asks[i % len(viewer_asks)](i)
                    ok = getattr(r, "accepted", getattr(r, "ok", True))
                    key = "answered" if ok else "refused"
                except ControllerUnavailable as exc:
                    text = str(exc)
                    key = ("refused_budget" if "budget" in text else
                           "no_answer" if "no reply" in text else "other_error")
                with lock:
                    counts[key] += 1

        threads = [threading.Thread(target=work, args=(t,)) for t in range(THREADS)]
        for t in threads:
            t.start()
        print("flooding", flush=True)
        stop_at[0] = time.monotonic() + seconds
        started.set()
        for t in threads:
            t.join()
    return counts


# -- the measuring side --------------------------------------------------------------------------


def _estop_trials(watch: ControllerClient, col: StateCollector, seconds: float,
                  period_s: float = 0.3) -> list[tuple[float, float]]:
    """Put an e-stop every `period_s` for `seconds`; (put UNIX time, its tick's wall time) of
    those whose tick the stream showed."""
    puts: list[tuple[float, int]] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        st = watch.status
        before = st.estop_seq if st is not None else -1
        t_put = time.time()
        watch.put_estop()
        seen: list[int] = []

        def new_estop(before: int = before, seen: list[int] = seen) -> bool:
            s = watch.status
            if s is not None and s.estop_seq != before:
                seen.append(s.estop_seq)
                return True
            return False

        if wait_until(new_estop, 3.0, poll_s=0.005):
            puts.append((t_put, seen[0]))
        time.sleep(period_s)
    out: list[tuple[float, float]] = []
    wait_until(lambda: col.last_seq() >= max((s for _, s in puts), default=-1), 3.0)
    samples = col.samples()
    for t_put, seq in puts:
        s = samples.get(seq)
        if s is not None:
            out.append((t_put, s["wall_s"]))
    return out


def _cpu_times() -> list[int]:
    """/proc/stat's first line: user nice system idle iowait irq softirq steal (jiffies)."""
    with open("/proc/stat") as f:
        return [int(x) for x in f.readline().split()[1:9]]


def _steal_pct(before: list[int], after: list[int]) -> float:
    d = [b - a for a, b in zip(before, after, strict=True)]
    return 100.0 * d[7] / max(1, sum(d))


def run_once(role: str, endpoint: str, auth: Path, seconds: float) -> dict[str, Any]:
    load = os.getloadavg()[0]
    cpu0 = _cpu_times()
    with _client(endpoint, auth, "watch") as watch:
        assert wait_until(lambda: watch.status is not None, 30.0)
        flooder = None
        if role != "none":
            code = (f"import sys, json; sys.path.insert(0, {str(Path(__file__).parent)!r}); "
                    "import bench_flood as b; "
                    f"print(json.dumps(b.flood({role!r}, {endpoint!r}, "
                    f"b.Path({str(auth)!r}), {seconds})))")
            flooder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                                       text=True)
            assert flooder.stdout is not None
            line = flooder.stdout.readline()
            assert line.startswith("flooding"), line
        col = StateCollector()
        sub = watch.session.declare_subscriber(proto.key_state(RIG), col.on_sample)
        try:
            st0 = watch.status
            assert st0 is not None
            worst = [0.0]
            stop = threading.Event()

            def worst_period() -> None:
                last = None
                while not stop.wait(0.05):
                    s = watch.status
                    if s is not None and s is not last:
                        last = s
                        worst[0] = max(worst[0], s.timing.period_max_us)

            wt = threading.Thread(target=worst_period, daemon=True)
            wt.start()
            trials = _estop_trials(watch, col, seconds)
            stop.set()
            wt.join()
            st1 = watch.status
            assert st1 is not None
        finally:
            sub.undeclare()
        counts: dict[str, int] = {}
        if flooder is not None:
            out, _ = flooder.communicate(timeout=60)
            counts = json.loads(out.strip().splitlines()[-1])
    steal = _steal_pct(cpu0, _cpu_times())
    ticks = st1.timing.ticks - st0.timing.ticks
    skipped = st1.timing.skipped_ticks - st0.timing.skipped_ticks
    return {"role": role, "lat_ms": [(b - a) * 1e3 for a, b in trials], "ticks": ticks,
            "skipped": skipped, "worst_period_ms": worst[0] / 1e3, "counts": counts,
            "load": load, "steal_pct": steal}


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def _skipped_pct(r: dict[str, Any]) -> float:
    return 100.0 * r["skipped"] / max(1, r["ticks"] + r["skipped"])


def print_runs(results: list[dict[str, Any]]) -> None:
    print(f"{'run':9} {'e-stops':>7} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} "
          f"{'ticks':>6} {'skipped':>13} {'worst ms':>8} "
          f"{'load':>5} {'steal':>6}  flood outcomes")
    for r in results:
        lat_ms = r["lat_ms"]
        counts = ", ".join(f"{k} {v}" for k, v in r["counts"].items() if v) or "-"
        if r["role"] == "estop":  # see the note printed below
            lat = f"{len(lat_ms):7d} {'-':>7} {'-':>7} {'-':>7}"
        else:
            lat = (f"{len(lat_ms):7d} {_pct(lat_ms, 50):7.2f} {_pct(lat_ms, 99):7.2f} "
                   f"{max(lat_ms, default=float('nan')):7.2f}")
        skipped = f"{r['skipped']} ({_skipped_pct(r):.1f} %)"
        print(f"{r['role']:9} {lat} {r['ticks']:6d} {skipped:>13} "
              f"{r['worst_period_ms']:8.2f} {r['load']:5.1f} {r['steal_pct']:5.1f}%  {counts}")
    if any(r["role"] == "estop" for r in results):
        print("estop: no latency: the flood's own e-stops latch the loop every tick, so the "
              "tick that saw the watch's e-stop cannot be told from the flood's (the stream's "
              "estop_seq moves with each; what it would time is the next Status, every 0.2 s)")


def print_summary(results: list[dict[str, Any]]) -> None:
    """Per role over its repeats: median skipped %, pooled e-stop latency, and beside each the
    no-flood runs' and the difference."""
    roles = list(dict.fromkeys(r["role"] for r in results))
    by = {role: [r for r in results if r["role"] == role] for role in roles}

    def figures(rs: list[dict[str, Any]]) -> tuple[float, float, float, float, int]:
        lat = [x for r in rs for x in r["lat_ms"]]
        return (float(np.median([_skipped_pct(r) for r in rs])), _pct(lat, 50),
                _pct(lat, 99), max(lat, default=float("nan")), len(lat))

    base = figures(by["none"]) if "none" in by else None
    print(f"summary over repeats: {'role':9} {'runs':>4} {'e-stops':>7} {'skipped med %':>13} "
          f"{'p50 ms':>7} {'p99 ms':>7} {'max ms':>7}   vs none: {'skipped':>8} {'p99':>8}")
    for role in roles:
        sk, p50, p99, mx, n = figures(by[role])
        vs = ("" if base is None or role == "none" or role == "estop" else
              f"{sk - base[0]:+7.2f}% {p99 - base[2]:+7.2f}ms")
        if role == "estop":
            p50 = p99 = mx = float("nan")
        print(f"                      {role:9} {len(by[role]):4d} {n:7d} {sk:13.2f} "
              f"{p50:7.2f} {p99:7.2f} {mx:7.2f}   {'':8} {vs}")
    steal = [r["steal_pct"] for r in results]
    load = [r["load"] for r in results]
    print(f"CPU steal per run {min(steal):.1f}-{max(steal):.1f} %, load (1 min) at each run's "
          f"start {min(load):.1f}-{max(load):.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--tree", type=Path, default=None)
    ap.add_argument("--runs", default="none,viewer,operator")
    ap.add_argument("--repeat", type=int, default=1,
                    help="run the --runs list N times, interleaved; then a summary per role")
    ap.add_argument("--budget", type=float, default=None,
                    help="--request-budget of the controller (e.g. 1e6: the process split "
                    "alone, no budget in effect)")
    args = ap.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        auth = Path(tmp) / "auth"
        init_auth_dir(auth, new_users([("op1", "operator"), ("view", "viewer"),
                                       ("watch", "viewer")]))
        budget = () if args.budget is None else ("--request-budget", f"{args.budget:g}")
        proc = start_controller(Path(tmp) / "state", rig=RIG, tree=args.tree,
                                extra_args=("--auth", str(auth), "--realtime-priority", *budget))
        try:
            def ready() -> bool:
                assert proc.proc.poll() is None, proc.log()
                try:
                    with _client(proc.endpoint, auth, "watch") as c:
                        c.get_config()
                        return True
                except ControllerUnavailable:
                    return False

            assert wait_until(ready, 180.0, poll_s=0.5), proc.log()
            for _ in range(args.repeat):
                for role in args.runs.split(","):
                    results.append(run_once(role, proc.endpoint, auth, args.seconds))
        finally:
            proc.stop()
    tree = f" (controller from {args.tree})" if args.tree else ""
    if args.budget is not None:
        tree += f", --request-budget {args.budget:g}"
    print(f"flood table{tree}: {args.seconds:g} s per run, e-stop put every 0.3 s, "
          f"load avg {os.getloadavg()[0]:.1f} at the end")
    print_runs(results)
    if args.repeat > 1:
        print_summary(results)


if __name__ == "__main__":
    main()
