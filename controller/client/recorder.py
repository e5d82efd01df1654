"""Recording a running controller into an MCAP file: a library object that returns a result.

One message per loop tick on `/state`, every Status on `/status`, each configuration version
on `/config`, and events (lost samples, mode changes, watchdog trips, identification runs with
what they executed, for `dobtune identify --from`) on `/events`. `dobtune record` and the
dashboard's Recordings tab are front ends over `Recorder`.

Complete under load (issue 33 item 4): a jump in the stream's sequence numbers is asked for
again from the controller's replay (`dobtune/<rig>/state/replay`, the last 30 s of the
published stream, `controller.process.replay`) before the batch after it is written, so the
file stays in seq order; what the replay cannot give is recorded as a `gap` event naming the
range and why (`too_old`, `never_published`: the loop dropped it, `refused`, `not_received`).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

from controller import protocol as proto
from controller.client.controller_client import (
    ClientOptions,
    ControllerUnavailable,
    open_client_session,
)

__all__ = ["RecordOptions", "RecordResult", "Recorder", "StateRecovery", "identify_event"]

#: How often the recorder asks the controller for its identification status.
IDENTIFY_POLL_S = 0.5


@dataclass(frozen=True)
class RecordOptions:
    connect: tuple[str, ...]
    out: Path
    rig_name: str = "demo"
    duration_s: float | None = None
    """None: until `stop` is set."""
    auth: Path | None = None
    user: str = ""
    timeout_s: float = 10.0
    """Give up (ControllerUnavailable) when no state arrived within this long."""
    recover: bool = True
    """Ask the controller's replay for samples missing from the stream."""
    drop_batch: Callable[[proto.StateBatch], bool] | None = None
    """Test hook: a received batch for which it returns True is treated as not received."""


@dataclass(frozen=True)
class RecordResult:
    path: Path
    samples: int
    lost: int
    """Samples missing by sequence number and not recovered (recorded as `gap` events with
    their reason, not an error)."""
    undecodable: int
    duration_s: float
    size_bytes: int
    recovered: int = 0
    """Samples missing from the stream and had again from the controller's replay."""
    missing: tuple[tuple[int, int, str], ...] = field(default=())
    """Each range of samples not had: (from_seq, to_seq, reason)."""

    def summary(self) -> str:
        bad = f", {self.undecodable} undecodable" if self.undecodable else ""
        text = (f"recorded {self.samples} samples ({self.lost} lost{bad}; {self.recovered} "
                f"recovered from the controller's replay) in {self.duration_s:.1f} s to "
                f"{self.path} ({self.size_bytes / 1e6:.2f} MB)")
        if self.missing:
            shown = [f"{a}-{z} ({why})" for a, z, why in self.missing[:5]]
            more = f" and {len(self.missing) - 5} more" if len(self.missing) > 5 else ""
            text += "; missing seq " + ", ".join(shown) + more
        return text


class StateRecovery:
    """Fills a jump in the state stream from the controller's replay into the MCAP writer."""

    def __init__(self, session: Any, key: str, rig: str, timeout_s: float = 2.0) -> None:
        self.session = session
        self.key = key
        self.rig = rig
        self.timeout_s = timeout_s
        self.recovered = 0

    def _ask(self, lo: int, hi: int) -> proto.StateReplay:
        replies = list(self.session.get(f"{self.key}?from={lo};to={hi}",
                                        timeout=self.timeout_s))
        for r in replies:
            if r.ok is not None:
                return proto.decode(r.ok.payload.to_bytes(), proto.StateReplay)
        errs = [r.err.payload.to_bytes().decode(errors="replace") for r in replies
                if r.err is not None]
        raise ValueError("; ".join(errs) or f"no reply within {self.timeout_s:g} s")

    def fill(self, rec: Any, lo: int, hi: int, t_s: float) -> None:
        """Write samples lo..hi to `rec` (an mcap_io.Recorder whose next_seq is lo), each part
        the replay cannot give as a gap with its reason."""
        nxt = lo
        while nxt <= hi:
            z = min(hi, nxt + proto.REPLAY_MAX_SAMPLES - 1)
            try:
                got = self._ask(nxt, z)
            except Exception as exc:  # recorded with the range: the recording goes on
                rec.gap(nxt, hi, "refused", t_s, text=f"the replay did not answer: {exc}")
                return
            parts: list[tuple[int, Any]] = [(b.seq0, b) for b in got.batches]
            parts += [(m.from_seq, m) for m in got.missing]
            for seq0, part in sorted(parts, key=lambda p: p[0]):
                if rec.next_seq is None or seq0 < rec.next_seq or seq0 > z:
                    continue  # not asked for (trust no reply)
                if isinstance(part, proto.ReplayMissing):
                    rec.gap(seq0, min(part.to_seq, z), part.reason, t_s, text=part.text)
                elif part.rig == self.rig:
                    n = min(len(part.t_s), z - seq0 + 1)
                    rec.state(part)
                    self.recovered += n
            if rec.next_seq is not None and rec.next_seq <= z:  # what the reply left out
                rec.gap(rec.next_seq, z, "refused", t_s, text="the replay left it out")
            nxt = z + 1


