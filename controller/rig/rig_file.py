"""The rig file: a TOML description of a real rig's CAN bus, drive and load encoder.

``load_rig_file(path)`` / ``parse_rig_file(text)`` return frozen dataclasses. Every missing,
mistyped, out-of-range or unknown key raises ``ConfigError`` (a ValueError) naming the field
(``drive.gear_ratio``), so a typo in a safety-relevant setting never passes silently.
See examples/rig_cia402.toml.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

from controller.core import validate
from controller.core.errors import ConfigError
from controller.rig import cia402

__all__ = [
    "VELOCITY_UNITS",
    "BusConfig",
    "CobIds",
    "DriveConfig",
    "FieldLayout",
    "LimitsConfig",
    "LoadEncoderConfig",
    "RawProfileConfig",
    "RigFile",
    "load_rig_file",
    "parse_rig_file",
]

# Drive velocity units (CiA 402 0x606C / 0x60FF) -> units per motor degree per second.
# "counts/s" depends on the motor encoder and is resolved in DriveConfig.
VELOCITY_UNITS: dict[str, float | None] = {
    "counts/s": None,
    "rpm": 1.0 / 6.0,
    "0.1rpm": 10.0 / 6.0,
    "0.01rpm": 100.0 / 6.0,
    "0.001rpm": 1000.0 / 6.0,
    "deg/s": 1.0,
}


@dataclass(frozen=True, slots=True)
class BusConfig:
    """How to open the CAN bus (passed to ``can.Bus``)."""

    interface: str
    """python-can interface name: socketcan, pcan, virtual, ..."""
    channel: str
    """Interface channel, e.g. can0."""
    bitrate: int
    """Bit rate in bit/s (ignored by socketcan and virtual, which take it from the system)."""


@dataclass(frozen=True, slots=True)
class FieldLayout:
    """Where an integer sits in a frame's data bytes."""

    offset: int
    length: int
    signed: bool
    byteorder: Literal["little", "big"]

    def codec(self) -> cia402.FieldCodec:
        return cia402.FieldCodec(self.offset, self.length, self.signed, self.byteorder)


@dataclass(frozen=True, slots=True)
class CobIds:
    """CAN identifiers of the CiA 402 profile (CiA 301 predefined connection set by default)."""

    nmt: int
    sync: int
    rpdo_command: int
    """RPDO1: controlword + target velocity."""
    tpdo_status_velocity: int
    """TPDO1: statusword + velocity actual value."""
    tpdo_position: int
    """TPDO2: position actual value."""
    emcy: int
    heartbeat: int
    sdo_rx: int
    """Client -> drive SDO requests."""
    sdo_tx: int
    """Drive -> client SDO replies."""


@dataclass(frozen=True, slots=True)
class RawProfileConfig:
    """Custom frames: one command frame per tick, optional motor velocity feedback frame."""

    command_id: int
    command_dlc: int
    command: FieldLayout
    """Target motor velocity in drive velocity units."""
    velocity_feedback_id: int | None
    velocity_feedback: FieldLayout | None
    """Actual motor velocity in drive velocity units."""


@dataclass(frozen=True, slots=True)
class DriveConfig:
    """The motor drive: profile, scaling and supervision."""

    node_id: int
    profile: Literal["cia402", "raw"]
    counts_per_rev: int
    """Motor encoder counts per motor revolution (position actual value units)."""
    gear_ratio: float
    """Motor revolutions per load revolution (motor speed = gear_ratio x load speed)."""
    direction: int
    """+1, or -1 when a positive drive velocity turns the load negative."""
    velocity_unit: str
    """Unit of the target/actual velocity objects, one of VELOCITY_UNITS."""
    max_speed_rpm: float
    """Motor speed limit applied to every command, rpm."""
    heartbeat_period_ms: int
    """Producer heartbeat time written to the drive (0x1017); 0 disables supervision."""
    heartbeat_timeout_ms: float
    """Heartbeat consumer time: longer than this without a heartbeat is a fault."""
    enable_timeout_s: float
    """Time allowed for SDO setup and the enable state machine in start()."""
    send_sync: bool
    """Send a SYNC after each command (the drive answers SYNC with its feedback)."""
    cob_ids: CobIds
    raw: RawProfileConfig | None

    @property
    def velocity_units_per_motor_deg_s(self) -> float:
        scale = VELOCITY_UNITS[self.velocity_unit]
        return self.counts_per_rev / 360.0 if scale is None else scale

    @property
    def velocity_units_per_load_deg_s(self) -> float:
        """Signed factor from a load-side speed in deg/s to drive velocity units."""
        return self.direction * self.gear_ratio * self.velocity_units_per_motor_deg_s


