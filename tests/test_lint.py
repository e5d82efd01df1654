"""Lint (ruff) and static types (mypy) are part of the test suite."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

#: Whole-tree checks in subprocesses (mypy alone ~1-2 min here): outside the fast subset.
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]


def _clean(*tool: str) -> None:
    """`python -m <tool...>` in the repository exits 0 (its output is the failure message)."""
    proc = subprocess.run([sys.executable, "-m", *tool], cwd=ROOT, capture_output=True,
                          text=True, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_ruff_clean() -> None:
    _clean("ruff", "check", "controller", "server", "tests")


def test_mypy_clean() -> None:
    _clean("mypy", "controller", "server")


def test_controller_never_imports_server_or_viser() -> None:
    code = (
        "import sys, controller.core.loop, controller.process.node, controller.gate.analysis,"
        " controller.__main__, controller.cli;"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('server', 'viser'));"
        "print(','.join(bad))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert proc.stdout.strip() == "", f"controller imported: {proc.stdout}"
