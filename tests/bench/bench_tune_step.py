"""The guided path's "Tune the whole loop" step: time from the press to a candidate (issue 35
item 3; goals: 5 s without identification, 60 s with it, the identification's 45 s among them).

    .venv/bin/python tests/bench/bench_tune_step.py [--repeats 3] [--no-identify]

Starts the demo's simulated controller (a child process, the demo's rig disturbances) and the
dashboard in-process, builds one candidate panel with its guided path (`Dashboard.panel_in`
without a browser: the same panel and step a browser gets), and presses the step as its button
does (`TuneStep.request`). "A candidate" is the moment the candidate panel holds the tune's
result (`TuneTarget.load` done, the step's state "done"); the websocket's few milliseconds to a
page are not in it.

1. Without identification (`--repeats` presses, the candidate reverted to the active
   configuration before each): nothing measured, so the tune runs on the built-in model.
2. With identification: the Identify panel's default run on the controller (the rig moves:
   the step's Measure, its confirmation answered), Use fit (the measured responses adopted by
   the controller: a new plant knowledge), then the tune on the rig's twin (its fit included).
   Each phase is printed, and the total against the goal.

Every figure is printed with the load average beside it (`os.getloadavg`, and `uptime` at the
start and the end).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from helpers import free_port

from controller.client import ClientOptions, ControllerClient
from controller.sim.rig_disturbances import DEFAULT_RIG_NAMES
from server.dashboard.app import Dashboard, DashboardOptions
from server.dashboard.demo import controller_process
from server.panels.guide import GuidePanel
from server.panels.identify import RUNNING

RIG = "benchtune"
GOAL_PLAIN_S = 5.0
GOAL_IDENTIFY_S = 60.0


def _load() -> str:
    return "load " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()


def _wait(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            raise TimeoutError(what)
        time.sleep(0.01)


def press_tune(guide: GuidePanel, timeout_s: float = 600.0) -> float:
    """Press the step; the seconds until the candidate holds the tune's result."""
    panel = guide.tuning
    before = panel.candidate()
    t0 = time.perf_counter()
    guide.tune.request()
    _wait(lambda: guide.tune.state.state in ("done", "failed"), timeout_s, "the tune never ended")
    elapsed = time.perf_counter() - t0
    res = guide.tune.last
    if guide.tune.state.state != "done" or res is None or res.best is None:
        raise RuntimeError(f"the tune did not give a candidate: {guide.tune.state.text}")
    cand = panel.candidate()
    if cand != res.best.config or cand == before:
        raise RuntimeError("the candidate is not the tune's result")
    return elapsed


def _describe(guide: GuidePanel) -> str:
    res = guide.tune.last
    assert res is not None and res.best is not None
    return (f"{res.runs} runs, RMSE {res.best.rmse_deg:.4g} deg (start "
            f"{res.start.rmse_deg:.4g}), {res.best.verdict}, on the {res.plant_source}")


def without_identification(d: Dashboard, guide: GuidePanel, repeats: int) -> list[float]:
    panel = guide.tuning
    times = []
    for i in range(repeats):
        active = d.candidates.active
        assert active is not None
        panel.load(active, d.candidates.active_version)
        load = _load()
        s = press_tune(guide)
        times.append(s)
        print(f"  press {i + 1}: {s:6.2f} s to a candidate ({_describe(guide)}); {load} before,"
              f" {_load()} after", flush=True)
    return times


def with_identification(d: Dashboard, guide: GuidePanel) -> float:
    idp = d.identify
    assert idp is not None
    active = d.candidates.active
    assert active is not None
    guide.tuning.load(active, d.candidates.active_version)  # from the running loop, as 1.
    settings = idp.settings()
    print(f"  identification: {settings.where}, {settings.values}; {_load()}", flush=True)
    plant0 = d.engine.plant
    t0 = time.perf_counter()
    if not idp.start(settings, None):  # what the confirmation's "Start identification" does
        raise RuntimeError(f"the identification did not start: {idp.text}")
    _wait(lambda: idp.state != RUNNING, 600.0, "the identification never ended")
    t_ident = time.perf_counter() - t0
    print(f"  measure: {t_ident:6.2f} s ({idp.state}: {idp.text}); {_load()}", flush=True)
    t1 = time.perf_counter()
    if not idp.use_as_nominal(None):
        raise RuntimeError("Use fit put nothing into the candidate")
    _wait(lambda: d.engine.plant is not plant0 and bool(d.engine.plant.measured), 60.0,
          "the controller's new plant knowledge never reached the dashboard")
    t_use = time.perf_counter() - t1
    print(f"  use fit (adopted: plant knowledge v{d.engine.plant.version}, "
          f"{len(d.engine.plant.measured)} measured): {t_use:6.2f} s; {_load()}", flush=True)
    t_tune = press_tune(guide)
    total = time.perf_counter() - t0
    print(f"  tune (the twin's fit included): {t_tune:6.2f} s ({_describe(guide)}); {_load()}",
          flush=True)
    print(f"  total, Measure to a candidate: {total:6.2f} s (goal {GOAL_IDENTIFY_S:.0f} s)",
          flush=True)
    return total


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-identify", action="store_true")
    args = ap.parse_args(argv)
    print(f"start: {_uptime()}", flush=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with controller_process(endpoint, RIG, disturbances=DEFAULT_RIG_NAMES), ControllerClient(
            ClientOptions(connect=(endpoint,), rig_name=RIG, client_name="bench")) as probe:
        _wait(lambda: probe.connected, 120.0, "the controller did not come up")
        opts = DashboardOptions(connect=(endpoint,), rig_name=RIG, port=free_port(),
                                verbose=False, sim_disturbances=DEFAULT_RIG_NAMES)
        with Dashboard(opts) as d:
            assert d.server is not None
            d.panel_in(d.server.gui)
            guide = d.candidates.guides[-1]
            _wait(lambda: d.candidates.active is not None
                  and d.engine.plant.source != "not yet fetched", 120.0,
                  "the dashboard never got the active configuration and plant knowledge")
            print(f"\n1. without identification (nothing measured), {args.repeats} presses:",
                  flush=True)
            times = without_identification(d, guide, args.repeats)
            print(f"  median {statistics.median(times):.2f} s, worst {max(times):.2f} s "
                  f"(goal {GOAL_PLAIN_S:.0f} s)", flush=True)
            if not args.no_identify:
                print("\n2. with identification (Measure, Use fit, Tune loop):", flush=True)
                with_identification(d, guide)
    print(f"\nend: {_uptime()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
