"""The watch: the twin beside the live loop, in a process of its own (`dobtune watch`).

It reads what the loop already publishes (the state stream: every tick's reference, position,
rate, command sent, d_hat and error, handed by the loop's ring of blocks to its publisher
thread: nothing is added to the tick), keeps the newest samples in the client's ring, and
every `window_s` of running:

- fits the twin's parts to the window (`controller.watch.estimate.fit_window`) and runs the
  active configuration on the twin over the window's reference (`loop_residual`);
- judges the parts against the plant knowledge's bound (`controller.watch.judge`): a part
  outside its range in two windows in a row is an alarm, with the gate's verdict on the
  active configuration against the drifted estimate;
- publishes a `DriftState` on `dobtune/<rig>/drift` and each alarm (and its clearing) as a
  `DriftAlarm` on `dobtune/<rig>/drift/alarm`;
- appends the window to the rig's trend (`controller.recording.trend`, MCAP per hour).

The model compared with: the rig's twin when the controller built one (the knowledge reply
carries it), else the simulated rig named by `disturbances` (a demo or test controller runs
exactly that), and the state says which. A window is judged only if the loop ran all of it
(mode running, one configuration, no lost samples); an identification run counts (its
excitation is what tells the parts a plain trajectory cannot).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from controller import protocol as proto
from controller.client import ClientOptions, ControllerClient, ControllerUnavailable
from controller.core.config import LoopConfig
from controller.gate.knowledge import PlantKnowledge
from controller.process.prediction_check import PredictionTracker
from controller.recording.trend import TrendWriter
from controller.sim.rig_disturbances import rig_setup
from controller.sim.sim_rig import RigFaults, RigParams
from controller.tune.plant import SimPlant, plant_for
from controller.twin.model import decode as decode_twin
from controller.watch.estimate import DriftFit, LoopResidual, Window
from controller.watch.judge import MEASURE_HINT, DriftJudge, gate_on_drift, part_ranges
from controller.watch.step import watch_window

__all__ = ["WatchOptions", "WatchState", "describe_state", "run_watch"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WatchOptions:
    client: ClientOptions
    window_s: float = 10.0
    """Seconds of samples per fit (the alarm needs two windows outside in a row)."""
    disturbances: tuple[str, ...] = ("article-rig",)
    """Without a twin: the simulated rig the controller runs (`dobtune controller
    --disturbance`), as the model to compare with."""
    resonance: tuple[float, float] = (0.0, 0.0)
    """Without a twin: the simulated rig's extra mode (frequency Hz, damping ratio; 0 Hz:
    none), as `dobtune ctl sim-fault` / `SimFault` gave it; its frequency and damping are then
    estimated with the other parts."""
    trend_dir: Path | None = None
    """Where the rig's trend is kept (None: not kept)."""
    prediction_window_s: float = 10.0
    """After each Apply: the shortest window the rig's figures are taken over (whole periods
    of a periodic trajectory), against the twin's prediction."""
    prediction_log: Path | None = None
    """Where every version's prediction check is kept (JSON lines; None: in memory only)."""


@dataclass
class WatchState:
    """What the watch holds between windows (its thread's alone)."""

    params: RigParams
    faults: RigFaults
    model: str
    knowledge: PlantKnowledge
    judge: DriftJudge
    start: Any = None
    windows: int = 0
    alarms: int = 0
    gaps: int = 0
    """Samples the state stream had lost at the previous window (the ring's count)."""
    notes: list[str] = field(default_factory=list)


def _model(c: ControllerClient, opts: WatchOptions) -> WatchState:
    reply = c.knowledge()
    knowledge = reply.record.to_knowledge()
    if reply.twin:
        twin = decode_twin(reply.twin)
        params, faults = twin.params, twin.faults
        model = f"the rig's twin of plant knowledge v{twin.knowledge_version}"
    else:
        params, faults = rig_setup(list(opts.disturbances)).params, RigFaults()
        hz, zeta = opts.resonance
        mode = ""
        if hz > 0.0:
            faults = RigFaults(resonance_hz=hz, resonance_damping=zeta)
            mode = f" with an extra mode at {hz:g} Hz, damping {zeta:g}"
        why = reply.twin_note or "no twin"
        model = (f"the simulated rig {'+'.join(opts.disturbances)}{mode} ({why}; plant "
                 f"knowledge v{knowledge.version})")
    rate = c.get_config().config.rate_hz
    ranges = part_ranges(params, faults, knowledge.bound, rate)
    st = WatchState(params, faults, model, knowledge, DriftJudge(ranges))
    if knowledge.bound is None:
        st.notes.append("the knowledge states no bound: each part allowed +-20 % (ours)")
    st.notes.append("motor friction allowed x0.5-x2 (ours: the knowledge bounds no friction)")
    return st


