"""Fleet through a Zenoh router (issue 16): how many simulated 1 kHz rigs one router carries
before a sample is lost, request latency through the router against peer to peer, and the
dashboard's CPU with the fleet overview open.

    .venv/bin/python tests/bench/bench_fleet.py [--rigs 1 2 3 4] [--window-s 10]

Per N: a router and N simulated controllers behind it (`dobtune demo --rigs N`'s processes); a
subscriber through the router counts every state sample per rig and the gaps in the sequence
numbers (lost on the way), and reads each controller's own count of skipped ticks (a loop that
could not keep up: the machine, not the router). Latency: the config query's round trip, p50 /
p99 of 200, through the router and straight to a controller. The dashboard: process CPU time
over the window with and without the Fleet tab (no browser attached: the server's own work).
"""

from __future__ import annotations

import argparse
import contextlib
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import zenoh

from controller import protocol as proto
from controller.client import ClientOptions, ControllerClient, ControllerUnavailable
from controller.client.session import zenoh_config
from server.dashboard.demo import DemoOptions, fleet_processes


def free_base_port(n: int) -> int:
    """A port p with p .. p+n free (roughly: bound and released one by one)."""
    while True:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            p = int(s.getsockname()[1])
        if p + n < 65000 and all(_free(p + i) for i in range(n + 1)):
            return p


def _free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


def wait_ready(ep: str, rigs: list[str], timeout_s: float = 90.0) -> None:
    deadline = time.monotonic() + timeout_s
    for rig in rigs:
        with ControllerClient(ClientOptions(connect=(ep,), rig_name=rig)) as c:
            while c.status is None or c.status.mode != "running":
                if time.monotonic() > deadline:
                    raise SystemExit(f"{rig} not running within {timeout_s} s")
                time.sleep(0.1)


def count_samples(router_ep: str, rigs: list[str], window_s: float) -> dict[str, Any]:
    session = zenoh.open(zenoh_config((), [router_ep]))
    got: dict[str, int] = dict.fromkeys(rigs, 0)
    gaps: dict[str, int] = dict.fromkeys(rigs, 0)
    last: dict[str, int] = {}
    skipped: dict[str, list[int]] = {r: [] for r in rigs}
    try:
        sub = session.declare_subscriber(f"{proto.KEY_PREFIX}/*/state",
                                         zenoh.handlers.FifoChannel(1 << 16))
        st = session.declare_subscriber(f"{proto.KEY_PREFIX}/*/status",
                                        zenoh.handlers.FifoChannel(4096))
        t_end = time.monotonic() + window_s
        while time.monotonic() < t_end:
            for s in iter(sub.try_recv, None):
                b = proto.decode(s.payload.to_bytes(), proto.StateBatch)
                n = len(b.t_s)
                if b.rig in last and b.seq0 > last[b.rig]:
                    gaps[b.rig] += b.seq0 - last[b.rig]
                last[b.rig] = b.seq0 + n
                got[b.rig] = got.get(b.rig, 0) + n
            for s in iter(st.try_recv, None):
                x = proto.decode(s.payload.to_bytes(), proto.Status)
                skipped.setdefault(x.rig, []).append(x.timing.skipped_ticks)
            time.sleep(0.005)
        sub.undeclare()
        st.undeclare()
    finally:
        session.close()
    return {"samples": got, "lost": gaps,
            "skipped": {r: (v[-1] - v[0]) if len(v) > 1 else 0 for r, v in skipped.items()}}


def extra_state_latency_ms(router_ep: str, direct_ep: str, rig: str,
                           window_s: float) -> tuple[float, float, int]:
    """The same state batches received straight from the controller and through the router,
    in one process: p50 / p99 of (arrival via router - arrival direct), and batches compared."""
    arrivals: dict[str, dict[int, float]] = {"router": {}, "direct": {}}
    sessions = {"router": zenoh.open(zenoh_config((), [router_ep])),
                "direct": zenoh.open(zenoh_config((), [direct_ep]))}
    subs = []
    try:
        for name, session in sessions.items():
            def on_sample(sample: Any, into: dict[int, float] = arrivals[name]) -> None:
                t = time.perf_counter()
                b = proto.decode(sample.payload.to_bytes(), proto.StateBatch)
                into[b.seq0] = t
            subs.append(session.declare_subscriber(proto.key_state(rig),
                                                   zenoh.handlers.Callback(on_sample)))
        time.sleep(window_s)
    finally:
        for sub in subs:
            sub.undeclare()
        for session in sessions.values():
            session.close()
    both = sorted(set(arrivals["router"]) & set(arrivals["direct"]))
    d = sorted((arrivals["router"][k] - arrivals["direct"][k]) * 1000 for k in both)
    if not d:
        return float("nan"), float("nan"), 0
    return statistics.median(d), d[int(0.99 * (len(d) - 1))], len(d)


