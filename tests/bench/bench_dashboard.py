"""Dashboard benchmarks: slider-to-update latency (server side, p50/p99); live refresh rate in
the browser and the dashboard process's CPU while one headless browser watches the live tab;
with --page, page load (to the controls visible, to the verdict drawn), how busy the page's main
thread is once loaded (long tasks, % of 3 s) and verdict update (typed cut-off to the verdict's
text changed) in Chromium on the machine as it is ("idle") and
with --hogs busy processes beside it ("loaded"), each half with the load `uptime` printed;
bounded (--loads, --verdicts, --phase-timeout per awaited phase, named when it times out,
--budget per half), progress on stderr.

Run: .venv/bin/python tests/bench/bench_dashboard.py [--seconds 15]
     .venv/bin/python tests/bench/bench_dashboard.py --page --skip-live --skip-slider
The controller is the real one (`python -m controller`, simulated plant); the dashboard runs as
its own process (`dobtune dashboard`) so its CPU time is measured alone.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from viser_frames import message_types  # noqa: E402

from server.dashboard.app import Dashboard, DashboardOptions  # noqa: E402
from server.dashboard.demo import controller_process, stop_process  # noqa: E402

CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
RIG = "bench"

REFRESH_JS = """(ms) => new Promise(resolve => {
  const ups = Object.values(window.__viserTestpoints?.uplots || {});
  const u = ups.find(x => x.chart.series.some(s => s.label === 'error'));
  if (!u) { resolve(-1); return; }
  let last = u.chart.data, n = 0, frames = 0;
  const t0 = performance.now();
  const iv = setInterval(() => { if (u.chart.data !== last) { n++; last = u.chart.data; } }, 2);
  function frame() {
    frames++;
    if (performance.now() - t0 < ms) requestAnimationFrame(frame);
    else { clearInterval(iv); resolve([n / (ms / 1000), frames / (ms / 1000)]); }
  }
  requestAnimationFrame(frame);
})"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def chromium_cpu_seconds() -> float:
    """CPU seconds (user + system) of the Chromium processes this bench started (its own
    descendants named chrom*: the browser, GPU, renderer and utility processes; another
    engineer's Chromium on the machine is not counted)."""
    parent: dict[int, int] = {}
    comm: dict[int, str] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                head, tail = f.read().rsplit(")", 1)
        except OSError:
            continue
        parent[int(d)] = int(tail.split()[1])
        comm[int(d)] = head.split("(", 1)[1]
    mine = {os.getpid()}
    grew = True
    while grew:
        more = {p for p, pp in parent.items() if pp in mine and p not in mine}
        mine |= more
        grew = bool(more)
    total = 0.0
    for p in mine:
        if comm.get(p, "").startswith("chrom"):
            with contextlib.suppress(OSError):  # ended between the listing and the read
                total += cpu_seconds(p)
    return total


def bench_slider(n: int = 200) -> dict[str, float]:
    opts = DashboardOptions(port=free_port(), connect=(f"tcp/127.0.0.1:{free_port()}",),
                            verbose=False)
    with Dashboard(opts) as d:
        t = d.panel_in(d.server.gui)
        t.wait_preview_idle(30.0)
        rng = np.random.default_rng(0)
        lat = []
        for x in rng.uniform(-1.3, 1.6, n):
            t0 = time.perf_counter()
            t.cutoff_log.value = float(round(x, 3))
            t.wait_idle(5.0)
            lat.append(time.perf_counter() - t0)
        ms = np.array(lat) * 1e3
        return {"slider_p50_ms": float(np.percentile(ms, 50)),
                "slider_p99_ms": float(np.percentile(ms, 99)),
                "slider_max_ms": float(ms.max()), "n": n}


def _dashboard_url(proc: subprocess.Popen[str], timeout_s: float) -> str:
    """The URL (with its access token) the dashboard prints when it is up."""
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    for line in proc.stdout:
        if line.startswith("dobtune dashboard: http"):
            return line.split()[2]
        if time.monotonic() > deadline:
            break
    raise TimeoutError("the dashboard printed no URL")


