"""Benchmark: the watch (issue 34) beside a simulated controller (article rig). Prints figures;
not a test.

    .venv/bin/python tests/bench/bench_watch.py [--seconds 60] [--window-s 10]
        [--only timing,normal,changes,trendweek|offline] [--trajectories sine,step,ramp,hold]
        [--changes stiffness,inertia,motor_friction,gain,resonance]

- timing: the loop's tick compute p99 (each Status's, ~2 Hz) in windows of `--timing-s`
  (default 15): `--timing-rounds` blocks (default 10), each a window without the watch and
  one with it at each `--timing-priorities` (default low; `low,idle` compares both), in a
  random order (`--seed`), in the same controller run. Per block, with minus without: the
  paired differences' median with its sign-test 95 % interval, bootstrap intervals of median
  and mean, and whether that is within `--target-us` (0.5) at 95 %; the watch's CPU share.
  `--only timing` alone: `.venv/bin/python tests/bench/bench_watch.py --only timing`
  (10 blocks of one arm: about 8 minutes; not niced: the controller it starts inherits the
  niceness).
- normal: `--seconds` of normal running per demo trajectory with the watch on: alarms raised
  (false alarms), the parts' estimates and how many windows told each.
- changes: each plant change of the issue on the running rig (belt stiffness -40 %, inertia
  +50 %, motor friction x3, drive gain -30 %, a resonance 20 % down: the rig first gets a
  30 Hz payload mode by a sim_fault, the watch is told of it), from a fresh watch each: the
  time from the change to the alarm, the part named, its estimate against the truth; then the
  plant is put back and the watch stopped.
- offline (alone): `--seconds` simulated per trajectory on the compiled offline loop through
  the watch's window code (the suite's ten-minute check), timed against real time.
- trendweek: a week of windows written to the hourly MCAP trend and read back (storage per rig
  per day, the time to read a week for a plot).
The controller runs with --realtime-priority as on a rig; report `uptime` beside the figures.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: helpers, for procs
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))

from procs import Client, start_controller

from controller import protocol as proto
from controller.core.trajectory import default_trajectory

RIG = "watchbench"
REPO = Path(__file__).resolve().parents[2]
#: (name, command, the part that must be named, its true factor).
CHANGES = (
    ("belt stiffness -40 %", proto.SimDrift(belt_stiffness_factor=0.6), "stiffness", 0.6),
    ("inertia +50 %", proto.SimDrift(load_inertia_factor=1.5), "inertia", 1.5),
    ("motor friction x3", proto.SimDrift(motor_friction_factor=3.0), "motor_friction", 3.0),
    ("drive gain -30 %", proto.SimFault(plant_gain=0.7), "gain", 0.7),
    ("resonance 20 % down", proto.SimDrift(resonance_factor=0.8), "resonance", 0.8),
)
#: The extra mode the rig gets (a sim_fault) before the resonance's change, and the watch is
#: told of (`--resonance-hz`: there is no twin): a payload mode at 30 Hz, damping 0.05.
MODE = proto.SimFault(resonance_hz=30.0, resonance_damping=0.05)
BACK = (proto.SimDrift(), proto.SimFault())


class Watch:
    """`dobtune watch` as a subprocess, and a subscriber to its states and alarms."""

    def __init__(self, endpoint: str, window_s: float, trend: Path | None, log: Path,
                 mode: proto.SimFault | None = None, priority: str = "low") -> None:
        cmd = [str(Path(sys.executable).parent / "dobtune"), "watch", "--connect", endpoint,
               "--rig-name", RIG, "--window-s", str(window_s), "--disturbance", "article-rig",
               "--parent-pid", str(os.getpid()), "--priority", priority]
        if mode is not None:
            cmd += ["--resonance-hz", str(mode.resonance_hz), "--resonance-damping",
                    str(mode.resonance_damping)]
        if trend is not None:
            cmd += ["--trend-dir", str(trend)]
        self._log = open(log, "ab")  # noqa: SIM115
        self.proc = subprocess.Popen(cmd, cwd=REPO, stdout=self._log, stderr=subprocess.STDOUT)

    def cpu_s(self) -> float:
        with open(f"/proc/{self.proc.pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._log.close()


class Heard:
    """Drift states, alarms and statuses received. The callbacks keep the raw bytes; they are
    decoded in the bench's thread (msgspec segfaulted here when two Zenoh threads built the
    first decoder of one type at the same time)."""

    def __init__(self, c: Client) -> None:
        self._raw: dict[str, list[tuple[float, bytes]]] = {"state": [], "alarm": [], "status": []}
        self._done: dict[str, list[tuple[float, object]]] = {k: [] for k in self._raw}
        self._lock = threading.Lock()
        s = c.session
        self._subs = [
            s.declare_subscriber(proto.key_drift(RIG), self._keep("state")),
            s.declare_subscriber(proto.key_drift_alarm(RIG), self._keep("alarm")),
            s.declare_subscriber(proto.key_status(RIG), self._keep("status")),
        ]

    def _keep(self, kind: str) -> object:
        def on(sample: object) -> None:
            data = sample.payload.to_bytes()  # type: ignore[attr-defined]
            with self._lock:
                self._raw[kind].append((time.monotonic(), data))
        return on

    def _get(self, kind: str, typ: type) -> list:  # type: ignore[type-arg]
        with self._lock:
            new = self._raw[kind][len(self._done[kind]):]
        for t, data in new:
            self._done[kind].append((t, proto.decode(data, typ)))
        return list(self._done[kind])

    @property
    def states(self) -> list[tuple[float, proto.DriftState]]:
        return self._get("state", proto.DriftState)

    @property
    def alarms(self) -> list[tuple[float, proto.DriftAlarm]]:
        return self._get("alarm", proto.DriftAlarm)

    @property
    def statuses(self) -> list[proto.Status]:
        return [s for _, s in self._get("status", proto.Status)]

    def p99s(self, since: int) -> list[float]:
        return [s.timing.compute_p99_us for s in self.statuses[since:] if s.mode == "running"]


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _paired(d: np.ndarray, target_us: float, rng: np.random.Generator) -> str:
    """The paired differences' median and mean with 95 % intervals (the sign test's for the
    median, distribution-free; a bootstrap's for both), and the one-sided sign test of "the
    cost is at least `target_us`" (pairs below the target, and its p)."""
    n = d.size
    srt = np.sort(d)
    # Sign-test interval: [d_(k), d_(n-k+1)], k the largest with P(Bin(n, 1/2) <= k-1) <= 2.5 %.
    cdf = np.cumsum([math.comb(n, i) for i in range(n + 1)]) / 2.0**n
    k = int(np.sum(cdf <= 0.025))
    sign_ci = (f"[{srt[k - 1]:+.2f}, {srt[n - k]:+.2f}] us (sign test, "
               f"{100 * (1 - 2 * cdf[k - 1]):.1f} %)" if k >= 1 else
               "none (the sign test needs 6 pairs for 95 %)")
    boot = rng.choice(d, size=(20000, n), replace=True)
    med_ci = np.percentile(np.median(boot, axis=1), [2.5, 97.5])
    mean_ci = np.percentile(boot.mean(axis=1), [2.5, 97.5])
    below = int(np.sum(d < target_us))
    p = float(sum(math.comb(n, i) for i in range(below, n + 1)) / 2.0**n)
    hi = srt[n - k] if k >= 1 else float("inf")
    lo = srt[k - 1] if k >= 1 else float("-inf")
    verdict = ("within the target at 95 % (the interval's top is below it)" if hi <= target_us
               else "above the target at 95 % (the interval's bottom is above it)"
               if lo > target_us else "not decided at 95 % (the interval spans the target)")
    return (f"median {np.median(d):+.2f} us, 95 % interval {sign_ci}, bootstrap "
            f"[{med_ci[0]:+.2f}, {med_ci[1]:+.2f}] us; mean {d.mean():+.2f} us, bootstrap 95 % "
            f"[{mean_ci[0]:+.2f}, {mean_ci[1]:+.2f}] us; {below} of {n} pairs below "
            f"+{target_us:g} us (one-sided sign test of a cost of at least {target_us:g} us: "
            f"p = {p:.3g}); {verdict}")


