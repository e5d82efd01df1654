"""The Zenoh contract: every key expression and message type, in one place.

Encoding: MessagePack (msgspec). Every message is a map with a `v` field (protocol version,
currently 2); a message of another version is rejected, never guessed at. Tagged unions carry
a `type` field. Units are in the field names. See docs/protocol.md for the full description.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import msgspec

from controller.core.config import LoopConfig
from controller.core.samples import STATE_COLUMNS
from controller.core.timing import LoopTiming
from controller.core.trajectory import Trajectory
from controller.core.validate import split_msgspec_error
from controller.core.verdict import Verdict
from controller.gate.knowledge import KnowledgeRecord
from controller.ident.spec import IdentifySpec

#: 2: the gate's verdict travels as one nested `Verdict` (ConfigReply, Status, HistoryEntry),
#: where version 1 carried its kind, margins and knowledge version side by side.
PROTOCOL_VERSION = 2
KEY_PREFIX = "dobtune"


def _rig_key(what: str) -> Callable[[str], str]:
    """The builder of `dobtune/<rig>/<what>` for one `what`."""

    def key(rig: str) -> str:
        return f"{KEY_PREFIX}/{rig}/{what}"

    return key


#: The keys of one rig, `dobtune/<rig>/<what>`, a builder each (`key_status(rig)`). The gate
#: uses the plant knowledge; the history is the applied configurations; the lease the operator's.
key_state = _rig_key("state")  # publisher: batches of loop samples (StateBatch)
# queryable (the loop's process): `from=<seq>;to=<seq>` -> StateReplay, the last seconds of
# the state stream again (a recorder's lost samples; docs/protocol.md)
key_state_replay = _rig_key("state/replay")
REPLAY_MAX_SAMPLES = 5000  # samples one replay query may ask for (5 s at 1 kHz)
key_status = _rig_key("status")  # publisher, a few Hz: Status
key_config = _rig_key("config")  # queryable: ConfigRequest -> ConfigReply
key_command = _rig_key("cmd")  # queryable: Command -> CommandReply
key_estop = _rig_key("estop")  # subscriber: any put is an emergency stop, whatever its payload
key_identify = _rig_key("identify")  # queryable: any payload (or none) -> IdentifyStatus
key_knowledge = _rig_key("knowledge")  # queryable: KnowledgeRequest -> KnowledgeReply
key_alive = _rig_key("alive")  # liveliness token of a running controller (`dobtune ctl rigs`)
key_history = _rig_key("history")  # queryable: HistoryRequest (or empty) -> HistoryReply
key_lease = _rig_key("lease")  # queryable: LeaseRequest -> LeaseReply
key_drift = _rig_key("drift")  # publisher (the watch), each window: DriftState
key_drift_alarm = _rig_key("drift/alarm")  # publisher (the watch): DriftAlarm, as they happen
# Publisher (the watch): PredictionCheck after each Apply (predicted, then measured); queryable:
# every version's check (`dobtune ctl prediction`).
key_prediction = _rig_key("prediction")


#: With authentication (`dobtune controller --auth`), requests go to per-user scopes:
#: `dobtune/<rig>/@user/<name>/<what>`, which the access control lets only <name> reach
#: (`@user` is a verbatim chunk: `*` and `**` never match it). The controller knows who sent a
#: request from the key it arrived on: zenoh gives no authenticated identity on a query.
USER_CHUNK = "@user"
USER_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def check_user_name(name: str, what: str = "user") -> str:
    if not isinstance(name, str) or not USER_NAME.fullmatch(name):
        raise ValueError(
            f"{what} {name!r}: 1-64 letters, digits, '_', '.', '-', starting with a letter or digit"
        )
    return name


def _split_rig_key(key: str) -> tuple[str, str]:
    prefix, rig, rest = [*key.split("/", 2), "", ""][:3]
    if prefix != KEY_PREFIX or not rig or not rest:
        raise ValueError(f"{key!r} is not a {KEY_PREFIX}/<rig>/<what> key")
    return rig, rest


def rig_of_key(key: object) -> str:
    """The `<rig>` chunk of a `dobtune/<rig>/<what>` key (a key expression or its string)."""
    return _split_rig_key(str(key))[0]


def user_key(key: str, user: str) -> str:
    """`dobtune/<rig>/<what>` as sent by `user`: `dobtune/<rig>/@user/<user>/<what>`."""
    rig, rest = _split_rig_key(key)
    return f"{KEY_PREFIX}/{rig}/{USER_CHUNK}/{check_user_name(user)}/{rest}"


def any_user_key(key: str) -> str:
    """The key expression a controller declares to serve `key` for every user."""
    rig, rest = _split_rig_key(key)
    return f"{KEY_PREFIX}/{rig}/{USER_CHUNK}/*/{rest}"


def user_of_key(key_expr: object) -> str | None:
    """The user a request key names (`str(query.key_expr)`), None if it names no valid user."""
    parts = str(key_expr).split("/")
    if len(parts) < 5 or parts[0] != KEY_PREFIX or parts[2] != USER_CHUNK:
        return None
    return parts[3] if USER_NAME.fullmatch(parts[3]) else None


def check_rig_name(rig: str) -> str:
    if not rig or any(c in rig for c in "/*$?#") or not rig.isprintable():
        raise ValueError(f"rig_name: {rig!r} is not a valid key chunk (no / * $ ? #, not empty)")
    return rig


class _Msg(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    v: int = PROTOCOL_VERSION


# -- state stream -----------------------------------------------------------------------------


class StateBatch(_Msg, frozen=True, kw_only=True):
    """Consecutive loop samples; sample i has sequence number seq0 + i (gaps are detectable).

    Columns are equal-length lists. Angles in load-side degrees, speeds in load-side deg/s.
    """

    rig: str
    seq0: int
    rate_hz: float
    config_version: int
    t_s: list[float]
    ref_deg: list[float]
    pos_deg: list[float]
    speed_deg_s: list[float]
    speed_ref_deg_s: list[float]
    command_deg_s: list[float]
    d_hat_deg_s: list[float]
    error_deg: list[float]
    epoch_s: float = 0.0  # UNIX time of t_s = 0 (sample i happened at epoch_s + t_s[i])
    mode: str = ""  # the mode during every sample of this batch ("" from older senders)


#: The per-sample columns of StateBatch, in order (one list each): `STATE_COLUMNS`, defined
#: in controller.core.samples (the runtime stores the same columns).


def state_batch(
    *,
    rig: str,
    seq0: int,
    rate_hz: float,
    config_version: int,
    columns: Sequence[list[float]],
    epoch_s: float,
    mode: str,
) -> StateBatch:
    """A StateBatch from the sample columns in STATE_COLUMNS order."""
    named: dict[str, Any] = dict(zip(STATE_COLUMNS, columns, strict=True))
    return StateBatch(
        rig=rig,
        seq0=seq0,
        rate_hz=rate_hz,
        config_version=config_version,
        epoch_s=epoch_s,
        mode=mode,
        **named,
    )


class ReplayMissing(_Msg, frozen=True, kw_only=True):
    """Samples from_seq..to_seq (inclusive) a replay could not give, and why: `too_old` (older
    than the window the publisher keeps), `never_published` (the loop dropped them: its ring to
    the publisher was full), `not_yet` (newer than the last batch published), `refused`."""

    from_seq: int
    to_seq: int
    reason: str
    text: str = ""


class StateReplay(_Msg, frozen=True, kw_only=True):
    """The reply to `key_state_replay`: the batches held within the asked range (cut to it, in
    seq order) and each part of the range not given, with why."""

    batches: list[StateBatch] = []
    missing: list[ReplayMissing] = []
    oldest_seq: int = -1  # the oldest sample the publisher still holds (-1: none)
    newest_seq: int = -1


# -- status -----------------------------------------------------------------------------------


#: Loop timing over the last status interval (the runtime's own type, one definition).
Timing = LoopTiming


class Status(_Msg, frozen=True, kw_only=True):
    rig: str
    plant: str  # "sim" | "can"
    mode: str  # "running" | "stopped" | "estop" | "fault"
    t_s: float
    seq: int  # sequence number of the latest sample
    trajectory: Trajectory
    config_version: int
    config: LoopConfig
    timing: Timing
    faults: list[str]
    operator: str = ""
    estop_seq: int = -1  # first tick of the latest e-stop (each e-stop, also while latched)
    notes: list[str] = []  # non-fault information (e.g. real-time priority refused)
    knowledge_version: int = 0  # the plant knowledge the controller judges candidates on now
    knowledge: str = ""  # its one-line description (version, source, band)
    # The gate's verdict on the running configuration (its own knowledge_version says what it
    # was judged on: the knowledge above once re-judged after an adoption).
    verdict: Verdict | None = None
    watchdog: str = ""  # the latest watchdog trip and what was done (rollback or fault)
    audit_head: str = ""  # "<seq>:<sha256>" of the newest audit record (anchors the log)
    auth: bool = False  # requests are authenticated (per-user key scopes, access control)
    rollbacks: int = 0  # watchdog rollbacks since the controller started
    # What Start runs (`trajectory` is what the loop follows now: a hold while stopped).
    run_trajectory: Trajectory | None = None


# -- config queryable -------------------------------------------------------------------------


class ConfigRequest(_Msg, frozen=True, kw_only=True):
    """candidate None: just return the active configuration. A candidate with the verdict
    `caution` is applied only with `confirm` true; with `expect_version` only if that is still
    the active version (compare-and-set); `lease`: the operator lease token (see LeaseRequest)."""

    candidate: LoopConfig | None = None
    client: str = ""
    confirm: bool = False
    expect_version: int | None = None
    lease: str = ""


class ConfigReply(_Msg, frozen=True, kw_only=True):
    accepted: bool
    version: int  # the active version after this request
    config: LoopConfig  # the active configuration after this request
    reasons: list[str] = []  # why not: the gate's reasons, or one "<field>: <why>"
    field: str = ""  # for a malformed request: the offending field ("payload", "candidate.x")
    # The gate's verdict on the candidate (on the active configuration for a GET); None when
    # the request was refused before the gate ran (malformed, stale expect_version...).
    verdict: Verdict | None = None


# -- history ------------------------------------------------------------------------------------


class HistoryRequest(_Msg, frozen=True, kw_only=True):
    last: int = 50  # how many of the newest entries (1..1000)


class HistoryEntry(msgspec.Struct, frozen=True, kw_only=True):
    version: int
    time_s: float  # UNIX time it was applied
    client: str  # who: the authenticated user, "startup (...)" or "watchdog rollback: ..."
    config: LoopConfig
    # The gate's verdict then (None: not logged; a line of an older version has no reasons).
    verdict: Verdict | None = None


class HistoryReply(_Msg, frozen=True, kw_only=True):
    ok: bool
    entries: list[HistoryEntry] = []  # oldest first
    message: str = ""
    field: str = ""


# -- the operator lease -------------------------------------------------------------------------

#: LeaseRequest.action values.
LEASE_ACTIONS: tuple[str, ...] = ("status", "acquire", "renew", "release", "takeover")


class LeaseRequest(_Msg, frozen=True, kw_only=True):
    """`acquire` (nobody holds the lease), `takeover` (whoever holds it), `renew` and `release`
    (with the `token` acquire gave), `status`. Only operators hold the lease; the token is
    bound to the user the request came from."""

    action: str = "status"
    token: str = ""
    duration_s: float = 60.0
    client: str = ""


class LeaseReply(_Msg, frozen=True, kw_only=True):
    ok: bool
    holder: str = ""  # who holds the lease after this request ("" nobody)
    expires_in_s: float = 0.0
    token: str = ""  # granted or renewed: the token to send with every change
    message: str = ""
    field: str = ""


# -- plant knowledge ----------------------------------------------------------------------------


class KnowledgeRequest(_Msg, frozen=True, kw_only=True):
    """Neither set: return the plant knowledge. `record`: adopt it (measured responses, the
    model and its bound; its version is ignored: the controller numbers versions).
    `adopt_run`: adopt the measured responses of this controller's identification run."""

    record: KnowledgeRecord | None = None
    adopt_run: int | None = None
    client: str = ""
    lease: str = ""


