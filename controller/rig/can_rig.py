"""The real rig over CAN: the I/O adapter, and the only module that imports python-can.

``CanRig`` duck-types ``controller.sim.sim_rig.SimRig`` (``read()``, ``step(u)``, ``time_s``,
``period_s``, ``motor_speed_deg_s``) so the loop drives either. Per tick the loop calls
``read()`` then ``step(u)``: ``step`` sends the target-velocity RPDO and a SYNC; the drive and
the load encoder answer the SYNC with their feedback frames, which the next ``read()`` drains.

Setup (NMT, two expedited SDO writes, the enable state machine) uses raw frames too, not the
``canopen`` library: canopen's Network runs a Notifier thread that consumes the bus, which
would race with the non-blocking per-tick drain here, and the setup needs only a handful of
frames. Frame layouts live in ``controller.rig.cia402`` (pure); this module only moves bytes.

Supervision (each sets ``fault`` and puts the drive in the safe state, zero speed then
disable operation; afterwards ``step`` only sends zero): feedback missing for
``feedback_timeout_ticks`` consecutive ticks, a bus error, a short/garbled frame on a feedback
id, an implausible encoder jump, the statusword fault bit or leaving Operation enabled, an
EMCY with a non-zero code, a heartbeat that is late or not "operational".

Timing: a tick counts as fed when every feedback frame (TPDO1, TPDO2 and the encoder for
cia402) arrived after its SYNC. ``read()`` may block until ``SYNC time + wait_feedback_s``
for missing frames; a 1 kHz loop that reads about a period after the SYNC therefore never
waits. The frames carry no SYNC counter: a frame later than that is still taken for its own
tick if it arrives before the next ``step()`` (which drains the bus before its SYNC), and counts
for the next tick only if it arrives after that SYNC. ``late_ticks`` counts the ticks that
ended without complete feedback.
While feedback is missing ``read()`` returns the last values. ``step()`` and ``stop()`` are
serialised by a lock, so an e-stop from another thread is never followed by a live command;
everything else is meant for the loop's thread.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import can

from controller.core.validate import positive
from controller.rig import cia402
from controller.rig.cia402 import NmtState, State
from controller.rig.rig_file import BusConfig, RigFile

__all__ = ["ERROR_FRAME_ID", "IGNORED_FRAME_ID", "CanBusError", "CanRig", "FrameBus", "RigFault"]

ERROR_FRAME_ID = -1
"""Pseudo identifier ``FrameBus.recv`` gives a CAN error frame."""
IGNORED_FRAME_ID = -2
"""Pseudo identifier for frames that carry no data (remote frames)."""

_ENC = 1
_TPDO1 = 2
_TPDO2 = 4
_RAW_VEL = 8


class RigFault(Exception):
    """The rig could not be brought up, or was stopped because of a fault."""


class CanBusError(Exception):
    """Sending or receiving on the CAN bus failed."""


class FrameBus:
    """A python-can bus seen as raw ``(can_id, data)`` frames; the rest of dobtune uses this."""

    __slots__ = ("_bus", "_owns")

    def __init__(self, bus: can.BusABC, *, owns: bool = False) -> None:
        self._bus = bus
        self._owns = owns

    @classmethod
    def open(cls, config: BusConfig) -> FrameBus:
        """Open the bus described by the rig file. No acceptance filters: error frames and
        every feedback id must come through, and a rig's bus carries a few frames per tick."""
        try:
            bus = can.Bus(
                interface=config.interface, channel=config.channel, bitrate=config.bitrate
            )
        except (can.CanError, OSError, ValueError) as exc:
            raise CanBusError(f"cannot open {config.interface}:{config.channel}: {exc}") from exc
        return cls(bus, owns=True)

    def send(self, can_id: int, data: bytes) -> None:
        msg = can.Message(
            arbitration_id=can_id, data=data, is_extended_id=can_id > 0x7FF, check=False
        )
        try:
            self._bus.send(msg)
        except can.CanError as exc:
            raise CanBusError(f"send 0x{can_id:X}: {exc}") from exc

    def recv(self, timeout: float) -> tuple[int, bytes] | None:
        """The next frame, or None when none came within ``timeout`` seconds (0: no wait)."""
        try:
            msg = self._bus.recv(timeout)
        except can.CanError as exc:
            raise CanBusError(f"receive: {exc}") from exc
        if msg is None:
            return None
        if msg.is_error_frame:
            return ERROR_FRAME_ID, bytes(msg.data)
        if msg.is_remote_frame:
            return IGNORED_FRAME_ID, b""
        return msg.arbitration_id, bytes(msg.data)

    def close(self) -> None:
        if self._owns:
            self._owns = False
            self._bus.shutdown()