def rtt_ms(ep: str, rig: str, n: int = 200) -> tuple[float, float, int]:
    """p50, p99 of the answered queries, and how many got no reply within 3 s."""
    times = []
    unanswered = 0
    with ControllerClient(ClientOptions(connect=(ep,), rig_name=rig)) as c:
        for _ in range(n + 1):
            t0 = time.perf_counter()
            try:
                c.get_config()
            except ControllerUnavailable:
                unanswered += 1
                continue
            times.append((time.perf_counter() - t0) * 1000)
    times = sorted(times[1:])
    return statistics.median(times), times[int(0.99 * (len(times) - 1))], unanswered


def dashboard_cpu(router_ep: str, window_s: float, fleet: bool) -> float:
    from server.dashboard.app import Dashboard, DashboardOptions

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    opts = DashboardOptions(connect=(router_ep,), rig_name="rig1", port=port, verbose=False,
                            fleet=fleet)
    with Dashboard(opts):
        time.sleep(3.0)  # settle: the first status, the first evaluation
        c0, t0 = time.process_time(), time.monotonic()
        time.sleep(window_s)
        return 100.0 * (time.process_time() - c0) / (time.monotonic() - t0)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rigs", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--window-s", type=float, default=10.0)
    args = ap.parse_args()
    print(f"{'rigs':>4} {'samples/s per rig':>18} {'lost':>6} {'loop skipped':>13} "
          f"{'rtt router p50/p99 ms':>22} {'rtt direct p50/p99 ms':>22}")
    for n in args.rigs:
        base = free_base_port(n)
        router_ep = f"tcp/127.0.0.1:{base}"
        with tempfile.TemporaryDirectory() as root, contextlib.ExitStack() as stack:
            stack.enter_context(fleet_processes(
                DemoOptions(zenoh_port=base, rigs=n, log_level="warning"), Path(root)))
            rigs = [f"rig{i}" for i in range(1, n + 1)]
            try:
                wait_ready(router_ep, rigs)
            except ControllerUnavailable as exc:
                print(f"{n}: not ready: {exc}")
                continue
            r = count_samples(router_ep, rigs, args.window_s)
            rate = statistics.mean(r["samples"][x] for x in rigs) / args.window_s
            lost = sum(r["lost"].values())
            skipped = sum(r["skipped"].values())
            via = rtt_ms(router_ep, "rig1")
            direct = rtt_ms(f"tcp/127.0.0.1:{base + 1}", "rig1")
            print(f"{n:>4} {rate:>18.0f} {lost:>6} {skipped:>13} "
                  f"{via[0]:>10.2f} / {via[1]:<9.2f} {direct[0]:>10.2f} / {direct[1]:<9.2f}"
                  f"  (no reply: {via[2]} via the router, {direct[2]} direct)", flush=True)
            lat = extra_state_latency_ms(router_ep, f"tcp/127.0.0.1:{base + 1}", "rig1",
                                         args.window_s)
            print(f"     state through the router vs straight, same batches ({lat[2]}): "
                  f"+{lat[0]:.2f} ms p50, +{lat[1]:.2f} ms p99", flush=True)
            if n == args.rigs[-1] or n == 3:
                off = dashboard_cpu(router_ep, args.window_s, fleet=False)
                on = dashboard_cpu(router_ep, args.window_s, fleet=True)
                print(f"     dashboard CPU with {n} rigs: {off:.1f} % without the Fleet tab, "
                      f"{on:.1f} % with it (no browser attached)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
