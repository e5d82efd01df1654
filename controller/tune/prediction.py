"""Predicted, then measured (pure): what the twin says a configuration will do on the running
trajectory, what the rig then did over the same length of running, and whether the prediction
held.

The figures are the preview's (peak |error|, RMSE, command noise: `controller.tune.autotune`)
plus the error's spectrum in a few bands (RMS per band, from one FFT of the window). Both sides
are computed by the same function on windows of the same length, in steady running: the
prediction runs the configuration on the twin (`SimPlant`: the rig's twin with the setup's
disturbances, as Suggest and the preview do) for `settle_s` and then the window; the rig's
window starts `settle_s` after the configuration became active.

The window holds whole periods of a periodic trajectory (at least `MIN_WINDOW_S`): a window
that cuts a sine in a different place each time changes its RMSE by several per cent.

Tolerances (relative, `TOLERANCE_REL`): what run-to-run noise and the twin's fit leave between a
good twin's prediction and the rig (bench_prediction.py: the twin of the demo's rig against the
simulated rig with other noise seeds); a figure outside twice its tolerance fails badly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controller.core.arrays import FloatArray
from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.tune.autotune import command_noise_deg_s, run_point
from controller.tune.plant import SimPlant

__all__ = [
    "BANDS_HZ",
    "MIN_WINDOW_S",
    "SETTLE_S",
    "TOLERANCE_REL",
    "Figures",
    "Judged",
    "band_rms_deg",
    "check_window_s",
    "figures_of",
    "judge",
    "meaning",
    "predict",
]

#: The shortest window the rig's figures are taken over (s).
MIN_WINDOW_S = 10.0
#: After a configuration becomes active: the switching transient left out (s).
SETTLE_S = 3.0
#: The error spectrum's bands (Hz): the trajectory's band, the loop's, the resonance's.
BANDS_HZ: tuple[tuple[float, float], ...] = ((0.0, 1.0), (1.0, 10.0), (10.0, 100.0),
                                             (100.0, 500.0))
#: How far (relative) the measured figure may be from the predicted one for the prediction to
#: hold. Measured: see the module docstring.
TOLERANCE_REL: dict[str, float] = {
    "rmse_deg": 0.10,
    "peak_error_deg": 0.25,
    "command_noise_deg_s": 0.20,
}
#: Beyond this multiple of a tolerance the prediction failed badly (the rollback is offered).
BADLY = 2.0


@dataclass(frozen=True)
class Figures:
    """One window's figures (deg, deg/s), both for the prediction and the rig."""

    peak_error_deg: float
    rmse_deg: float
    command_noise_deg_s: float
    band_rms_deg: tuple[float, ...]
    """RMS error per band of `BANDS_HZ`."""

    def main(self) -> dict[str, float]:
        return {"rmse_deg": self.rmse_deg, "peak_error_deg": self.peak_error_deg,
                "command_noise_deg_s": self.command_noise_deg_s}


def check_window_s(trajectory: Trajectory, min_window_s: float = MIN_WINDOW_S) -> float:
    """Whole periods of a periodic trajectory, at least `min_window_s`; else `min_window_s`."""
    if not (math.isfinite(min_window_s) and min_window_s > 0.0):
        raise ValueError(f"min_window_s: {min_window_s!r} must be > 0")
    period = trajectory.period_s
    if period is None:
        return min_window_s
    return math.ceil(min_window_s / period - 1e-9) * period


def band_rms_deg(error_deg: FloatArray, rate_hz: float,
                 bands: tuple[tuple[float, float], ...] = BANDS_HZ) -> tuple[float, ...]:
    """RMS of `error_deg` (mean removed) per band [lo, hi) Hz, by Parseval on one FFT: the
    squares of the bands add up to the signal's variance (the band holding Nyquist included)."""
    e = np.asarray(error_deg, dtype=np.float64)
    n = e.size
    if n < 2:
        return tuple(math.nan for _ in bands)
    spec = np.fft.rfft(e - e.mean())
    power = np.abs(spec) ** 2 / n**2
    power[1:] *= 2.0
    if n % 2 == 0:
        power[-1] /= 2.0  # the Nyquist bin is its own mirror
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)
    out = []
    for lo, hi in bands:
        sel = (f >= lo) & (f < hi) if hi < rate_hz / 2 else (f >= lo)
        out.append(float(math.sqrt(float(np.sum(power[sel])))))
    return tuple(out)


