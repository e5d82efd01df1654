"""Recording cost: MCAP write throughput against the loop's 1 kHz, file size per hour, and the
loop's timing with and without a recording running.

    nice -n 5 .venv/bin/python tests/bench/bench_record.py --live-s 600   # the issue's figures

1. Synthetic: 60 s of StateBatches (1 kHz, batches of 20) written with `Recorder`:
   messages per second and bytes per sample -> MB per hour.
2. Live (with --live-s > 0): a simulated controller process started as `dobtune demo` starts
   it (--realtime adds --realtime-priority); its loop timing from every Status (period p99
   per status interval, overruns, skipped ticks, samples the publisher dropped) for
   --baseline-s without, during a `dobtune record` of --live-s seconds (its own process), and
   --baseline-s after; the recording's samples and gaps, file size per hour, sustained write
   rate and the recorder's CPU, and the time to open, compute the metrics of and report
   (`dobtune report`) the file.
"""

from __future__ import annotations

import argparse
import io
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: helpers, for procs
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))

from controller import protocol as proto
from controller.recording.mcap_io import Recorder, read_recording


def synthetic(seconds: float = 60.0) -> None:
    n = round(seconds * 1000)
    batches = []
    for seq0 in range(0, n, 20):
        t = np.arange(seq0, seq0 + 20) / 1000.0
        cols = [t, 5 * np.sin(0.5 * t), 5 * np.sin(0.5 * t) + 1e-3, np.cos(t), np.cos(t),
                np.cos(t), 0.01 * t, 1e-3 * np.ones(20)]
        batches.append(proto.state_batch(rig="b", seq0=seq0, rate_hz=1000.0, config_version=1,
                                         columns=[c.tolist() for c in cols], epoch_s=1.7e9,
                                         mode="running"))
    buf = io.BytesIO()
    t0 = time.perf_counter()
    with Recorder(buf) as r:
        for b in batches:
            r.state(b)
    dt = time.perf_counter() - t0
    size = len(buf.getvalue())
    print(f"synthetic: {n} samples in {dt:.2f} s = {n / dt:,.0f} messages/s "
          f"({n / dt / 1000:.1f}x the loop's 1 kHz); {size / n:.1f} B/sample -> "
          f"{size / seconds * 3600 / 1e6:.0f} MB per hour")


def _recorder_cmd(endpoint: str, rig: str, out: Path, seconds: float) -> list[str]:
    return [sys.executable, "-c", "from controller.cli.main import dobtune_main; "
            "import sys; sys.exit(dobtune_main(sys.argv[1:]))", "record",
            "--connect", endpoint, "--rig-name", rig, "--out", str(out),
            "--duration", str(seconds)]


def _timing(c: Any, seconds: float, until: Callable[[], bool] | None = None) -> dict[str, float]:
    """The loop's period p99 (each Status covers its last interval) over `seconds` (or until
    `until()`): median and worst of the per-interval p99, overruns and skipped ticks."""
    p99: list[float] = []
    st0 = c.fresh_status()
    end = time.monotonic() + seconds
    st = st0
    while time.monotonic() < end and not (until is not None and until()):
        st = c.fresh_status()
        p99.append(st.timing.period_p99_us)
    t0, t1 = st0.timing, st.timing
    return {"p99_median_us": statistics.median(p99), "p99_worst_us": max(p99),
            "intervals": len(p99), "overruns": t1.overruns - t0.overruns,
            "skipped": t1.skipped_ticks - t0.skipped_ticks,
            "dropped": t1.dropped_samples - t0.dropped_samples,
            "ticks": t1.ticks - t0.ticks}


def _line(name: str, t: dict[str, float], period_us: float) -> str:
    return (f"  {name}: period p99 {t['p99_median_us']:.0f} us median of {t['intervals']} "
            f"status intervals (jitter p99 {t['p99_median_us'] - period_us:+.0f} us), worst "
            f"interval {t['p99_worst_us']:.0f} us; {t['ticks']} ticks, {t['overruns']} "
            f"overruns, {t['skipped']} skipped, {t['dropped']} samples dropped by the "
            "publisher")