@contextmanager
def dashboard_and_chromium() -> Iterator[tuple[subprocess.Popen[str], str, Any]]:
    """The real controller (`python -m controller`, simulated plant), the dashboard as its own
    process and headless Chromium: yields the dashboard's process, the URL it printed (with its
    access token) and the browser; all three are stopped on leaving."""
    import threading

    from playwright.sync_api import sync_playwright

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    port = free_port()
    with controller_process(endpoint, RIG):
        dash = subprocess.Popen(
            [sys.executable, "-m", "controller.cli.main", "dashboard", "--connect", endpoint,
             "--rig-name", RIG, "--port", str(port)], cwd=ROOT, stdout=subprocess.PIPE, text=True)
        try:
            url = _dashboard_url(dash, 60.0)
            # Keep reading its output so the pipe never fills.
            threading.Thread(target=lambda: [None for _ in dash.stdout or ()],
                             daemon=True).start()
            with sync_playwright() as p:
                b = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
                try:
                    yield dash, url, b
                finally:
                    b.close()
        finally:
            stop_process(dash)


def bench_live(seconds: float, browsers: int = 1) -> dict[str, Any]:
    """`browsers` headless pages on the Live tab and Live traces: the dashboard process's CPU
    and, per page, how often the error chart's data changed and the browser's frame rate."""
    with dashboard_and_chromium() as (dash, url, b):
        pages = []
        ws_frames: list[tuple[float, int, list[str]]] = []
        for k in range(browsers):
            pg = b.new_context(viewport={"width": 1600, "height": 1000}).new_page()
            if k == 0:
                pg.on("websocket", lambda ws: ws.on(
                    "framereceived",
                    lambda data: ws_frames.append(
                        (time.monotonic(), len(data),
                         message_types(data) if isinstance(data, bytes) else ["text"]))))
            pg.goto(url)
            pg.wait_for_selector(".dt-banner.dt-ok", timeout=60_000)
            pg.get_by_role("tab", name="Live traces").click()
            pg.get_by_role("tab", name="Live", exact=True).click()
            pages.append(pg)
        pages[-1].wait_for_timeout(2000)
        cdp = pages[0].context.new_cdp_session(pages[0])
        cdp.send("Performance.enable")
        m0 = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
        b0 = chromium_cpu_seconds()
        c0, w0 = cpu_seconds(dash.pid), time.monotonic()
        n0 = len(ws_frames)
        # Measured in every page at once: each page starts its own measurement (a
        # promise kept in the page), then each is collected.
        for pg in pages:
            pg.evaluate(f"() => {{ window.__dt_bench = ({REFRESH_JS})"
                        f"({seconds * 1000}); }}")
        results: list[Any] = [None] * len(pages)
        for i, pg in enumerate(pages):
            results[i] = pg.evaluate("() => window.__dt_bench")
        c1, w1 = cpu_seconds(dash.pid), time.monotonic()
        b1 = chromium_cpu_seconds()
        m1 = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
        got = [f for f in ws_frames[n0:] if f[0] <= w1]
    types: dict[str, int] = {}
    for _, _, kinds in got:
        for k in kinds:
            types[k] = types.get(k, 0) + 1
    wall = w1 - w0
    # The first page's renderer main thread, per second of wall time (CDP Performance
    # metrics): all its tasks, and of them script, layout and style.
    renderer = {k: (m1.get(k, 0.0) - m0.get(k, 0.0)) / wall
                for k in ("TaskDuration", "ScriptDuration", "LayoutDuration",
                          "RecalcStyleDuration")}
    applied = [float(r[0]) for r in results]
    raf = [float(r[1]) for r in results]
    return {"browsers": browsers,
            "ws_frames_received_hz": len(got) / (w1 - w0),
            "ws_kbytes_per_s": sum(n for _, n, _ in got) / (w1 - w0) / 1e3,
            "ws_messages_per_s_by_type": {k: round(v / wall, 2) for k, v in
                                          sorted(types.items(), key=lambda kv: -kv[1])},
            "chromium_cores": (b1 - b0) / wall,
            "renderer_main_thread_cores": renderer,
            "uptime_at_end": _uptime(),
            "charts_applied_hz_min": min(applied),
            "charts_applied_hz_mean": float(np.mean(applied)),
            "browser_raf_fps_min": min(raf),
            "dashboard_cpu_pct": 100.0 * (c1 - c0) / (w1 - w0),
            "seconds": w1 - w0}