def figures_of(error_deg: FloatArray, command_deg_s: FloatArray, rate_hz: float) -> Figures:
    """The figures of one window of running (the same for the twin's run and the rig's)."""
    e = np.asarray(error_deg, dtype=np.float64)
    if e.size == 0:
        raise ValueError("error_deg: an empty window")
    return Figures(peak_error_deg=float(np.max(np.abs(e))),
                   rmse_deg=float(np.sqrt(np.mean(e * e))),
                   command_noise_deg_s=command_noise_deg_s(command_deg_s, rate_hz),
                   band_rms_deg=band_rms_deg(e, rate_hz))


def predict(cfg: LoopConfig, trajectory: Trajectory, plant: SimPlant, window_s: float,
            settle_s: float = SETTLE_S) -> Figures:
    """The twin's figures for `cfg` on `trajectory` over `window_s` of steady running (after
    `settle_s` and, for a periodic trajectory, whole periods of start-up)."""
    lead = settle_s if trajectory.period_s is None else check_window_s(trajectory, settle_s)
    res = run_point(cfg, trajectory, lead + window_s, plant=plant)
    n = round(window_s * cfg.rate_hz)
    err = np.asarray(res.error_deg)[-n:]
    return figures_of(err, np.asarray(res.command_deg_s)[-n:], cfg.rate_hz)


@dataclass(frozen=True)
class Judged:
    state: str
    """"held", "failed" or "failed badly"."""
    off_rel: dict[str, float]
    """Per figure: (measured - predicted) / predicted."""
    outside: tuple[str, ...]
    """The figures outside their tolerance."""


def judge(predicted: Figures, measured: Figures,
          tolerance_rel: dict[str, float] | None = None) -> Judged:
    """Whether the prediction held: every main figure within its tolerance (relative)."""
    tol = TOLERANCE_REL if tolerance_rel is None else tolerance_rel
    off: dict[str, float] = {}
    outside: list[str] = []
    badly = False
    p, m = predicted.main(), measured.main()
    for name, t in tol.items():
        if not (math.isfinite(p[name]) and math.isfinite(m[name])):
            raise ValueError(f"{name}: predicted {p[name]!r}, measured {m[name]!r}: not finite")
        scale = max(abs(p[name]), 1e-12)
        off[name] = (m[name] - p[name]) / scale
        if abs(off[name]) > t:
            outside.append(name)
            badly = badly or abs(off[name]) > BADLY * t
    state = "held" if not outside else ("failed badly" if badly else "failed")
    return Judged(state, off, tuple(outside))


def meaning(judged: Judged, plant_moved: str) -> str:
    """What the verdict means for the engineer. `plant_moved`: the parts of the plant found
    outside the twin's bound on the same window ("" when the plant matches the twin)."""
    if judged.state == "held":
        return ("the rig does what the twin predicted: the twin can be trusted for the next "
                "tuning")
    worse = [n for n in judged.outside if judged.off_rel[n] > 0]
    how = ", ".join(f"{n} {judged.off_rel[n]:+.0%}" for n in judged.outside)
    if plant_moved:
        why = (f"the model is wrong: the plant differs from the twin ({plant_moved}); measure "
               "again (Identify) before tuning on it")
    else:
        why = ("the plant matches the twin, the error does not: a disturbance the twin lacks "
               "(load torque, friction or noise not in its model); record a run and compare")
    return f"the prediction did not hold ({how}{'; worse than predicted' if worse else ''}): {why}"
