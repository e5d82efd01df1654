"""numba as the product's compiled kernels import it: `from controller.core.numba_start import
numba`, so that a process's first compile (or load from numba's cache) does not import
scipy.linalg.

numba sets itself up on a process's first compile; part of that imports `numba.np.arraymath`,
which decides whether `np.dot` may call BLAS by importing `scipy.linalg.cython_blas`: the whole
of scipy.linalg and, through scipy >= 1.15's array-API layer (it clones numpy's namespace),
numpy.f2py and numpy.testing. That was 0.2-0.3 CPU s of every controller start, every analysis
worker and every `dobtune check`, for kernels none of which calls BLAS. Here the question is
answered the same way without the import: scipy.linalg can be found (`importlib.util.find_spec`),
or an ImportError as numba's own check raises. The check is replaced only for that one question
(arraymath binds it when it is imported) and numba's own `ensure_blas` is back at once: a kernel
that used BLAS would import scipy.linalg on its first compile as numba always does.
"""

from __future__ import annotations

import importlib.util
import sys

import numba
import numba.np.linalg as _numba_linalg

__all__ = ["numba"]


def _blas_without_import() -> None:
    """numba's BLAS check for arraymath's import: scipy.linalg present, not imported."""
    _numba_linalg.ensure_blas = _ensure_blas  # numba's own from now on
    if importlib.util.find_spec("scipy.linalg") is None:
        raise ImportError("scipy 0.16+ is required for linear algebra")


_ensure_blas = _numba_linalg.ensure_blas
if "numba.np.arraymath" not in sys.modules:  # numba not set up yet in this process
    _numba_linalg.ensure_blas = _blas_without_import
