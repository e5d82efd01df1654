"""The rig's twin (controller/twin): identified on the simulated article rig offline, as the
controller identifies, then checked against the rig it was measured from: its linear response
at each position against the true rig's exact one, and the closed-loop sine run (the compiled
offline loop) on the twin against the same run on the true rig."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import COMMISSIONING_BOUND, PlantKnowledge
from controller.ident.offline import run_offline
from controller.ident.spec import IdentifySpec
from controller.sim.experiment import run_experiment
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import RigFaults, SimRig
from controller.twin.fit import position_fit, position_of, rig_response, twin_from_knowledge
from controller.twin.model import RigTwin, decode, encode

SETUP = rig_setup(("article-rig",))
CFG = LoopConfig()


class _Never:
    def is_set(self) -> bool:
        return False

    def wait(self, timeout: float | None = None) -> bool:
        return False


@pytest.fixture(scope="module")
def identified() -> PlantKnowledge:
    out = run_offline(IdentifySpec(positions=3), CFG.with_(dob_on=False), _Never(),
                      rig_factory=lambda c, seed: SimRig(SETUP.params, rate_hz=c.rate_hz,
                                                         seed=seed, disturbance=SETUP.torque))
    assert out.complete and out.result is not None, out.reason
    res = out.result
    return PlantKnowledge(measured=res.measured_responses(), bound=COMMISSIONING_BOUND,
                          model=res.nominal or CFG.nominal, version=4, source="identified")


@pytest.fixture(scope="module")
def twin(identified: PlantKnowledge) -> RigTwin:
    return twin_from_knowledge(identified, rate_hz=CFG.rate_hz)


def test_the_twin_fits_what_it_was_measured_from(twin: RigTwin) -> None:
    assert [p.position_deg for p in twin.positions] == [0.0, 120.0, 240.0]
    for p in twin.positions:  # the measurement's own error included (friction at 0.1 Hz)
        assert p.rms_db < 1.0 and p.rms_deg < 5.0, p.describe()


def test_the_twin_responds_as_the_true_rig(twin: RigTwin) -> None:
    """Against the true rig's exact linear response at each measured position, 0.1-20 Hz
    (measured: 0.06 dB / 0.2 deg rms at worst)."""
    f = np.geomspace(0.1, 20.0, 60)
    for pos in (0.0, 120.0, 240.0):
        truth = rig_response(SETUP.params, RigFaults(), f, pos, CFG.rate_hz)
        fit = position_fit(f"{pos:g} deg", pos, f, truth, rig_response(
            twin.params, twin.faults, f, pos, CFG.rate_hz))
        assert fit.rms_db < 0.3 and fit.max_db < 0.6, fit.describe()
        assert fit.rms_deg < 2.0 and fit.max_deg < 4.0, fit.describe()


@pytest.mark.parametrize("dob_on", [False, True])
def test_the_twin_predicts_the_closed_loop_sine(twin: RigTwin, dob_on: bool) -> None:
    """theta = 5 sin(0.5 t) deg, 30 s, the default loop; on the true rig and on the twin (the
    same load torque): RMSE within 10 %, peak within 20 % (measured: 0.0299 vs 0.0297 deg
    without the DOB)."""
    cfg = CFG.with_(dob_on=dob_on)
    traj = Trajectory(kind="sine", amplitude_deg=5.0, omega_rad_s=0.5)
    true = run_experiment(cfg, traj, 30.0, rig=SimRig(SETUP.params, disturbance=SETUP.torque))
    pred = run_experiment(cfg, traj, 30.0, rig=twin.sim_rig(disturbance=SETUP.torque))
    assert pred.rmse_deg == pytest.approx(true.rmse_deg, rel=0.10)
    assert pred.peak_error_deg == pytest.approx(true.peak_error_deg, rel=0.20)


def test_a_twin_knows_its_knowledge(identified: PlantKnowledge, twin: RigTwin) -> None:
    assert twin.matches(identified)
    assert not twin.matches(replace(identified, version=5))
    other = replace(identified, measured=identified.measured[:2])
    assert not twin.matches(replace(other, version=identified.version))


def test_a_twin_travels_as_it_is(twin: RigTwin) -> None:
    assert decode(encode(twin)) == twin
    text = encode(twin).decode()
    start = text.index('"load_inertia_kg_m2":') + len('"load_inertia_kg_m2":')
    end = text.index(",", start)
    with pytest.raises(ValueError, match="load_inertia_kg_m2"):
        decode(text[:start] + "-0.5" + text[end:])


def test_without_measurements_the_twin_is_the_base_rig_and_says_so() -> None:
    tw = twin_from_knowledge(PlantKnowledge())
    assert tw.positions == () and tw.params == SETUP.params.__class__()
    assert any("nothing measured" in n for n in tw.notes)


def test_a_d_hat_window_is_stated_and_its_mean_is_the_drive_offset() -> None:
    t = np.arange(4000) * 1e-3
    d = 0.3 + 0.1 * np.sin(2 * np.pi * 2.0 * t)
    tw = twin_from_knowledge(PlantKnowledge(), d_hat_deg_s=d)
    assert tw.disturbance is not None
    assert tw.disturbance.mean_deg_s == pytest.approx(0.3, abs=1e-9)
    assert tw.disturbance.rms_deg_s == pytest.approx(0.1 / np.sqrt(2), rel=1e-6)
    i = int(np.argmax(tw.disturbance.amplitude_deg_s))
    assert tw.disturbance.freq_hz[i] == pytest.approx(2.0, abs=0.25)
    assert tw.disturbance.amplitude_deg_s[i] == pytest.approx(0.1, rel=0.02)
    # 0.3 deg/s at the load is 0.3 x 132 / 6 rpm at the motor
    assert tw.params.drive_offset_rpm == pytest.approx(0.3 * 132 / 6, rel=1e-9)


def test_positions_come_from_the_names() -> None:
    assert position_of("pos1_120deg") == 120.0
    assert position_of("true 90 deg") == 90.0
    assert position_of("bench") is None


def test_identify_writes_the_knowledge_and_its_twin(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """`dobtune identify --plant sim`: knowledge.json (what autotune --knowledge reads) and
    twin.json (built from it: its digest matches), the fit per position in the summary and
    the printed report."""
    import io
    import json

    from controller.cli.identify import identify_main
    from controller.cli.inputs import load_knowledge

    out, err = io.StringIO(), io.StringIO()
    code = identify_main(plant="sim", connect=None, rig_name=None, out_dir=tmp_path / "id",
                         as_json=False, out=out, err=err,
                         spec_fields={"positions": 2, "f_min_hz": 0.3})
    assert code == 0, err.getvalue()
    k = load_knowledge(tmp_path / "id" / "knowledge.json")
    tw = decode((tmp_path / "id" / "twin.json").read_bytes())
    assert tw.matches(k) and len(tw.positions) == 2
    summary = json.loads((tmp_path / "id" / "summary.json").read_text())
    assert [p["name"] for p in summary["twin"]["positions"]] == [m.name for m in k.measured]
    for p in tw.positions:
        assert f"{p.name}: {p.rms_db:.2f} dB / {p.rms_deg:.1f} deg rms" in out.getvalue()


def test_a_recorded_run_replayed_on_the_twin(twin: RigTwin) -> None:
    """The default loop with Q20 at 3.85 Hz (the demo's autotune pick) on the true rig (the
    "recording": its position error per tick), replayed on the twin: RMSE within 10 %, peak
    within 20 %."""
    from controller.twin.replay import replay

    cfg = CFG.with_(dob_on=True, q_type="q20", q_cutoff_hz=3.85)
    traj = Trajectory(kind="sine", amplitude_deg=5.0, omega_rad_s=0.5)
    true = run_experiment(cfg, traj, 20.0, rig=SimRig(SETUP.params, disturbance=SETUP.torque))
    fit = replay(twin, cfg, traj, true.error_deg, label="q20 3.85 Hz sine",
                 disturbance=SETUP.torque)
    assert fit.duration_s == pytest.approx(20.0)
    assert fit.measured_rmse_deg == pytest.approx(true.rmse_deg, rel=1e-9)
    assert fit.predicted_rmse_deg == pytest.approx(fit.measured_rmse_deg, rel=0.10)
    assert fit.predicted_peak_deg == pytest.approx(fit.measured_peak_deg, rel=0.20)
    with pytest.raises(ValueError, match="measured_error_deg"):
        replay(twin, cfg, traj, np.array([0.0, np.nan]))
