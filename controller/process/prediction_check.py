"""Predicted, then measured, after every Apply (issue 35 item 5), in the watch's process.

When the running configuration's version changes (an Apply, a rollback, the startup's), the
tracker asks the twin what the configuration will do on the running trajectory
(`controller.tune.prediction.predict`, on the plant Suggest and the preview use), publishes
that prediction at once (state "predicted"), then waits for the rig's window: `settle_s` of
running under that version left out, then `window_s` (whole periods) of samples all under it,
none lost. It then measures the same figures on the rig's samples, judges them against the
prediction, says what a failure means (the watch's latest fit of the plant tells "model wrong"
from "a disturbance the twin lacks"), and when the prediction failed badly offers the rollback
to the last version whose prediction held.

Every version's check is kept (a JSON line per check in `log_path`, read back at start) and
served on `dobtune/<rig>/prediction` (`dobtune ctl prediction`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np

from controller import protocol as proto
from controller.client import ControllerClient
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.tune.plant import SimPlant
from controller.tune.prediction import (
    BANDS_HZ,
    SETTLE_S,
    TOLERANCE_REL,
    Figures,
    check_window_s,
    figures_of,
    judge,
    meaning,
    predict,
)

__all__ = ["PredictionTracker", "describe_check", "rollback_offer"]

log = logging.getLogger(__name__)

#: Kept in memory and served (the newest).
KEPT = 200


@dataclass
class _Pending:
    version: int
    cfg: LoopConfig
    trajectory: Trajectory
    predicted: Figures
    check: proto.PredictionCheck
    start_total: int
    """The ring's sample count when the version was first seen running."""
    gaps: int


def _figures(p: Figures, m: Figures | None) -> tuple[list[proto.PredictionFigure],
                                                       list[proto.PredictionFigure]]:
    main = [proto.PredictionFigure(name=k, predicted=v,
                                   measured=None if m is None else m.main()[k],
                                   tolerance_rel=TOLERANCE_REL[k]) for k, v in p.main().items()]
    bands = [proto.PredictionFigure(
        name=f"error_rms_deg {lo:g}-{hi:g} Hz", predicted=pv,
        measured=None if m is None else m.band_rms_deg[i])
        for i, ((lo, hi), pv) in enumerate(zip(BANDS_HZ, p.band_rms_deg, strict=True))]
    return main, bands


