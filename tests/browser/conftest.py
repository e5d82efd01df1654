"""Browser-test harness: the real controller process (`python -m controller` on the simulated
plant), the dashboard in-process, headless Chromium. A separate Zenoh client (`probe`) checks
what the controller really runs, independently of the page.

The `page` fixture hands the tests a page that is ready: the viser websocket is connected and
the first controls are drawn. A cold Chromium on a fresh machine can take tens of seconds for
that, so the first load has its own generous timeout instead of the tests' short waits.

One Chromium serves all the browser tests of a run (`chromium_browser`: launched at first use,
closed after the last browser test); each module opens its pages in browser contexts of its
own (their own cookies, storage and cache, as separate browsers) and closes them.
"""

from __future__ import annotations

import contextlib
import os
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import free_port, wait_for

from controller.client import ClientOptions, ControllerClient
from server.dashboard.app import Dashboard, DashboardOptions
from server.dashboard.demo import controller_process

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
VIEWPORT = {"width": 1600, "height": 1000}
#: The first load of the page: Chromium's cold start, the viser client's bundle, the websocket.
#: At load 20 on 2 cores one page.evaluate took 33-50 s (measured on main and with the guide
#: alike): 60 s failed every module's first load.
FIRST_LOAD_S = 180.0
#: The controller process's start (interpreter, imports, numba-compiled plant) on a cold machine.
#: At load 25 with two busy loops beside, 60 s was not enough (fifth session): a deadline on a
#: condition, so a generous one costs nothing when the start is quick.
CONTROLLER_START_S = 180.0




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
    with controller_process(endpoint, RIG):
        yield endpoint


@pytest.fixture(scope="module")
def probe(controller_endpoint: str) -> Iterator[ControllerClient]:
    """The test's own Zenoh view of the controller (not through the page)."""
    with ControllerClient(
        ClientOptions(connect=(controller_endpoint,), rig_name=RIG, client_name="probe")
    ) as c:
        wait_for(lambda: c.connected, CONTROLLER_START_S, "the controller did not come up")
        yield c


@pytest.fixture(scope="module")
def dashboard(controller_endpoint: str, probe: ControllerClient) -> Iterator[Dashboard]:
    opts = DashboardOptions(connect=(controller_endpoint,), rig_name=RIG, port=free_port(),
                            verbose=False)
    with Dashboard(opts) as d:
        yield d


