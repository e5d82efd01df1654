"""controller.core.numba_start: a process's first compile (numba's set-up) without scipy.linalg,
and numba's BLAS path as it was for a kernel that uses it. Fresh processes (numba sets itself
up once per process)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _run(code: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=REPO, timeout=600)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()


def test_dobtune_check_runs_its_kernels_without_scipy_linalg() -> None:
    """`dobtune check` runs the nonlinear check (compiled kernels: numba set up) and imports
    neither scipy.linalg nor what scipy's array-API layer drags in (numpy.f2py, numpy.testing):
    0.2-0.3 CPU s of every start."""
    last = _run(
        "import io, sys, contextlib\n"
        "from controller.cli.main import dobtune_main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    rc = dobtune_main(['check'])\n"
        "print(rc, *(m in sys.modules for m in ('numba.np.arraymath', 'scipy.linalg', "
        "'numpy.f2py', 'numpy.testing')))\n")[-1]
    assert last == "0 True False False False", last


def test_a_kernel_that_uses_blas_still_gets_it() -> None:
    """np.dot in a kernel compiled after the set-up: numba's BLAS path (it imports scipy.linalg
    then), the same product as numpy's; numba's own check is back in place."""
    last = _run(
        "import sys\n"
        "import numpy as np\n"
        "from controller.core.numba_start import numba\n"
        "import numba.np.linalg as nl\n"
        "@numba.njit\n"
        "def one(x):\n"
        "    return x + 1.0\n"
        "one(1.0)\n"  # numba set up: arraymath's check answered without scipy.linalg
        "before = 'scipy.linalg' in sys.modules\n"
        "@numba.njit\n"
        "def dot(a, b):\n"
        "    return np.dot(a, b)\n"
        "a = np.arange(12.0).reshape(3, 4) / 7.0\n"
        "b = np.arange(8.0).reshape(4, 2) - 3.0\n"
        "import numba.np.arraymath as am\n"
        "print(before, am._HAVE_BLAS, nl.ensure_blas.__name__, np.allclose(dot(a, b), a @ b, "
        "rtol=1e-15, atol=0.0), 'scipy.linalg' in sys.modules)\n")[-1]
    assert last == "False True ensure_blas True True", last