def _stats(xs: list[float], unit: str = "s") -> dict[str, float]:
    if not xs:
        return {"n": 0}
    a = np.array(xs)
    return {"n": len(xs), f"p50_{unit}": float(np.percentile(a, 50)),
            f"p99_{unit}": float(np.percentile(a, 99)),
            f"max_{unit}": float(a.max()), f"min_{unit}": float(a.min())}


def _spin() -> None:
    while True:
        pass


def _uptime() -> str:
    """What `uptime` prints (its load averages over 1, 5 and 15 minutes)."""
    return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()


class PhaseTimeout(RuntimeError):
    """A phase of a measurement did not end in its time; the message names what was awaited."""


#: JS predicates polled in the page (every 50 ms, by the page: a round trip per poll from here
#: took seconds at load 20).
CONTROLS_SHOWN_JS = """() => [...document.querySelectorAll('label')].some(
  l => l.textContent.startsWith('Q cut-off (Hz)') && l.getBoundingClientRect().width > 0)"""
VERDICT_DRAWN_JS = """() => (document.querySelector('.dt-verdict')?.innerText || '')
  .includes('Verdict')"""
SETTLED_JS = "() => !document.querySelector('.dt-computing-on')"
#: The share of `ms` the page's main thread spent in long tasks (> 50 ms each: the browser's
#: own measure of "busy": input waits for them), and the frames drawn per second.
MAIN_THREAD_JS = """(ms) => new Promise(resolve => {
  let busy = 0, frames = 0, go = true;
  const t0 = performance.now();
  const o = new PerformanceObserver(l => { for (const e of l.getEntries()) {  // in the window
    const end = Math.min(e.startTime + e.duration, t0 + ms);
    busy += Math.max(0, end - Math.max(e.startTime, t0)); } });
  o.observe({type: 'longtask', buffered: false});
  function frame() { frames++; if (go) requestAnimationFrame(frame); }
  requestAnimationFrame(frame);
  setTimeout(() => { go = false; o.disconnect();
                     resolve([100 * busy / ms, frames / (ms / 1000)]); }, ms);
})"""
#: Arms the page's own clock for one typed cut-off (the round trips of a poll from here took
#: seconds at load 20). The clock starts at the typed value's `input` event (capture): the
#: page sends a text field's value on every change, not on Enter (viser's TextInput), so the
#: verdict may be drawn before an Enter pressed after the typing (on a quiet machine one
#: cut-off in three was: a clock started at Enter then took some later, unrelated change of
#: the page as the verdict's, or waited for one that never came). window.__dt_verdict gets
#: `input`, `shown` (the first animation frame after the verdict's text changed from
#: `before`: the verdict on screen) and `settled` (the first frame after that with nothing
#: computing). A verdict whose text is the same as before (`same`) is shown when the
#: computing indicator it raised goes off.
VERDICT_ARM_JS = """(before) => {
  window.__dt_verdict = {before};
  const text = () => document.querySelector('.dt-verdict')?.innerText || '';
  const computing = () => !!document.querySelector('.dt-computing-on');
  if (!window.__dt_verdict_hooked) {
    window.__dt_verdict_hooked = true;
    document.addEventListener('input', () => {
      const d = window.__dt_verdict;
      if (d && d.input === undefined) d.input = performance.now();
    }, true);
    new MutationObserver(() => {
      const d = window.__dt_verdict;
      if (!d || d.input === undefined) return;
      if (computing()) d.raised = true;
      if (d.changed === undefined && text() !== d.before && text().includes('Verdict')) {
        d.changed = true;
        requestAnimationFrame(() => { d.shown = performance.now(); });
      }
      if (d.calm === undefined && (d.changed || d.raised) && !computing()) {
        d.calm = true;
        if (!d.changed) {
          d.changed = d.same = true;
          requestAnimationFrame(() => { d.shown = performance.now(); });
        }
        requestAnimationFrame(() => { d.settled = performance.now(); });
      }
    }).observe(document.body, {childList: true, subtree: true, characterData: true,
                               attributes: true});
  }
}"""
VERDICT_TIMED_JS = """() => window.__dt_verdict && window.__dt_verdict.settled !== undefined
  && window.__dt_verdict.shown !== undefined"""