class _IdentifyWatch:
    """Records an `identify` event whenever the controller's identification run changes state
    (run id, state): the run's spec, configuration, start position and first tick
    (`IdentifyRun`), which `dobtune identify --from` needs to analyse the run again."""

    def __init__(self) -> None:
        self.last: tuple[int, str] | None = None
        self.failed = False

    def poll(self, session: Any, key: str, rec: Any) -> None:
        try:
            replies = list(session.get(key, timeout=1.0))
            ok = [r.ok for r in replies if r.ok is not None]
            if not ok:
                raise ValueError("no reply")
            st = proto.decode(ok[0].payload.to_bytes(), proto.IdentifyStatus)
        except Exception as exc:  # said once in the recording, the recording goes on
            if not self.failed:
                self.failed = True
                rec.event("note", f"identification status unavailable: {exc}")
            return
        now = (st.run_id, st.state)
        if st.run is None or now == self.last:
            return
        self.last = now
        identify_event(rec, st)


class _TwinWatch:
    """Records a `twin` event (the rig's twin the controller built from its plant knowledge,
    `controller.twin.model.RigTwin` as plain data, or why there is none) for the knowledge the
    controller holds when the recording starts and after each change of it."""

    def __init__(self, recorded: list[int]) -> None:
        self.version: int | None = None
        self.failed = False
        self.recorded = recorded
        """The knowledge versions whose twin event was written."""

    def poll(self, session: Any, key: str, rec: Any, version: int | None) -> None:
        if version is None or version == self.version:
            return
        try:
            replies = list(session.get(key, timeout=2.0))
            ok = [r.ok for r in replies if r.ok is not None]
            if not ok:
                raise ValueError("no reply")
            got = proto.decode(ok[0].payload.to_bytes(), proto.KnowledgeReply)
        except Exception as exc:  # said once in the recording, the recording goes on
            if not self.failed:
                self.failed = True
                rec.event("note", f"plant knowledge unavailable (no twin recorded): {exc}")
            return
        if not got.twin and got.twin_note.startswith("no twin yet"):
            return  # being built: asked again at the next poll
        self.version = version
        v = got.record.version
        if got.twin:
            rec.event("twin", f"the rig's twin of plant knowledge v{v}", knowledge_version=v,
                      twin=json.loads(got.twin))
        else:
            rec.event("twin", got.twin_note, knowledge_version=v, twin=None)
        self.recorded.append(v)


def identify_event(rec: Any, st: Any) -> None:
    """Record the `identify` event of an IdentifyStatus `st` (which carries `run`) into the
    MCAP writer `rec`: what `dobtune identify --from` reads."""
    rec.event(
        "identify",
        f"identification {st.run_id}: {st.state}"
        + (f" ({st.abort_reason})" if st.abort_reason else ""),
        run_id=st.run_id,
        state=st.state,
        abort_reason=st.abort_reason,
        run=msgspec.to_builtins(st.run),
    )


