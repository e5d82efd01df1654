"""The twin's friction, backlash and encoder noise from the controller's own running (issue 35
item 1): a real controller process over Zenoh on loopback, on the simulated article rig (its
disturbances), builds the twin after a knowledge change with the newest 25 s of normal running
from its black box (`controller/process/twin_running.py`, in the analysis worker). A window
that tells nothing (a ramp: the command never reverses, no slow sample) leaves the base rig's
values and the twin's notes say why; the article's sine tells them, each with its deviation,
against the simulated rig's own values (the independent reference): the noise within the
offline test's tolerance, the Coulomb friction and the backlash within 4 of their deviations."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import wait_until
from procs import APPLY_TIMEOUT_S, Client, ControllerProcess

from controller import protocol as proto
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import (
    COMMISSIONING_BOUND,
    KnowledgeRecord,
    MeasuredResponse,
    PlantKnowledge,
)
from controller.process.twin_running import BASE_RIG, WINDOW_S
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import RigFaults
from controller.twin.fit import rig_response
from controller.twin.model import RigTwin, decode

pytestmark = [pytest.mark.integration, pytest.mark.timeout(900)]

TRUE = rig_setup(("article-rig",)).params
TRUE_BACKLASH_DEG = TRUE.backlash_deg + TRUE.gearbox_backlash_deg
#: The noise's tolerance tests/test_twin_nonlinear.py states for a 20 s sine window (its
#: Coulomb's and backlash's are not met live: see the test).
NOISE_TOL = 0.15  # relative


@pytest.fixture
def article_controller(start_controller_factory: object) -> ControllerProcess:
    return start_controller_factory(  # type: ignore[operator,no-any-return]
        rig="twinrun", extra_args=("--realtime-priority", "--disturbance", "article-rig"))


def _knowledge(c: Client, req: proto.KnowledgeRequest | None = None) -> proto.KnowledgeReply:
    payload = proto.encode(req) if req is not None else None
    timeout_s = APPLY_TIMEOUT_S if req is not None else None
    return proto.decode(c.query_raw(proto.key_knowledge(c.rig), payload, timeout_s),
                        proto.KnowledgeReply)


def _record(positions: tuple[float, ...]) -> KnowledgeRecord:
    """The article rig's exact linear responses at `positions` (what a clean identification
    measures)."""
    f = np.geomspace(0.2, 20.0, 25)
    measured = tuple(MeasuredResponse(f"pos{i}_{p:g}deg", f, rig_response(TRUE, RigFaults(), f, p))
                     for i, p in enumerate(positions))
    return KnowledgeRecord.of(PlantKnowledge(measured=measured, bound=COMMISSIONING_BOUND,
                                             source="test"))


def _run_then_adopt(c: Client, traj: Trajectory, positions: tuple[float, ...]) -> RigTwin:
    """Run `traj` for more than the window (`WINDOW_S`), adopt knowledge, wait for its twin."""
    with c.state() as col:
        reply = c.command(proto.SetTrajectory(trajectory=traj))
        assert reply.ok, reply
        # the whole window after the change of trajectory (its first second: the transition)
        assert col.wait_for_seq(reply.seq + round((WINDOW_S + 1.5) * 1000), timeout_s=120.0)
        modes = {b.mode for _, b in col.batches()}
    assert modes == {"running"}, modes
    adopted = _knowledge(c, proto.KnowledgeRequest(record=_record(positions)))
    assert adopted.ok, adopted.message
    assert wait_until(lambda: bool(_knowledge(c).twin) or "being built" not in
                      _knowledge(c).twin_note, timeout_s=600.0)
    got = _knowledge(c)
    assert got.twin, got.twin_note
    twin = decode(got.twin)
    assert twin.knowledge_version == adopted.record.version
    return twin


def test_the_twin_takes_friction_backlash_and_noise_from_recent_running(
        article_controller: ControllerProcess) -> None:
    with Client(article_controller.endpoint, article_controller.rig) as c:
        c.wait_ready(article_controller)
        # A ramp: the window tells nothing; the twin keeps the base rig's and says why.
        ramp = _run_then_adopt(c, Trajectory(kind="ramp", slope_deg_s=1.0), (0.0, 180.0))
        said = [n for n in ramp.notes if n.startswith(BASE_RIG)]
        assert len(said) == 1 and "tells nothing" in said[0], ramp.notes
        assert "the controller's running" in said[0] and "UTC" in said[0], said
        est = ramp.nonlinear
        assert est is not None and est.coulomb_std_n_m is None and est.window == ""
        assert est.backlash_std_deg is None and est.position_noise_std_deg is None
        assert any("assumed" in h for h in est.how), est.how
        # The article's sine: each estimated, with its deviation, from the window named.
        sine = _run_then_adopt(c, Trajectory(), (0.0, 120.0, 240.0))
        est = sine.nonlinear
        assert est is not None
        print("sine window:", est.window, "|", est.describe())
        said = [n for n in sine.notes if n.startswith("estimated from the controller's running")]
        assert len(said) == 1 and est.describe() in said[0], sine.notes
        assert f"{WINDOW_S:.3g} s" in est.window and "UTC" in est.window, est.window
        assert est.coulomb_std_n_m is not None and est.backlash_std_deg is not None
        assert est.position_noise_std_deg is not None
        assert not any(n.startswith(BASE_RIG) for n in sine.notes)
        fc, bl, sd = est.coulomb_torque_n_m, est.backlash_deg, est.position_noise_deg
        # The encoder noise within the offline test's tolerance; the Coulomb friction and the
        # backlash less well told live than offline (the drive's offset, ripple and the belt's
        # variation are in the live rig, not in the twin fitted to its responses, and the
        # d_hat offset is not taken into the twin first): three runs gave Coulomb 0.262 +-
        # 0.065, 0.393 +- 0.305 (15 s windows), 0.368 +- 0.069 N m (25 s) against 0.25, and
        # backlash 0.083 +- 0.056, 0.002 +- 0.18, 0.014 +- 0.063 deg against 0.05. Each
        # within 4 of its stated deviations, and those not vacuous (the fit's ranges: Coulomb
        # x0.125-x8 of the twin's 0.25 N m, the dead zone 0-0.6 deg).
        assert sd == pytest.approx(TRUE.position_noise_deg, rel=NOISE_TOL), est.describe()
        assert abs(sd - TRUE.position_noise_deg) <= 4 * est.position_noise_std_deg
        assert abs(fc - TRUE.coulomb_torque_n_m) <= 4 * est.coulomb_std_n_m, est.describe()
        assert abs(bl - TRUE_BACKLASH_DEG) <= 4 * est.backlash_std_deg + 1e-4, est.describe()
        assert est.coulomb_std_n_m < 0.25 and est.backlash_std_deg < 0.3, est.describe()
        # in the twin the offline loop runs
        assert sine.params.coulomb_torque_n_m == fc and sine.params.position_noise_deg == sd
