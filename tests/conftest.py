"""Shared by every test folder: the marks by folder, `tests/` on the import path for
`helpers` (free ports, waiting on conditions), and `dash` (a dashboard without a controller).

Every test under `tests/integration/` is marked `integration` and every one under
`tests/browser/` `browser`, here, so no file can forget it. The fast subset is
`pytest -m "not integration and not browser and not slow"` (README).
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


@pytest.fixture(scope="module")
def dash() -> Iterator[Any]:
    """A dashboard (`server.app.Dashboard`) with no controller to reach (its endpoint is a free
    port) and one candidate panel built without a browser, its first preview done."""
    from helpers import free_port

    from server.app import Dashboard, DashboardOptions

    opts = DashboardOptions(
        port=free_port(), connect=(f"tcp/127.0.0.1:{free_port()}",), verbose=False
    )
    with Dashboard(opts) as d:
        t = d.panel_in(d.server.gui)  # a candidate panel without a browser
        assert d.panel_of(None) is t and d.identify is not None
        assert t.wait_preview_idle(30.0)
        yield d