def _timing(c: Client, heard: Heard, endpoint: str, args: argparse.Namespace, tmp: Path
            ) -> None:
    """Blocks (`--timing-rounds`) of one window of `--timing-s` without the watch and one with
    it at each `--timing-priorities`, in a random order within each block (seeded), all in
    the same controller run. A window's figure is the median of its Status intervals' compute
    p99; with the watch, the window starts at its first fitted window (loaded and fitting).
    The load drifts over minutes: each window with the watch is paired with the window without
    it in the same block, and the paired differences get 95 % intervals (`_paired`)."""
    rng = np.random.default_rng(args.seed)
    arms = ["without", *args.timing_priorities.split(",")]
    rows: list[tuple[int, str, float]] = []
    cpus: dict[str, list[tuple[float, int]]] = {a: [] for a in arms[1:]}
    k = 0
    for block in range(args.timing_rounds):
        for arm in rng.permutation(arms):
            k += 1
            watch = None
            if arm != "without":
                watch = Watch(endpoint, args.window_s, None, tmp / "watch-timing.log",
                              priority=str(arm))
                s0 = len(heard.states)
                deadline = time.monotonic() + 300.0
                while len(heard.states) <= s0 and time.monotonic() < deadline:
                    if watch.proc.poll() is not None:
                        raise SystemExit(f"the watch exited ({watch.proc.returncode}): see "
                                         f"{tmp / 'watch-timing.log'}")
                    time.sleep(0.2)  # measured from its first window on: loaded and fitting
                if len(heard.states) <= s0:
                    raise SystemExit("the watch fitted no window within 300 s")
                cpu0, t0, w0 = watch.cpu_s(), time.monotonic(), len(heard.states)
            i0 = len(heard.statuses)
            time.sleep(args.timing_s)
            p = np.asarray(heard.p99s(i0))
            rows.append((block, str(arm), float(np.median(p)) if p.size else float("nan")))
            extra = ""
            if watch is not None:
                cpu = (watch.cpu_s() - cpu0) / (time.monotonic() - t0)
                cpus[str(arm)].append((cpu, len(heard.states) - w0))
                watch.stop()
                extra = (f"; watch CPU {100 * cpu:.1f} % of one core ({cpus[str(arm)][-1][1]} "
                         f"windows fitted)")
            print(f"  block {block + 1}/{args.timing_rounds} window {k}: {arm:7s} p99 "
                  f"{rows[-1][2]:.1f} us (median of {p.size} status intervals' p99){extra}; "
                  f"load {os.getloadavg()[0]:.1f}", flush=True)
    for arm in arms:
        a = np.array([v for _, ar, v in rows if ar == arm])
        name = "without the watch" if arm == "without" else f"with the watch ({arm})"
        print(f"tick compute p99 {name}: median of {a.size} windows of {args.timing_s:g} s "
              f"{np.median(a):.2f} us (windows {np.min(a):.1f}-{np.max(a):.1f} us)")
    without = {b: v for b, ar, v in rows if ar == "without"}
    for arm in arms[1:]:
        d = np.array([v - without[b] for b, ar, v in rows if ar == arm])
        print(f"with ({arm}) minus without, paired within each block: "
              f"{_paired(d, args.target_us, rng)}")
        ws = [w for _, w in cpus[arm]]
        print(f"watch ({arm}) CPU: median {100 * np.median([c for c, _ in cpus[arm]]):.1f} % "
              f"of one core ({sum(ws)} windows fitted in {len(ws)} x {args.timing_s:g} s)")
    print(f"load: {_uptime()}")