def live(seconds: float, baseline_s: float, realtime: bool) -> None:
    """A running simulated controller (as `dobtune demo` starts it), recorded by `dobtune
    record` in its own process for `seconds`; the loop's timing before and during."""
    from procs import Client, free_port, start_controller

    from controller.cli.report import report_main
    from controller.recording.report import metrics

    with tempfile.TemporaryDirectory() as d:
        extra = ("--realtime-priority",) if realtime else ()
        proc = start_controller(Path(d) / "state", port=free_port(), extra_args=extra)
        try:
            with Client(proc.endpoint, proc.rig) as c:
                c.wait_ready(proc, timeout_s=120.0)  # start-up is slow on a loaded machine
                period_us = 1e6 / c.get_config().config.rate_hz
                _timing(c, 5.0)  # settle after start-up
                base = _timing(c, baseline_s)
                out = Path(d) / "live.mcap"
                cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                t0 = time.monotonic()
                r = subprocess.Popen(_recorder_cmd(proc.endpoint, proc.rig, out, seconds),
                                     stdout=subprocess.PIPE, text=True)
                during = _timing(c, seconds + 60.0, until=lambda: r.poll() is not None)
                said, _ = r.communicate(timeout=120)
                wall = time.monotonic() - t0
                cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                after = _timing(c, baseline_s)
            cpu_s = (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime)
            t_open = time.perf_counter()
            got = read_recording(out)
            open_s = time.perf_counter() - t_open
            t_an = time.perf_counter()
            m = metrics(got)
            analyse_s = time.perf_counter() - t_an
            t_rep = time.perf_counter()
            buf = io.StringIO()
            code = report_main([out], Path(d) / "report.html", None, buf)
            report_s = time.perf_counter() - t_rep
            seq = got.state["seq"]
            lost_seq = int(np.sum(np.diff(seq) - 1)) if seq.size else -1
            size = out.stat().st_size
            span_s = float(got.log_time_s[-1] - got.log_time_s[0]) if got.n > 1 else 0.0
            print(f"live ({seconds:g} s recording, loop at {1e6 / period_us:g} Hz"
                  f"{', SCHED_FIFO' if realtime else ''}):")
            print(f"  recorder said: {said.strip()}")
            print(f"  recorded {got.n} samples over {span_s:.1f} s of loop time; gaps: "
                  f"{lost_seq} samples missing in seq, {m.gaps} in gap events")
            print(f"  file {size / 1e6:.1f} MB = {size / got.n:.1f} B/sample -> "
                  f"{size / span_s * 3600 / 1e6:.0f} MB per hour")
            print(f"  write throughput: {got.n / wall:,.0f} messages/s sustained (the loop's "
                  f"{1e6 / period_us:,.0f}/s); the recorder process used {cpu_s:.1f} s CPU = "
                  f"{cpu_s / wall * 100:.0f} % of one core -> capacity ~{got.n / cpu_s:,.0f} "
                  "messages per CPU second")
            print(_line("without recording (before)", base, period_us))
            print(_line("during the recording", during, period_us))
            print(_line("without recording (after)", after, period_us))
            print(f"  open (read_recording) {open_s:.1f} s, metrics {analyse_s:.2f} s; "
                  f"`dobtune report` (open + metrics + HTML) {report_s:.1f} s, exit {code}: "
                  f"{buf.getvalue().strip()}")
        finally:
            proc.stop()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--live-s", type=float, default=0.0,
                    help="seconds of live recording (the issue's measurement: 600)")
    ap.add_argument("--baseline-s", type=float, default=60.0,
                    help="loop timing measured this long before and after the recording")
    ap.add_argument("--realtime", action="store_true",
                    help="controller with --realtime-priority (the demo runs without)")
    a = ap.parse_args()
    synthetic()
    if a.live_s > 0:
        live(a.live_s, a.baseline_s, a.realtime)

