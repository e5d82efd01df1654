"""The twin's friction, backlash and encoder noise from the controller's own running (issue 35
item 1): a real controller process over Zenoh on loopback, on the simulated article rig (its
disturbances), builds the twin after a knowledge change with the newest 25 s of normal running
from its black box (`controller/process/twin_running.py`, in the twin's worker): the
stretch where the loop followed its trajectory (the approach onto it cut off), the drive
offset the twin lacks taken from the DOB's d_hat first. The twin starts from the structure of
the rig the controller simulates (the article rig: its motor and gearbox friction, drive
offset, ...; as `dobtune tune` and the watch do). A window that tells nothing (a ramp: the
command never reverses, no slow sample) leaves the base rig's values and the twin's notes say
why; the article's sine tells them, each with its deviation, against the simulated rig's own
values (the independent reference)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import wait_until
from procs import APPLY_TIMEOUT_S, Client, ClientError, ControllerProcess, StateCollector

from controller import protocol as proto
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import (
    COMMISSIONING_BOUND,
    KnowledgeRecord,
    MeasuredResponse,
    PlantKnowledge,
)
from controller.process.twin_running import BASE_RIG, OFFSET_KEPT, WINDOW_S
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import RigFaults
from controller.twin.fit import rig_response
from controller.twin.model import RigTwin, decode

pytestmark = [pytest.mark.integration, pytest.mark.timeout(900)]

TRUE = rig_setup(("article-rig",)).params
TRUE_BACKLASH_DEG = TRUE.backlash_deg + TRUE.gearbox_backlash_deg
#: The noise's tolerance tests/test_twin_nonlinear.py states for a 20 s sine window.
NOISE_TOL = 0.15  # relative
ADOPT_TIMEOUT_S = max(APPLY_TIMEOUT_S, 180.0)
#: A plain knowledge query's (the client's 5 s is not met at load 30+: seen).
QUERY_TIMEOUT_S = 60.0
#: The truth within this many of each stated deviation.
K_STD = 4.0
#: The deviations live are below these (a fifth of the true Coulomb friction, 60 % of the
#: true dead zone; see the measured runs in the test): a deviation as wide as the estimate
#: would pass K_STD vacuously.
COULOMB_STD_MAX_N_M = 0.05
BACKLASH_STD_MAX_DEG = 0.03


@pytest.fixture
def article_controller(start_controller_factory: object) -> ControllerProcess:
    return start_controller_factory(  # type: ignore[operator,no-any-return]
        rig="twinrun", extra_args=("--realtime-priority", "--disturbance", "article-rig"))


def _knowledge(c: Client, req: proto.KnowledgeRequest | None = None) -> proto.KnowledgeReply:
    payload = proto.encode(req) if req is not None else None
    # an adoption is judged by the gate first: at load 28 with two busy loops beside, more
    # than the dashboard's APPLY_TIMEOUT_S (30 s) (a generous deadline, not a timing claim;
    # the edge forwards it for 30 s at most: `_run_then_adopt`)
    timeout_s = ADOPT_TIMEOUT_S if req is not None else QUERY_TIMEOUT_S
    return proto.decode(c.query_raw(proto.key_knowledge(c.rig), payload, timeout_s),
                        proto.KnowledgeReply)


def _polled(c: Client) -> proto.KnowledgeReply | None:
    """The knowledge as a poll sees it; None while the loop process does not answer in time
    (at load 30+: the next poll asks again, the caller's deadline bounds it)."""
    try:
        return _knowledge(c)
    except ClientError:
        return None


def _record(positions: tuple[float, ...]) -> KnowledgeRecord:
    """The article rig's exact linear responses at `positions` (what a clean identification
    measures)."""
    f = np.geomspace(0.2, 20.0, 25)
    measured = tuple(MeasuredResponse(f"pos{i}_{p:g}deg", f, rig_response(TRUE, RigFaults(), f, p))
                     for i, p in enumerate(positions))
    return KnowledgeRecord.of(PlantKnowledge(measured=measured, bound=COMMISSIONING_BOUND,
                                             source="test"))


#: The reference's rate above which it is the approach onto a trajectory (up to 20 deg/s),
#: not one of this test's trajectories (the sine's rate is at most 2.5 deg/s, the ramp's 1).
APPROACH_DEG_S = 3.0


def _followed_s(col: StateCollector, since_seq: int) -> float:
    """Seconds of the newest samples (from `since_seq` on) since the reference last moved
    faster than `APPROACH_DEG_S` or jumped (a lost batch counts as a break)."""
    got = sorted((b for _, b in col.batches() if b.seq0 >= since_seq), key=lambda b: b.seq0)
    if not got:
        return 0.0
    ref = np.concatenate([np.asarray(b.ref_deg) for b in got])
    seq = np.concatenate([b.seq0 + np.arange(len(b.ref_deg)) for b in got])
    fast = (np.abs(np.diff(ref)) * got[-1].rate_hz > APPROACH_DEG_S) | (np.diff(seq) != 1)
    last = int(np.flatnonzero(fast)[-1]) + 1 if fast.any() else 0
    return (ref.size - last) / got[-1].rate_hz


def _run_then_adopt(c: Client, traj: Trajectory, positions: tuple[float, ...]) -> RigTwin:
    """Run `traj` until the loop has followed it (the approach onto it over) for more than
    the window (`WINDOW_S`), adopt knowledge, wait for its twin."""
    with c.state() as col:
        reply = c.command(proto.SetTrajectory(trajectory=traj))
        assert reply.ok, reply
        assert wait_until(lambda: _followed_s(col, reply.seq) >= WINDOW_S + 1.5,
                          timeout_s=300.0, poll_s=0.5), _followed_s(col, reply.seq)
        modes = {b.mode for _, b in col.batches()}
    assert modes == {"running"}, modes
    before = _knowledge(c).record.version
    try:
        adopted = _knowledge(c, proto.KnowledgeRequest(record=_record(positions)))
        assert adopted.ok, adopted.message
        version = adopted.record.version
    except ClientError as exc:
        # at load 30+ the loop process may answer after the edge's 30 s: it still takes
        # effect (the edge says so); wait for the new version (a generous deadline)
        assert "may still take effect" in str(exc), exc
        assert wait_until(lambda: (k := _polled(c)) is not None and k.record.version > before,
                          timeout_s=300.0, poll_s=1.0), exc
        version = _knowledge(c).record.version
    assert wait_until(lambda: (k := _polled(c)) is not None and (
        bool(k.twin) or "being built" not in k.twin_note), timeout_s=600.0, poll_s=0.5)
    got = _knowledge(c)
    assert got.twin, got.twin_note
    twin = decode(got.twin)
    assert twin.knowledge_version == version
    return twin


def test_the_twin_takes_friction_backlash_and_noise_from_recent_running(
        article_controller: ControllerProcess) -> None:
    with Client(article_controller.endpoint, article_controller.rig) as c:
        c.wait_ready(article_controller, timeout_s=300.0)  # start-up at load 25: > 120 s
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
        lack = sine.disturbance
        assert lack is not None and lack.mean_std_deg_s is not None, sine.notes
        rpm = TRUE.gear_ratio / 6.0
        print("sine window:", est.window, "|", est.describe(), "| drive offset lacking "
              f"{lack.mean_deg_s * rpm:.3g} +- {lack.mean_std_deg_s * rpm:.2g} rpm")
        said = [n for n in sine.notes if n.startswith("estimated from the controller's running")]
        assert len(said) == 1 and est.describe() in said[0], sine.notes
        # the whole window is the sine's running: the approach onto it is before it
        assert f"{WINDOW_S:.3g} s" in est.window and "UTC" in est.window, est.window
        assert "sine from its" in est.window, est.window
        assert est.coulomb_std_n_m is not None and est.backlash_std_deg is not None
        assert est.position_noise_std_deg is not None
        assert not any(n.startswith(BASE_RIG) or n.startswith(OFFSET_KEPT)
                       for n in sine.notes), sine.notes
        assert any(n.startswith("structure and unfitted parts: the simulated rig article-rig")
                   for n in sine.notes), sine.notes
        # The drive offset the twin lacks, from d_hat (the twin starts from the rig's own 2
        # rpm: it lacks none), within 4 of its deviation.
        assert abs(lack.mean_deg_s) <= 4 * lack.mean_std_deg_s + 1e-3, lack
        fc, bl, sd = est.coulomb_torque_n_m, est.backlash_deg, est.position_noise_deg
        # Each within K_STD of its stated deviations, and those not vacuous. Measured live
        # (load 21-25): Coulomb 0.227 +- 0.0115 / 0.247 +- 0.0029 N m, backlash 0.0638 +-
        # 0.0096 / 0.052 +- 0.0031 deg, noise 2.92e-5 +- 1.6e-6 deg against 0.25, 0.05, 3e-5
        # (before the twin took the rig's
        # structure and the window only the trajectory's following: 0.262 +- 0.065, 0.393 +-
        # 0.305, 0.368 +- 0.069, 0.372 +- 0.415 N m).
        assert sd == pytest.approx(TRUE.position_noise_deg, rel=NOISE_TOL), est.describe()
        assert abs(sd - TRUE.position_noise_deg) <= K_STD * est.position_noise_std_deg
        assert abs(fc - TRUE.coulomb_torque_n_m) <= K_STD * est.coulomb_std_n_m, est.describe()
        assert abs(bl - TRUE_BACKLASH_DEG) <= K_STD * est.backlash_std_deg + 1e-4, est.describe()
        assert est.coulomb_std_n_m < COULOMB_STD_MAX_N_M, est.describe()
        assert est.backlash_std_deg < BACKLASH_STD_MAX_DEG, est.describe()
        # in the twin the offline loop runs
        assert sine.params.coulomb_torque_n_m == fc and sine.params.position_noise_deg == sd
