"""Identification above the first band (controller.ident.zoom): the multisine's resolution
apart from its band's low end, the scan that finds a mode, the zoomed pass that resolves it,
the passes merged; on a family rig whose lightly damped mode lies above 20 Hz, the identified
responses show the mode where the true rig has it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from controller.gate.knowledge import MeasuredResponse, measured_modes_hz
from controller.gate.loop_model import discrete_equivalent
from controller.ident.plan import _build_excitation
from controller.ident.spec import IdentifySpec
from controller.ident.zoom import (
    SCAN_BAND_HZ,
    merge_responses,
    scan_spec,
    zoom_band_hz,
    zoom_spec,
)
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import RigFaults, RigParams
from controller.tune.family import FamilyRig, identify
from controller.twin.fit import rig_response


def test_resolution_sets_the_period_and_the_band_its_lines() -> None:
    plain = _build_excitation(IdentifySpec(f_min_hz=20.0, f_max_hz=30.0,
                                           points_per_decade=200), 1000.0)
    fine = _build_excitation(IdentifySpec(f_min_hz=20.0, f_max_hz=30.0, points_per_decade=200,
                                          resolution_hz=0.1), 1000.0)
    f = np.asarray(fine.freq_hz)
    # at a 20 Hz resolution the odd lines in 20-30 Hz are 20 Hz alone; at 0.1 Hz the band's
    # 200 per decade, every line an odd multiple of 0.1 Hz
    assert np.asarray(plain.freq_hz).size <= 2
    assert f.size > 25
    assert f[0] >= 20.0 - 1e-9 and f[-1] <= 30.0 + 1e-9
    assert np.max(f[1:] / f[:-1]) < 1.03
    odd = np.round(f / 0.1)
    assert np.allclose(f / 0.1, odd) and np.all(odd % 2 == 1)
    with pytest.raises(ConfigError, match=r"^resolution_hz"):
        IdentifySpec(f_min_hz=1.0, resolution_hz=2.0)


def _response(name: str, f: list[float], scale: float, spread: float) -> MeasuredResponse:
    fa = np.array(f)
    return MeasuredResponse(name, fa, scale * (1.0 + 1j * fa), spread=np.full(fa.size, spread))


def test_merge_keeps_every_point_sorted_and_the_later_pass_where_both_measured() -> None:
    a = (_response("p0", [1.0, 2.0, 4.0], 1.0, 0.01), _response("p1", [1.0, 2.0, 4.0], 1.0, 0.01))
    b = (_response("s0", [3.0, 4.0, 5.0], 2.0, 0.02), _response("s1", [3.0, 4.0, 5.0], 2.0, 0.02))
    got = merge_responses(a, b)
    assert [m.name for m in got] == ["p0", "p1"]
    m = got[0]
    assert list(m.freq_hz) == [1.0, 2.0, 3.0, 4.0, 5.0]
    scale = np.abs(m.response) / np.abs(1.0 + 1j * m.freq_hz)
    assert list(np.round(scale, 9)) == [1.0, 1.0, 2.0, 2.0, 2.0]  # 4 Hz from the later pass
    assert m.spread is not None and list(m.spread) == [0.01, 0.01, 0.02, 0.02, 0.02]
    with pytest.raises(ValueError, match="one response per position"):
        merge_responses(a, b[:1])


def _scan_of(faults: RigFaults) -> tuple[MeasuredResponse, ...]:
    """The rig's exact (sampled) responses on the scan's grid."""
    spec = scan_spec(IdentifySpec())
    f = np.asarray(_build_excitation(spec, 1000.0).freq_hz)
    params = RigParams()
    return tuple(
        MeasuredResponse(f"p{pos:g}", f, discrete_equivalent(
            rig_response(params, faults, f, pos), f, 1000.0))
        for pos in (0.0, 120.0, 240.0))


def test_zoom_band_is_about_the_scans_lowest_mode() -> None:
    band = zoom_band_hz(_scan_of(RigFaults(resonance_hz=27.0, resonance_damping=0.02)))
    assert band is not None
    lo, hi = band
    assert lo < 27.0 < hi and hi / lo < 2.0
    assert SCAN_BAND_HZ[0] <= lo and hi <= SCAN_BAND_HZ[1]
    zs = zoom_spec(IdentifySpec(f_min_hz=0.5, resolution_hz=0.5 / 3), band)
    assert (zs.f_min_hz, zs.f_max_hz) == band and zs.resolution_hz is not None
    assert zs.resolution_hz <= 0.01 * lo / 1.5
    # a rig without the extra mode: the scan shows none, nothing to zoom
    assert zoom_band_hz(_scan_of(RigFaults())) is None


def test_a_family_rigs_mode_above_the_first_band_is_measured() -> None:
    """A lightly damped mode at 25 Hz (damping 0.01: its half-power band 0.5 Hz wide), above
    the first pass's 20 Hz: the identified responses show a mode and peak where the true rig
    does, ten or more points lie within 10 % of the peak, and they agree with the true rig's
    sampled response."""
    fr, z = 25.0, 0.01
    params = RigParams()
    faults = RigFaults(resonance_hz=fr, resonance_damping=z)
    rig = FamilyRig(0, 1.0, 1.0, 1.0, fr, z, params.command_delay_ticks, params, faults)
    known = identify(rig.plant, LoopConfig())
    params = rig_setup(("article-rig",), base=params).params  # the rig that was measured
    assert "zoomed" in known.source, known.source
    assert len(measured_modes_hz(known)) == len(known.measured) == 3  # each shows a mode
    fine = np.linspace(20.0, 40.0, 4001)
    for m in known.measured:
        band = (m.freq_hz > 20.0) & (m.freq_hz < 40.0)
        f_peak = float(m.freq_hz[band][int(np.argmax(np.abs(m.response[band])))])
        pos = float(m.name.split("_")[-1].removesuffix("deg"))
        # the coupled mode's peak (the load's 20 % on its spring: not at fr itself)
        true_fine = np.abs(discrete_equivalent(rig_response(params, faults, fine, pos), fine,
                                               1000.0))
        at = float(fine[int(np.argmax(true_fine))])
        assert f_peak == pytest.approx(at, rel=0.015), (f_peak, at)
        near = (m.freq_hz > at / 1.1) & (m.freq_hz < at * 1.1)
        assert np.count_nonzero(near) >= 10  # zoomed: dense across the mode
        f = m.freq_hz[near]
        true = discrete_equivalent(rig_response(params, faults, f, pos), f, 1000.0)
        ratio = m.response[near] / true
        # magnitude within 1 dB across the mode (0.5 dB in the median); the phase leads
        # `discrete_equivalent` of the continuous response by one tick (0.36 deg/Hz, seen
        # over the whole band: the two count the held command's tick differently), within
        # 5 deg of that (2.5 in the median)
        db = np.abs(20.0 * np.log10(np.abs(ratio)))
        assert np.all(db < 1.0) and float(np.median(db)) < 0.5, db
        lag = np.degrees(np.angle(ratio * np.exp(-2j * math.pi * f / 1000.0)))
        assert np.all(np.abs(lag) < 5.0) and float(np.median(np.abs(lag))) < 2.5, lag
