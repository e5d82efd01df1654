"""Opening recordings: a 10-minute recording listed (read + metrics, as the Recordings tab's
row), two overlaid (the tab's compare: both read, aligned, metrics), and `dobtune report`;
the general decoder (before: the chunk walk, a msgspec Struct per /state message, a Python list
per column) against the column scan (after: `state_scan`), in one run. `--library` adds the
`mcap` library's reader (the reader before the chunk walk; slow).

    .venv/bin/python tests/bench/bench_open_recording.py [--minutes 10] [--runs 2]

The recordings (1 kHz state, a status per second, like `dobtune record`) are written once and
kept in /tmp/dobtune-bench-recordings/. The machine's load average is printed.
"""

from __future__ import annotations

import argparse
import io
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from controller import protocol as proto
from controller.cli.report import report_main
from controller.recording import mcap_io
from controller.recording.compare import align_runs, summary_row
from controller.recording.mcap_io import Recorder, read_recording, read_recordings
from controller.recording.report import metrics

CACHE = Path("/tmp/dobtune-bench-recordings")


def write(path: Path, minutes: float, phase: float) -> None:
    n = round(minutes * 60_000)
    tmp = path.with_suffix(".part")
    with Recorder(tmp, rig="bench") as r:
        r.config(1, {"q_cutoff_hz": 0.5}, t_s=1.7e9)
        for s in range(0, n, 20):
            t = np.arange(s, s + 20) / 1000.0
            ref = 5 * np.sin(0.5 * t + phase)
            pos = ref - 0.02 * np.sin(7 * t)
            cols = [t, ref, pos, np.cos(t), np.cos(t), np.cos(t), 0.01 * np.sin(t), ref - pos]
            r.state(proto.state_batch(rig="bench", seq0=s, rate_hz=1000.0, config_version=1,
                                      columns=[c.tolist() for c in cols], epoch_s=1.7e9,
                                      mode="running"))
    tmp.rename(path)


def _library_messages(path: Path) -> Iterator[tuple[str, str, int, bytes]]:
    """The reader before: the `mcap` library's."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            yield channel.topic, schema.name if schema else "", message.log_time, message.data


def _timed(fn: Callable[[], object]) -> tuple[float, float]:
    """(wall, CPU) seconds: the CPU time of this process is the figure a loaded machine
    disturbs least."""
    t0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - t0, time.process_time() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--library", action="store_true", help="also the mcap library's reader")
    a = ap.parse_args()
    CACHE.mkdir(exist_ok=True)
    files = [CACHE / f"run{i}-{a.minutes:g}min.mcap" for i in (1, 2)]
    for i, f in enumerate(files):
        if not f.exists():
            print(f"writing {f} ...", flush=True)
            write(f, a.minutes, 0.1 * i)
    print(f"{files[0].name}: {files[0].stat().st_size / 1e6:.1f} MB")

    scanned = mcap_io._read_scanned

    def listed() -> None:
        summary_row(files[0].name, (r := read_recording(files[0])).configs, metrics(r))

    def overlaid() -> None:
        # after: both at once, as the Recordings tab's compare; before: one after the other
        ra, rb = (read_recordings(files) if mcap_io._read_scanned is scanned
                  else [read_recording(f) for f in files])
        cols = [(r.state["t_s"], r.state["ref_deg"], r.state["error_deg"]) for r in (ra, rb)]
        align_runs(*cols[0], *cols[1])
        for name, r in ((files[0].name, ra), (files[1].name, rb)):
            summary_row(name, r.configs, metrics(r))

    def report() -> None:
        code = report_main([files[0]], CACHE / "report.html", None, io.StringIO())
        assert code == 0

    readers: dict[str, Callable[[], None]] = {
        "general": lambda: setattr(mcap_io, "_read_scanned", lambda path: None),
        "scan": lambda: setattr(mcap_io, "_read_scanned", scanned),
    }
    if a.library:
        def library() -> None:
            mcap_io._read_scanned = lambda path: None  # type: ignore[assignment]
            mcap_io._messages = _library_messages  # type: ignore[assignment]
        readers = {"mcap lib": library, **readers}
    chunk_walk = mcap_io._messages
    read_recording(files[0])  # numba's cache loaded once, outside the timing
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; {os.cpu_count()} CPUs")
    print(f"{'best of ' + str(a.runs):>14s}" + "".join(f"{n + ' wall (CPU)':>24s}"
                                                    for n in readers))
    for what, fn in (("list one", listed), ("overlay two", overlaid), ("dobtune report", report)):
        times = []
        for use in readers.values():
            use()
            times.append(min((_timed(fn) for _ in range(a.runs)), key=lambda wc: wc[0]))
            mcap_io._messages = chunk_walk  # type: ignore[assignment]
            mcap_io._read_scanned = scanned  # type: ignore[assignment]
        print(f"{what:>14s}" + "".join(f"{w:14.2f} s ({c:5.2f} s)" for w, c in times))
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} (at the end)")


if __name__ == "__main__":
    main()
