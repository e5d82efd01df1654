"""The twin fitted from measured knowledge includes a measured resonance (issue 35 item 1):
a lightly damped peak in the measured responses (the tune's detector,
`controller.gate.knowledge.measured_modes_hz`) becomes the twin's extra mode
(`RigFaults.resonance_*`), fitted with the other parts, kept only where it lowers the fit's
error clearly; the rig without a mode in the band gets none."""

from __future__ import annotations

import numpy as np
import pytest

from controller.sim.sim_rig import RigFaults, RigParams
from controller.tune.family import POSITIONS_DEG, true_knowledge
from controller.twin.fit import position_fit, rig_response, twin_from_knowledge

RATE = 1000.0


def test_a_measured_25_hz_mode_is_in_the_twin() -> None:
    """The rig's exact responses at three positions (a 25 Hz mode at damping 0.02): the
    twin's mode within 3 % in frequency and 30 % in damping, its fit below 1 dB rms at every
    position (10.9 dB without the mode), the notes state the before and after; the twin's
    response against the true rig's on a grid of its own through the peak."""
    true = RigFaults(resonance_hz=25.0, resonance_damping=0.02)
    twin = twin_from_knowledge(true_knowledge(RigParams(), true, RATE), rate_hz=RATE)
    assert twin.faults.resonance_hz == pytest.approx(25.0, rel=0.03)
    assert twin.faults.resonance_damping == pytest.approx(0.02, rel=0.30)
    assert twin.fitted["resonance_hz"] == twin.faults.resonance_hz
    for p in twin.positions:
        assert p.rms_db < 1.0, p.describe()
    said = [n for n in twin.notes if n.startswith("extra mode")]
    assert len(said) == 1 and said[0].endswith(": kept"), twin.notes
    before, after = (float(v) for v in said[0].split("fit ")[1].split(" dB")[0].split(" -> "))
    assert before > 3.0 and after < 1.0, said
    f = np.geomspace(15.0, 40.0, 77)  # not the measured grid
    for pos in POSITIONS_DEG:
        fit = position_fit("check", pos, f, rig_response(RigParams(), true, f, pos, RATE),
                           rig_response(twin.params, twin.faults, f, pos, RATE))
        assert fit.rms_db < 1.0, fit.describe()


def test_the_rig_without_a_mode_in_band_gets_none() -> None:
    twin = twin_from_knowledge(true_knowledge(RigParams(), RigFaults(), RATE), rate_hz=RATE)
    assert twin.faults.resonance_hz == 0.0
    assert "resonance_hz" not in twin.fitted
    assert not [n for n in twin.notes if n.startswith("extra mode")], twin.notes
    for p in twin.positions:
        assert p.rms_db < 1.0, p.describe()
