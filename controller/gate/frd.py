"""Measured plant responses for the stability check: CSV data -> `MeasuredResponse`.

The CSV codec is `controller.gate.frd_csv` (format ``freq_hz,mag_db,phase_deg[,coherence]``;
errors name the source and line; `controller.cli.frd_files` reads the files); this module only
turns its data into the analysis's plant knowledge and builds model variants.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from controller.gate.frd_csv import FrdData
from controller.gate.knowledge import MeasuredResponse

__all__ = ["measured_from_frd", "measured_from_model"]


def measured_from_frd(
    data: FrdData,
    name: str,
    *,
    sampled: bool = False,
    min_coherence: float = 0.0,
) -> MeasuredResponse:
    """One response as plant knowledge.

    Points whose coherence is below `min_coherence` are dropped (when the data have that
    column). `sampled` says the data are already the sampled u[k] -> w[k] response.
    Raises ValueError("<source>: ...") when fewer than 2 points are left.
    """
    keep = np.ones(data.freq_hz.shape, dtype=bool)
    if data.coherence is not None and min_coherence > 0.0:
        keep = data.coherence >= min_coherence
    if np.count_nonzero(keep) < 2:
        raise ValueError(f"{data.source}: fewer than 2 points left "
                         f"(coherence >= {min_coherence})")
    return MeasuredResponse(
        name=name,
        freq_hz=data.freq_hz[keep],
        response=data.response[keep],
        sampled=sampled,
    )


def measured_from_model(
    name: str, freq_hz: ArrayLike, num: ArrayLike, den: ArrayLike
) -> MeasuredResponse:
    """A model variant (continuous num(s)/den(s), u -> load rate) sampled at `freq_hz`."""
    f = np.asarray(freq_hz, dtype=np.float64)
    s = 2j * np.pi * f
    h = np.polyval(np.asarray(num, dtype=np.float64), s) / np.polyval(
        np.asarray(den, dtype=np.float64), s
    )
    return MeasuredResponse(name=name, freq_hz=f, response=h)
