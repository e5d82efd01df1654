"""Browser-test harness: a controller process, the dashboard in-process, headless Chromium.

The controller is the real one (`python -m controller`) when it exists, else the
stand-in of fake_controller.py (same Zenoh contract). A separate Zenoh client (`probe`) checks
what the controller really runs, independently of the page.
"""

from __future__ import annotations

import importlib.util
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from controller.client import ClientOptions, ControllerClient
from server.app import Dashboard, DashboardOptions
from server.demo import controller_command, stop_process

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"
RIG = "browsertest"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _require_chromium() -> None:
    if CHROMIUM.exists():
        return
    msg = f"{CHROMIUM} is missing: install the Debian package 'chromium' to run browser tests"
    if os.environ.get("CI") == "true":
        pytest.fail(msg)
    pytest.skip("!!! BROWSER TESTS SKIPPED !!! " + msg)


@pytest.fixture(scope="session")
def artifacts() -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS


@pytest.fixture(scope="module")
def controller_endpoint() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory(prefix="dobtune-browser-") as state:
        if importlib.util.find_spec("controller.process.node") is not None:
            cmd = controller_command(endpoint, RIG, Path(state))
        else:
            cmd = [sys.executable, str(Path(__file__).with_name("fake_controller.py")),
                   endpoint, RIG]
        proc = subprocess.Popen(cmd)
        try:
            yield endpoint
        finally:
            stop_process(proc)


@pytest.fixture(scope="module")
def probe(controller_endpoint: str) -> Iterator[ControllerClient]:
    """The test's own Zenoh view of the controller (not through the page)."""
    with ControllerClient(
        ClientOptions(connect=(controller_endpoint,), rig_name=RIG, client_name="probe")
    ) as c:
        deadline = time.monotonic() + 30
        while not c.connected:
            assert time.monotonic() < deadline, "controller did not come up"
            time.sleep(0.05)
        yield c


@pytest.fixture(scope="module")
def dashboard(controller_endpoint: str, probe: ControllerClient) -> Iterator[Dashboard]:
    opts = DashboardOptions(connect=(controller_endpoint,), rig_name=RIG, port=free_port(),
                            verbose=False)
    with Dashboard(opts) as d:
        yield d


@pytest.fixture(scope="module")
def page(dashboard: Dashboard) -> Iterator[Any]:
    _require_chromium()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            pg = browser.new_page(viewport={"width": 1600, "height": 1000})
            pg.goto(dashboard.url)
            yield pg
        finally:
            browser.close()
