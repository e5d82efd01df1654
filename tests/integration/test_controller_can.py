"""The controller on the CAN path: CanRig + a simulated CiA 402 drive node on python-can's
`virtual` bus (no hardware). The virtual bus lives inside one process, so the controller
process runs the simulated node itself (`--sim-drive-node`).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pytest
from procs import Client, ControllerProcess, wait_until

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.trajectory import Trajectory
from controller.process.runtime import FAULT, Runtime
from controller.rig.can_rig import CanRig
from controller.rig.cia402 import State
from controller.rig.rig_file import RigFile, load_rig_file, parse_rig_file
from controller.rig.sim_drive_node import SimDriveNode
from controller.sim.experiment import run_experiment
from controller.sim.sim_rig import SimRig

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rig_cia402.toml"
SETTLE_S = 2.0
PERIOD_S = 4.0 * math.pi  # of the default trajectory 5 sin(0.5 t) deg
DURATION_S = SETTLE_S + PERIOD_S


def virtual_rig_text(channel: str, enable_timeout_s: float = 3.0) -> str:
    """The example rig file on a virtual bus, with supervision timings for a shared machine."""
    text = EXAMPLE.read_text()
    replacements = {
        'interface = "socketcan"': 'interface = "virtual"',
        'channel = "can0"': f'channel = "{channel}"',
        "heartbeat_period_ms = 100": "heartbeat_period_ms = 20",
        "heartbeat_timeout_ms = 250.0": "heartbeat_timeout_ms = 500.0",
        "enable_timeout_s = 1.0": f"enable_timeout_s = {enable_timeout_s}",
        "feedback_wait_s = 0.0005": "feedback_wait_s = 0.02",
    }
    for a, b in replacements.items():
        assert a in text, a
        text = text.replace(a, b)
    parse_rig_file(text)  # still valid
    return text


def test_sine_through_can_tracks_like_the_simulated_plant(
    start_controller_factory: Callable[..., ControllerProcess], tmp_path: Path
) -> None:
    rig_path = tmp_path / "rig.toml"
    rig_path.write_text(virtual_rig_text(f"ctl-{uuid.uuid4().hex}"))
    proc = start_controller_factory(
        extra_args=("--plant", "can", "--rig", str(rig_path), "--sim-drive-node"),
    )
    with Client(proc.endpoint, proc.rig) as c:
        c.wait_ready(proc)
        st = c.fresh_status()
        assert st.plant == "can" and st.mode == "running", st
        with c.state() as col:
            assert wait_until(lambda: len(col.batches()) > 0, 5.0)
            # One whole period of the sine in steady state (after the settling time), from
            # wherever our subscription started.
            s0 = max(col.batches()[0][1].seq0, int(SETTLE_S * 1000))
            n = int(PERIOD_S * 1000)
            assert col.wait_for_seq(s0 + n, PERIOD_S + 30.0), c.fresh_status()
        st = c.fresh_status()
        assert st.mode == "running" and not st.faults, st
        # The rig file's command limit (60 deg/s) bounds the loop's: the default config starts
        # with it, and a candidate above it is rejected (the drive would clamp behind the DOB).
        assert st.config.command_limit_deg_s == 60.0
        reply = c.apply(st.config.with_(command_limit_deg_s=100.0))
        assert not reply.accepted and reply.reasons[0].startswith("command_limit_deg_s 100")
        assert reply.config == st.config and reply.version == st.config_version
    samples = col.samples()
    seqs = range(s0, s0 + n)
    missing = [s for s in seqs if s not in samples]
    assert not missing, f"{len(missing)} samples missing"
    err = np.array([samples[s]["ref_deg"] - samples[s]["pos_deg"] for s in seqs])
    peak, rmse = float(np.max(np.abs(err))), float(np.sqrt(np.mean(err**2)))
    ref = run_experiment(LoopConfig(), Trajectory(), DURATION_S, settle_s=SETTLE_S)
    ref_peak, ref_rmse = ref.metrics.peak_error_deg, ref.metrics.rmse_deg
    assert rmse == pytest.approx(ref_rmse, rel=0.2), (rmse, ref_rmse)
    assert peak == pytest.approx(ref_peak, rel=0.2), (peak, ref_peak)


def test_no_drive_on_the_bus_is_a_published_fault_and_zenoh_keeps_serving(
    start_controller_factory: Callable[..., ControllerProcess], tmp_path: Path
) -> None:
    rig_path = tmp_path / "rig.toml"
    rig_path.write_text(virtual_rig_text(f"ctl-{uuid.uuid4().hex}", enable_timeout_s=0.5))
    proc = start_controller_factory(extra_args=("--plant", "can", "--rig", str(rig_path)))
    with Client(proc.endpoint, proc.rig) as c:
        c.wait_ready(proc)
        st = c.fresh_status()
        assert st.mode == "fault" and st.faults and "did not start" in st.faults[0], st
        with c.state() as col:
            assert col.wait_for_seq(st.seq + 50, 5.0)
        assert all(b.mode == "fault" for _, b in col.batches())
        assert all(u == 0.0 for _, b in col.batches() for u in b.command_deg_s)
        # Still serving: config, commands (a reset fails again: still no drive).
        assert c.get_config().accepted
        reset = c.reset()
        assert not reset.ok and reset.mode == "fault" and "did not enable" in reset.message
        assert not c.command(proto.Start()).ok


# -- in-process: the runtime with CanRig and the simulated node, fault injection -------------


def _virtual(rig: RigFile) -> RigFile:
    return dataclasses.replace(
        rig,
        bus=dataclasses.replace(rig.bus, interface="virtual", channel=f"t-{uuid.uuid4().hex}"),
        drive=dataclasses.replace(
            rig.drive, heartbeat_period_ms=20, heartbeat_timeout_ms=500.0, enable_timeout_s=3.0
        ),
    )


class _Modes:
    def __init__(self) -> None:
        self.first: dict[str, int] = {}
        self.commands: dict[int, float] = {}

    def __call__(self, seq0: int, version: int, mode: str, cols: Sequence[list[float]]) -> None:
        self.first.setdefault(mode, seq0)
        for i, u in enumerate(cols[5]):
            self.commands[seq0 + i] = u


@pytest.mark.parametrize("injection", ["no_feedback", "silent", "garbage", "fault"])
def test_lost_feedback_or_drive_fault_gives_the_safe_state_within_5_ticks(
    injection: str,
) -> None:
    rig_file = _virtual(load_rig_file(EXAMPLE))
    timeout_ticks = rig_file.limits.feedback_timeout_ticks
    assert timeout_ticks == 5
    plant = SimRig(seed=0)
    modes = _Modes()
    stop = threading.Event()
    with (
        SimDriveNode(rig_file, plant) as node,
        CanRig(rig_file, wait_feedback_s=0.1) as rig,
    ):
        rig.start()
        rt = Runtime(ServoLoop(LoopCoefficients.build(LoopConfig(), 1)), rig)
        pub = threading.Thread(target=rt.publisher, args=(modes, stop, 0.001))
        pub.start()
        runner = threading.Thread(target=rt.run)
        runner.start()
        try:
            assert wait_until(lambda: rt.seq >= 1500, 20.0)  # moving on the sine
            injected_after = rt.seq
            node.inject(injection)  # type: ignore[arg-type]
            assert wait_until(lambda: rt.mode == FAULT, 10.0), rt.fault
            assert wait_until(lambda: rt.seq > injected_after + 20, 10.0)
        finally:
            rt.stop()
            runner.join(10.0)
            stop.set()
            pub.join(10.0)
        assert node.error is None
        fault_seq = modes.first[FAULT]
        # The first tick whose SYNC goes unanswered is at most one after `injected_after`;
        # the fault comes with the 5th tick without feedback (immediately for a bad frame).
        assert fault_seq - injected_after <= timeout_ticks + 1, (fault_seq, injected_after)
        assert rt.fault is not None and rig.fault is not None
        assert all(modes.commands[s] == 0.0 for s in range(fault_seq, rt.seq))
        assert any(modes.commands[s] != 0.0 for s in range(fault_seq - 50, fault_seq))
        if injection != "silent":
            assert wait_until(lambda: node.state is not State.OPERATION_ENABLED, 2.0)
            assert node.target_units == 0
