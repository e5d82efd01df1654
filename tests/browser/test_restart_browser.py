"""Issue 22: a candidate survives a restart of the dashboard, in headless Chromium.

The dashboard runs as a process of its own (over real Zenoh to the real controller process),
with its candidates kept in a directory of the test's; it is stopped (SIGTERM, as a service
manager stops it) and started again on the same port with the same token, and the same browser
tab is reloaded: the candidate's cut-off and its verdict are back as the user left them. Then
the controller moves on while the dashboard is down: after the next restart the candidate
comes back stale ("Based on vN", Apply off), never applicable as it was; and a damaged file is
said on the page (and kept aside). What is checked is what the page shows; what the
controller runs is read through a separate Zenoh client (`probe`).
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import FIRST_LOAD_S, RIG, VIEWPORT, cutoff_box, set_number, wait_shown_text
from helpers import Output, free_port, spawn

from controller.client import ControllerClient

pytestmark = pytest.mark.browser

#: A dashboard process with a known token (`dobtune dashboard` makes a random one per start).
_DASHBOARD = """
import sys
from pathlib import Path
from server.dashboard.app import DashboardOptions, run_dashboard
endpoint, rig, port, token, kept = sys.argv[1:]
sys.exit(run_dashboard(DashboardOptions(connect=(endpoint,), rig_name=rig, port=int(port),
                                        token=token, candidates_dir=Path(kept))))
"""
TOKEN = "restart-test-token-0123456789"
APPLY_DISABLED_JS = """() => [...document.querySelectorAll('button')].find(
  b => b.textContent.trim() === 'Apply candidate')?.disabled"""


@contextlib.contextmanager
def _dashboard_process(endpoint: str, port: int, kept: Path, token: str = TOKEN
                       ) -> Iterator[str]:
    """The dashboard in a process of its own; its URL once it listens. Stopped with SIGTERM
    (it must then exit 0)."""
    proc = spawn(
        [sys.executable, "-c", _DASHBOARD, endpoint, RIG, str(port), token, str(kept)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = Output(proc)
    try:
        url = out.wait_url(FIRST_LOAD_S)
        assert url == f"http://127.0.0.1:{port}/?token={token}", out.lines
        yield url
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            code = proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise
        out.reader.join(timeout=10)
    assert code == 0, out.text()


def _ready(page: Any) -> None:
    page.wait_for_selector("text=E-STOP", timeout=FIRST_LOAD_S * 1000)
    page.wait_for_selector(".dt-verdict", timeout=FIRST_LOAD_S * 1000)
    tab = page.get_by_role("tab", name="Tune")
    if tab.get_attribute("aria-selected", timeout=FIRST_LOAD_S * 1000) != "true":
        tab.click(timeout=FIRST_LOAD_S * 1000)


def _settled(page: Any) -> None:
    """The verdict shown is the present candidate's."""
    page.wait_for_selector(".dt-computing-on", state="detached", timeout=FIRST_LOAD_S * 1000)


def _text(page: Any, sel: str) -> str:
    return str(page.locator(sel).first.inner_text())


def _apply_disabled(page: Any, disabled: bool) -> None:
    page.wait_for_function(f"() => ({APPLY_DISABLED_JS})() === {str(disabled).lower()}",
                           timeout=FIRST_LOAD_S * 1000)


