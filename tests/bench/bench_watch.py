"""Benchmark: the watch (issue 34) beside a simulated controller (article rig). Prints figures;
not a test.

    .venv/bin/python tests/bench/bench_watch.py [--seconds 60] [--window-s 10]
        [--only timing,normal,changes,trendweek|offline] [--trajectories sine,step,ramp,hold]
        [--changes stiffness,inertia,motor_friction,gain,resonance]

- timing: the loop's tick compute p99 with and without the watch, in the same controller run,
  from every tick's compute time (the controller runs with a probe on its timing history,
  tests/bench/tick_probe.py). `--timing-rounds` blocks (default 6) of four windows of
  `--timing-s` (default 15): without, with, with, without the watch (one `dobtune watch
  --priority --timing-priority` per block, measured from its first fitted window on, stopped
  and exited before the last window). Printed: the pooled p50/p99/p99.9 of all ticks per arm,
  with minus without, and its 95 % interval from a bootstrap over whole blocks (windows near in
  time share the load), and whether the p99's interval lies within +-`--target-us` (0.5).
  `nice -n 10 .venv/bin/python tests/bench/bench_watch.py --only timing` (about 8 minutes;
  the loop's thread is SCHED_FIFO whatever the niceness).
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

import tick_probe
from procs import Client, start_controller
from tick_probe import Probe, block_bootstrap, histogram

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
#: After the watch has exited, before the next window without it.
SETTLE_S = 2.0
#: After the controller is ready, before the first window.
WARMUP_S = 15.0
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


class Decoy(Watch):
    """A control for `--only timing`: a process of the watch's niceness that burns `share` of
    a core (in bursts of 0.1 s) and has no Zenoh session: is a change in the tick the watch's
    connection to the loop, or only another busy process on the machine?"""

    def __init__(self, share: float) -> None:  # not Watch.__init__: no watch started
        code = ("import os, time\nos.nice(10)\nwhile True:\n    t = time.perf_counter()\n"
                f"    while time.perf_counter() - t < 0.1 * {share!r}: pass\n"
                f"    time.sleep(0.1 * (1 - {share!r}))\n")
        self._log = open(os.devnull, "ab")  # noqa: SIM115
        self.proc = subprocess.Popen([sys.executable, "-c", code], stdout=self._log,
                                     stderr=subprocess.STDOUT)


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


def _timing(c: Client, heard: Heard, endpoint: str, args: argparse.Namespace, tmp: Path,
            probe: Probe) -> None:
    """`--timing-rounds` blocks, each four windows of `--timing-s` in the order without, with,
    with, without (symmetric in time: a load drifting linearly over the block weighs on both
    arms alike), all in the same controller run. Per window the controller's own per-tick
    compute times (`tick_probe`), all of them, not the statuses' p99s. With the watch: one
    `dobtune watch` process per block, started after the first window and measured from its
    first fitted window on (loaded and fitting); stopped (exited) after the third, then
    `SETTLE_S` before the fourth. The figure: the p99 of all ticks with the watch minus that of
    all ticks without it, with a 95 % interval from a bootstrap over whole blocks (windows near
    in time share the load; resampling blocks keeps that dependence in)."""
    rng = np.random.default_rng(args.seed)
    hists: dict[str, list[np.ndarray]] = {"without": [], "with": []}
    win_p99: dict[str, list[float]] = {"without": [], "with": []}
    cpus: list[float] = []
    starts: list[float] = []
    missed = {"without": 0, "with": 0}
    periods: dict[str, list[float]] = {"without": [], "with": []}
    t_start = time.monotonic()

    def window(arm: str) -> np.ndarray:
        i0 = len(heard.statuses)
        probe.mark()
        time.sleep(args.timing_s)
        x, period = probe.dump()
        if args.timing_save:
            k = sum(len(v) for v in win_p99.values())
            np.save(Path(args.timing_save) / f"window{k:02d}-{arm}.npy", np.stack([x, period]))
        missed[arm] += int(np.rint(period.sum() / 1e3)) - period.size  # deadlines given up
        periods[arm].append(float(np.percentile(np.abs(period - 1e3), 99)))
        modes = {s.mode for s in heard.statuses[i0:]}
        if modes != {"running"}:
            raise SystemExit(f"the loop was not only running in a window: {modes}")
        win_p99[arm].append(float(np.percentile(x, 99)))
        print(f"    {arm:7s} {x.size} ticks: p50 {np.percentile(x, 50):.1f} p99 "
              f"{win_p99[arm][-1]:.1f} p99.9 {np.percentile(x, 99.9):.1f} us; start jitter "
              f"p99 {periods[arm][-1]:.0f} us; load "
              f"{os.getloadavg()[0]:.1f}", flush=True)
        return x

    time.sleep(WARMUP_S)  # the controller's start-up work (its workers' first jobs) done
    for block in range(args.timing_rounds):
        print(f"  block {block + 1}/{args.timing_rounds} ({time.monotonic() - t_start:.0f} s)",
              flush=True)
        a = [window("without")]
        t_w = time.monotonic()
        watch: Watch | Decoy
        if args.timing_against == "decoy":
            watch = Decoy(args.timing_decoy_share)
            time.sleep(SETTLE_S)
        else:
            watch = Watch(endpoint, args.window_s, None, tmp / "watch-timing.log",
                          priority=args.timing_priority)
        s0 = len(heard.states)
        deadline = time.monotonic() + 300.0
        fits = args.timing_against == "watch"  # a decoy fits nothing
        while fits and len(heard.states) <= s0 and time.monotonic() < deadline:
            if watch.proc.poll() is not None:
                raise SystemExit(f"the watch exited ({watch.proc.returncode}): see "
                                 f"{tmp / 'watch-timing.log'}")
            time.sleep(0.2)
        if fits and len(heard.states) <= s0:
            raise SystemExit("the watch fitted no window within 300 s")
        starts.append(time.monotonic() - t_w)
        cpu0, t0 = watch.cpu_s(), time.monotonic()
        b = [window("with"), window("with")]
        cpus.append((watch.cpu_s() - cpu0) / (time.monotonic() - t0))
        watch.stop()
        time.sleep(SETTLE_S)
        a.append(window("without"))
        hists["without"].append(histogram(np.concatenate(a)))
        hists["with"].append(histogram(np.concatenate(b)))
    wh, woh = np.array(hists["with"]), np.array(hists["without"])
    print(f"{args.timing_rounds} blocks, {2 * args.timing_rounds} windows of {args.timing_s:g} s "
          f"per arm ({int(woh.sum())} ticks without, {int(wh.sum())} with), "
          f"{time.monotonic() - t_start:.0f} s; the watch's start to its first window: median "
          f"{np.median(starts):.1f} s; its CPU: median {100 * np.median(cpus):.1f} % of one core")
    for arm in ("without", "with"):
        v = win_p99[arm]
        print(f"  windows' p99 {arm:7s}: {min(v):.1f}-{max(v):.1f} us (median {np.median(v):.1f}); "
              f"the period's deviation p99 {min(periods[arm]):.0f}-{max(periods[arm]):.0f} us; "
              f"{missed[arm]} deadlines given up (skipped ticks)")
    for q in (0.5, 0.99, 0.999):
        w, wo, d, lo, hi = block_bootstrap(wh, woh, q, rng)
        line = (f"tick compute p{100 * q:g} of all ticks: with the watch {w:.2f} us, without "
                f"{wo:.2f} us; with minus without {d:+.2f} us, 95 % interval [{lo:+.2f}, "
                f"{hi:+.2f}] us (bootstrap over {wh.shape[0]} blocks)")
        if q == 0.99:
            t = args.target_us
            line += ("; WITHIN" if -t <= lo and hi <= t else "; NOT within") + (
                f" +-{t:g} us at 95 %" + ("" if hi <= t else
                                          f" (the top is {hi - t:+.2f} us past +{t:g})"))
        print(line)
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
    ap.add_argument("--timing-rounds", type=int, default=6,
                    help="timing: blocks, each windows without, with, with, without the watch")
    ap.add_argument("--timing-priority", default="low", choices=("low", "idle"),
                    help="timing: the watch's --priority in the windows with it")
    ap.add_argument("--timing-against", default="watch", choices=("watch", "decoy"),
                    help="timing: the windows 'with' run the watch, or a decoy process of "
                         "its niceness burning --timing-decoy-share of a core (a control)")
    ap.add_argument("--timing-decoy-share", type=float, default=0.1)
    ap.add_argument("--timing-save", default="",
                    help="timing: a directory for each window's ticks (compute_us, period_us)")
    ap.add_argument("--target-us", type=float, default=0.5,
                    help="timing: the stated bound on the watch's cost to the p99")
    ap.add_argument("--seed", type=int, default=0, help="timing: the bootstrap's")
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
        fifo = tmp / "tick-probe"
        os.mkfifo(fifo)
        os.environ["DOBTUNE_TICK_PROBE"] = str(fifo)  # the controller's probe reads it
        proc = start_controller(tmp / "state", rig=RIG, python_code=tick_probe.CODE,
                                extra_args=("--realtime-priority", "--disturbance",
                                            "article-rig", "--no-watch"))
        try:
            with Client(proc.endpoint, RIG, timeout_s=30.0) as c:
                c.wait_ready(proc, timeout_s=600.0)  # start-up: 30-60 s at load 15
                heard = Heard(c)
                for what in args.only.split(","):
                    if what == "trendweek":
                        _trend_week(args, tmp)
                        continue
                    if what == "timing":
                        _timing(c, heard, proc.endpoint, args, tmp, Probe(fifo, tmp))
                        continue
                    {"normal": _normal, "changes": _changes}[what](
                        c, heard, proc.endpoint, args, tmp)
        finally:
            proc.stop()


if __name__ == "__main__":
    main()
