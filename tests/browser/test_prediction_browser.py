"""Predicted, then measured, after an Apply (issue 35 item 5), as the user sees it: the demo's
controller (the article rig, with the watch it starts beside its loop) and the dashboard's
History tab. The running version's check shows the twin's figures beside the rig's and says
HELD; after the plant moves away from the twin and a new version is applied, it says FAILED
BADLY and what that means; when the watch has not yet seen the plant move it offers the
rollback to the version whose prediction held, ready under Version for "Use as candidate"
(when it has, no version judged on the old plant is offered)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import CONTROLLER_START_S, FIRST_LOAD_S, free_port, ready_page
from helpers import spawn, wait_for

from controller import protocol as proto
from controller.client import ClientOptions, ControllerClient
from server.dashboard.app import Dashboard, DashboardOptions
from server.dashboard.demo import DemoOptions, controller_command, stop_process

RIG = "predictview"
DISTURBANCES = DemoOptions.disturbances


@pytest.fixture(scope="module")
def endpoint(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    d = tmp_path_factory.mktemp("predictview")
    ep = f"tcp/127.0.0.1:{free_port()}"
    args = tuple(a for n in DISTURBANCES for a in ("--disturbance", n))
    proc = spawn(controller_command(ep, RIG, d / "state", "info", args))  # with its watch
    try:
        yield ep
    finally:
        stop_process(proc)


@pytest.fixture(scope="module")
def client(endpoint: str) -> Iterator[ControllerClient]:
    with ControllerClient(ClientOptions(connect=(endpoint,), rig_name=RIG, client_name="test",
                                        query_timeout_s=30.0)) as c:
        wait_for(lambda: c.connected and c.status is not None, CONTROLLER_START_S,
                 "the controller did not come up")
        yield c


@pytest.fixture(scope="module")
def dash(endpoint: str, client: ControllerClient) -> Iterator[Dashboard]:
    opts = DashboardOptions(connect=(endpoint,), rig_name=RIG, port=free_port(), verbose=False,
                            sim_disturbances=DISTURBANCES, query_timeout_s=30.0)
    with Dashboard(opts) as d:
        yield d


@pytest.fixture(scope="module")
def page(dash: Dashboard, chromium_browser: Any) -> Iterator[Any]:
    yield from ready_page(dash, chromium_browser, 3 * FIRST_LOAD_S)


def _box(page: Any) -> str:
    return str(page.locator(".dt-prediction").first.inner_text())


def test_history_shows_predicted_then_measured(page: Any, dash: Dashboard,
                                              client: ControllerClient,
                                              artifacts: Path) -> None:
    page.get_by_role("tab", name="History").click()
    v1 = client.status.config_version if client.status is not None else -1
    page.wait_for_selector(f".dt-prediction >> text=Predicted, then measured: v{v1}",
                           timeout=240_000)
    page.wait_for_selector(".dt-prediction-state >> text=HELD", timeout=240_000)
    text = _box(page)
    # every main figure with both sides and its tolerance, as numbers
    for name in ("RMSE (deg)", "peak |error| (deg)", "command noise (deg/s)"):
        row = re.search(re.escape(name) + r"\s+([0-9.e+-]+)\s+([0-9.e+-]+)\s+([+-][0-9.]+%)"
                        r"\s+±(\d+)%", text)
        assert row is not None, text
        predicted, measured = float(row.group(1)), float(row.group(2))
        off = (measured - predicted) / predicted * 100
        assert abs(off - float(row.group(3)[:-1])) < 0.11, (name, row.groups())
        assert abs(off) <= float(row.group(4)), (name, row.groups())  # HELD: each within
    assert "can be trusted" in text
    page.screenshot(path=str(artifacts / "prediction_held.png"))

    # The plant moves away from the twin; the next version's prediction fails badly.
    assert client.command(proto.SimDrift(belt_stiffness_factor=0.4,
                                         load_inertia_factor=3.0)).ok
    r = client.apply(client.get_config().config.with_(q_cutoff_hz=0.8))
    assert r.accepted, r
    page.wait_for_selector(f".dt-prediction >> text=Predicted, then measured: v{r.version}",
                           timeout=120_000)
    page.wait_for_selector(".dt-prediction-state >> text=FAILED BADLY", timeout=240_000)
    text = _box(page)
    assert "did not hold" in text, text
    if "the model is wrong" in text:
        # the watch saw the plant move: no rollback to a version judged on the old plant
        assert "Roll back to" not in text and "measure it again first" in text, text
    else:
        assert f"Roll back to v{v1}" in text, text
        # the offered version is ready under Version for Use as candidate
        wait_for(lambda: dash.history is not None and dash.history.pick.value == f"v{v1}",
                 30.0, "the offered version under Version")
    page.screenshot(path=str(artifacts / "prediction_failed.png"))