class KnowledgeReply(_Msg, frozen=True, kw_only=True):
    ok: bool
    record: KnowledgeRecord  # the plant knowledge after this request
    message: str = ""
    field: str = ""
    #: The rig's twin of `record`, built by the controller when the knowledge is adopted (off
    #: the tick): `controller.twin.model.RigTwin` as JSON (`controller.twin.model.decode`);
    #: "" when nothing was measured or it could not be built (`twin_note` says why).
    twin: str = ""
    twin_note: str = ""


# -- commands ---------------------------------------------------------------------------------


class SetTrajectory(
    msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="trajectory"
):
    trajectory: Trajectory


class Start(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="start"):
    pass


class Stop(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="stop"):
    """Controlled stop: hold the present position."""


class EStop(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="estop"):
    """Speed command 0 from the next tick, drive disabled, until ResetFault + Start."""


class ResetFault(
    msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="reset"
):
    """Leave e-stop or fault. `estop_seq`: the latest e-stop its sender saw (Status.estop_seq,
    -1 if none): a reset acknowledges only that e-stop and is refused when a newer one exists
    (an e-stop pressed in another session a moment earlier). Required: a reset without it (an
    older client) is refused, naming `body.estop_seq`."""

    estop_seq: int | None = None


class IdentifyStart(
    msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="identify_start"
):
    """Run an identification inside the loop (mode must be running or stopped). The spec is
    `controller.ident.spec.IdentifySpec` itself (validated on decode: errors name
    `body.spec.<field>`, unknown fields included)."""

    spec: IdentifySpec = msgspec.field(default_factory=IdentifySpec)