@contextlib.contextmanager
def chromium() -> Iterator[Any]:
    """The system's headless Chromium (a Playwright browser), closed on exit. Callers check
    that it is installed first (`_require_chromium`, or their own failure)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS,
                                    timeout=FIRST_LOAD_S * 1000)
        try:
            yield browser
        finally:
            browser.close()


class _SharedChromium:
    """The one Chromium of the browser tests: `get` launches it at first use (and again if it
    went away), `close` ends it."""

    def __init__(self) -> None:
        self._stack: contextlib.ExitStack | None = None
        self._browser: Any = None

    def get(self) -> Any:
        if self._browser is None or not self._browser.is_connected():
            self.close()
            stack = contextlib.ExitStack()
            self._browser = stack.enter_context(chromium())
            self._stack = stack
        return self._browser

    def close(self) -> None:
        stack, self._stack, self._browser = self._stack, None, None
        if stack is not None:
            stack.close()


_SHARED = _SharedChromium()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """After the last browser test (its module's pages closed first), Chromium closes: the
    rest of the suite does not run beside it."""
    try:
        return (yield)
    finally:
        here = Path(__file__).resolve().parent
        if nextitem is None or here not in Path(str(nextitem.path)).resolve().parents:
            _SHARED.close()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    """A failed browser test's page as it was (the `page` fixture's), saved beside the other
    artifacts as failed_<test>.png and named in the report: what the user would have seen
    (a later test of the module failing behind it shows whether the page was still usable)."""
    rep = yield
    page = getattr(item, "funcargs", {}).get("page")
    if rep.failed and page is not None:
        _FAILED_ON.add(id(page))  # the next test of the module loads it again
    if rep.when == "call" and rep.failed and page is not None and not page.is_closed():
        path = ARTIFACTS / f"failed_{item.name}.png"
        try:
            ARTIFACTS.mkdir(exist_ok=True)
            page.screenshot(path=str(path), timeout=15_000)
            rep.sections.append(("failure screenshot", str(path)))
        except Exception as exc:  # the report says why; the test's own failure stands
            rep.sections.append(("failure screenshot", f"not taken: {exc!r}"))
    return rep


#: The pages (ids) a test failed on: a module's page is shared by its tests, and a failure can
#: leave it unusable for the next (a confirmation dialog left open intercepted every click of
#: the six tests after it at load 14).
_FAILED_ON: set[int] = set()


@pytest.fixture(autouse=True)
def _page_loaded_again_after_a_failure(request: pytest.FixtureRequest) -> None:
    """Before a test that takes `page` and `dashboard`: if a test failed on that page, load
    the page again (`open_when_ready`), so one failure is one failure."""
    names = request.fixturenames
    if "page" not in names or "dashboard" not in names:
        return
    page = request.getfixturevalue("page")
    if id(page) not in _FAILED_ON or page.is_closed():
        return
    _FAILED_ON.discard(id(page))
    open_when_ready(page, request.getfixturevalue("dashboard"), FIRST_LOAD_S)


@pytest.fixture(scope="module")
def chromium_browser() -> Any:
    """The browser tests' shared Chromium (`_SharedChromium`); a module opens its pages in
    browser contexts of its own and closes them."""
    _require_chromium()
    return _SHARED.get()


def ready_page(dashboard: Dashboard, browser: Any,
               first_load_s: float = FIRST_LOAD_S) -> Iterator[Any]:
    """A page of `dashboard` in a fresh browser context of `browser` (a new user's browser),
    once it is usable (`open_when_ready`); the context is closed after."""
    context = browser.new_context(viewport=VIEWPORT)
    try:
        pg = context.new_page()
        open_when_ready(pg, dashboard, first_load_s)
        yield pg
    finally:
        context.close()


@pytest.fixture(scope="module")
def page(dashboard: Dashboard, chromium_browser: Any) -> Iterator[Any]:
    yield from ready_page(dashboard, chromium_browser)


def open_when_ready(page: Any, dashboard: Dashboard, timeout_s: float) -> None:
    """Load the dashboard and return once it is usable: the page's viser websocket is connected
    (the server counts it as a client) and the first controls are rendered."""
    deadline = time.monotonic() + timeout_s

    def left_ms() -> float:
        return max(1.0, (deadline - time.monotonic()) * 1000)

    assert dashboard.server is not None
    before = set(dashboard.server.get_clients())
    page.goto(dashboard.url, wait_until="domcontentloaded", timeout=left_ms())
    wait_for(lambda: set(dashboard.server.get_clients()) - before,
                deadline - time.monotonic(), "the page's websocket never connected")
    page.wait_for_selector("text=E-STOP", timeout=left_ms())
    page.wait_for_selector(".dt-verdict", timeout=left_ms())
    page.wait_for_selector(".dt-banner", timeout=left_ms())


#: JS: number of finite points of a series of any uPlot, by label.
FINITE_JS = """(label) => {
  const ups = Object.values(window.__viserTestpoints?.uplots || {});
  for (const u of ups) {
    const i = u.chart.series.findIndex(s => s.label === label);
    if (i > 0) return Array.from(u.chart.data[i]).filter(v => v !== null && isFinite(v)).length;
  }
  return -1;
}"""


def slider_row(page: Any, label: str) -> Any:
    fid = page.locator("label", has_text=label).first.get_attribute("for")
    return page.locator(f"[id='{fid}']")


def wait_shown_text(page: Any, selector: str, text: str, timeout_ms: float) -> None:
    """Wait until an element matching `selector` is shown with `text` in it. Checked in the
    page (not through a locator), so an element the dashboard redraws while it is awaited
    counts as soon as it shows the text (a locator can resolve to the visible element and
    still time out while it is replaced: seen with the apply box in CI)."""
    page.wait_for_function(
        """([sel, text]) => [...document.querySelectorAll(sel)].some(
               e => e.offsetParent !== null && e.innerText.includes(text))""",
        arg=[selector, text], timeout=timeout_ms, polling=100)


def cutoff_box(page: Any) -> Any:
    """The Q cut-off's text field (its row holds one input)."""
    lab = page.locator("label", has_text="Q cut-off (Hz)").first
    return lab.locator("xpath=ancestor::div[contains(@class,'mantine-Flex-root')][1]").locator(
        "input").last


def field_box(page: Any, label: str) -> Any:
    """The input of the control labelled exactly `label` (a text field, a number field, or
    the number box beside a slider: the last input of its row)."""
    lab = page.locator("label").filter(has_text=re.compile("^" + re.escape(label) + "$")).first
    return lab.locator("xpath=ancestor::div[contains(@class,'mantine-Flex-root')][1]").locator(
        "input").last


def set_number(page: Any, label: str, value: float | str) -> None:
    """Type into the control labelled `label` (the gains' and the cut-off's text fields, a
    number field, a slider's number box): what a user does for an exact value."""
    box = field_box(page, label)
    box.fill(str(value))
    box.press("Enter")
    box.blur()


def only_panel(dashboard: Dashboard) -> Any:
    """The candidate panel of the one browser connected (each browser has its own)."""
    panels = list(dashboard.panels.values())
    assert len(panels) == 1, f"{len(panels)} candidate panels: one browser expected"
    return panels[0]