def test_the_candidate_survives_a_dashboard_restart_and_comes_back_stale_if_the_rig_moved_on(
        controller_endpoint: str, probe: ControllerClient, chromium_browser: Any,
        tmp_path: Path, artifacts: Path) -> None:
    port, kept = free_port(), tmp_path / "candidates"
    start = probe.get_config()
    hz = 0.9 if start.config.q_cutoff_hz != 0.9 else 0.85
    context = chromium_browser.new_context(viewport=VIEWPORT)
    try:
        page = context.new_page()
        with _dashboard_process(controller_endpoint, port, kept) as url:
            page.goto(url, wait_until="domcontentloaded", timeout=FIRST_LOAD_S * 1000)
            _ready(page)
            page.wait_for_selector(".dt-diff >> text=same as active", timeout=FIRST_LOAD_S * 1000)
            set_number(page, "Q cut-off (Hz)", hz)
            wait_shown_text(page, ".dt-cutoff", f"{hz:.3f} Hz", FIRST_LOAD_S * 1000)
            _settled(page)
            verdict, diff = _text(page, ".dt-verdict"), _text(page, ".dt-diff")
            assert "q_cutoff_hz" in diff
            _apply_disabled(page, False)

        # The dashboard is down: the page has lost it. Started again (same port, same token):
        # the same tab, reloaded, shows the same candidate and its verdict.
        with _dashboard_process(controller_endpoint, port, kept):
            page.reload(wait_until="domcontentloaded", timeout=FIRST_LOAD_S * 1000)
            _ready(page)
            wait_shown_text(page, ".dt-apply-restored", "dashboard's restart",
                            FIRST_LOAD_S * 1000)
            wait_shown_text(page, ".dt-cutoff", f"{hz:.3f} Hz", FIRST_LOAD_S * 1000)
            _settled(page)
            assert float(cutoff_box(page).input_value()) == hz
            assert _text(page, ".dt-verdict") == verdict
            assert _text(page, ".dt-diff") == diff
            assert _text(page, ".dt-stale").strip() == ""
            assert _text(page, ".dt-kept-problem").strip() == ""
            _apply_disabled(page, False)  # made against the version the controller still runs
            page.locator(".dt-apply-restored").first.scroll_into_view_if_needed()
            page.screenshot(path=str(artifacts / "restart_kept.png"))

        # While the dashboard is down, someone else applies: after the next restart the
        # candidate is back, stale (made against the old version), Apply off. This start has
        # a new token, as `dobtune dashboard` makes one per start: the user opens the new URL
        # in the same tab.
        other_hz = 0.6 if start.config.q_cutoff_hz != 0.6 else 0.65
        moved = probe.apply(start.config.with_(q_cutoff_hz=other_hz),
                            expect_version=start.version)
        assert moved.accepted, moved
        with _dashboard_process(controller_endpoint, port, kept, TOKEN + "-new") as new_url:
            page.goto(new_url, wait_until="domcontentloaded", timeout=FIRST_LOAD_S * 1000)
            _ready(page)
            wait_shown_text(page, ".dt-stale", f"Based on v{start.version}", FIRST_LOAD_S * 1000)
            assert f"now v{moved.version}" in _text(page, ".dt-stale")
            assert float(cutoff_box(page).input_value()) == hz
            _settled(page)
            _apply_disabled(page, True)
            assert "based on an older version" in _text(page, ".dt-apply-blocked")
            page.locator(".dt-stale").first.scroll_into_view_if_needed()
            page.screenshot(path=str(artifacts / "restart_stale.png"))
        after = probe.get_config()
        assert after.version == moved.version and after.config.q_cutoff_hz == other_hz

        # The file is damaged while the dashboard is down: the page says so, and where the file
        # went (kept aside, not deleted); the candidate starts from the active configuration.
        files = list((kept / RIG).glob("*.json"))
        assert [f.name for f in files] == ["_anyone.json"], files
        files[0].write_bytes(files[0].read_bytes()[:40])
        with _dashboard_process(controller_endpoint, port, kept) as url:
            page.goto(url, wait_until="domcontentloaded", timeout=FIRST_LOAD_S * 1000)
            _ready(page)
            wait_shown_text(page, ".dt-kept-problem", "could not be restored",
                            FIRST_LOAD_S * 1000)
            problem = _text(page, ".dt-kept-problem")
            aside = [p for p in (kept / RIG).iterdir() if ".unreadable-" in p.name]
            assert len(aside) == 1 and f"moved aside to {aside[0]}" in problem, problem
            page.wait_for_selector(".dt-diff >> text=same as active", timeout=FIRST_LOAD_S * 1000)
            assert float(cutoff_box(page).input_value()) == other_hz
            page.locator(".dt-kept-problem").first.scroll_into_view_if_needed()
            page.screenshot(path=str(artifacts / "restart_unreadable.png"))
    finally:
        context.close()