class SimFault(
    msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="sim_fault"
):
    """Simulated rig only: replace the injected faults (all defaults: clear them), to rehearse
    and test the watchdog. `plant_gain` scales what the drive does, `extra_backlash_deg`
    loosens the belt, `resonance_hz` (> 0) adds a mode. Refused on a CAN rig."""

    plant_gain: float = 1.0
    extra_backlash_deg: float = 0.0
    resonance_hz: float = 0.0
    resonance_damping: float = 0.02
    resonance_mass_fraction: float = 0.2


class SimDrift(
    msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="sim_drift"
):
    """Simulated rig only, for tests and the demo: the plant drifts from the next tick on,
    each factor on the rig's parameters as it started (all 1: back to them), its state kept
    (`SimRig.set_params`). Drive gain and adding a resonance are `SimFault`'s;
    `resonance_factor` moves the extra mode the last `SimFault` added (its frequency then).
    Refused on a CAN rig; an operator's command (the lease), as every command but the e-stop."""

    belt_stiffness_factor: float = 1.0
    load_inertia_factor: float = 1.0
    motor_friction_factor: float = 1.0
    resonance_factor: float = 1.0


class IdentifyAbort(
    msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag="identify_abort"
):
    """Abort the running identification: the loop holds the present position."""


