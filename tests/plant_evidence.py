"""Plant knowledge as identification hands it over: the default nominal model measured at three
positions (0.1-20 Hz, 24 points, 2 % scatter, spread 0.04). Shared by the gate-cache tests and
the apply/gate benches (tests/bench adds tests/ to sys.path)."""

from __future__ import annotations

import numpy as np

from controller.core.config import NominalModel
from controller.gate.knowledge import COMMISSIONING_BOUND, MeasuredResponse, PlantKnowledge
from controller.gate.loop_model import nominal_continuous_response


def three_positions(version: int = 2, source: str = "test: 3 positions") -> PlantKnowledge:
    f = np.logspace(-1.0, np.log10(20.0), 24)
    h = nominal_continuous_response(NominalModel(), f)
    rng = np.random.default_rng(0)
    measured = tuple(
        MeasuredResponse(f"pos{i}", f, h * (1.0 + 0.02 * rng.standard_normal(f.size)),
                         spread=np.full(f.size, 0.04))
        for i in range(3)
    )
    return PlantKnowledge(measured, COMMISSIONING_BOUND, version=version, source=source)
