"""Shared by every test folder: the marks by folder, and `tests/` on the import path for
`helpers` (free ports, waiting on conditions).

Every test under `tests/integration/` is marked `integration` and every one under
`tests/browser/` `browser`, here, so no file can forget it. The fast subset is
`pytest -m "not integration and not browser and not slow"` (README).
"""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
FOLDER_MARKS = {"integration": pytest.mark.integration, "browser": pytest.mark.browser}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        rel = Path(str(item.path)).resolve().relative_to(HERE)
        mark = FOLDER_MARKS.get(rel.parts[0]) if len(rel.parts) > 1 else None
        if mark is not None:
            item.add_marker(mark)