CommandBody = (
    SetTrajectory | Start | Stop | EStop | ResetFault | IdentifyStart | IdentifyAbort | SimFault
    | SimDrift
)


class Command(_Msg, frozen=True, kw_only=True):
    body: CommandBody
    client: str = ""
    lease: str = ""  # the operator lease token (every command but estop needs the lease)


class CommandReply(_Msg, frozen=True, kw_only=True):
    ok: bool
    message: str = ""
    mode: str = ""  # the mode after the command
    field: str = ""  # for a malformed request: the offending field
    seq: int = -1  # first tick (sequence number) at which the command was in effect
    received_seq: int = -1  # the last completed tick when the command arrived


# -- identification -----------------------------------------------------------------------------


class PositionResponse(msgspec.Struct, frozen=True, kw_only=True):
    """The response measured at one position (continuous equivalent, u -> w).

    While the run goes on, the frequencies measured so far (points_done of points_total;
    complete False until the position is finished). The std lists are per point, on the same
    grid as freq_hz; NaN where unknown (one period), empty from older senders."""

    index: int
    center_deg: float
    complete: bool
    points_done: int
    points_total: int
    freq_hz: list[float] = []
    mag_db: list[float] = []
    phase_deg: list[float] = []
    coherence: list[float] = []
    mag_std_db: list[float] = []  # standard deviation of mag_db (dB)
    phase_std_deg: list[float] = []  # standard deviation of phase_deg (deg)


#: Values of IdentifyStatus.state.
IDENTIFY_STATES: tuple[str, ...] = ("idle", "running", "analysing", "done", "aborted")


