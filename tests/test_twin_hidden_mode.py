"""The twin finds a mode the 3 dB rule misses (issue 35 item 4: the twin predicted half, or
2.7x, the true rig's tracking error on several family rigs). Measured over the family's
identification band (0.5-60 Hz), a well-damped mode inside the band lifts the response by less
than 3 dB (`measured_modes_hz` shows none), and a mode above the band shows only as a rising
top; without it the fit bent the load's inertia, stiffness, friction, the droop and the delay
to mimic it. Here, on the family rigs' exact responses cut to that band, the twin's fitted
parts come back to the true rig's, and the rig without a mode gets none."""

from __future__ import annotations

from dataclasses import replace

import pytest

from controller.gate.knowledge import PlantKnowledge, measured_modes_hz
from controller.sim.sim_rig import RigFaults, RigParams
from controller.tune.family import draw_family, true_knowledge
from controller.twin.fit import twin_from_knowledge

BAND_HZ = (0.5, 60.0)  # the family's identification: the first pass and the scan


def _banded(k: PlantKnowledge) -> PlantKnowledge:
    lo, hi = BAND_HZ
    out = []
    for m in k.measured:
        keep = (m.freq_hz >= lo) & (m.freq_hz <= hi)
        out.append(replace(m, freq_hz=m.freq_hz[keep], response=m.response[keep]))
    return replace(k, measured=tuple(out))


@pytest.mark.parametrize(("seed", "index", "where"), [
    (819073823, 3, "in the band"),  # 36 Hz, damping 0.044: a 2 dB bump
    (2632146472, 7, "above the band"),  # 98 Hz, damping 0.030
])
def test_a_mode_the_3_db_rule_misses_is_in_the_twin(seed: int, index: int, where: str) -> None:
    """The mode within 3 % and the load's inertia, stiffness, the drive's gain within 5 % of
    the true rig's, its delay exact; the notes say which way the mode was found (the fit
    without it missed the inertia by 2x or more, the delay by 2-3 ticks)."""
    rig = draw_family(seed, index + 1)[index]
    k = _banded(true_knowledge(rig.params, rig.faults))
    assert not measured_modes_hz(k)
    tw = twin_from_knowledge(k)
    assert tw.faults.resonance_hz == pytest.approx(rig.resonance_hz, rel=0.03)
    assert tw.fitted["inertia_factor"] == pytest.approx(rig.inertia_factor, rel=0.05)
    assert tw.fitted["stiffness_factor"] == pytest.approx(rig.stiffness_factor, rel=0.05)
    assert tw.fitted["gain_factor"] == pytest.approx(rig.drive_gain, rel=0.05)
    assert tw.params.command_delay_ticks == rig.delay_ticks
    said = [n for n in tw.notes if n.startswith("extra mode")]
    assert len(said) == 1 and "kept" in said[0] and "not kept" not in said[0], tw.notes
    key = "under 3 dB" if where == "in the band" else "above the measured band"
    assert key in said[0], said


def test_the_rig_without_a_mode_gets_none_above_the_band() -> None:
    """The built-in rig over the same band: a mode above it is tried (the fit is no better
    and the base rig no nearer), not kept, and said."""
    tw = twin_from_knowledge(_banded(true_knowledge(RigParams(), RigFaults())))
    assert tw.faults.resonance_hz == 0.0 and "resonance_hz" not in tw.fitted
    said = [n for n in tw.notes if n.startswith("extra mode")]
    assert len(said) == 1 and said[0].endswith(": not kept"), tw.notes
    assert tw.fitted["inertia_factor"] == pytest.approx(1.0, rel=0.02)
    assert tw.params.command_delay_ticks == 0
