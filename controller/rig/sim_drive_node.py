"""A simulated CiA 402 drive node (plus load encoder) on a CAN bus, wrapping a simulated rig.

For tests and demos of ``CanRig`` without hardware: run it on python-can's ``virtual`` bus,
on the channel of the rig file, and point a ``CanRig`` at the same channel. The node runs on
its own thread and its own bus object. It implements what ``CanRig`` uses: NMT, expedited SDO
writes of 0x6060 and 0x1017, the CiA 402 state machine, RPDO1 (controlword + target
velocity), and on each SYNC it steps the rig one tick with the last target velocity (converted
back to load deg/s; zero unless Operation enabled) and answers with TPDO1 (statusword +
velocity actual), TPDO2 (position actual) and the load encoder frame; plus the heartbeat.
The raw profile is simulated too (command frame in, encoder + velocity frames out on SYNC).

Faults can be injected (``inject``) to test the supervision.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Literal, Protocol

from controller.rig import cia402
from controller.rig.can_rig import FrameBus
from controller.rig.cia402 import NmtCommand, NmtState, State
from controller.rig.rig_file import RigFile

__all__ = ["Injection", "Plant", "SimDriveNode"]

Injection = Literal["silent", "no_feedback", "garbage", "fault", "emcy", "no_heartbeat", "hold"]
"""silent: the node sends nothing at all (it still obeys frames: a dead transmitter);
no_feedback: no answer to SYNC (heartbeat continues); garbage: a 3-byte TPDO1 and a
truncated encoder frame instead of the real ones; fault: the drive goes to Fault (statusword
bit 3, no EMCY); emcy: Fault plus an EMCY 0x2310 (over-current); no_heartbeat: heartbeat stops;
hold: the answer to the next SYNC waits for ``release()`` (one late answer, then it ends)."""


class Plant(Protocol):
    """What the node needs of the simulated rig (``controller.sim.sim_rig.SimRig`` fits)."""

    def read(self) -> tuple[float, float]: ...

    def step(self, command_deg_s: float) -> None: ...

    @property
    def motor_speed_deg_s(self) -> float: ...


_INT32_MIN = -(2**31)
_INT32_MAX = 2**31 - 1


def _i32(value: float) -> int:
    v = round(value)
    return _INT32_MIN if v < _INT32_MIN else _INT32_MAX if v > _INT32_MAX else v


class SimDriveNode:
    """The simulated drive + encoder node; ``start()``/``stop()`` or use as context manager."""

    def __init__(
        self,
        rig: RigFile,
        plant: Plant | None = None,
        *,
        bus: FrameBus | None = None,
        rate_hz: float = 1000.0,
        answer_before_step: bool = False,
        poll_s: float = 0.005,
        on_thread_start: Callable[[], object] | None = None,
    ) -> None:
        """``answer_before_step``: sample and send the feedback at the SYNC, then step (a
        real drive: one tick more delay); default steps first so a CanRig tick equals a
        SimRig tick exactly."""
        if plant is None:
            from controller.sim.sim_rig import SimRig

            plant = SimRig(rate_hz=rate_hz)
        self.plant = plant
        self.rig_file = rig
        self._owns_bus = bus is None
        self._bus = bus if bus is not None else FrameBus.open(rig.bus)
        drive, enc, ids = rig.drive, rig.load_encoder, rig.drive.cob_ids
        self._cia402 = drive.profile == "cia402"
        self._period_s = 1.0 / rate_hz
        self._answer_before_step = answer_before_step
        self._poll_s = poll_s
        self._ids = ids
        self._node_id = drive.node_id
        self._units_per_load_deg_s = drive.velocity_units_per_load_deg_s
        self._units_per_motor_deg_s = drive.direction * drive.velocity_units_per_motor_deg_s
        self._counts_per_motor_deg = drive.direction * drive.counts_per_rev / 360.0
        self._enc_counts_per_deg = enc.direction * enc.counts_per_rev / 360.0
        self._enc = enc
        self._enc_codec = enc.layout.codec()
        self._enc_modulus = enc.counts_per_rev if enc.single_turn else self._enc_codec.modulus
        self._raw = drive.raw if not self._cia402 else None
        self._raw_cmd = self._raw.command.codec() if self._raw is not None else None
        self._raw_vel = (
            self._raw.velocity_feedback.codec()
            if self._raw is not None and self._raw.velocity_feedback
            else None
        )
        # Drive state (touched by the node thread only, read by tests).
        self.nmt_state = NmtState.PRE_OPERATIONAL if self._cia402 else NmtState.OPERATIONAL
        self.state = State.SWITCH_ON_DISABLED
        self.mode_of_operation = 0
        self.heartbeat_period_ms = 0
        self.controlword = 0
        self.target_units = 0
        self.syncs = 0
        self._on_thread_start = on_thread_start
        self.thread_start_result: object = None
        self._motor_position_deg = 0.0
        self._injection: Injection | None = None
        self._released = threading.Event()
        self._running = False
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        """An exception that ended the node thread (tests assert it stays None)."""

    # --- control from the test ------------------------------------------------------------
    def inject(self, injection: Injection | None) -> None:
        """Start (or with None, end) a fault injection; applies from the next frame handled."""
        self._injection = injection

    def release(self) -> None:
        """Send the answer a ``hold`` injection is keeping back."""
        self._released.set()

    def start(self) -> SimDriveNode:
        if self._thread is not None:
            return self
        self._running = True
        self._thread = threading.Thread(target=self._run, name="sim-drive-node", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._running = False
        self._released.set()  # a held answer must not keep the thread
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._owns_bus:
            self._bus.close()

    def __enter__(self) -> SimDriveNode:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def target_velocity_deg_s(self) -> float:
        """The last target velocity as a load-side speed."""
        return self.target_units / self._units_per_load_deg_s

    # --- node thread ----------------------------------------------------------------------
    def _run(self) -> None:
        try:
            if self._on_thread_start is not None:
                # E.g. real-time priority for this thread: a drive is hardware, it is never
                # starved by the host's load (an in-process simulation otherwise is).
                self.thread_start_result = self._on_thread_start()
            self._loop()
        except BaseException as exc:  # surfaced to the test through .error
            self.error = exc
            raise

    def _loop(self) -> None:
        bus = self._bus
        if self._cia402:
            self._send(self._ids.heartbeat, cia402.make_heartbeat(NmtState.BOOTUP))
        next_heartbeat = time.monotonic()
        while self._running:
            timeout = self._poll_s
            if self._cia402 and self.heartbeat_period_ms > 0:
                now = time.monotonic()
                if now >= next_heartbeat:
                    if self._injection != "no_heartbeat":
                        self._send(self._ids.heartbeat, cia402.make_heartbeat(self.nmt_state))
                    period_s = self.heartbeat_period_ms / 1000.0
                    next_heartbeat = max(next_heartbeat + period_s, now)
                timeout = min(timeout, max(0.0, next_heartbeat - now))
            frame = bus.recv(timeout)
            if frame is not None:
                self._handle(frame[0], frame[1])

    def _send(self, can_id: int, data: bytes) -> None:
        if self._injection != "silent":
            self._bus.send(can_id, data)

    def _handle(self, can_id: int, data: bytes) -> None:
        ids = self._ids
        if can_id == ids.sync:
            if self.nmt_state == NmtState.OPERATIONAL:
                self._on_sync()
        elif self._raw is not None:
            if can_id == self._raw.command_id and self._raw_cmd is not None:
                self.target_units = self._raw_cmd.decode(data)
        elif can_id == ids.rpdo_command:
            if self.nmt_state == NmtState.OPERATIONAL:
                controlword, target = cia402.parse_rpdo_command(data)
                self.state = cia402.drive_next_state(self.state, controlword, self.controlword)
                self.controlword = controlword
                self.target_units = target
        elif can_id == ids.nmt:
            command, node = cia402.parse_nmt(data)
            if node in (0, self._node_id):
                self._on_nmt(command)
        elif can_id == ids.sdo_rx and self.nmt_state in (
            NmtState.PRE_OPERATIONAL,
            NmtState.OPERATIONAL,
        ):
            self._on_sdo(data)

    def _on_nmt(self, command: int) -> None:
        if command == NmtCommand.START:
            self.nmt_state = NmtState.OPERATIONAL
        elif command == NmtCommand.STOP:
            self.nmt_state = NmtState.STOPPED
        elif command == NmtCommand.ENTER_PRE_OPERATIONAL:
            self.nmt_state = NmtState.PRE_OPERATIONAL
        elif command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            if command == NmtCommand.RESET_NODE:
                self.state = State.SWITCH_ON_DISABLED
                self.target_units = 0
            self._send(self._ids.heartbeat, cia402.make_heartbeat(NmtState.BOOTUP))
            self.nmt_state = NmtState.PRE_OPERATIONAL

    def _on_sdo(self, data: bytes) -> None:
        try:
            request = cia402.parse_sdo_request(data)
        except ValueError:
            index = int.from_bytes(data[1:3], "little") if len(data) >= 3 else 0
            self._send(self._ids.sdo_tx, cia402.make_sdo_abort(index, 0, 0x05040001))
            return
        index, sub = request.index, request.subindex
        abort = 0
        if index == cia402.MODES_OF_OPERATION and sub == 0 and request.size == 1:
            if request.value == cia402.PROFILE_VELOCITY_MODE:
                self.mode_of_operation = request.value
            else:
                abort = cia402.SDO_ABORT_VALUE_RANGE
        elif index == cia402.PRODUCER_HEARTBEAT_TIME and sub == 0 and request.size == 2:
            self.heartbeat_period_ms = request.value
        else:
            abort = cia402.SDO_ABORT_NO_OBJECT
        reply = (
            cia402.make_sdo_abort(index, sub, abort)
            if abort
            else cia402.make_sdo_download_reply(index, sub)
        )
        self._send(self._ids.sdo_tx, reply)

    def _on_sync(self) -> None:
        self.syncs += 1
        injection = self._injection
        if injection in ("fault", "emcy") and self.state is not State.FAULT:
            self.state = State.FAULT
            if injection == "emcy":
                self._send(self._ids.emcy, cia402.make_emcy(0x2310, 0x03))
        live = self._raw is not None or (
            self.state is State.OPERATION_ENABLED
            and self.mode_of_operation == cia402.PROFILE_VELOCITY_MODE
        )
        command_deg_s = self.target_units / self._units_per_load_deg_s if live else 0.0
        if injection == "hold":
            self._injection = injection = None
            self._released.wait()
            self._released.clear()
        if self._answer_before_step:
            self._answer(injection)
            self._advance(command_deg_s)
        else:
            self._advance(command_deg_s)
            self._answer(injection)

    def _advance(self, command_deg_s: float) -> None:
        self.plant.step(command_deg_s)
        self._motor_position_deg += self.plant.motor_speed_deg_s * self._period_s

    def _answer(self, injection: Injection | None) -> None:
        if injection == "no_feedback":
            return
        ids = self._ids
        if injection == "garbage":
            if self._cia402:
                self._send(ids.tpdo_status_velocity, b"\x27\x06\x00")
            self._send(self._enc.frame_id, b"\xff")
            return
        motor_units = _i32(self.plant.motor_speed_deg_s * self._units_per_motor_deg_s)
        if self._cia402:
            statusword = cia402.statusword_for(self.state)
            self._send(
                ids.tpdo_status_velocity, cia402.make_tpdo_status_velocity(statusword, motor_units)
            )
            counts = _i32(self._motor_position_deg * self._counts_per_motor_deg)
            self._send(ids.tpdo_position, cia402.make_tpdo_position(counts))
        elif self._raw is not None and self._raw.velocity_feedback_id is not None:
            assert self._raw_vel is not None
            data = bytearray(self._raw_vel.min_dlc)
            self._raw_vel.encode_into(data, motor_units)
            self._send(self._raw.velocity_feedback_id, bytes(data))
        position_deg, _ = self.plant.read()
        codec = self._enc_codec
        counts = round(position_deg * self._enc_counts_per_deg) % self._enc_modulus
        if codec.signed and counts > codec.max_value:
            counts -= codec.modulus
        data = bytearray(codec.min_dlc)
        codec.encode_into(data, counts)
        self._send(self._enc.frame_id, bytes(data))