class IdentifyRun(msgspec.Struct, frozen=True, kw_only=True):
    """What a run executes, so a recording of the state stream can be analysed again
    (`dobtune identify --from`): the plan is `plan_program(spec, config, start_deg)`; tick i
    of it is state sample `start_seq + i`."""

    spec: IdentifySpec
    config: LoopConfig  # the configuration the plan was made with
    start_deg: float  # the position the plan was made from
    start_seq: int  # sequence number of the program's first tick
    ticks_planned: int
    ticks_done: int  # ticks executed so far (final once the state is not running)


class IdentifyStatus(_Msg, frozen=True, kw_only=True):
    """The latest identification run (run_id counts runs since the controller started)."""

    rig: str
    state: str  # idle | running | analysing | done | aborted
    run_id: int = 0
    progress: float = 0.0  # 0..1
    text: str = ""
    abort_reason: str = ""
    # running/analysing: the segments finished so far; done: all; aborted: the partial data
    positions: list[PositionResponse] = []
    natural_freq_hz: float | None = None  # fit of Mn Pn (done only)
    zeta: float | None = None
    agreement_freq_hz: float | None = None
    recommended_cutoff_hz: dict[str, float | None] = {}
    summary_json: str = ""  # the summary.json `dobtune identify` writes (done/aborted)
    run: IdentifyRun | None = None  # what the run executes (None: idle, older senders)


# -- drift (the watch: controller/process/watch.py) ----------------------------------------------


class DriftPart(msgspec.Struct, frozen=True, kw_only=True):
    """One part of the plant as the latest window estimates it: `value` a factor on the
    twin's (unit "x"; the motor friction in "N m" when the twin has none) +- `std`; whether
    the window tells it; its allowed range (from the knowledge's bound); `state`: ok, note,
    outside, alarm or not told; `since_epoch_s` when it first left its range."""

    name: str
    value: float
    std: float
    unit: str = "x"
    told: bool
    state: str
    low: float
    high: float
    since_epoch_s: float | None = None


class DriftState(_Msg, frozen=True, kw_only=True):
    """The watch's state after each window: the parts, the delay, the plant's residual
    (measured rate against the twin's answer to the same commands: with the twin as it is and
    with the fitted parts, rms deg/s), the loop's residual (measured error against the one
    the twin predicts for the configuration, rms deg), what it is judged on, the parts in
    alarm, and what each part's line says."""

    rig: str
    epoch_s: float  # UNIX time of the window's end
    window_s: float
    config_version: int
    model: str  # what the watch compares with (the twin of knowledge vN, or the sim's model)
    parts: list[DriftPart]
    delay_ticks: int
    twin_delay_ticks: int
    plant_residual_rms_deg_s: float
    fitted_residual_rms_deg_s: float
    loop_measured_rms_deg: float
    loop_predicted_rms_deg: float
    loop_residual_rms_deg: float
    alarms: list[str] = []
    lines: list[str] = []
    fit_s: float = 0.0  # the window's fit took this long (the watch's own process)
    windows: int = 0  # windows judged since the watch started


class DriftAlarm(_Msg, frozen=True, kw_only=True):
    """A part of the plant left its allowed range (`cleared`: it came back): which, by how
    much, since when, what to do, and the gate's verdict on the active configuration with the
    drifted estimate as the plant's evidence."""

    rig: str
    seq: int  # alarms of this watch, counted from 1
    epoch_s: float
    part: str
    value: float
    std: float
    unit: str = "x"
    low: float
    high: float
    since_epoch_s: float
    text: str
    action: str
    gate_verdict: str = ""  # accept | caution | reject ("" not judged)
    gate_reasons: list[str] = []
    cleared: bool = False


class PredictionFigure(msgspec.Struct, frozen=True, kw_only=True):
    """One figure of a prediction check: the twin's value and the rig's (None: not measured
    yet), the relative tolerance it is judged with (0: shown, not judged)."""

    name: str  # rmse_deg | peak_error_deg | command_noise_deg_s | error_rms_deg <lo>-<hi> Hz
    predicted: float
    measured: float | None = None
    tolerance_rel: float = 0.0