def _window(c: ControllerClient, window_s: float, rate_hz: float) -> tuple[Window, int] | None:
    """The newest `window_s` of samples if the loop ran all of them under one configuration,
    else None. (A tick the loop skipped when late leaves a gap in t_s, not in the plant's
    samples: the simulated plant advances with each executed tick, a drive's speed loop holds
    the command; samples lost on the way are the caller's check, by sequence number.)"""
    # By samples, not by time: a loaded loop skips ticks (the sim stays in lockstep).
    n = round(window_s * rate_hz)
    cols, versions = c.ring.window(3.0 * window_s)
    if cols["t_s"].size < n:
        return None
    cols = {k: v[-n:] for k, v in cols.items()}
    versions = versions[-n:]
    t = cols["t_s"]
    if np.any(versions != versions[-1]):
        return None
    win = Window(t0_s=float(t[0]), rate_hz=rate_hz, pos_deg=cols["pos_deg"],
                 speed_deg_s=cols["speed_deg_s"], command_deg_s=cols["command_deg_s"],
                 ref_deg=cols["ref_deg"], error_deg=cols["error_deg"])
    return win, int(versions[-1])


def _publish_alarm(pub: Any, st: WatchState, rig: str, name: str, cfg: LoopConfig,
                   fit: DriftFit, epoch_s: float, cleared: bool) -> proto.DriftAlarm:
    ps = st.judge.parts[name]
    est = fit.part(name)
    st.alarms += 1
    verdict, reasons = "", []
    if not cleared:
        try:
            told = [n for n, p in st.judge.parts.items() if p.told]
            v = gate_on_drift(cfg, st.knowledge, st.params, st.faults, fit, cfg.rate_hz, told)
            verdict, reasons = v.verdict, [*v.rejections, *v.cautions][:6]
        except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
            verdict, reasons = "", [f"the gate could not judge the drifted estimate: {exc}"]
    since = ps.since_s if ps.since_s is not None else epoch_s
    way = "below" if est.value < ps.low else "above"
    text = (f"{name} x{est.value:.3g} +-{est.std:.2g} of the twin's, {way} its range "
            f"{ps.low:.3g}-{ps.high:.3g} (the knowledge's bound) since "
            f"{time.strftime('%H:%M:%S', time.gmtime(since))} UTC"
            if not cleared else f"{name} back inside its range (x{est.value:.3g})")
    action = MEASURE_HINT + (f"; the gate on the active configuration with the drifted "
                             f"estimate: {verdict}" if verdict else "")
    alarm = proto.DriftAlarm(
        rig=rig, seq=st.alarms, epoch_s=epoch_s, part=name, value=est.value, std=est.std,
        unit=est.unit, low=ps.low, high=ps.high, since_epoch_s=since, text=text,
        action=action if not cleared else "", gate_verdict=verdict, gate_reasons=reasons,
        cleared=cleared)
    pub.put(proto.encode(alarm), encoding=proto.encoding(proto.DriftAlarm))
    log.warning("drift alarm: %s; %s", text, action)
    return alarm


def _state_msg(rig: str, st: WatchState, fit: DriftFit, lr: LoopResidual, epoch_s: float,
               window_s: float, version: int, lines: tuple[str, ...], fit_s: float
               ) -> proto.DriftState:
    parts = []
    for est in fit.parts:
        ps = st.judge.parts[est.name]
        parts.append(proto.DriftPart(name=est.name, value=est.value, std=est.std, unit=est.unit,
                                     told=ps.told, state=ps.state, low=ps.low, high=ps.high,
                                     since_epoch_s=ps.since_s))
    return proto.DriftState(
        rig=rig, epoch_s=epoch_s, window_s=window_s, config_version=version, model=st.model,
        parts=parts, delay_ticks=fit.delay_ticks, twin_delay_ticks=fit.twin_delay_ticks,
        plant_residual_rms_deg_s=fit.residual_rms_deg_s,
        fitted_residual_rms_deg_s=fit.fitted_rms_deg_s,
        loop_measured_rms_deg=lr.measured_rms_deg, loop_predicted_rms_deg=lr.predicted_rms_deg,
        loop_residual_rms_deg=lr.residual_rms_deg,
        alarms=[n for n, p in st.judge.parts.items() if p.state == "alarm"],
        lines=[*st.notes, *lines], fit_s=fit_s, windows=st.windows)