def bench_page(loads: int, verdicts: int, hogs: int, phase_timeout_s: float,
               budget_s: float, half: str) -> dict[str, Any]:
    """Page load and verdict update in headless Chromium, with `hogs` busy processes beside the
    controller and dashboard (0: the machine as it is).

    - page load: a new browser context opens the URL; the time until the controls are visible
      (the Q cut-off field) and until the verdict is drawn;
    - verdict update: a cut-off typed into the Q cut-off field until the page recorded the
      verdict shown and nothing computing (from here); and on the page's own clock, the typed
      value's input event to the first frame with the new verdict ("shown") and to the first
      with nothing computing ("settled").

    Bounded: `loads` page loads and `verdicts` cut-offs at most, each phase waited for at most
    `phase_timeout_s` (a timeout is counted and named, and the half goes on), and no new
    repetition after `budget_s` of the half. Progress goes to stderr as each repetition ends."""
    import multiprocessing

    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    t_half = time.monotonic()

    def say(msg: str) -> None:
        print(f"[{half} {time.monotonic() - t_half:6.1f} s, load {os.getloadavg()[0]:.1f}] "
              f"{msg}", file=sys.stderr, flush=True)

    def until(pg: Any, what: str, js: str, arg: Any = None) -> None:
        """Until the page's `js(arg)` is true; PhaseTimeout naming `what`."""
        try:
            pg.wait_for_function(js, arg=arg, polling=50, timeout=phase_timeout_s * 1000)
        except PlaywrightTimeout:
            raise PhaseTimeout(f"{what}: not seen after {phase_timeout_s:.0f} s") from None

    def over_budget() -> bool:
        return time.monotonic() - t_half > budget_s

    spinners = []
    timeouts: list[str] = []
    say(f"starting the controller, the dashboard and Chromium ({_uptime()})")
    with dashboard_and_chromium() as (_, url, b):
        try:
            warm = b.new_page()  # Chromium's cold start is not the page's load
            warm.goto(url, wait_until="commit", timeout=phase_timeout_s * 1000)
            until(warm, "warm-up page: the verdict drawn", VERDICT_DRAWN_JS)
            warm.close()
            say("warm-up page drew its verdict")
            for _ in range(hogs):
                sp = multiprocessing.Process(target=_spin, daemon=True)
                sp.start()
                spinners.append(sp)
            if hogs:
                time.sleep(5.0)  # the busy processes show in the load average
            uptime_before = _uptime()
            say(f"{hogs} busy processes; {uptime_before}")
            controls_s: list[float] = []
            verdict_drawn_s: list[float] = []
            verdict_s: list[float] = []
            in_page: dict[str, list[float]] = {"shown": [], "settled": []}
            busy: dict[str, list[float]] = {"busy_pct": [], "frames_per_s": []}
            for k in range(loads):
                if over_budget():
                    say(f"budget {budget_s:.0f} s spent: {k} of {loads} page loads")
                    break
                ctx = b.new_context(viewport={"width": 1600, "height": 1000})
                try:
                    pg = ctx.new_page()
                    t0 = time.perf_counter()
                    pg.goto(url, wait_until="commit", timeout=phase_timeout_s * 1000)
                    until(pg, "page load: the Q cut-off field visible", CONTROLS_SHOWN_JS)
                    controls_s.append(time.perf_counter() - t0)
                    until(pg, "page load: the verdict drawn", VERDICT_DRAWN_JS)
                    verdict_drawn_s.append(time.perf_counter() - t0)
                    say(f"page load {k + 1}/{loads}: controls {controls_s[-1]:.2f} s, verdict "
                        f"{verdict_drawn_s[-1]:.2f} s")
                    pct, fps = pg.evaluate(MAIN_THREAD_JS, 3000)
                    busy["busy_pct"].append(pct)
                    busy["frames_per_s"].append(fps)
                    say(f"page {k + 1}: main thread busy {pct:.0f} % of 3 s, {fps:.0f} frames/s")
                    if k == loads - 1:
                        verdict_s += _verdict_updates(pg, verdicts, until, say, over_budget,
                                                      timeouts, in_page)
                except PhaseTimeout as exc:
                    timeouts.append(str(exc))
                    say(f"TIMEOUT {exc}")
                finally:
                    ctx.close()
            return {"busy_processes": hogs, "cores": os.cpu_count(),
                    "uptime_at_start": uptime_before, "uptime_at_end": _uptime(),
                    "page_load_to_controls": _stats(controls_s),
                    "page_load_to_verdict": _stats(verdict_drawn_s),
                    "verdict_update": _stats(verdict_s),
                    "verdict_shown_in_page": _stats(in_page["shown"]),
                    "verdict_settled_in_page": _stats(in_page["settled"]),
                    "main_thread_busy": _stats(busy["busy_pct"], "pct"),
                    "frames": _stats(busy["frames_per_s"], "per_s"),
                    "phase_timeout_s": phase_timeout_s, "timeouts": timeouts,
                    "seconds": time.monotonic() - t_half}
        finally:
            for sp in spinners:
                sp.terminate()
            for sp in spinners:
                sp.join(5.0)


