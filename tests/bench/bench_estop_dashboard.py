"""Benchmark: e-stop latency from the dashboard's E-STOP button (headless Chromium) to the first
tick that commands 0, against a real controller (simulated rig). Prints figures; not a test.

    .venv/bin/python tests/bench/bench_estop_dashboard.py [--n N]

Each trial: the loop runs (reset + start through Zenoh), the bench notes the wall time and
clicks E-STOP in the page; the state stream gives the wall time of the first sample in mode
estop with command 0 (the tick's own clock, same machine). The path: browser -> websocket ->
viser -> the dashboard's callback -> Zenoh put on the e-stop key -> the controller's tick.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "integration"))

from bench_estop import estop_tick_wall_s, start_running
from procs import Client, free_port, start_controller

from server.dashboard.app import Dashboard, DashboardOptions

#: JS: the page notes when the E-STOP button is pressed (pointerdown, capture) and when its
#: banner first says "E-STOP ACTIVE" (in the DOM), on its own clock, in window.__dt_estop.
PAGE_WATCH_JS = """() => {
  window.__dt_estop = {};
  document.addEventListener('pointerdown', (e) => {
    const b = e.target.closest && e.target.closest('button');
    if (b && b.textContent.trim() === 'E-STOP') window.__dt_estop.click = performance.now();
  }, true);
  new MutationObserver(() => {
    const d = window.__dt_estop;
    if (d.click !== undefined && d.shown === undefined
        && document.querySelector('.dt-banner.dt-estop')) d.shown = performance.now();
  }).observe(document.body, {childList: true, subtree: true, characterData: true});
}"""


def uptime() -> str:
    """What `uptime` prints (the load averages over 1, 5 and 15 minutes)."""
    return subprocess.run(["uptime"], capture_output=True, text=True,
                          check=False).stdout.strip()


def main() -> None:
    import importlib.util

    from playwright.sync_api import sync_playwright

    spec = importlib.util.spec_from_file_location(
        "browser_conftest", Path(__file__).resolve().parents[1] / "browser" / "conftest.py")
    assert spec is not None and spec.loader is not None
    bc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bc)
    CHROMIUM, CHROMIUM_ARGS, open_when_ready = bc.CHROMIUM, bc.CHROMIUM_ARGS, bc.open_when_ready

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=30)
    args = ap.parse_args()
    lat_ms: list[float] = []
    server_ms: list[float] = []
    shown_ms: list[float] = []
    load_before = uptime()
    with tempfile.TemporaryDirectory() as tmp:
        proc = start_controller(Path(tmp) / "state", rig="bench-dash")
        try:
            with Client(proc.endpoint, proc.rig) as client:
                client.wait_ready(proc)
                opts = DashboardOptions(connect=(proc.endpoint,), rig_name=proc.rig,
                                        port=free_port(), verbose=False)
                with Dashboard(opts) as dash, sync_playwright() as p:
                    browser = p.chromium.launch(executable_path=str(CHROMIUM),
                                                args=CHROMIUM_ARGS)
                    page = browser.new_page(viewport={"width": 1600, "height": 1000})
                    open_when_ready(page, dash, 180.0)  # a loaded machine: minutes
                    button = page.get_by_role("button", name="E-STOP")
                    # When the dashboard's callback ran (server side): splits the latency
                    # into browser + websocket + viser, and dashboard + Zenoh + tick.
                    got_at: list[float] = []
                    live = dash.live
                    assert live is not None
                    send = live._send

                    def timed(*args: Any) -> None:  # (body, the page's client)
                        got_at.append(time.time())
                        send(*args)

                    live._send = timed
                    page.evaluate(PAGE_WATCH_JS)
                    with client.state() as col:
                        for i in range(args.n):
                            before = start_running(client, col)
                            page.wait_for_function(
                                "() => !document.querySelector('.dt-banner.dt-estop')",
                                timeout=60_000)
                            page.evaluate("() => { window.__dt_estop = {}; }")
                            t_click = time.time()
                            button.click()
                            t_tick = estop_tick_wall_s(client, col, before, 10.0, f"trial {i}")
                            lat_ms.append((t_tick - t_click) * 1e3)
                            server_ms.append((t_tick - got_at[-1]) * 1e3)
                            page.wait_for_function(
                                "() => window.__dt_estop.shown !== undefined", timeout=60_000)
                            shown_ms.append(page.evaluate(
                                "() => window.__dt_estop.shown - window.__dt_estop.click"))
                            col.clear()
                    browser.close()
        finally:
            proc.stop()
    s = np.asarray(shown_ms)
    print(f"E-STOP click -> the page shows 'E-STOP ACTIVE' (the page's own clock: pointerdown "
          f"to the banner in the DOM; {len(s)} trials): p50 {np.percentile(s, 50):.1f} ms, "
          f"p99 {np.percentile(s, 99):.1f} ms, max {s.max():.1f} ms")
    print(f"load: before {load_before}; after {uptime()}")
    a = np.asarray(lat_ms)
    print(f"e-stop latency, dashboard button -> first tick with command 0 ({args.n} trials, "
          f"headless Chromium): p50 {np.percentile(a, 50):.1f} ms, p99 "
          f"{np.percentile(a, 99):.1f} ms, max {a.max():.1f} ms, min {a.min():.1f} ms; of which "
          f"from the dashboard's callback: p50 {np.percentile(server_ms, 50):.1f} ms, p99 "
          f"{np.percentile(server_ms, 99):.1f} ms")


if __name__ == "__main__":
    main()
