"""CANopen (CiA 301) and CiA 402 frame packing and parsing: pure functions, no I/O.

Frames are plain ``(can_id, data)`` values; only ``controller.rig.can_rig`` touches python-can.
The per-tick frames use precompiled ``struct.Struct`` objects so that packing a command and
parsing the feedback of one tick costs a few microseconds.

PDO mapping used by this project (configurable COB-IDs, fixed layouts, little endian as
CiA 301 requires):

- RPDO1 (0x200 + node): controlword 0x6040 (u16), target velocity 0x60FF (i32): 6 bytes.
- TPDO1 (0x180 + node): statusword 0x6041 (u16), velocity actual value 0x606C (i32): 6 bytes.
- TPDO2 (0x280 + node): position actual value 0x6064 (i32): 4 bytes.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Literal

__all__ = [
    "CONTROLWORD",
    "CW_DISABLE_OPERATION",
    "CW_DISABLE_VOLTAGE",
    "CW_ENABLE_OPERATION",
    "CW_FAULT_RESET",
    "CW_QUICK_STOP",
    "CW_SHUTDOWN",
    "CW_SWITCH_ON",
    "EMCY_BASE",
    "HEARTBEAT_BASE",
    "MODES_OF_OPERATION",
    "NMT_ID",
    "PRODUCER_HEARTBEAT_TIME",
    "PROFILE_VELOCITY_MODE",
    "RPDO1_BASE",
    "SDO_ABORT_NO_OBJECT",
    "SDO_ABORT_VALUE_RANGE",
    "SDO_RX_BASE",
    "SDO_TX_BASE",
    "SW_FAULT",
    "SW_OPERATION_ENABLED",
    "SW_QUICK_STOP",
    "SW_READY_TO_SWITCH_ON",
    "SW_REMOTE",
    "SW_SWITCHED_ON",
    "SW_SWITCH_ON_DISABLED",
    "SW_TARGET_REACHED",
    "SW_VOLTAGE_ENABLED",
    "SW_WARNING",
    "SYNC_ID",
    "TPDO1_BASE",
    "TPDO2_BASE",
    "FieldCodec",
    "NmtCommand",
    "NmtState",
    "SdoReply",
    "SdoRequest",
    "State",
    "decode_state",
    "drive_next_state",
    "enable_controlword",
    "make_emcy",
    "make_heartbeat",
    "make_nmt",
    "make_rpdo_command",
    "make_sdo_abort",
    "make_sdo_download",
    "make_sdo_download_reply",
    "make_tpdo_position",
    "make_tpdo_status_velocity",
    "parse_emcy",
    "parse_heartbeat",
    "parse_nmt",
    "parse_rpdo_command",
    "parse_sdo_reply",
    "parse_sdo_request",
    "parse_tpdo_position",
    "parse_tpdo_status_velocity",
    "statusword_for",
]

# --- CiA 301 predefined connection set (function code bases; add the node id) -------------
NMT_ID = 0x000
SYNC_ID = 0x080
EMCY_BASE = 0x080
TPDO1_BASE = 0x180
RPDO1_BASE = 0x200
TPDO2_BASE = 0x280
SDO_TX_BASE = 0x580  # server (drive) -> client
SDO_RX_BASE = 0x600  # client -> server (drive)
HEARTBEAT_BASE = 0x700

# --- Object dictionary entries used --------------------------------------------------------
PRODUCER_HEARTBEAT_TIME = 0x1017  # u16, ms
CONTROLWORD = 0x6040
MODES_OF_OPERATION = 0x6060  # i8
PROFILE_VELOCITY_MODE = 3

SDO_ABORT_NO_OBJECT = 0x06020000
SDO_ABORT_VALUE_RANGE = 0x06090030


class NmtCommand(IntEnum):
    """NMT command specifiers (CiA 301 7.2.8.3.1)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """NMT states as reported by the heartbeat (CiA 301 7.2.8.3.2)."""

    BOOTUP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


# --- CiA 402 controlword commands (bits 0..3 and 7) ----------------------------------------
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_DISABLE_OPERATION = 0x0007  # same bits as switch on; from Operation enabled -> Switched on
CW_ENABLE_OPERATION = 0x000F
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_FAULT_RESET = 0x0080  # acts on the rising edge of bit 7

# --- CiA 402 statusword bits ---------------------------------------------------------------
SW_READY_TO_SWITCH_ON = 0x0001
SW_SWITCHED_ON = 0x0002
SW_OPERATION_ENABLED = 0x0004
SW_FAULT = 0x0008
SW_VOLTAGE_ENABLED = 0x0010
SW_QUICK_STOP = 0x0020  # 1 = quick stop NOT active
SW_SWITCH_ON_DISABLED = 0x0040
SW_WARNING = 0x0080
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400