def _normal(c: Client, heard: Heard, endpoint: str, args: argparse.Namespace, tmp: Path
            ) -> None:
    for kind in args.trajectories.split(","):
        assert c.command(proto.SetTrajectory(trajectory=default_trajectory(kind))).ok
        watch = Watch(endpoint, args.window_s, tmp / "trend", tmp / f"watch-{kind}.log")
        a0, s0 = len(heard.alarms), len(heard.states)
        time.sleep(args.seconds)
        watch.stop()
        alarms = [a for _, a in heard.alarms[a0:] if not a.cleared]
        states = [s for _, s in heard.states[s0:]]
        told = {p.name: 0 for p in states[0].parts} if states else {}
        for s in states:
            for p in s.parts:
                told[p.name] += p.told
        last = states[-1] if states else None
        est = ", ".join(f"{p.name} {p.value:.3f}+-{p.std:.2g}" for p in last.parts) if last else ""
        print(f"normal {kind:5s}: {args.seconds:g} s, {len(states)} windows, "
              f"{len(alarms)} alarms {[a.part for a in alarms]}; told in windows {told}; "
              f"last {est}; load {os.getloadavg()[0]:.1f}")


def _trend_week(args: argparse.Namespace, tmp: Path) -> None:
    """A week of windows (one per `--window-s`) written as the watch writes them, then read
    back by time range: bytes per rig per day, and the time to read a week for a plot."""
    from controller.recording.trend import TrendWriter, read_trend

    root = tmp / "week"
    t0 = time.time() - 7 * 86400
    t0 -= t0 % 3600
    n = int(7 * 86400 / args.window_s)
    rng = np.random.default_rng(0)
    t_w = time.perf_counter()
    with TrendWriter(root, RIG) as tw:
        for i in range(n):
            e = t0 + i * args.window_s
            v = 1.0 + 0.001 * rng.standard_normal(4)
            tw.write("/drift/residual", e, {
                "plant_residual_rms_deg_s": 0.004, "fitted_residual_rms_deg_s": 0.004,
                "loop_measured_rms_deg": 0.03, "loop_predicted_rms_deg": 0.03,
                "loop_residual_rms_deg": 0.003, "delay_ticks": 0})
            tw.write("/drift/parts", e, {
                **{k: float(x) for k, x in zip(("gain", "stiffness", "inertia",
                                                 "motor_friction"), v, strict=True)},
                **{k + "_std": 0.001 for k in ("gain", "stiffness", "inertia",
                                               "motor_friction")},
                **{k + "_state": "ok" for k in ("gain", "stiffness", "inertia",
                                                "motor_friction")}})
            tw.write("/drift/health", e, {"config_version": 1, "alarms": [],
                                          "compute_p99_us": 40.0, "skipped_ticks": 0,
                                          "mode": "running"})
    write_s = time.perf_counter() - t_w
    size = sum(f.stat().st_size for f in (root / RIG).glob("*.mcap"))
    t_r = time.perf_counter()
    pts = read_trend(root, RIG, t0, t0 + 7 * 86400, "/drift/parts")
    read_s = time.perf_counter() - t_r
    print(f"trend: a week of {args.window_s:g} s windows = {n} windows x 3 channels in "
          f"{len(list((root / RIG).glob('*.mcap')))} hourly files, {size / 7 / 1e6:.2f} MB per "
          f"rig per day; written in {write_s:.1f} s; a week's /drift/parts read back "
          f"({len(pts)} points) in {read_s:.1f} s; load {os.getloadavg()[0]:.1f}")