class PredictionCheck(_Msg, frozen=True, kw_only=True):
    """Predicted, then measured, for one applied configuration: what the twin predicted for
    the running trajectory, what the rig did over the window that followed, and whether the
    prediction held. `state`: "predicted" (the rig's window is not complete yet), "held",
    "failed", "failed badly" (the rollback to `rollback_to`, the last version whose prediction
    held, is offered), or "not judged" (`meaning` says why: the run was interrupted...)."""

    rig: str
    config_version: int
    epoch_s: float  # UNIX time of the prediction, then of the verdict
    trajectory: Trajectory
    model: str  # what predicted: the rig's twin of knowledge vN, or the built-in model
    window_s: float  # the rig's window (whole periods of a periodic trajectory)
    settle_s: float  # left out after the configuration became active
    state: str
    figures: list[PredictionFigure] = []
    bands: list[PredictionFigure] = []  # the error's spectrum: RMS per band
    meaning: str = ""
    rollback_to: int | None = None
    measured_from_epoch_s: float | None = None  # the rig's window, UNIX time of its start


# -- encoding ---------------------------------------------------------------------------------

_encoder = msgspec.msgpack.Encoder()
Message = _Msg
"""The base of every versioned wire message (what `decode` decodes)."""
M = TypeVar("M", bound=_Msg)


class ProtocolError(ValueError):
    """A payload that cannot be accepted; the message starts with the field ("field: why")."""

    def __init__(self, message: str, field: str | None = None) -> None:
        if field is None:
            field = message.split(": ", 1)[0] if ": " in message else "payload"
        super().__init__(message)
        self.field = field


def _validation_error(text: str) -> ProtocolError:
    """Turn a msgspec validation message into "path.to.field: why"."""
    field, why = split_msgspec_error(text)
    return ProtocolError(f"{field}: {why}", field)


class _Versioned(msgspec.Struct):
    v: Any = None


_version_decoder = msgspec.msgpack.Decoder(_Versioned)
_decoders: dict[type, msgspec.msgpack.Decoder[Any]] = {}
# Decoders are built once per type, under a lock: two Zenoh callback threads building the first
# decoder of one type at once crashed msgspec (a segfault seen in test_flood_isolation and in
# bench_watch; drift34).
_decoders_lock = threading.Lock()


def encoding(kind: type[msgspec.Struct] | str) -> str:
    """The Zenoh encoding every put and reply carries: `application/msgpack;<MessageName>`, so
    that generic Zenoh tools and bridges can tell what they receive."""
    name = kind if isinstance(kind, str) else kind.__name__
    return f"application/msgpack;{name}"


def encode(msg: msgspec.Struct) -> bytes:
    return _encoder.encode(msg)


def decode(data: bytes | bytearray | memoryview, kind: type[M]) -> M:
    """Decode and validate a message; ProtocolError names the offending field."""
    raw = bytes(data)
    try:
        head = _version_decoder.decode(raw)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise ProtocolError(f"payload: not a MessagePack map ({exc})", "payload") from exc
    except RecursionError as exc:
        raise ProtocolError("payload: nested too deeply", "payload") from exc
    except UnicodeDecodeError as exc:
        raise ProtocolError("payload: a string is not valid UTF-8", "payload") from exc
    if head.v != PROTOCOL_VERSION or isinstance(head.v, bool):
        shown = repr(head.v)
        shown = shown if len(shown) <= 40 else shown[:37] + "..."
        raise ProtocolError(
            f"v: unsupported protocol version {shown}; this side speaks {PROTOCOL_VERSION} "
            "(the other side runs another dobtune version: run the same on both)",
            "v",
        )
    dec = _decoders.get(kind)
    if dec is None:
        with _decoders_lock:
            dec = _decoders.get(kind)
            if dec is None:
                dec = _decoders[kind] = msgspec.msgpack.Decoder(kind)
    try:
        return dec.decode(raw)  # type: ignore[no-any-return]
    except msgspec.ValidationError as exc:
        raise _validation_error(str(exc)) from exc
    except msgspec.DecodeError as exc:
        raise ProtocolError(f"payload: {exc}", "payload") from exc
    except RecursionError as exc:
        raise ProtocolError("payload: nested too deeply", "payload") from exc
    except UnicodeDecodeError as exc:
        # msgspec reports no path for it: name the payload, never the exception.
        raise ProtocolError("payload: a string is not valid UTF-8", "payload") from exc
