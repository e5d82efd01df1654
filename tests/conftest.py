"""Shared by every test folder: the marks by folder, `tests/` on the import path for
`helpers` (free ports, waiting on conditions), and `dash` (a dashboard without a controller).

Every test under `tests/integration/` is marked `integration` and every one under
`tests/browser/` `browser`, here, so no file can forget it. The fast subset is
`pytest -m "not integration and not browser and not slow"` (README).

Under pytest-xdist (`bash .ci/test` runs `-n 2`, README) the tests are handed to the workers
a file at a time (each module's module-scoped fixtures start once), except `tests/browser/`,
which goes to one worker as a whole, one module after another: one Chromium and one demo
controller at a time (two at once on 2 cores starve each other's page loads). The browser
files are the longest stretch of the suite, so the other worker takes everything else.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

HERE = Path(__file__).resolve().parent
FOLDER_MARKS = {"integration": pytest.mark.integration, "browser": pytest.mark.browser}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        rel = Path(str(item.path)).resolve().relative_to(HERE)
        mark = FOLDER_MARKS.get(rel.parts[0]) if len(rel.parts) > 1 else None
        if mark is not None:
            item.add_marker(mark)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """The scheduler for `-n N` (see the module docstring). Not `xdist_group` marks with
    `--dist loadgroup`: xdist 3.8 tags a group onto `item._nodeid`, which pytest 9 no longer
    reads, so the groups were silently ignored (files split across workers)."""
    from xdist.scheduler import LoadScopeScheduling

    class BrowserFilesTogether(LoadScopeScheduling):
        """Whole files (`--dist loadfile`), and all of tests/browser/ as one unit, handed out
        first (xdist orders units by their number of tests: 33 browser tests came after the
        bigger unit files, so the suite's longest stretch started late)."""

        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            return BROWSER if path.startswith(BROWSER + "/") else path

        def _assign_work_unit(self, node: Any) -> None:
            if BROWSER in self.workqueue:
                self.workqueue.move_to_end(BROWSER, last=False)
            super()._assign_work_unit(node)

    BROWSER = "tests/browser"

    return BrowserFilesTogether(config, log)


@pytest.fixture(scope="module")
def dash() -> Iterator[Any]:
    """A dashboard (`server.dashboard.app.Dashboard`) with no controller to reach (its
    endpoint is a free port) and one candidate panel built without a browser, its first
    preview done."""
    from helpers import free_port

    from server.dashboard.app import Dashboard, DashboardOptions

    opts = DashboardOptions(
        port=free_port(), connect=(f"tcp/127.0.0.1:{free_port()}",), verbose=False
    )
    with Dashboard(opts) as d:
        t = d.panel_in(d.server.gui)  # a candidate panel without a browser
        assert d.panel_of(None) is t and d.identify is not None
        assert t.wait_preview_idle(30.0)
        yield d