def _changes(c: Client, heard: Heard, endpoint: str, args: argparse.Namespace, tmp: Path
             ) -> None:
    assert c.command(proto.SetTrajectory(trajectory=default_trajectory("sine"))).ok
    wanted = args.changes.split(",") if args.changes else None
    for name, cmd, part, truth in CHANGES:
        if wanted is not None and part not in wanted:
            continue
        mode = MODE if part == "resonance" else None
        if mode is not None:
            assert c.command(mode).ok
        watch = Watch(endpoint, args.window_s, None, tmp / f"watch-{part}.log", mode)
        s0 = len(heard.states)
        deadline = time.monotonic() + 120.0
        while len(heard.states) < s0 + 2 and time.monotonic() < deadline:
            time.sleep(0.2)  # two windows of normal running first
        a0 = len(heard.alarms)
        t_change = time.monotonic()
        assert c.command(cmd).ok
        got = None
        while time.monotonic() < t_change + args.detect_timeout_s:
            new = [(t, a) for t, a in heard.alarms[a0:] if not a.cleared]
            if new:
                got = new[0]
                break
            time.sleep(0.2)
        if got is None:
            last = heard.states[-1][1] if heard.states else None
            print(f"{name:22s}: NO alarm within {args.detect_timeout_s:g} s; last state "
                  f"{[(p.name, round(p.value, 3), p.state) for p in last.parts] if last else '-'}")
        else:
            t, a = got
            err = (a.value - truth) / truth
            print(f"{name:22s}: alarm after {t - t_change:5.1f} s, part {a.part} "
                  f"({'right' if a.part == part else 'WRONG, expected ' + part}), estimate "
                  f"x{a.value:.3f} +-{a.std:.2g} vs x{truth:g} ({100 * err:+.1f} %); gate on "
                  f"the drifted estimate: {a.gate_verdict or '-'}; load "
                  f"{os.getloadavg()[0]:.1f}")
        watch.stop()
        for back in BACK:
            assert c.command(back).ok
        time.sleep(2.0)