class PredictionTracker:
    """Fed by the watch's loop (`step`, its thread only); publishes through `publish`."""

    def __init__(self, rig: str, plant: Callable[[], tuple[SimPlant, str]],
                 publish: Callable[[proto.PredictionCheck], None],
                 plant_moved: Callable[[], str], *, min_window_s: float = 10.0,
                 settle_s: float = SETTLE_S, log_path: Path | None = None) -> None:
        self.rig = rig
        self._plant = plant
        self._publish = publish
        self._plant_moved = plant_moved
        self.min_window_s = min_window_s
        self.settle_s = settle_s
        self.log_path = log_path
        self.checks: dict[int, proto.PredictionCheck] = {}
        self._pending: _Pending | None = None
        self._seen_version = -1
        if log_path is not None and log_path.exists():
            dec = msgspec.json.Decoder(proto.PredictionCheck)
            for line in log_path.read_bytes().splitlines():
                if line.strip():
                    c = dec.decode(line)
                    self.checks[c.config_version] = c

    # -- what the watch calls ------------------------------------------------------------

    def step(self, c: ControllerClient) -> None:
        st = c.status
        if st is None or st.mode != "running":
            if self._pending is not None and st is not None and st.mode != "running":
                self._close(self._pending, "not judged", f"the loop left running ({st.mode}) "
                            "before the rig's window was complete")
            return
        p = self._pending
        if p is not None and st.config_version != p.version:
            self._close(p, "not judged", f"replaced by v{st.config_version} before the rig's "
                        "window was complete")
            p = None
        if p is not None and st.trajectory != p.trajectory:
            p = None  # the running trajectory changed: predict for the new one
            self._pending = None
        if p is None:
            kept = self.checks.get(st.config_version)
            if st.config_version == self._seen_version and kept is not None \
                    and kept.trajectory == st.trajectory and kept.state != "not judged":
                return  # checked already (a check not judged is made again)
            self._start(c, st)
            return
        self._measure(c, p, st.config.rate_hz)

    def _start(self, c: ControllerClient, st: proto.Status) -> None:
        self._seen_version = st.config_version
        cfg, traj = st.config, st.trajectory
        window = check_window_s(traj, self.min_window_s)
        t0 = time.perf_counter()
        try:
            plant, model = self._plant()
            predicted = predict(cfg, traj, plant, window, self.settle_s)
        except (ValueError, ArithmeticError) as exc:
            self._emit(proto.PredictionCheck(
                rig=self.rig, config_version=st.config_version, epoch_s=time.time(),
                trajectory=traj, model="", window_s=window, settle_s=self.settle_s,
                state="not predicted", meaning=f"the twin could not predict: {exc}"), keep=True)
            return
        log.info("prediction for v%d on %s: %.2f s", st.config_version, model,
                 time.perf_counter() - t0)
        figures, bands = _figures(predicted, None)
        check = proto.PredictionCheck(
            rig=self.rig, config_version=st.config_version, epoch_s=time.time(),
            trajectory=traj, model=model, window_s=window, settle_s=self.settle_s,
            state="predicted", figures=figures, bands=bands,
            meaning=f"waiting for {self.settle_s:g} + {window:.3g} s of running under "
                    f"v{st.config_version}")
        self._pending = _Pending(st.config_version, cfg, traj, predicted, check,
                                 c.ring.total, c.ring.gaps)
        self._emit(check, keep=False)

    def _measure(self, c: ControllerClient, p: _Pending, rate_hz: float) -> None:
        n = round(p.check.window_s * rate_hz)
        need = round(p.check.settle_s * rate_hz) + n
        if c.ring.total - p.start_total < need:
            return
        if c.ring.gaps != p.gaps:  # samples lost on the way: start the window again
            p.start_total, p.gaps = c.ring.total, c.ring.gaps
            log.info("prediction check v%d: samples lost; its window starts again", p.version)
            return
        cols, versions = c.ring.window(2.0 * p.check.window_s + 10.0)
        if versions.size < n or np.any(versions[-n:] != p.version):
            p.start_total = c.ring.total
            return
        t0 = float(cols["t_s"][-n])
        measured = figures_of(cols["error_deg"][-n:], cols["command_deg_s"][-n:], rate_hz)
        j = judge(p.predicted, measured)
        moved = self._plant_moved()
        rollback, offer = rollback_offer(j.state, moved, self.checks, p.version)
        text = meaning(j, moved) + offer
        figures, bands = _figures(p.predicted, measured)
        latest = c.ring.latest()
        epoch0 = time.time() - (float(latest["t_s"]) if latest is not None else 0.0)
        check = msgspec.structs.replace(
            p.check, epoch_s=time.time(), state=j.state, figures=figures, bands=bands,
            meaning=text, rollback_to=rollback, measured_from_epoch_s=epoch0 + t0)
        self._pending = None
        self._emit(check, keep=True)

    def _close(self, p: _Pending, state: str, why: str) -> None:
        self._pending = None
        self._emit(msgspec.structs.replace(p.check, epoch_s=time.time(), state=state,
                                           meaning=why), keep=True)

    def _emit(self, check: proto.PredictionCheck, keep: bool) -> None:
        kept = self.checks.get(check.config_version)
        judged = ("held", "failed", "failed badly")
        if not (kept is not None and kept.state in judged and check.state not in judged):
            # (a verdict is not overwritten by a later prediction of the same version, or by
            # its "not judged": after a restart the running version is predicted again)
            self.checks[check.config_version] = check
        while len(self.checks) > KEPT:
            del self.checks[next(iter(self.checks))]
        if keep and self.log_path is not None:
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.log_path, "ab") as f:
                f.write(msgspec.json.encode(check) + b"\n")
        log.info("prediction check: %s", describe_check(check).splitlines()[0])
        self._publish(check)

    def all(self) -> list[proto.PredictionCheck]:
        """Every version's check kept, oldest version first (the pending one's prediction)."""
        return [self.checks[v] for v in sorted(self.checks)]


def rollback_offer(state: str, moved: str, checks: dict[int, proto.PredictionCheck],
                   version: int) -> tuple[int | None, str]:
    """(the version offered, the text) after a check of `version` ended in `state`; `moved`:
    the plant's parts the watch finds outside their range ("": none). Only a prediction that
    failed badly offers a rollback, to the newest other version whose prediction held, and
    only when the plant has not moved: every earlier prediction was made on the plant as it
    was, and a version that held then can be unsafe on the moved plant (seen: one the
    watchdog rolled back at once)."""
    if state != "failed badly":
        return None, ""
    if moved:
        return None, ("; no rollback offered: the versions whose predictions held were judged "
                      "on the plant before it moved; measure it again first")
    held = [v for v, k in checks.items() if k.state == "held" and v != version]
    if not held:
        return None, "; no earlier version's prediction held to roll back to"
    v = max(held)
    return v, f"; roll back to v{v} (its prediction held): `dobtune ctl rollback {v}`"


def describe_check(k: proto.PredictionCheck) -> str:
    """A check in a few lines (`dobtune ctl prediction`)."""
    head = (f"v{k.config_version} on {k.trajectory.kind}: {k.state.upper()} "
            f"(window {k.window_s:.3g} s after {k.settle_s:g} s; predicted on {k.model})")
    rows = []
    for f in [*k.figures, *k.bands]:
        m = "-" if f.measured is None else f"{f.measured:.4g}"
        off = ("" if f.measured is None or f.predicted == 0.0
               else f" ({(f.measured - f.predicted) / abs(f.predicted):+.1%})")
        tol = f", tolerance {f.tolerance_rel:.0%}" if f.tolerance_rel else ""
        rows.append(f"  {f.name}: predicted {f.predicted:.4g}, measured {m}{off}{tol}")
    return "\n".join([head, *rows, f"  {k.meaning}"])