@dataclass(frozen=True, slots=True)
class LoadEncoderConfig:
    """The load-side encoder frame."""

    frame_id: int
    layout: FieldLayout
    counts_per_rev: int
    single_turn: bool
    """True: the value is the angle within one turn (0..counts_per_rev-1); the first reading
    is placed in [-180, 180) deg and later ones are unwrapped. False: a multi-turn count."""
    direction: int


@dataclass(frozen=True, slots=True)
class LimitsConfig:
    """Supervision and command limits."""

    command_limit_deg_s: float
    """Load-side speed command limit (deg/s)."""
    feedback_timeout_ticks: int
    """Consecutive ticks without complete feedback that make a fault (safe state)."""
    feedback_wait_s: float
    """How long read() may block for the feedback answering the last SYNC."""
    max_encoder_speed_factor: float
    """An encoder step implying more than this x the top load speed is a garbage frame."""


@dataclass(frozen=True, slots=True)
class RigFile:
    """A complete rig description."""

    name: str
    bus: BusConfig
    drive: DriveConfig
    load_encoder: LoadEncoderConfig
    limits: LimitsConfig

    @property
    def max_load_speed_deg_s(self) -> float:
        """The tighter of the command limit and the drive's speed limit, load side."""
        return min(
            self.limits.command_limit_deg_s, self.drive.max_speed_rpm * 6.0 / self.drive.gear_ratio
        )