class Recorder:
    """Records one rig until the duration is over or `stop` is set (`run`)."""

    def __init__(self, opts: RecordOptions) -> None:
        """ValueError naming the option when `opts` cannot work."""
        if opts.duration_s is not None and not (0.0 < opts.duration_s <= 86_400.0):
            raise ValueError(f"--duration: {opts.duration_s} not in (0, 86400] s")
        try:
            proto.check_rig_name(opts.rig_name)
        except ValueError as exc:
            raise ValueError(f"--rig-name: {exc}") from exc
        if not Path(opts.out).parent.is_dir():
            raise ValueError(f"--out: directory {Path(opts.out).parent} does not exist")
        self.opts = opts
        #: The plant knowledge versions whose twin the recording holds (a `twin` event each).
        self.twins_recorded: list[int] = []

    def run(self, stop: threading.Event | None = None) -> RecordResult:
        """Record; ControllerUnavailable when there is no connection or no state arrived within
        `timeout_s` (the file is then written, empty)."""
        import zenoh

        from controller.recording.mcap_io import Recorder as McapWriter

        o = self.opts
        stop = stop if stop is not None else threading.Event()
        client = ClientOptions(connect=tuple(o.connect), rig_name=o.rig_name, auth=o.auth,
                               user=o.user, connect_timeout_s=o.timeout_s, client_name="record")
        try:
            session = open_client_session(client)
        except ControllerUnavailable:
            raise
        except Exception as exc:  # zenoh.ZError, AuthError: said plainly
            raise ControllerUnavailable(
                f"no connection to {', '.join(o.connect)}: {exc}") from exc
        t0 = time.monotonic()
        last_status = ""
        bad = 0
        identify_key = proto.key_identify(o.rig_name)
        if o.auth is not None:
            identify_key = proto.user_key(identify_key, o.user)
        identify = _IdentifyWatch()
        twin = _TwinWatch(self.twins_recorded)
        twin_key = proto.key_knowledge(o.rig_name)
        replay_key = proto.key_state_replay(o.rig_name)
        if o.auth is not None:
            twin_key = proto.user_key(twin_key, o.user)
            replay_key = proto.user_key(replay_key, o.user)
        recovery = StateRecovery(session, replay_key, o.rig_name) if o.recover else None
        knowledge_version: int | None = None
        next_poll = t0
        with session, McapWriter(Path(o.out), rig=o.rig_name) as rec:
            state = session.declare_subscriber(proto.key_state(o.rig_name),
                                               zenoh.handlers.FifoChannel(16384))
            status = session.declare_subscriber(proto.key_status(o.rig_name),
                                                zenoh.handlers.FifoChannel(256))
            try:
                while not stop.is_set():
                    if o.duration_s is not None and time.monotonic() - t0 >= o.duration_s:
                        break
                    if rec.samples == 0 and time.monotonic() - t0 > o.timeout_s:
                        break
                    got = False
                    for sample in iter(state.try_recv, None):
                        got = True
                        try:
                            batch = proto.decode(sample.payload.to_bytes(), proto.StateBatch)
                        except proto.ProtocolError as exc:
                            bad += 1
                            rec.event("note", f"undecodable state message: {exc}")
                            continue
                        if o.drop_batch is not None and o.drop_batch(batch):
                            continue
                        nxt = rec.next_seq
                        if recovery is not None and nxt is not None and batch.seq0 > nxt:
                            t_gap = batch.epoch_s + (batch.t_s[0] if batch.t_s else 0.0)
                            recovery.fill(rec, nxt, batch.seq0 - 1, t_gap)
                        rec.state(batch)
                    for sample in iter(status.try_recv, None):
                        got = True
                        try:
                            st = proto.decode(sample.payload.to_bytes(), proto.Status)
                        except proto.ProtocolError as exc:
                            bad += 1
                            rec.event("note", f"undecodable status message: {exc}")
                            continue
                        rec.status(st, time.time())
                        knowledge_version = st.knowledge_version
                        text = f"{st.mode}|{st.watchdog}|{';'.join(st.faults)}"
                        if text != last_status and last_status:
                            rec.event("status", f"mode {st.mode}; faults: "
                                      f"{'; '.join(st.faults) or '-'}; {st.watchdog}",
                                      time.time())
                        last_status = text
                    if time.monotonic() >= next_poll:
                        next_poll = time.monotonic() + IDENTIFY_POLL_S
                        identify.poll(session, identify_key, rec)
                        twin.poll(session, twin_key, rec, knowledge_version)
                    if not got:
                        stop.wait(0.01)
                identify.poll(session, identify_key, rec)  # a run that ended in the last poll
            finally:
                state.undeclare()
                status.undeclare()
            n, gaps, missing = rec.samples, rec.gaps, tuple(rec.missing)
        if n == 0:
            raise ControllerUnavailable(
                f"no state from rig {o.rig_name!r} on {', '.join(o.connect)} within "
                f"{o.timeout_s:g} s (wrong endpoint, rig name or credentials)")
        path = Path(o.out)
        return RecordResult(path=path, samples=n, lost=gaps, undecodable=bad,
                            duration_s=time.monotonic() - t0, size_bytes=path.stat().st_size,
                            recovered=recovery.recovered if recovery is not None else 0,
                            missing=missing)
