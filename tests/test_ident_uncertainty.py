"""Measurements that tell the truth (issue 35 item 0): a difference between positions is
judged against the measurement's own uncertainty (its noise lines: the estimate's standard
deviations), the statements agree with each other, and on the demo's rig (article-rig) the
one unreliable low point no longer decides the recommended cut-off."""

from __future__ import annotations

import math

import numpy as np
import pytest
from demo_identification import DEMO_CONFIG, demo_identification

from controller.gate.knowledge import (
    COMMISSIONING_BOUND,
    DIVERGENCE_FRACTION,
    UNCERTAINTY_SIGMAS,
    MeasuredResponse,
    PlantKnowledge,
    position_spread,
)
from controller.ident.estimate import FrdEstimate, agreement
from controller.ident.result import relative_uncertainty_of

F = np.geomspace(0.1, 10.0, 12)


def _pair(low_db: float) -> tuple[np.ndarray, np.ndarray]:
    a = np.ones(F.size, dtype=np.complex128)
    b = a.copy()
    b[0] = 10 ** (low_db / 20)  # only the lowest point differs
    return a, b


def _est(h: np.ndarray, std_db: np.ndarray) -> FrdEstimate:
    n = h.size
    return FrdEstimate(freq_hz=F, response=h, coherence=np.ones(n), mag_std_db=std_db,
                       phase_std_deg=np.zeros(n), n_averages=np.ones(n, dtype=np.int64),
                       method="open_loop_h1")


def test_a_difference_within_the_uncertainty_is_not_a_divergence() -> None:
    a, b = _pair(2.5)
    std = np.full(F.size, 0.01)
    plain = position_spread((MeasuredResponse("p0_0deg", F, a),
                             MeasuredResponse("p1_120deg", F, b)))
    assert plain is not None and plain.divergence_hz == pytest.approx(F[0])
    u = std.copy()
    u[0] = 0.2  # 2 sigma = 0.4 > |10^(2.5/20) - 1| - ... : the point cannot show it
    spread = position_spread((MeasuredResponse("p0_0deg", F, a, spread=u),
                              MeasuredResponse("p1_120deg", F, b, spread=u)))
    assert spread is not None and spread.divergence_hz is None
    # the closed form: the geometric mean sits halfway in dB, each differs by 1.25 dB from it
    d = 10 ** (1.25 / 20) - 1
    assert spread.measured is not None
    assert spread.measured[0] == pytest.approx(d, rel=1e-9)
    assert spread.relative[0] == pytest.approx(max(0.0, d - UNCERTAINTY_SIGMAS * 0.2), abs=1e-12)
    assert d > DIVERGENCE_FRACTION


def test_a_difference_beyond_the_uncertainty_still_is() -> None:
    a, b = _pair(6.0)
    u = np.full(F.size, 0.01)
    spread = position_spread((MeasuredResponse("p0", F, a, spread=u),
                              MeasuredResponse("p1", F, b, spread=u)))
    assert spread is not None and spread.divergence_hz == pytest.approx(F[0])


def test_agreement_states_what_its_numbers_say() -> None:
    a, b = _pair(2.5)
    low_std = np.full(F.size, 0.02)
    noisy = low_std.copy()
    noisy[0] = 1.5  # 2 sigma = 3 dB > 2.5 dB - 1 dB
    ag = agreement([_est(a, noisy), _est(b, noisy)])
    assert ag.first_disagree_hz is None and ag.unresolved_hz == (pytest.approx(0.1),)
    assert "whole band" in ag.describe() and "0.1 Hz" in ag.describe()
    ag = agreement([_est(a, low_std), _est(b, low_std)])
    assert ag.differs_at_lowest
    text = ag.describe()
    assert "already at the lowest frequency (0.1 Hz)" in text and "below 0 Hz" not in text
    c = a.copy()
    c[5:] *= 10 ** (2 / 20)
    ag = agreement([_est(a, low_std), _est(c, low_std)])
    assert ag.describe().startswith(f"curves agree within 1 dB / 10 deg up to {F[4]:.3g} Hz")


