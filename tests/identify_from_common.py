"""What the `identify --from` tests share: the small identification they record and a
comparison of two results that is exact for text and within a relative tolerance for
numbers."""

from __future__ import annotations

import pytest

from controller.ident.spec import IdentifySpec

__all__ = ["RTOL", "SMALL", "same_structure"]

#: A small identification at one position, 1-3 Hz (the default excitation: a multisine).
SMALL = IdentifySpec(
    f_min_hz=1.0, f_max_hz=3.0, points_per_decade=2, positions=1, amplitude_deg_s=5.0,
    min_measure_s=1.0, settle_s=0.2,
)
#: The re-analysis is the same code on the same float64 values: equal to rounding.
RTOL = 1e-9


def same_structure(a: object, b: object, rtol: float = RTOL) -> None:
    """Equal structures whose numbers agree to `rtol` (strings, bools and None exactly)."""
    if isinstance(a, dict) and isinstance(b, dict):
        assert a.keys() == b.keys()
        for k in a:
            same_structure(a[k], b[k], rtol)
    elif isinstance(a, list) and isinstance(b, list):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            same_structure(x, y, rtol)
    elif isinstance(a, float) and isinstance(b, float):
        assert a == pytest.approx(b, rel=rtol, abs=1e-300)
    else:
        assert a == b
