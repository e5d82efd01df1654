"""A page closed while its candidate is evaluated: viser removes the page's elements at the
disconnect, before the dashboard stops the page's panel, so the verdict's or the preview's
worker that was mid-way finds them removed. A closed page is normal: nothing is logged as an
error (it was `RuntimeError: Cannot assign to 'data' on a removed GuiUplotHandle` from the
preview, and 'content' on a removed GuiHtmlHandle from the verdict), while a page that is open
still gets its verdict. A real dashboard (no controller needed) and a raw websocket client that
connects and closes as a page does."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from helpers import free_port, wait_for
from viser_raw import connected

from server import viser_adapter
from server.dashboard.app import Dashboard, DashboardOptions
from server.viser_adapter import control_uuid


@pytest.fixture(scope="module")
def dash() -> Iterator[Dashboard]:
    opts = DashboardOptions(connect=(f"tcp/127.0.0.1:{free_port()}",), rig_name="closed",
                            port=free_port(), verbose=False, query_timeout_s=0.5)
    with Dashboard(opts) as d:
        yield d


class _Gate:
    """Wraps one of the engine's methods: a call waits (on a condition) until released."""

    def __init__(self, fn: Any) -> None:
        self.fn = fn
        self.entered = threading.Event()
        self.release = threading.Event()
        self.returned = threading.Event()

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.entered.set()
        assert self.release.wait(300.0), "the test never released the gate"
        try:
            return self.fn(*args, **kwargs)
        finally:
            self.returned.set()


def _panel_of_new_page(dash: Dashboard, before: set[int]) -> Any:
    got: list[Any] = []

    def built() -> bool:
        new = set(dash.candidates.panels) - before - {-1}
        if new:
            got[:] = [dash.candidates.panels[next(iter(new))]]
        return bool(got) and got[0].analysis.built and got[0].update_count > 0

    wait_for(built, 120.0, "the page's candidate panel was never built and evaluated")
    return got[0]


@pytest.mark.parametrize("method", ["compare", "compare_preview"])
def test_a_page_closed_while_its_candidate_is_evaluated_logs_no_error(
        dash: Dashboard, method: str, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """`compare`: the verdict's worker (tuning-update); `compare_preview`: the preview's
    (tuning-preview). The page types a cut-off, its evaluation is held inside the engine,
    the page closes, viser removes its elements, then the evaluation goes on."""
    caplog.set_level(logging.DEBUG)
    before = set(dash.candidates.panels)
    with connected(dash) as page:
        panel = _panel_of_new_page(dash, before)
        assert panel.wait_preview_idle(120.0), "the first evaluation never ended"
        gate = _Gate(getattr(panel.engine, method))
        monkeypatch.setattr(panel.engine, method, gate)
        page.update(control_uuid(panel.cutoff_hz_input), {"value": "2.5"})
        assert gate.entered.wait(120.0), f"the typed cut-off never reached {method}"
    wait_for(lambda: viser_adapter.removed(panel.verdict), 60.0,
             "the closed page's elements were never removed")
    gate.release.set()
    assert gate.returned.wait(120.0), f"{method} never returned"
    assert panel.wait_preview_idle(120.0), "the page's workers never ended"
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert not errors, [r.getMessage() for r in errors]
    assert any("its page was closed" in r.getMessage() for r in caplog.records)


def test_an_open_pages_failure_is_still_an_error(dash: Dashboard,
                                                monkeypatch: pytest.MonkeyPatch,
                                                caplog: pytest.LogCaptureFixture) -> None:
    """The same RuntimeError while the page is open is not taken for a closed page: it is
    logged as the worker's failure (with its traceback), and the page goes on being judged."""
    before = set(dash.candidates.panels)
    with connected(dash) as page:
        panel = _panel_of_new_page(dash, before)
        assert panel.wait_preview_idle(120.0), "the first evaluation never ended"
        real = panel.engine.compare
        calls: list[int] = []

        def broken(*args: Any, **kwargs: Any) -> Any:
            calls.append(1)
            if len(calls) == 1:
                raise RuntimeError("a real failure")
            return real(*args, **kwargs)

        monkeypatch.setattr(panel.engine, "compare", broken)
        page.update(control_uuid(panel.cutoff_hz_input), {"value": "2.5"})
        wait_for(lambda: any(r.levelno >= logging.ERROR and "tuning-update failed"
                             in r.getMessage() for r in caplog.records), 120.0,
                 "the failure was not logged as an error")
        done = panel.update_count
        page.update(control_uuid(panel.cutoff_hz_input), {"value": "2.6"})
        wait_for(lambda: panel.update_count > done, 120.0, "the next cut-off was not judged")
        assert not viser_adapter.removed(panel.verdict)
