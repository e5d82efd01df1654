"""The twin fitted from measured knowledge includes a measured resonance (issue 35 item 1):
a lightly damped peak in the measured responses (the tune's detector,
`controller.gate.knowledge.measured_modes_hz`) becomes the twin's extra mode
(`RigFaults.resonance_*`), fitted with the other parts, kept only where it lowers the fit's
error clearly; the rig without a mode in the band gets none."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from controller.gate.knowledge import MeasuredResponse, PlantKnowledge, measured_modes_hz
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


def _noisy(k: PlantKnowledge, sigma_db: float, sigma_deg: float, seed: int) -> PlantKnowledge:
    """`k` measured with noise: each point's magnitude off by a normal `sigma_db` and its
    phase by a normal `sigma_deg`, independent from point to point (seeded)."""
    rng = np.random.default_rng(seed)
    measured = []
    for m in k.measured:
        n = m.freq_hz.size
        g = 10.0 ** (rng.normal(0.0, sigma_db, n) / 20.0) * np.exp(
            1j * np.deg2rad(rng.normal(0.0, sigma_deg, n)))
        measured.append(MeasuredResponse(m.name, m.freq_hz, m.response * g))
    return replace(k, measured=tuple(measured))


def _against_the_true_rig(twin_params: RigParams, twin_faults: RigFaults, true: RigFaults
                          ) -> list[float]:
    """The twin's response against the true rig's, rms dB per position, on a grid of its
    own (0.5-100 Hz, not the measured one)."""
    f = np.geomspace(0.5, 100.0, 200)
    return [position_fit("check", pos, f, rig_response(RigParams(), true, f, pos, RATE),
                         rig_response(twin_params, twin_faults, f, pos, RATE)).rms_db
            for pos in POSITIONS_DEG]


@pytest.mark.slow
def test_a_mode_measured_with_noise_is_found_and_sized() -> None:
    """The 25 Hz / 0.02 mode rig measured with 0.5 dB and 3 deg of noise per point: the mode
    kept, its frequency within 1 % and its damping within 15 % of the true rig's, the fit's
    error at the noise's level (below 0.8 dB rms per position, 10.9 dB without the mode), and
    the twin's response within 0.2 dB rms of the true rig's at every position (the noise
    averaged out, not fitted)."""
    true = RigFaults(resonance_hz=25.0, resonance_damping=0.02)
    knowledge = _noisy(true_knowledge(RigParams(), true, RATE), 0.5, 3.0, seed=1)
    assert measured_modes_hz(knowledge), "the noisy responses must still show the peak"
    twin = twin_from_knowledge(knowledge, rate_hz=RATE)
    said = [n for n in twin.notes if n.startswith("extra mode")]
    assert len(said) == 1 and said[0].endswith(": kept"), twin.notes
    assert twin.faults.resonance_hz == pytest.approx(25.0, rel=0.01)
    assert twin.faults.resonance_damping == pytest.approx(0.02, rel=0.15)
    for p in twin.positions:
        assert p.rms_db < 0.8, p.describe()
    worst = max(_against_the_true_rig(twin.params, twin.faults, true))
    assert worst < 0.2, worst


@pytest.mark.slow
def test_a_peak_a_mode_does_not_explain_is_not_kept() -> None:
    """The rig without a mode measured with 2 dB and 10 deg of noise per point: the detector
    finds a 'peak' (a bump of the noise near 2 Hz), the fit with a mode there does not halve
    the error, so the twin has no mode, the notes say 'not kept' with the errors before and
    after, and the twin without it is within 0.5 dB rms of the true rig at every position."""
    knowledge = _noisy(true_knowledge(RigParams(), RigFaults(), RATE), 2.0, 10.0, seed=2)
    peaks = measured_modes_hz(knowledge)
    assert peaks and min(f for f, _ in peaks) < 5.0, peaks
    twin = twin_from_knowledge(knowledge, rate_hz=RATE)
    said = [n for n in twin.notes if n.startswith("extra mode")]
    assert len(said) == 1 and said[0].endswith("not kept (it does not lower the error clearly)"), (
        twin.notes)
    before, after = (float(v) for v in said[0].split("fit ")[1].split(" dB")[0].split(" -> "))
    assert after > 0.5 * before or after > before - 0.3, said
    assert twin.faults.resonance_hz == 0.0
    assert "resonance_hz" not in twin.fitted
    worst = max(_against_the_true_rig(twin.params, twin.faults, RigFaults()))
    assert worst < 0.5, worst