def _verdict_updates(pg: Any, verdicts: int, until: Any, say: Any, over_budget: Any,
                     timeouts: list[str], in_page: dict[str, list[float]]) -> list[float]:
    """Cut-offs typed into the page's Q cut-off field (then Enter, which the page does not
    need): the seconds from the typing (from here) until the page recorded its verdict shown
    and nothing computing, per cut-off (a timed-out one is named in `timeouts`); `in_page`
    gets the page's own seconds from the typed value's input event to the new verdict's
    first frame ("shown") and to the first frame with nothing computing ("settled")."""
    field = pg.locator("label", has_text="Q cut-off (Hz)").first
    box = field.locator("xpath=ancestor::div[contains(@class,'mantine-Flex-root')][1]").locator(
        "input").last
    until(pg, "the first verdict settled (nothing computing)", SETTLED_JS)
    out: list[float] = []
    for i, hz in enumerate(np.round(np.geomspace(0.3, 3.0, verdicts), 2)):
        if over_budget():
            say(f"budget spent: {i} of {verdicts} verdict updates")
            break
        before = pg.evaluate("() => document.querySelector('.dt-verdict')?.innerText || ''")
        pg.evaluate(VERDICT_ARM_JS, before)
        t0 = time.perf_counter()
        box.fill(f"{hz:g}")
        box.press("Enter")
        try:
            until(pg, f"verdict update to {hz:g} Hz: its verdict shown and nothing computing",
                  VERDICT_TIMED_JS)
        except PhaseTimeout as exc:
            timeouts.append(str(exc))
            say(f"TIMEOUT {exc}")
            continue
        out.append(time.perf_counter() - t0)
        d = pg.evaluate("() => window.__dt_verdict")
        in_page["shown"].append((d["shown"] - d["input"]) / 1e3)
        in_page["settled"].append((d["settled"] - d["input"]) / 1e3)
        say(f"verdict update {i + 1}/{verdicts} ({hz:g} Hz): {out[-1]:.2f} s; in the page: "
            f"shown {in_page['shown'][-1]:.3f} s, settled {in_page['settled'][-1]:.3f} s"
            + (" (the same verdict text)" if d.get("same") else ""))
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--skip-live", action="store_true")
    ap.add_argument("--skip-slider", action="store_true")
    ap.add_argument("--browsers", type=int, nargs="+", default=[1, 3],
                    help="numbers of browsers to measure the live view with")
    ap.add_argument("--page", action="store_true",
                    help="page load and verdict update times, idle and loaded")
    ap.add_argument("--loads", type=int, default=5, help="page loads per machine state")
    ap.add_argument("--verdicts", type=int, default=8, help="typed cut-offs per machine state")
    ap.add_argument("--hogs", type=int, default=4,
                    help="busy processes for the loaded machine (besides whatever else runs)")
    ap.add_argument("--phase-timeout", type=float, default=180.0,
                    help="seconds to wait for one phase (a page's controls, its verdict, one "
                    "verdict update) before it counts as timed out, named")
    ap.add_argument("--budget", type=float, default=600.0,
                    help="seconds per half after which no new repetition starts")
    args = ap.parse_args()
    out: dict[str, Any] = {}
    if not args.skip_slider:
        out["slider"] = bench_slider()
    if args.page:  # each half printed as it ends (a loaded machine makes them long)
        for half, hogs in (("page_idle", 0), ("page_loaded", args.hogs)):
            out[half] = bench_page(args.loads, args.verdicts, hogs, args.phase_timeout,
                                   args.budget, half)
            print(json.dumps({half: out[half]}, indent=1), flush=True)
    if not args.skip_live:
        for n in args.browsers:
            out[f"live_{n}_browsers"] = bench_live(args.seconds, n)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