class CanRig:
    """The rig through a CiA 402 (or raw-frame) drive; context manager, call ``start()``."""

    def __init__(
        self,
        rig: RigFile,
        *,
        bus: can.BusABC | None = None,
        rate_hz: float = 1000.0,
        wait_feedback_s: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        positive(rate_hz, "rate_hz")
        self.rig_file = rig
        """The rig description this adapter was built from."""
        self.fault: str | None = None
        """Why the rig was stopped, or None."""
        drive, enc, ids = rig.drive, rig.load_encoder, rig.drive.cob_ids
        self._cia402 = drive.profile == "cia402"
        self._period_s = 1.0 / rate_hz
        self._wait_s = rig.limits.feedback_wait_s if wait_feedback_s is None else wait_feedback_s
        self._clock = clock
        # Identifiers and layouts.
        self._id_enc = enc.frame_id
        self._id_tpdo1 = ids.tpdo_status_velocity if self._cia402 else None
        self._id_tpdo2 = ids.tpdo_position if self._cia402 else None
        self._id_hb = ids.heartbeat if self._cia402 else None
        self._id_emcy = ids.emcy if self._cia402 else None
        self._id_sdo_tx = ids.sdo_tx if self._cia402 else None
        self._id_rpdo = ids.rpdo_command
        self._id_sync = ids.sync
        self._send_sync = drive.send_sync
        self._enc_codec = enc.layout.codec()
        self._raw_cmd: cia402.FieldCodec | None = None
        self._raw_cmd_id = 0
        self._raw_cmd_dlc = 0
        self._id_raw_vel: int | None = None
        self._raw_vel: cia402.FieldCodec | None = None
        self._need = _ENC | (_TPDO1 | _TPDO2 if self._cia402 else 0)
        if drive.raw is not None and not self._cia402:
            self._raw_cmd = drive.raw.command.codec()
            self._raw_cmd_id = drive.raw.command_id
            self._raw_cmd_dlc = drive.raw.command_dlc
            if drive.raw.velocity_feedback_id is not None and drive.raw.velocity_feedback:
                self._id_raw_vel = drive.raw.velocity_feedback_id
                self._raw_vel = drive.raw.velocity_feedback.codec()
                self._need |= _RAW_VEL
        # Scaling: load deg/s <-> drive velocity units; counts -> deg.
        self._units_per_load_deg_s = drive.velocity_units_per_load_deg_s
        self._motor_deg_s_per_unit = drive.direction / drive.velocity_units_per_motor_deg_s
        self._motor_deg_per_count = drive.direction * 360.0 / drive.counts_per_rev
        self._limit_deg_s = rig.max_load_speed_deg_s
        self._enc_deg_per_count = enc.direction * 360.0 / enc.counts_per_rev
        self._enc_modulus = enc.counts_per_rev if enc.single_turn else self._enc_codec.modulus
        self._max_encoder_speed_deg_s = rig.limits.max_encoder_speed_factor * self._limit_deg_s
        self._timeout_ticks = rig.limits.feedback_timeout_ticks
        self._hb_timeout_s = drive.heartbeat_timeout_ms / 1000.0
        self._hb_supervised = self._cia402 and drive.heartbeat_period_ms > 0
        # Bus.
        if bus is None:
            self._bus = FrameBus.open(rig.bus)
        else:
            self._bus = FrameBus(bus, owns=False)
        # State.
        self._lock = threading.RLock()
        self._enabled = False  # commands are live (after start, before stop/fault)
        self._stopped = True
        self._closed = False
        self._syncs = 0
        self._sync_pending = False
        self._sync_time = 0.0
        self._got = 0
        self._missed = 0
        self._late_ticks = 0
        self._pos_deg = 0.0
        self._speed_deg_s = 0.0
        self._enc_counts = 0  # unwrapped
        self._enc_raw = 0
        self._enc_sync = -1  # SYNC count when the last encoder frame came; -1: none yet
        self._motor_speed_deg_s = 0.0
        self._motor_position_deg = 0.0
        self._statusword = 0
        self._drive_state: State | None = None
        self._hb_state: int | None = None
        self._hb_time = 0.0
        self._sdo_reply: cia402.SdoReply | None = None
        self.last_command_deg_s = 0.0
        """The load-side speed command actually sent last tick (after limits and rounding)."""

    # --- duck-typed SimRig interface ------------------------------------------------------
    @property
    def period_s(self) -> float:
        return self._period_s

    @property
    def time_s(self) -> float:
        """Ticks (SYNCs) sent since start(), times the period."""
        return self._syncs * self._period_s

    @property
    def motor_speed_deg_s(self) -> float:
        """Motor speed from the drive's velocity actual value, MOTOR side (as SimRig)."""
        return self._motor_speed_deg_s

    @property
    def motor_position_deg(self) -> float:
        """Motor position from the drive's position actual value, motor side."""
        return self._motor_position_deg

    @property
    def statusword(self) -> int:
        return self._statusword

    @property
    def drive_state(self) -> State | None:
        return self._drive_state

    @property
    def missed_ticks(self) -> int:
        """Consecutive ticks that ended without complete feedback."""
        return self._missed

    @property
    def late_ticks(self) -> int:
        """Ticks since construction whose feedback was not complete within the wait."""
        return self._late_ticks

    def read(self) -> tuple[float, float]:
        """(load position deg, load speed deg/s) from the latest load encoder frames.

        The speed is the backward difference of the encoder over the ticks between its two
        latest frames. Counts ticks without complete feedback; too many make a fault.
        """
        if self._sync_pending:
            self._sync_pending = False
            self._collect(self._sync_time + self._wait_s)
            if self._got == self._need:
                self._missed = 0
            else:
                self._missed += 1
                self._late_ticks += 1
                if self._enabled and self._missed >= self._timeout_ticks:
                    self._set_fault(f"no complete feedback for {self._missed} ticks")
        else:
            self._collect(0.0)
        if self._enabled and self._hb_supervised:
            age = self._clock() - self._hb_time
            if age > self._hb_timeout_s:
                self._set_fault(f"heartbeat lost ({age * 1000.0:.0f} ms since the last)")
        return self._pos_deg, self._speed_deg_s

    def step(self, command_deg_s: float) -> None:
        """Send the load-side speed command (limited, scaled to the drive) and a SYNC.

        Frames that came after ``read()`` gave up waiting are handled first, so they count
        for the tick they answer, not for the next one.
        """
        self._collect(0.0)
        with self._lock:  # serialised with stop(): no live command can follow the safe state
            if self._enabled and not math.isfinite(command_deg_s):
                self._set_fault(f"non-finite speed command {command_deg_s!r}")
            if self._enabled:
                limit = self._limit_deg_s
                u = command_deg_s
                u = limit if u > limit else -limit if u < -limit else u
                units = round(u * self._units_per_load_deg_s)
                controlword = cia402.CW_ENABLE_OPERATION
                self.last_command_deg_s = units / self._units_per_load_deg_s
            else:
                units = 0
                controlword = cia402.CW_DISABLE_OPERATION
                self.last_command_deg_s = 0.0
            try:
                self._send_command(controlword, units)
            except CanBusError as exc:
                self._set_fault(f"bus error: {exc}")

    # --- life cycle -----------------------------------------------------------------------
    def start(self) -> None:
        """Bring the drive to Operation enabled (cia402) and arm supervision; RigFault if not.

        Clears a previous fault: calling start() again is the operator's explicit re-enable.
        """
        if self._closed:
            raise RigFault("rig is closed")
        self.fault = None
        self._enabled = False
        self._stopped = False
        self._missed = 0
        self._hb_state = None  # only a heartbeat received during this start counts
        deadline = self._clock() + self.rig_file.drive.enable_timeout_s
        try:
            self._collect(0.0)
            if self._cia402:
                self._start_cia402(deadline)
            else:
                self._exchange(0, deadline)
        except CanBusError as exc:
            self._fail_start(f"bus error during start: {exc}")
        except RigFault as exc:
            self._fail_start(str(exc))
        if self._enc_sync < 0:
            self._fail_start("no load encoder frame during start")
        if self._hb_supervised and self._clock() - self._hb_time > self._hb_timeout_s:
            # The heartbeat is never assumed: it must have come during this start.
            self._fail_start("heartbeat lost during start: the drive is not enabled")
        self._sync_pending = False
        self._missed = 0
        self._enabled = True

    def stop(self) -> None:
        """Safe state: target velocity 0, then disable operation. Idempotent; may be called
        from another thread (an e-stop) while the loop runs."""
        with self._lock:
            if self._stopped:
                return
            was_enabled = self._enabled
            self._stopped = True
            self._enabled = False
            self.last_command_deg_s = 0.0
            try:
                if was_enabled:  # never enable a drive just to stop it
                    self._send_command(cia402.CW_ENABLE_OPERATION, 0)
                self._send_command(cia402.CW_DISABLE_OPERATION, 0)
            except CanBusError as exc:
                if self.fault is None:
                    self.fault = f"bus error while stopping: {exc}"

    def close(self) -> None:
        """Stop, then release the bus if this rig opened it."""
        if self._closed:
            return
        self.stop()
        self._closed = True
        self._bus.close()

    def __enter__(self) -> CanRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- internals ------------------------------------------------------------------------
    def _set_fault(self, reason: str) -> None:
        if self.fault is None:
            self.fault = reason
        self.stop()

    def _fail_start(self, reason: str) -> None:
        self._set_fault(reason)
        raise RigFault(reason)

    def _send_command(self, controlword: int, units: int) -> None:
        if self._raw_cmd is None:
            self._bus.send(self._id_rpdo, cia402.make_rpdo_command(controlword, units))
        else:
            data = bytearray(self._raw_cmd_dlc)
            self._raw_cmd.encode_into(data, units)
            self._bus.send(self._raw_cmd_id, bytes(data))
        if self._send_sync:
            self._bus.send(self._id_sync, b"")
        self._syncs += 1
        self._got = 0
        self._sync_pending = True
        self._sync_time = self._clock()

    def _collect(self, deadline: float) -> None:
        """Handle every frame waiting; then, until ``deadline``, wait for missing feedback."""
        bus = self._bus
        try:
            while True:
                frame = bus.recv(0.0)
                if frame is None:
                    break
                self._handle(frame[0], frame[1])
            while self._got != self._need:
                remaining = deadline - self._clock()
                if remaining <= 0.0:
                    break
                frame = bus.recv(remaining)
                if frame is None:
                    break
                self._handle(frame[0], frame[1])
        except CanBusError as exc:
            self._set_fault(f"bus error: {exc}")

    def _handle(self, can_id: int, data: bytes) -> None:
        try:
            if can_id == self._id_enc:
                self._on_encoder(data)
            elif can_id == self._id_tpdo1:
                statusword, velocity = cia402.parse_tpdo_status_velocity(data)
                self._on_status(statusword)
                self._motor_speed_deg_s = velocity * self._motor_deg_s_per_unit
                self._got |= _TPDO1
            elif can_id == self._id_tpdo2:
                self._motor_position_deg = (
                    cia402.parse_tpdo_position(data) * self._motor_deg_per_count
                )
                self._got |= _TPDO2
            elif can_id == self._id_raw_vel:
                assert self._raw_vel is not None
                velocity = self._raw_vel.decode(data)
                self._motor_speed_deg_s = velocity * self._motor_deg_s_per_unit
                self._got |= _RAW_VEL
            elif can_id == self._id_hb:
                self._on_heartbeat(cia402.parse_heartbeat(data))
            elif can_id == self._id_emcy:
                code, register = cia402.parse_emcy(data)
                if code != 0:
                    self._set_fault(f"drive EMCY 0x{code:04X} (error register 0x{register:02X})")
            elif can_id == self._id_sdo_tx:
                self._sdo_reply = cia402.parse_sdo_reply(data)
            elif can_id == ERROR_FRAME_ID:
                self._set_fault(f"CAN error frame {data.hex()}")
        except ValueError as exc:
            self._set_fault(f"garbage frame on 0x{can_id:X} ({data.hex()}): {exc}")

    def _on_encoder(self, data: bytes) -> None:
        raw = self._enc_codec.decode(data)
        modulus = self._enc_modulus
        syncs = self._syncs
        if self._enc_sync < 0:
            counts = raw % modulus
            if counts >= modulus // 2:
                counts -= modulus  # first reading placed in [-half, half) of the range
            self._enc_counts = counts
            self._speed_deg_s = 0.0
        else:
            delta = (raw - self._enc_raw) % modulus
            if delta >= modulus // 2:
                delta -= modulus
            ticks = syncs - self._enc_sync
            if ticks < 1:
                ticks = 1
            step_deg = delta * self._enc_deg_per_count
            if abs(step_deg) > self._max_encoder_speed_deg_s * ticks * self._period_s + 0.01:
                raise ValueError(f"encoder jump of {step_deg:.3f} deg in {ticks} ticks")
            self._enc_counts += delta
            self._speed_deg_s = step_deg / (ticks * self._period_s)
        self._enc_raw = raw
        self._enc_sync = syncs
        self._pos_deg = self._enc_counts * self._enc_deg_per_count
        self._got |= _ENC

    def _on_status(self, statusword: int) -> None:
        self._statusword = statusword
        state = cia402.decode_state(statusword)
        self._drive_state = state
        if not self._enabled:
            return
        if statusword & cia402.SW_FAULT:
            self._set_fault(f"drive fault (statusword 0x{statusword:04X})")
        elif state is not State.OPERATION_ENABLED:
            name = "unknown state" if state is None else state.name
            self._set_fault(f"drive left Operation enabled: {name} (statusword 0x{statusword:04X})")

    def _on_heartbeat(self, nmt_state: int) -> None:
        self._hb_state = nmt_state
        self._hb_time = self._clock()
        if self._enabled and nmt_state != NmtState.OPERATIONAL:
            self._set_fault(f"drive NMT state 0x{nmt_state:02X} in heartbeat, not operational")

    def _exchange(self, controlword: int, deadline: float) -> None:
        """Setup only: send one command + SYNC and wait for its complete feedback."""
        self._send_command(controlword, 0)
        self._sync_pending = False
        self._collect(deadline)
        if self.fault is not None:
            raise RigFault(self.fault)
        if self._got != self._need:
            raise RigFault(
                "timeout waiting for the drive's feedback during start "
                f"(frames 0b{self._got:03b} of 0b{self._need:03b})"
            )

    def _sdo_write(self, index: int, subindex: int, value: int, size: int, deadline: float) -> None:
        assert self._id_sdo_tx is not None
        ids = self.rig_file.drive.cob_ids
        self._sdo_reply = None
        self._bus.send(ids.sdo_rx, cia402.make_sdo_download(index, subindex, value, size))
        bus = self._bus
        while self._sdo_reply is None:
            remaining = deadline - self._clock()
            frame = bus.recv(remaining) if remaining > 0.0 else None
            if frame is None:
                raise RigFault(f"timeout waiting for the SDO reply writing 0x{index:04X}")
            self._handle(frame[0], frame[1])
        reply = self._sdo_reply
        if (reply.index, reply.subindex) != (index, subindex):
            raise RigFault(f"SDO reply for 0x{reply.index:04X} while writing 0x{index:04X}")
        if not reply.ok:
            raise RigFault(
                f"SDO write 0x{index:04X}:{subindex} = {value} aborted (0x{reply.abort_code:08X})"
            )

    def _wait_heartbeat(self, since: float, deadline: float) -> None:
        """Setup only: wait for an operational heartbeat received after `since`."""
        bus = self._bus
        while not (self._hb_state == NmtState.OPERATIONAL and self._hb_time >= since):
            remaining = deadline - self._clock()
            frame = bus.recv(remaining) if remaining > 0.0 else None
            if frame is None:
                seen = "none" if self._hb_state is None else f"NMT state 0x{self._hb_state:02X}"
                raise RigFault(
                    "no operational heartbeat from the drive after NMT start (last: "
                    f"{seen}): the drive is not enabled"
                )
            self._handle(frame[0], frame[1])
            if self.fault is not None:
                raise RigFault(self.fault)

    def _check_heartbeat_live(self) -> None:
        age = self._clock() - self._hb_time
        if age > self._hb_timeout_s:
            raise RigFault(
                f"heartbeat lost during start ({age * 1000.0:.0f} ms since the last): "
                "the drive is not enabled"
            )

    def _start_cia402(self, deadline: float) -> None:
        drive = self.rig_file.drive
        self._sdo_write(cia402.MODES_OF_OPERATION, 0, cia402.PROFILE_VELOCITY_MODE, 1, deadline)
        if drive.heartbeat_period_ms > 0:
            self._sdo_write(
                cia402.PRODUCER_HEARTBEAT_TIME, 0, drive.heartbeat_period_ms, 2, deadline
            )
        nmt_sent = self._clock()
        self._bus.send(drive.cob_ids.nmt, cia402.make_nmt(cia402.NmtCommand.START, drive.node_id))
        if self._hb_supervised:
            # Never enable a drive whose heartbeat is not live: wait for an "operational" one
            # sent after the NMT start (a reset with a dead heartbeat stays disabled).
            self._wait_heartbeat(nmt_sent, deadline)
        # Disable voltage first: a known starting point, and the low edge a fault reset needs.
        controlword = cia402.CW_DISABLE_VOLTAGE
        resets = 0
        while True:
            if self._hb_supervised and controlword != cia402.CW_DISABLE_VOLTAGE:
                self._check_heartbeat_live()
            self._exchange(controlword, deadline)
            state = self._drive_state
            if state is State.OPERATION_ENABLED:
                return
            if state is State.FAULT:
                if controlword == cia402.CW_FAULT_RESET:
                    controlword = cia402.CW_DISABLE_VOLTAGE  # release bit 7 for a new edge
                    continue
                resets += 1
                if resets > 2:
                    raise RigFault(f"drive stays in Fault (statusword 0x{self._statusword:04X})")
            if state is None:
                raise RigFault(f"statusword 0x{self._statusword:04X} is no CiA 402 state")
            if self._clock() > deadline:
                raise RigFault(f"drive not enabled in time: {state.name}")
            next_controlword = cia402.enable_controlword(state)
            if next_controlword is not None:
                controlword = next_controlword