class State(IntEnum):
    """CiA 402 power drive system states."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


# (mask, value, state), tried in order: the CiA 402 statusword state table.
_STATE_TABLE: tuple[tuple[int, int, State], ...] = (
    (0x4F, 0x00, State.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State.SWITCHED_ON),
    (0x6F, 0x27, State.OPERATION_ENABLED),
    (0x6F, 0x07, State.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State.FAULT),
)


def decode_state(statusword: int) -> State | None:
    """The CiA 402 state encoded in a statusword, or None for a pattern the table lacks."""
    for mask, value, state in _STATE_TABLE:
        if statusword & mask == value:
            return state
    return None


_STATUSWORD_OF_STATE: dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: SW_SWITCH_ON_DISABLED,
    State.READY_TO_SWITCH_ON: SW_QUICK_STOP | SW_READY_TO_SWITCH_ON,
    State.SWITCHED_ON: SW_QUICK_STOP | SW_VOLTAGE_ENABLED | SW_SWITCHED_ON | SW_READY_TO_SWITCH_ON,
    State.OPERATION_ENABLED: SW_QUICK_STOP
    | SW_VOLTAGE_ENABLED
    | SW_OPERATION_ENABLED
    | SW_SWITCHED_ON
    | SW_READY_TO_SWITCH_ON,
    State.QUICK_STOP_ACTIVE: SW_VOLTAGE_ENABLED
    | SW_OPERATION_ENABLED
    | SW_SWITCHED_ON
    | SW_READY_TO_SWITCH_ON,
    State.FAULT_REACTION_ACTIVE: 0x000F,
    State.FAULT: SW_FAULT,
}


def statusword_for(state: State, *, remote: bool = True) -> int:
    """A statusword a drive reports in ``state`` (drive side, used by the simulated node)."""
    return _STATUSWORD_OF_STATE[state] | (SW_REMOTE if remote else 0)


def enable_controlword(state: State) -> int | None:
    """Master side: the controlword that moves a drive in ``state`` towards Operation enabled.

    None when the drive is already enabled or must be left alone (automatic transitions).
    """
    if state is State.SWITCH_ON_DISABLED:
        return CW_SHUTDOWN
    if state is State.READY_TO_SWITCH_ON:
        return CW_SWITCH_ON
    if state is State.SWITCHED_ON:
        return CW_ENABLE_OPERATION
    if state is State.QUICK_STOP_ACTIVE:
        return CW_DISABLE_VOLTAGE
    if state is State.FAULT:
        return CW_FAULT_RESET
    return None


def drive_next_state(state: State, controlword: int, previous_controlword: int) -> State:
    """Drive side: the CiA 402 transition a controlword causes (automatic ones excluded)."""
    if state is State.FAULT:
        if controlword & 0x80 and not previous_controlword & 0x80:
            return State.SWITCH_ON_DISABLED  # transition 15
        return state
    if state in (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE):
        return state
    if controlword & 0x80:
        return state  # fault reset outside Fault: ignored
    bits = controlword & 0x0F
    if not bits & 0x02:  # disable voltage: transitions 7, 9, 10, 12
        return State.SWITCH_ON_DISABLED
    if not bits & 0x04:  # quick stop: 11 from Operation enabled; 7, 10 otherwise
        if state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
            return State.QUICK_STOP_ACTIVE
        return State.SWITCH_ON_DISABLED
    if not bits & 0x01:  # shutdown: transitions 2, 6, 8
        if state is State.QUICK_STOP_ACTIVE:
            return state
        return State.READY_TO_SWITCH_ON
    if state is State.SWITCH_ON_DISABLED:
        return state  # switch on is not allowed before shutdown
    if bits & 0x08:  # enable operation: 3+4, 4, 16
        return State.OPERATION_ENABLED
    # switch on / disable operation: 3, 5
    if state is State.QUICK_STOP_ACTIVE:
        return state
    return State.SWITCHED_ON


# --- Precompiled layouts -------------------------------------------------------------------
_U8 = struct.Struct("<B")
_NMT = struct.Struct("<BB")
_CW_VEL = struct.Struct("<Hi")  # RPDO1 and, with statusword, TPDO1
_I32 = struct.Struct("<i")
_EMCY = struct.Struct("<HB5s")
_SDO = struct.Struct("<BHBI")

_INT32_MIN = -(2**31)
_INT32_MAX = 2**31 - 1


def _check_u(field: str, value: int, bits: int) -> None:
    if not 0 <= value < 1 << bits:
        raise ValueError(f"{field}={value} out of range for u{bits}")


def _check_i32(field: str, value: int) -> None:
    if not _INT32_MIN <= value <= _INT32_MAX:
        raise ValueError(f"{field}={value} out of range for i32")


def _check_len(what: str, data: bytes, expected: int) -> None:
    if len(data) != expected:
        raise ValueError(f"{what}: expected {expected} bytes, got {len(data)}")


def make_nmt(command: int, node_id: int) -> bytes:
    """NMT module control frame data (send on COB-ID 0); node_id 0 addresses every node."""
    _check_u("command", command, 8)
    if not 0 <= node_id <= 127:
        raise ValueError(f"node_id={node_id} out of range 0..127")
    return _NMT.pack(command, node_id)


def parse_nmt(data: bytes) -> tuple[int, int]:
    """(command, node_id) of an NMT frame."""
    _check_len("NMT", data, 2)
    return _NMT.unpack(data)


def make_heartbeat(state: int) -> bytes:
    _check_u("state", state, 8)
    return _U8.pack(state)


def parse_heartbeat(data: bytes) -> int:
    """The NMT state byte of a heartbeat frame (bit 7, the legacy toggle bit, is not masked)."""
    _check_len("heartbeat", data, 1)
    return data[0]


def _make_word_velocity(word_field: str, word: int, velocity_field: str, velocity: int) -> bytes:
    """A u16 word + an i32 velocity, the layout RPDO1 and TPDO1 share; a value out of its
    range is named by its field."""
    try:
        return _CW_VEL.pack(word, velocity)
    except struct.error:
        _check_u(word_field, word, 16)
        _check_i32(velocity_field, velocity)
        raise


def make_rpdo_command(controlword: int, target_velocity: int) -> bytes:
    """RPDO1: controlword (u16) + target velocity (i32, drive velocity units)."""
    return _make_word_velocity("controlword", controlword, "target_velocity", target_velocity)


def parse_rpdo_command(data: bytes) -> tuple[int, int]:
    """(controlword, target_velocity) of RPDO1."""
    _check_len("RPDO1", data, 6)
    return _CW_VEL.unpack(data)


def make_tpdo_status_velocity(statusword: int, velocity_actual: int) -> bytes:
    """TPDO1: statusword (u16) + velocity actual value (i32, drive velocity units)."""
    return _make_word_velocity("statusword", statusword, "velocity_actual", velocity_actual)


def parse_tpdo_status_velocity(data: bytes) -> tuple[int, int]:
    """(statusword, velocity_actual) of TPDO1."""
    _check_len("TPDO1", data, 6)
    return _CW_VEL.unpack(data)


def make_tpdo_position(position_actual: int) -> bytes:
    """TPDO2: position actual value (i32, motor encoder counts)."""
    try:
        return _I32.pack(position_actual)
    except struct.error:
        _check_i32("position_actual", position_actual)
        raise


def parse_tpdo_position(data: bytes) -> int:
    _check_len("TPDO2", data, 4)
    value: int = _I32.unpack(data)[0]
    return value


def make_emcy(error_code: int, error_register: int, vendor: bytes = b"") -> bytes:
    """EMCY frame data; error_code 0 means "error reset / no error"."""
    _check_u("error_code", error_code, 16)
    _check_u("error_register", error_register, 8)
    if len(vendor) > 5:
        raise ValueError(f"vendor: at most 5 bytes, got {len(vendor)}")
    return _EMCY.pack(error_code, error_register, vendor)


def parse_emcy(data: bytes) -> tuple[int, int]:
    """(error_code, error_register) of an EMCY frame."""
    _check_len("EMCY", data, 8)
    code, register, _ = _EMCY.unpack(data)
    return code, register


# --- Expedited SDO (setup only, never on the tick) -----------------------------------------
_SDO_DOWNLOAD_CS = {1: 0x2F, 2: 0x2B, 3: 0x27, 4: 0x23}
_SDO_SIZE_OF_CS = {cs: size for size, cs in _SDO_DOWNLOAD_CS.items()}


@dataclass(frozen=True, slots=True)
class SdoRequest:
    """An expedited SDO download (write) request as the server sees it."""

    index: int
    subindex: int
    value: int
    size: int


@dataclass(frozen=True, slots=True)
class SdoReply:
    """A server's answer to a download: ok, or an abort code."""

    index: int
    subindex: int
    abort_code: int | None

    @property
    def ok(self) -> bool:
        return self.abort_code is None