def _offline(args: argparse.Namespace) -> None:
    """The suite's check, timed: `--seconds` simulated per trajectory through the watch's own
    window code on the compiled offline loop (article rig, all disturbances and sensor noise),
    no change: alarms, windows with a part outside, and how much faster than real time."""
    from controller.gate.knowledge import COMMISSIONING_BOUND
    from controller.sim.rig_disturbances import rig_setup
    from controller.watch.offline import run_offline_watch

    setup = rig_setup(("article-rig",))
    for kind in args.trajectories.split(","):
        t = time.perf_counter()
        run = run_offline_watch(setup, default_trajectory(kind), args.seconds,
                                bound=COMMISSIONING_BOUND, window_s=args.window_s)
        wall = time.perf_counter() - t
        outside = sum(any("(outside" in ln or "(alarm" in ln for ln in r.verdict.lines)
                      for _, r in run.windows)
        fit = [r.fit_s for _, r in run.windows]
        print(f"offline {kind:5s}: {args.seconds:g} simulated s, {len(run.windows)} windows, "
              f"{len(run.alarms)} alarms, {outside} windows with a part outside; wall "
              f"{wall:.0f} s ({args.seconds / wall:.1f}x real time), fit per window median "
              f"{np.median(fit):.2f} s; load {os.getloadavg()[0]:.1f}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--timing-s", type=float, default=15.0,
                    help="timing: seconds per window without or with the watch")
    ap.add_argument("--timing-rounds", type=int, default=10,
                    help="timing: blocks, each a window without the watch and one with it at "
                         "each --timing-priorities, in a random order")
    ap.add_argument("--timing-priorities", default="low",
                    help="timing: the watch's --priority in the windows with it "
                         "(comma-separated: low, idle)")
    ap.add_argument("--target-us", type=float, default=0.5,
                    help="timing: the stated bound on the watch's cost to the p99")
    ap.add_argument("--seed", type=int, default=0, help="timing: the blocks' orders")
    ap.add_argument("--window-s", type=float, default=10.0)
    ap.add_argument("--detect-timeout-s", type=float, default=120.0)
    ap.add_argument("--only", default="timing,normal,changes")
    ap.add_argument("--trajectories", default="sine,step,ramp,hold")
    ap.add_argument("--changes", default="",
                    help="changes: only these parts (e.g. resonance), comma-separated")
    args = ap.parse_args()
    print(f"start: {_uptime()}")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if args.only == "trendweek":  # no controller needed
            _trend_week(args, tmp)
            return
        if args.only == "offline":
            _offline(args)
            return
        proc = start_controller(tmp / "state", rig=RIG, extra_args=(
            "--realtime-priority", "--disturbance", "article-rig"))
        try:
            with Client(proc.endpoint, RIG, timeout_s=30.0) as c:
                c.wait_ready(proc, timeout_s=600.0)  # start-up: 30-60 s at load 15
                heard = Heard(c)
                for what in args.only.split(","):
                    if what == "trendweek":
                        _trend_week(args, tmp)
                        continue
                    {"timing": _timing, "normal": _normal, "changes": _changes}[what](
                        c, heard, proc.endpoint, args, tmp)
        finally:
            proc.stop()


if __name__ == "__main__":
    main()
