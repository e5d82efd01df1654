"""The Trends view on a week (issue 34: "storage per rig per day of the trends and the time to
plot a week"): a synthetic week at the watch's own rate (one window every 10 s, the four
channels as the watch writes them, tests/trend_week.py), then

- storage per rig per day (the hourly MCAP files' bytes / 7);
- a week read cold (every hour from disk: `TrendReader.read`), read again (the closed hours
  kept, one hour changed: the newest file touched), reduced to 900 px (`trend_charts`);
- the whole plot in a dashboard's Trends tab (a viser server, no browser: read + reduce + the
  charts' data assigned, i.e. serialised and queued for the browsers): `TrendsPanel`'s load,
  cold and warm, and the bytes of chart data it sends.

    nice -n 10 .venv/bin/python tests/bench/bench_trends.py [--window-s 10] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))
sys.path.insert(0, str(HERE.parent))

from trend_week import write_week  # noqa: E402

from server.charts_trend import trend_charts  # noqa: E402
from server.trends_data import TrendReader  # noqa: E402

RIG = "benchrig"
WIDTH_PX = 900


def _load() -> str:
    return "load {:.1f} {:.1f} {:.1f}".format(*os.getloadavg())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--window-s", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-trends-") as tmp:
        root = Path(tmp)
        end = time.time()
        t_w = time.perf_counter()
        week = write_week(root, RIG, end, window_s=args.window_s, noise_seed=1)
        write_s = time.perf_counter() - t_w
        files = sorted((root / RIG).glob("*.mcap"))
        size = sum(f.stat().st_size for f in files)
        print(f"week: {week.windows} windows of {args.window_s:g} s (a 6 h gap, noisy values as a "
              f"live watch's), {len(files)} "
              f"hourly files, written in {write_s:.1f} s; storage {size / 7 / 1e6:.2f} MB per "
              f"rig per day ({size / week.windows:.0f} B per window, 4 channels); {_load()}")
        cold, cold_cpu, warm, reduce, points = [], [], [], [], 0
        for _ in range(args.repeats):
            reader = TrendReader()
            t, c = time.perf_counter(), time.process_time()
            span = reader.read(root, RIG, week.t0_epoch_s, end)
            cold.append(time.perf_counter() - t)
            cold_cpu.append(time.process_time() - c)
            os.utime(files[-1])
            t = time.perf_counter()
            span = reader.read(root, RIG, week.t0_epoch_s, end)
            warm.append(time.perf_counter() - t)
            t = time.perf_counter()
            charts = trend_charts(span, WIDTH_PX)
            reduce.append(time.perf_counter() - t)
            points = sum(c.data[0].size for c in charts)
        print(f"read a week cold (all {len(files)} files): median {statistics.median(cold):.2f} s "
              f"(min {min(cold):.2f}; CPU {statistics.median(cold_cpu):.2f} s); again, one "
              f"hour changed: median {statistics.median(warm):.3f} s; reduce to {WIDTH_PX} px, "
              f"{len(charts)} charts: median {statistics.median(reduce) * 1e3:.0f} ms "
              f"({points} x values in all, from {span.windows} windows); {_load()}")
        _panel(root, end, args.repeats)
    return 0


def _panel(root: Path, end: float, repeats: int) -> None:
    """The plot as the dashboard makes it: `TrendsPanel` in a viser server (no browser)."""
    import viser
    from helpers import free_port

    from server.gui import set_value
    from server.panels.trends import TrendsPanel

    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        loads: list[tuple[float, float]] = []
        sent = 0
        for _ in range(repeats):
            with server.gui.add_folder("bench") as folder:
                panel = TrendsPanel(server.gui, (root,), RIG, WIDTH_PX, refresh_s=3600.0,
                                    now=lambda: end)
                panel.build()
            set_value(panel.range, "last week")
            panel.start()
            try:
                t = time.perf_counter()
                panel.reload()
                assert panel.wait_idle(300.0)
                first = time.perf_counter() - t
                assert panel.span is not None, panel.status.content
                t = time.perf_counter()
                panel.reload()
                assert panel.wait_idle(300.0)
                loads.append((first, time.perf_counter() - t))
                sent = sum(sum(a.nbytes for a in h.data) for h in panel.charts.values())
            finally:
                panel.stop()
                folder.remove()
        print(f"plot a week in the Trends tab (read + reduce + the charts' data sent to viser): "
              f"first median {statistics.median(f for f, _ in loads):.2f} s, again (cached "
              f"hours) median {statistics.median(w for _, w in loads):.3f} s; {sent / 1e3:.0f} kB "
              f"of chart data; {_load()}")
    finally:
        server.stop()


if __name__ == "__main__":
    sys.exit(main())