def _trend(tw: TrendWriter, msg: proto.DriftState, status: proto.Status | None) -> None:
    e = msg.epoch_s
    tw.write("/drift/residual", e, {
        "plant_residual_rms_deg_s": msg.plant_residual_rms_deg_s,
        "fitted_residual_rms_deg_s": msg.fitted_residual_rms_deg_s,
        "loop_measured_rms_deg": msg.loop_measured_rms_deg,
        "loop_predicted_rms_deg": msg.loop_predicted_rms_deg,
        "loop_residual_rms_deg": msg.loop_residual_rms_deg, "delay_ticks": msg.delay_ticks})
    parts: dict[str, Any] = {}
    for p in msg.parts:
        parts[p.name] = p.value
        parts[p.name + "_std"] = p.std
        parts[p.name + "_state"] = p.state
        parts[p.name + "_low"] = p.low  # its allowed range: the dashboard's Trends tab draws it
        parts[p.name + "_high"] = p.high
    tw.write("/drift/parts", e, parts)
    health: dict[str, Any] = {"config_version": msg.config_version, "alarms": msg.alarms}
    if status is not None:
        health.update(compute_p99_us=status.timing.compute_p99_us,
                      skipped_ticks=status.timing.skipped_ticks, mode=status.mode)
    tw.write("/drift/health", e, health)


def _tracker(rig: str, st: WatchState, opts: WatchOptions, pub: Any) -> PredictionTracker:
    """The prediction check after each Apply, on the plant Suggest and the preview use (the
    rig's twin with the named disturbances; the built-in model when nothing was measured)."""
    made: list[tuple[SimPlant, str]] = []

    def plant() -> tuple[SimPlant, str]:
        if not made:
            p = plant_for(st.knowledge, rig_setup(list(opts.disturbances)))
            made.append((p, p.source))
        return made[0]

    def moved() -> str:
        return ", ".join(f"{n} {p.state}" for n, p in st.judge.parts.items()
                         if p.state in ("outside", "alarm"))

    def publish(check: proto.PredictionCheck) -> None:
        pub.put(proto.encode(check), encoding=proto.encoding(proto.PredictionCheck))

    return PredictionTracker(rig, plant, publish, moved, min_window_s=opts.prediction_window_s,
                             log_path=opts.prediction_log)