def make_sdo_download(index: int, subindex: int, value: int, size: int) -> bytes:
    """Expedited SDO download request writing ``size`` bytes (unsigned two's complement)."""
    if size not in _SDO_DOWNLOAD_CS:
        raise ValueError(f"size={size} must be 1..4 bytes")
    _check_u("index", index, 16)
    _check_u("subindex", subindex, 8)
    if not -(1 << (8 * size - 1)) <= value < 1 << (8 * size):
        raise ValueError(f"value={value} does not fit in {size} bytes")
    return _SDO.pack(_SDO_DOWNLOAD_CS[size], index, subindex, value & ((1 << (8 * size)) - 1))


def parse_sdo_request(data: bytes) -> SdoRequest:
    """Decode an expedited download request; ValueError for anything else."""
    _check_len("SDO request", data, 8)
    cs, index, subindex, raw = _SDO.unpack(data)
    size = _SDO_SIZE_OF_CS.get(cs)
    if size is None:
        raise ValueError(f"SDO request: unsupported command specifier 0x{cs:02X}")
    return SdoRequest(index, subindex, raw & ((1 << (8 * size)) - 1), size)


def make_sdo_download_reply(index: int, subindex: int) -> bytes:
    return _SDO.pack(0x60, index, subindex, 0)


def make_sdo_abort(index: int, subindex: int, abort_code: int) -> bytes:
    _check_u("abort_code", abort_code, 32)
    return _SDO.pack(0x80, index, subindex, abort_code)