# --- Parsing -------------------------------------------------------------------------------
class _Table:
    """Typed access to one TOML table; records which keys were used to reject unknown ones."""

    def __init__(self, data: Any, path: str) -> None:
        if not isinstance(data, dict):
            raise ConfigError(path or "rig file", "expected a table")
        self.data: dict[str, Any] = data
        self.path = path
        self.used: set[str] = set()

    def _name(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def _get(self, key: str, default: Any) -> Any:
        self.used.add(key)
        if key in self.data:
            return self.data[key]
        if default is _REQUIRED:
            raise ConfigError(self._name(key), "missing")
        return default

    def table(self, key: str, *, optional: bool = False) -> _Table | None:
        self.used.add(key)
        if key not in self.data:
            if optional:
                return None
            raise ConfigError(self._name(key), "missing table")
        return _Table(self.data[key], self._name(key))

    def req_table(self, key: str) -> _Table:
        table = self.table(key)
        assert table is not None
        return table

    def str_(self, key: str, default: Any = None, choices: tuple[str, ...] | None = None) -> str:
        value = self._get(key, _REQUIRED if default is None else default)
        if not isinstance(value, str) or not value:
            raise ConfigError(self._name(key), f"expected a non-empty string, got {value!r}")
        if choices is not None and value not in choices:
            raise ConfigError(self._name(key), f"{value!r} is not one of {', '.join(choices)}")
        return value

    def bool_(self, key: str, default: bool | None = None) -> bool:
        value = self._get(key, _REQUIRED if default is None else default)
        if not isinstance(value, bool):
            raise ConfigError(self._name(key), f"expected true or false, got {value!r}")
        return value

    def int_(
        self, key: str, default: int | None = None, *, lo: int | None = None, hi: int | None = None
    ) -> int:
        value = self._get(key, _REQUIRED if default is None else default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(self._name(key), f"expected an integer, got {value!r}")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise ConfigError(self._name(key), f"{value} out of range {lo}..{hi}")
        return value

    def opt_int(self, key: str, *, lo: int, hi: int) -> int | None:
        if key not in self.data:
            self.used.add(key)
            return None
        return self.int_(key, lo=lo, hi=hi)

    def float_(
        self,
        key: str,
        default: float | None = None,
        *,
        positive: bool = False,
        nonnegative: bool = False,
    ) -> float:
        value = self._get(key, _REQUIRED if default is None else default)
        if positive:
            return validate.positive(value, self._name(key))
        if nonnegative:
            return validate.nonnegative(value, self._name(key))
        return validate.number(value, self._name(key))

    def direction(self, key: str) -> int:
        value = self.int_(key, 1)
        if value not in (1, -1):
            raise ConfigError(self._name(key), f"must be 1 or -1, got {value}")
        return value

    def done(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            raise ConfigError(self._name(unknown[0]), "unknown key")


_REQUIRED: Any = object()
_MAX_STD_ID = 0x7FF
_MAX_EXT_ID = 0x1FFFFFFF


def _layout(t: _Table, prefix: str = "") -> FieldLayout:
    offset = t.int_(prefix + "offset", lo=0, hi=7)
    length = t.int_(prefix + "length", lo=1, hi=8 - offset)
    signed = t.bool_(prefix + "signed", False)
    byteorder = t.str_(prefix + "byteorder", "little", ("little", "big"))
    return FieldLayout(offset, length, signed, cast(Literal["little", "big"], byteorder))


def _cob_ids(t: _Table | None, node_id: int) -> CobIds:
    defaults = {
        "nmt": cia402.NMT_ID,
        "sync": cia402.SYNC_ID,
        "rpdo_command": cia402.RPDO1_BASE + node_id,
        "tpdo_status_velocity": cia402.TPDO1_BASE + node_id,
        "tpdo_position": cia402.TPDO2_BASE + node_id,
        "emcy": cia402.EMCY_BASE + node_id,
        "heartbeat": cia402.HEARTBEAT_BASE + node_id,
        "sdo_rx": cia402.SDO_RX_BASE + node_id,
        "sdo_tx": cia402.SDO_TX_BASE + node_id,
    }
    if t is None:
        return CobIds(**defaults)
    ids = {key: t.int_(key, value, lo=0, hi=_MAX_EXT_ID) for key, value in defaults.items()}
    t.done()
    values = list(ids.values())
    if len(set(values)) != len(values):
        raise ConfigError(t.path, "identifiers must be distinct")
    return CobIds(**ids)


def _raw(t: _Table) -> RawProfileConfig:
    command_id = t.int_("command_id", lo=0, hi=_MAX_EXT_ID)
    command = _layout(t, "command_")
    command_dlc = t.int_(
        "command_dlc", command.offset + command.length, lo=command.offset + command.length, hi=8
    )
    feedback_id = t.opt_int("velocity_feedback_id", lo=0, hi=_MAX_EXT_ID)
    feedback = _layout(t, "velocity_feedback_") if feedback_id is not None else None
    t.done()
    return RawProfileConfig(command_id, command_dlc, command, feedback_id, feedback)


def _drive(t: _Table) -> DriveConfig:
    node_id = t.int_("node_id", lo=1, hi=127)
    profile = t.str_("profile", "cia402", ("cia402", "raw"))
    counts_per_rev = t.int_("counts_per_rev", lo=1)
    gear_ratio = t.float_("gear_ratio", positive=True)
    direction = t.direction("direction")
    velocity_unit = t.str_("velocity_unit", choices=tuple(VELOCITY_UNITS))
    max_speed_rpm = t.float_("max_speed_rpm", positive=True)
    heartbeat_period_ms = t.int_("heartbeat_period_ms", 100, lo=0, hi=65535)
    heartbeat_timeout_ms = t.float_(
        "heartbeat_timeout_ms", 2.5 * heartbeat_period_ms, nonnegative=True
    )
    if heartbeat_period_ms and heartbeat_timeout_ms <= heartbeat_period_ms:
        raise ConfigError(
            f"{t.path}.heartbeat_timeout_ms",
            f"must exceed heartbeat_period_ms ({heartbeat_timeout_ms} <= {heartbeat_period_ms})",
        )
    enable_timeout_s = t.float_("enable_timeout_s", 1.0, positive=True)
    send_sync = t.bool_("send_sync", True)
    cob_ids = _cob_ids(t.table("cob_ids", optional=True), node_id)
    raw_table = t.table("raw", optional=True)
    raw = _raw(raw_table) if raw_table is not None else None
    if profile == "raw" and raw is None:
        raise ConfigError(f"{t.path}.raw", "missing table (required by profile = 'raw')")
    if profile == "cia402" and not send_sync:
        raise ConfigError(f"{t.path}.send_sync", "the cia402 profile needs SYNC for its TPDOs")
    t.done()
    drive = DriveConfig(
        node_id,
        cast(Literal["cia402", "raw"], profile),
        counts_per_rev,
        gear_ratio,
        direction,
        velocity_unit,
        max_speed_rpm,
        heartbeat_period_ms,
        heartbeat_timeout_ms,
        enable_timeout_s,
        send_sync,
        cob_ids,
        raw,
    )
    top_units = max_speed_rpm * 6.0 * drive.velocity_units_per_motor_deg_s
    if top_units > 2**31 - 1:
        raise ConfigError(
            f"{t.path}.max_speed_rpm",
            f"{max_speed_rpm} rpm overflows the i32 velocity in {velocity_unit}",
        )
    return drive


def _load_encoder(t: _Table) -> LoadEncoderConfig:
    frame_id = t.int_("frame_id", lo=0, hi=_MAX_EXT_ID)
    layout = _layout(t)
    counts_per_rev = t.int_("counts_per_rev", lo=2)
    single_turn = t.bool_("single_turn", True)
    direction = t.direction("direction")
    t.done()
    if single_turn and counts_per_rev > 1 << (8 * layout.length - (1 if layout.signed else 0)):
        raise ConfigError(
            f"{t.path}.counts_per_rev", f"{counts_per_rev} does not fit in {layout.length} bytes"
        )
    return LoadEncoderConfig(frame_id, layout, counts_per_rev, single_turn, direction)


def _limits(t: _Table | None) -> LimitsConfig:
    if t is None:
        raise ConfigError("limits", "missing table")
    command_limit_deg_s = t.float_("command_limit_deg_s", positive=True)
    timeout_ticks = t.int_("feedback_timeout_ticks", 5, lo=1, hi=1000)
    wait_s = t.float_("feedback_wait_s", 0.0005, nonnegative=True)
    factor = t.float_("max_encoder_speed_factor", 3.0, positive=True)
    t.done()
    return LimitsConfig(command_limit_deg_s, timeout_ticks, wait_s, factor)


def parse_rig_file(text: str) -> RigFile:
    """Parse rig-file TOML text; ConfigError (a ValueError) naming the field on any problem."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError("rig file", f"invalid TOML: {exc}") from exc
    top = _Table(data, "")
    name = top.str_("name", "rig")
    bus_t = top.req_table("bus")
    bus = BusConfig(
        bus_t.str_("interface"),
        str(bus_t.str_("channel")),
        bus_t.int_("bitrate", 1_000_000, lo=10_000, hi=8_000_000),
    )
    bus_t.done()
    drive = _drive(top.req_table("drive"))
    encoder = _load_encoder(top.req_table("load_encoder"))
    limits = _limits(top.table("limits", optional=True))
    top.done()
    ids = [encoder.frame_id]
    if drive.profile == "cia402":
        c = drive.cob_ids
        ids += [c.tpdo_status_velocity, c.tpdo_position, c.heartbeat, c.emcy, c.sdo_tx]
    elif drive.raw is not None and drive.raw.velocity_feedback_id is not None:
        ids.append(drive.raw.velocity_feedback_id)
    if len(set(ids)) != len(ids):
        raise ConfigError("load_encoder.frame_id", "collides with a drive feedback identifier")
    return RigFile(name, bus, drive, encoder, limits)


def load_rig_file(path: str | Path) -> RigFile:
    """Read and parse a rig file."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError("rig file", f"{path}: {exc}") from exc
    return parse_rig_file(text)