def run_watch(opts: WatchOptions, stop: threading.Event,
              on_state: Callable[[proto.DriftState], None] | None = None) -> int:
    """Watch until `stop` is set; 0. `on_state(DriftState)` after each window (tests)."""
    rig = opts.client.rig_name
    with ControllerClient(opts.client) as c:
        session = c.session
        pub_state = session.declare_publisher(proto.key_drift(rig))
        pub_alarm = session.declare_publisher(proto.key_drift_alarm(rig))
        latest: list[bytes] = []

        def on_query(query: Any) -> None:
            # `dobtune ctl drift`: the latest state (no reply before the first window).
            if latest:
                with contextlib.suppress(Exception):
                    query.reply(query.key_expr, latest[-1],
                                encoding=proto.encoding(proto.DriftState))

        sent: list[bytes] = []

        def on_alarm_query(query: Any) -> None:
            # `dobtune ctl wait-alarm --since`: the alarms so far (the newest 100), one reply each.
            for raw in list(sent):
                with contextlib.suppress(Exception):
                    query.reply(query.key_expr, raw, encoding=proto.encoding(proto.DriftAlarm))

        import zenoh

        queryable = session.declare_queryable(
            proto.key_drift(rig), zenoh.handlers.Callback(on_query, indirect=False))
        alarm_queryable = session.declare_queryable(
            proto.key_drift_alarm(rig), zenoh.handlers.Callback(on_alarm_query, indirect=False))
        entities: list[Any] = []
        st = None
        while st is None:
            try:
                st = _model(c, opts)
            except ControllerUnavailable as exc:  # starting, or busy: ask again
                log.info("watch: %s; asking again", exc)
                if stop.wait(1.0):
                    return 0
        log.info("watch: rig %s against %s", rig, st.model)
        pub_pred = session.declare_publisher(proto.key_prediction(rig))
        entities.append(pub_pred)
        tracker = _tracker(rig, st, opts, pub_pred)

        def on_prediction_query(query: Any) -> None:
            # `dobtune ctl prediction`: every version's check kept, oldest first.
            for check in tracker.all():
                with contextlib.suppress(Exception):
                    query.reply(query.key_expr, proto.encode(check),
                                encoding=proto.encoding(proto.PredictionCheck))

        entities.append(session.declare_queryable(
            proto.key_prediction(rig),
            zenoh.handlers.Callback(on_prediction_query, indirect=False)))
        trend = TrendWriter(opts.trend_dir, rig) if opts.trend_dir is not None else None
        cfg_version, cfg = -1, None
        next_at = 0
        try:
            while not stop.is_set():
                tracker.step(c)
                status = c.status
                if status is None or status.mode != "running":
                    stop.wait(0.2)
                    next_at = c.ring.total + round(opts.window_s * 1000.0)
                    continue
                rate = status.config.rate_hz
                if c.ring.total < next_at:
                    stop.wait(0.1)
                    continue
                got = _window(c, opts.window_s, rate)
                next_at = c.ring.total + round(opts.window_s * rate)
                gaps, st_gaps = c.ring.gaps, st.gaps
                st.gaps = gaps
                if got is None or gaps != st_gaps:  # samples lost: not one run
                    continue
                win, version = got
                if version != cfg_version:
                    try:
                        cfg = c.get_config().config
                    except ControllerUnavailable as exc:
                        log.info("watch: %s; the window is skipped", exc)
                        continue
                    cfg_version = version
                assert cfg is not None
                # UNIX time of the loop's t_s = 0: the newest sample arrived about now.
                epoch0 = time.time() - float(c.ring.latest()["t_s"])  # type: ignore[index]
                res = watch_window(st.params, st.faults, st.judge, win, cfg, st.start,
                                   epoch0 + win.t0_s)
                fit, lr, verdict, fit_s = res.fit, res.loop, res.verdict, res.fit_s
                st.start = np.array(fit.x)
                st.windows += 1
                epoch_s = epoch0 + win.t0_s + win.duration_s
                for name, cleared in ([(n, False) for n in verdict.new_alarms]
                                      + [(n, True) for n in verdict.cleared]):
                    alarm = _publish_alarm(pub_alarm, st, rig, name, cfg, fit, epoch_s, cleared)
                    sent.append(proto.encode(alarm))
                    if trend is not None:  # marked at its time in the Trends tab
                        trend.write("/drift/alarm", epoch_s, msgspec.to_builtins(alarm))
                    del sent[:-100]
                msg = _state_msg(rig, st, fit, lr, epoch_s, win.duration_s, version,
                                 verdict.lines, fit_s)
                raw = proto.encode(msg)
                latest[:] = [raw]
                pub_state.put(raw, encoding=proto.encoding(proto.DriftState))
                if trend is not None:
                    _trend(trend, msg, status)
                if on_state is not None:
                    on_state(msg)
        finally:
            if trend is not None:
                trend.close()
            for e in (queryable, alarm_queryable, pub_state, pub_alarm, *entities):
                with contextlib.suppress(Exception):
                    e.undeclare()
    return 0


def describe_state(msg: proto.DriftState) -> str:
    """The state in a few lines (`dobtune ctl drift`)."""
    head = (f"{msg.rig}: window {msg.window_s:g} s at "
            f"{time.strftime('%H:%M:%S', time.gmtime(msg.epoch_s))} UTC, config "
            f"v{msg.config_version}, against {msg.model}; alarms: "
            f"{', '.join(msg.alarms) or 'none'}")
    res = (f"plant residual {msg.plant_residual_rms_deg_s:.3g} deg/s rms "
           f"({msg.fitted_residual_rms_deg_s:.3g} with the fitted parts); loop error "
           f"{msg.loop_measured_rms_deg:.3g} deg rms measured, {msg.loop_predicted_rms_deg:.3g} "
           f"predicted, residual {msg.loop_residual_rms_deg:.3g}; delay {msg.delay_ticks} "
           f"ticks (twin {msg.twin_delay_ticks})")
    parts = [f"  {p.name}: {p.value:.3g} {p.unit} +-{p.std:.2g} {p.state} (range "
             f"{p.low:.3g}-{p.high:.3g})" for p in msg.parts]
    return "\n".join([head, res, *parts])