def parse_sdo_reply(data: bytes) -> SdoReply:
    _check_len("SDO reply", data, 8)
    cs, index, subindex, raw = _SDO.unpack(data)
    if cs == 0x60:
        return SdoReply(index, subindex, None)
    if cs == 0x80:
        return SdoReply(index, subindex, raw)
    raise ValueError(f"SDO reply: unexpected command specifier 0x{cs:02X}")


# --- Generic integer fields for raw frames and encoders ------------------------------------
_STRUCT_CODES = {1: "b", 2: "h", 4: "i", 8: "q"}


class FieldCodec:
    """Reads/writes one integer field at a byte offset of a frame (any length 1..8)."""

    __slots__ = (
        "_struct",
        "byteorder",
        "length",
        "max_value",
        "min_dlc",
        "min_value",
        "modulus",
        "offset",
        "signed",
    )

    def __init__(
        self, offset: int, length: int, signed: bool, byteorder: Literal["little", "big"]
    ) -> None:
        if not 0 <= offset <= 7:
            raise ValueError(f"offset={offset} must be 0..7")
        if not 1 <= length <= 8 - offset:
            raise ValueError(f"length={length} must be 1..{8 - offset} at offset {offset}")
        if byteorder not in ("little", "big"):
            raise ValueError(f"byteorder={byteorder!r} must be 'little' or 'big'")
        self.offset = offset
        self.length = length
        self.signed = signed
        self.byteorder = byteorder
        self.min_dlc = offset + length
        self.modulus = 1 << (8 * length)
        self.min_value = -(self.modulus >> 1) if signed else 0
        self.max_value = (self.modulus >> 1) - 1 if signed else self.modulus - 1
        code = _STRUCT_CODES.get(length)
        self._struct: struct.Struct | None = None
        if code is not None:
            prefix = "<" if byteorder == "little" else ">"
            self._struct = struct.Struct(prefix + (code if signed else code.upper()))

    def decode(self, data: bytes) -> int:
        """The field's value; ValueError when the frame is too short to hold it."""
        if len(data) < self.min_dlc:
            raise ValueError(
                f"frame of {len(data)} bytes too short for field ending at byte {self.min_dlc}"
            )
        if self._struct is not None:
            value: int = self._struct.unpack_from(data, self.offset)[0]
            return value
        return int.from_bytes(data[self.offset : self.min_dlc], self.byteorder, signed=self.signed)

    def encode_into(self, buffer: bytearray, value: int) -> None:
        """Write ``value`` into ``buffer`` (which must be at least ``min_dlc`` long)."""
        if not self.min_value <= value <= self.max_value:
            raise ValueError(f"value={value} out of range {self.min_value}..{self.max_value}")
        if self._struct is not None:
            self._struct.pack_into(buffer, self.offset, value)
        else:
            buffer[self.offset : self.min_dlc] = value.to_bytes(
                self.length, self.byteorder, signed=self.signed
            )