def test_relative_uncertainty_is_magnitude_and_phase_together() -> None:
    e = _est(np.ones(F.size, dtype=np.complex128), np.full(F.size, 1.0))
    e = FrdEstimate(e.freq_hz, e.response, e.coherence, e.mag_std_db,
                    np.full(F.size, 2.0), e.n_averages, e.method)
    want = math.hypot(math.log(10) / 20, math.radians(2.0))
    assert relative_uncertainty_of(e) == pytest.approx(np.full(F.size, want))


def test_on_the_demo_rig_the_low_point_does_not_decide_the_cut_off() -> None:
    """`dobtune identify --plant sim --positions 3 --disturbance article-rig`: before, the
    0.1 Hz point (about 2.2 dB apart, 2 sigma about 3.4 dB) made the responses 'diverge above
    0.1 Hz' and capped Q31 at 0.113 Hz. Now the divergence is where the spread table shows it
    (between 2 Hz, 0.3 dB, and 5 Hz, 1.35 dB) and the cut-off is the gate's."""
    res = demo_identification()
    sp = res.position_spread
    assert sp is not None and sp.divergence_hz is not None
    assert 2.0 < sp.divergence_hz < 5.0
    assert res.agreement is not None and res.agreement.first_disagree_hz is not None
    assert 2.0 < res.agreement.first_disagree_hz <= 5.5
    assert res.recommended_cutoff_hz["q31"] is not None
    assert res.recommended_cutoff_hz["q31"] > 1.0


def _status_of(out_positions: list, state: str = "done") -> object:
    """The identification status a controller sends for these offline positions, through the
    wire (the controller's own column builder)."""
    from controller import protocol as proto
    from controller.process.identify_runs import _position_response, _response_columns

    pos = [_position_response(i, p.center_deg, 1, 1, _response_columns(p.estimate))
           for i, p in enumerate(out_positions)]
    st = proto.IdentifyStatus(rig="r", state=state, run_id=1, progress=1.0, positions=pos)
    return proto.decode(proto.encode(st), proto.IdentifyStatus)


def test_the_dashboard_and_the_controller_state_the_uncertainty_the_command_line_does() -> None:
    """The Measure of the guided path adopts the responses from the controller's status
    (`view_from_status`, `IdentifyRuns.adoptable`): they carried no uncertainty (dashboard)
    or twice it (controller), so the demo's Measure at 3 positions still capped Q31 at
    0.113 Hz where `dobtune identify` said the gate's 4.8 Hz. Both now state exactly the
    estimate's `relative_uncertainty_of`, and with NaN standard deviations the coherence's
    random error (Bendat & Piersol, n = 1: sqrt(1 - g^2) / (g sqrt 2) in nepers and rad)."""
    from controller.gate.search import knowledge_spread, recommend
    from controller.ident.result import position_uncertainty
    from server.identify_view import view_from_status

    cfg = DEMO_CONFIG
    result = demo_identification()
    positions = list(result.positions)
    st = _status_of(positions)
    view = view_from_status(st, 3, cfg.nominal)  # type: ignore[arg-type]
    assert len(view.measured) == 3
    for p, m in zip(positions, view.measured, strict=True):
        want = relative_uncertainty_of(p.estimate)
        assert m.spread is not None
        np.testing.assert_allclose(m.spread, want, rtol=1e-12, atol=1e-15)
    # the 0.1 Hz point is the uncertain one (friction at small amplitude, noise lines)
    assert max(float(m.spread[0]) for m in view.measured if m.spread is not None) > 0.1
    # the recommendation on the dashboard's knowledge is the command line's, not 0.113 Hz
    kn = PlantKnowledge(measured=view.measured, bound=COMMISSIONING_BOUND)  # as the CLI judges
    sp = knowledge_spread(kn, cfg.rate_hz)
    assert sp is not None and sp.divergence_hz is not None and sp.divergence_hz > 2.0
    rec = recommend(cfg, kn, q_type="q31")
    assert rec.recommended_hz is not None and rec.recommended_hz > 1.0, rec.describe()
    # an older sender: no standard deviations, only the coherence
    g = np.array([0.5, 0.9, 0.99])
    u = position_uncertainty([1.0, 2.0, 3.0], g.tolist(), [], [])
    eps = np.sqrt(1 - g) / np.sqrt(2 * g)
    assert u is not None
    np.testing.assert_allclose(u, np.hypot(eps, eps), rtol=1e-12)
    assert position_uncertainty([1.0, 2.0], [], [], []) is None
