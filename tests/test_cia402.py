"""CiA 301/402 frame packing against hand-computed bytes, the state machine, and the rig file."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import pytest

from controller.core.errors import ConfigError
from controller.rig import cia402
from controller.rig.cia402 import State
from controller.rig.rig_file import load_rig_file, parse_rig_file

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "rig_cia402.toml"


# --- Frames against the spec, byte by byte --------------------------------------------------
@pytest.mark.parametrize(
    ("controlword", "velocity", "expected"),
    [
        (0x000F, 0, b"\x0f\x00\x00\x00\x00\x00"),  # enable operation, stand still
        (0x000F, 1000, b"\x0f\x00\xe8\x03\x00\x00"),  # 1000 = 0x3E8, little endian
        (0x0007, -1, b"\x07\x00\xff\xff\xff\xff"),  # disable operation, two's complement
        (0x0080, -(2**31), b"\x80\x00\x00\x00\x00\x80"),  # fault reset, i32 minimum
    ],
)
def test_rpdo_command_bytes(controlword: int, velocity: int, expected: bytes) -> None:
    assert cia402.make_rpdo_command(controlword, velocity) == expected
    assert cia402.parse_rpdo_command(expected) == (controlword, velocity)


def test_tpdo1_statusword_0627_is_operation_enabled() -> None:
    data = b"\x27\x06\x10\x27\x00\x00"  # statusword 0x0627, velocity actual 10000 (0x2710)
    statusword, velocity = cia402.parse_tpdo_status_velocity(data)
    assert (statusword, velocity) == (0x0627, 10000)
    assert cia402.decode_state(statusword) is State.OPERATION_ENABLED
    assert cia402.make_tpdo_status_velocity(0x0627, 10000) == data


def test_tpdo2_position_bytes() -> None:
    assert cia402.make_tpdo_position(-2) == b"\xfe\xff\xff\xff"
    assert cia402.parse_tpdo_position(b"\x00\x00\x01\x00") == 65536


@pytest.mark.parametrize(
    ("statusword", "state"),
    [
        (0x0000, State.NOT_READY_TO_SWITCH_ON),
        (0x0250, State.SWITCH_ON_DISABLED),  # bit 4 (voltage) does not matter
        (0x0231, State.READY_TO_SWITCH_ON),
        (0x0233, State.SWITCHED_ON),
        (0x0637, State.OPERATION_ENABLED),
        (0x0217, State.QUICK_STOP_ACTIVE),  # bit 5 clear: quick stop active
        (0x021F, State.FAULT_REACTION_ACTIVE),
        (0x0208, State.FAULT),
        (0x0288, State.FAULT),  # warning bit set too
    ],
)
def test_decode_state_table(statusword: int, state: State) -> None:
    assert cia402.decode_state(statusword) is state


def test_statusword_for_each_state_decodes_back() -> None:
    for state in State:
        assert cia402.decode_state(cia402.statusword_for(state)) is state


def test_nmt_heartbeat_sdo_emcy_bytes() -> None:
    assert cia402.make_nmt(cia402.NmtCommand.START, 1) == b"\x01\x01"
    assert cia402.parse_nmt(b"\x80\x05") == (0x80, 5)
    assert cia402.make_heartbeat(cia402.NmtState.OPERATIONAL) == b"\x05"
    assert cia402.parse_heartbeat(b"\x7f") == cia402.NmtState.PRE_OPERATIONAL
    # 0x6060 modes of operation := 3 (profile velocity), 1 byte: ccs 0x2F
    write_mode = cia402.make_sdo_download(0x6060, 0, 3, 1)
    assert write_mode == b"\x2f\x60\x60\x00\x03\x00\x00\x00"
    request = cia402.parse_sdo_request(write_mode)
    assert (request.index, request.subindex, request.value, request.size) == (0x6060, 0, 3, 1)
    # 0x1017 producer heartbeat := 100 ms, 2 bytes: ccs 0x2B
    assert cia402.make_sdo_download(0x1017, 0, 100, 2) == b"\x2b\x17\x10\x00\x64\x00\x00\x00"
    assert cia402.make_sdo_download(0x6060, 0, -1, 1) == b"\x2f\x60\x60\x00\xff\x00\x00\x00"
    assert cia402.make_sdo_download_reply(0x6060, 0) == b"\x60\x60\x60\x00\x00\x00\x00\x00"
    abort = cia402.make_sdo_abort(0x6060, 0, 0x06090030)
    assert abort == b"\x80\x60\x60\x00\x30\x00\x09\x06"
    reply = cia402.parse_sdo_reply(abort)
    assert not reply.ok and reply.abort_code == 0x06090030
    assert cia402.parse_sdo_reply(cia402.make_sdo_download_reply(0x1017, 0)).ok
    emcy = cia402.make_emcy(0x2310, 0x03)  # continuous over-current, current + generic
    assert emcy == b"\x10\x23\x03\x00\x00\x00\x00\x00"
    assert cia402.parse_emcy(emcy) == (0x2310, 0x03)


@pytest.mark.parametrize(
    ("call", "field"),
    [
        (lambda: cia402.make_rpdo_command(0x10000, 0), "controlword"),
        (lambda: cia402.make_rpdo_command(-1, 0), "controlword"),
        (lambda: cia402.make_rpdo_command(0x000F, 2**31), "target_velocity"),
        (lambda: cia402.make_tpdo_status_velocity(0x10000, 0), "statusword"),
        (lambda: cia402.make_tpdo_status_velocity(0, -(2**31) - 1), "velocity_actual"),
        (lambda: cia402.make_tpdo_position(2**31), "position_actual"),
        (lambda: cia402.make_nmt(1, 128), "node_id"),
        (lambda: cia402.make_heartbeat(256), "state"),
        (lambda: cia402.make_sdo_download(0x6060, 0, 256, 1), "value"),
        (lambda: cia402.make_sdo_download(0x6060, 0, 0, 5), "size"),
        (lambda: cia402.make_emcy(0x10000, 0), "error_code"),
        (lambda: cia402.FieldCodec(6, 4, False, "little"), "length"),
    ],
)
def test_out_of_range_raises_naming_field(call: Callable[[], object], field: str) -> None:
    with pytest.raises(ValueError, match=rf"^{field}="):
        call()


@pytest.mark.parametrize(
    "parse",
    [
        cia402.parse_rpdo_command,
        cia402.parse_tpdo_status_velocity,
        cia402.parse_tpdo_position,
        cia402.parse_heartbeat,
        cia402.parse_sdo_reply,
        cia402.parse_emcy,
    ],
)
def test_short_frames_are_rejected(parse: Callable[[bytes], object]) -> None:
    with pytest.raises(ValueError, match=r"expected \d bytes, got 3"):
        parse(b"\x01\x02\x03")


# --- State machine --------------------------------------------------------------------------
def test_enable_sequence_reaches_operation_enabled() -> None:
    state, previous = State.SWITCH_ON_DISABLED, 0
    visited = [state]
    for _ in range(5):
        controlword = cia402.enable_controlword(state)
        if controlword is None:
            break
        state, previous = cia402.drive_next_state(state, controlword, previous), controlword
        visited.append(state)
    assert visited == [
        State.SWITCH_ON_DISABLED,
        State.READY_TO_SWITCH_ON,
        State.SWITCHED_ON,
        State.OPERATION_ENABLED,
    ]


@pytest.mark.parametrize(
    ("state", "controlword", "previous", "expected"),
    [
        (State.OPERATION_ENABLED, cia402.CW_DISABLE_OPERATION, 0x0F, State.SWITCHED_ON),  # 5
        (State.OPERATION_ENABLED, cia402.CW_SHUTDOWN, 0x0F, State.READY_TO_SWITCH_ON),  # 8
        (State.OPERATION_ENABLED, cia402.CW_QUICK_STOP, 0x0F, State.QUICK_STOP_ACTIVE),  # 11
        (State.OPERATION_ENABLED, cia402.CW_DISABLE_VOLTAGE, 0x0F, State.SWITCH_ON_DISABLED),
        (State.READY_TO_SWITCH_ON, cia402.CW_ENABLE_OPERATION, 0x06, State.OPERATION_ENABLED),
        (State.SWITCH_ON_DISABLED, cia402.CW_ENABLE_OPERATION, 0x00, State.SWITCH_ON_DISABLED),
        (State.FAULT, cia402.CW_FAULT_RESET, 0x00, State.SWITCH_ON_DISABLED),  # 15, rising edge
        (State.FAULT, cia402.CW_FAULT_RESET, 0x80, State.FAULT),  # bit held: no edge
        (State.FAULT, cia402.CW_ENABLE_OPERATION, 0x00, State.FAULT),
    ],
)
def test_drive_transitions(state: State, controlword: int, previous: int, expected: State) -> None:
    assert cia402.drive_next_state(state, controlword, previous) is expected


# --- Generic fields -------------------------------------------------------------------------
def test_field_codec_layouts() -> None:
    be24 = cia402.FieldCodec(1, 3, True, "big")
    assert be24.decode(b"\x00\xff\xff\xfe") == -2
    buf = bytearray(4)
    be24.encode_into(buf, -2)
    assert bytes(buf) == b"\x00\xff\xff\xfe"
    le32 = cia402.FieldCodec(0, 4, False, "little")
    assert le32.decode(b"\xff\xff\xff\x03") == 2**26 - 1
    with pytest.raises(ValueError, match="too short"):
        le32.decode(b"\x00\x00")
    with pytest.raises(ValueError, match="value=-1"):
        le32.encode_into(bytearray(4), -1)


# --- Rig file -------------------------------------------------------------------------------
def test_example_rig_file_loads() -> None:
    rig = load_rig_file(EXAMPLE)
    assert rig.bus.interface == "socketcan" and rig.bus.channel == "can0"
    assert rig.drive.profile == "cia402" and rig.drive.node_id == 1
    assert rig.drive.gear_ratio == 132.0
    assert rig.drive.cob_ids.rpdo_command == 0x201
    assert rig.drive.cob_ids.tpdo_status_velocity == 0x181
    assert rig.drive.cob_ids.tpdo_position == 0x281
    assert rig.drive.cob_ids.heartbeat == 0x701
    assert rig.load_encoder.counts_per_rev == 2**26
    assert rig.limits.feedback_timeout_ticks == 5
    # 1 deg/s at the load = 132 deg/s at the motor = 22 rpm = 220 units of 0.1 rpm
    assert rig.drive.velocity_units_per_load_deg_s == pytest.approx(220.0)
    assert rig.max_load_speed_deg_s == pytest.approx(60.0)


def _edit(pattern: str, replacement: str) -> str:
    text = EXAMPLE.read_text()
    edited, n = re.subn(pattern, replacement, text, count=1, flags=re.MULTILINE)
    assert n == 1, pattern
    return edited


@pytest.mark.parametrize(
    ("pattern", "replacement", "field"),
    [
        (r"^gear_ratio = .*$", "", "drive.gear_ratio"),  # missing
        (r"^gear_ratio = .*$", "gear_ratio = -132.0", "drive.gear_ratio"),
        (r"^gear_ratio = .*$", 'gear_ratio = "132"', "drive.gear_ratio"),
        (r"^node_id = .*$", "node_id = 200", "drive.node_id"),
        (r"^node_id = .*$", "node_id = true", "drive.node_id"),
        (r"^velocity_unit = .*$", 'velocity_unit = "furlong/fortnight"', "drive.velocity_unit"),
        (r"^profile = .*$", 'profile = "raw"', "drive.raw"),
        (r"^direction = 1 ", "direction = 2 ", "drive.direction"),
        (
            r"^heartbeat_timeout_ms = .*$",
            "heartbeat_timeout_ms = 50.0",
            "drive.heartbeat_timeout_ms",
        ),
        (r"^max_speed_rpm = .*$", "max_speed_rpm = inf", "drive.max_speed_rpm"),
        (r"^\[bus\]", "[buss]", "bus"),
        (r"^channel = .*$", "", "bus.channel"),
        (r"^frame_id = .*$", "frame_id = 0x181", "load_encoder.frame_id"),  # = TPDO1
        (r"^length = 4 ", "length = 9 ", "load_encoder.length"),
        (r"^length = 4 ", "length = 2 ", "load_encoder.counts_per_rev"),  # 2^26 > 16 bits
        (r"^byteorder = .*$", 'byteorder = "middle"', "load_encoder.byteorder"),
        (r"^command_limit_deg_s = .*$", "", "limits.command_limit_deg_s"),
        (
            r"^feedback_timeout_ticks = .*$",
            "feedback_timeout_tick = 5",
            "limits.feedback_timeout_tick",
        ),  # a typo is an unknown key, not a silent default
        (
            r"^feedback_timeout_ticks = .*$",
            "feedback_timeout_ticks = 0",
            "limits.feedback_timeout_ticks",
        ),
        (
            r"^# \[drive.cob_ids\]\n# nmt = 0x000",
            "[drive.cob_ids]\nrpdo_command = 0x181",
            "drive.cob_ids",
        ),
        (r"^name = .*$", "name = 'x'\nspeed = 3", "speed"),
    ],
)
def test_bad_rig_file_names_the_field(pattern: str, replacement: str, field: str) -> None:
    text = _edit(pattern, replacement)
    with pytest.raises(ConfigError) as info:
        parse_rig_file(text)
    assert info.value.field == field, str(info.value)
    assert str(info.value).startswith(field)


def test_cob_id_override_and_defaults() -> None:
    text = _edit(r"^# \[drive.cob_ids\]\n# nmt = 0x000", "[drive.cob_ids]\nrpdo_command = 0x301")
    rig = parse_rig_file(text)
    assert rig.drive.cob_ids.rpdo_command == 0x301
    assert rig.drive.cob_ids.sync == 0x080


def test_raw_profile_parses() -> None:
    text = EXAMPLE.read_text().replace('profile = "cia402"', 'profile = "raw"')
    text = re.sub(
        r"^# (\[drive\.raw\]|command_|velocity_feedback_)", r"\1", text, flags=re.MULTILINE
    )
    rig = parse_rig_file(text)
    assert rig.drive.raw is not None
    assert rig.drive.raw.command_id == 0x120 and rig.drive.raw.command_dlc == 8
    assert rig.drive.raw.velocity_feedback_id == 0x121


def test_invalid_toml_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="invalid TOML"):
        parse_rig_file("[bus\n")
