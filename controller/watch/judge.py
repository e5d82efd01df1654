"""Drift judged against the plant knowledge's stated bound (pure).

Each part's allowed range comes from the knowledge's uncertainty bound |Delta| <= |W|: the
factor on that part alone whose response (the twin's exact linear response u -> w,
`controller.twin.fit.rig_response`) stays within |G' / G - 1| <= |W(f)| at every frequency of
the band (`part_ranges`, by bisection). The motor friction does not enter the linear
response: its range is ours (`FRICTION_RANGE`), and the text says so.

`DriftJudge` follows the windows' fits: a part told by the window and outside its range (by
more than `SIGMAS` deviations) in `CONFIRM` windows in a row is an alarm (which part, by how
much, since when, what to do, and the gate's verdict on the active configuration against the
drifted estimate, `gate_on_drift`); a part that moved significantly but stays inside is a
note; a part the window does not tell is listed as such, with the short measurement that
would tell it.

A window tells a part when the fit says so (its deviation) and when its bias bound
(`PartEstimate.bias`: how far a model error as large as the residual the twin leaves could move
the estimate) is below the part's reach, the distance from the twin's value to the nearer end
of its range: a window whose command barely moves a part (a constant-speed ramp: the belt's
stiffness and the load's inertia show only in the small corrections of the loop, the drive's
gain and the motor's friction in one steady level) cannot tell whether that part left its
range, and its estimate there follows whatever the twin does not model. It says so (not told),
never alarms on it.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass, field

import numpy as np

from controller.core.arrays import FloatArray
from controller.core.config import LoopConfig
from controller.core.verdict import Verdict
from controller.gate.knowledge import MeasuredResponse, PlantKnowledge, UncertaintyBound
from controller.gate.verdict import judge
from controller.sim.sim_rig import RigFaults, RigParams
from controller.twin.fit import rig_response
from controller.watch.estimate import MODE_PARTS, PARTS, DriftFit, drifted, friction_scale_n_m

__all__ = [
    "CONFIRM",
    "FRICTION_RANGE",
    "MEASURE_HINT",
    "DriftJudge",
    "PartState",
    "WindowVerdict",
    "gate_on_drift",
    "part_ranges",
]

#: Windows in a row a part must be outside its range before the alarm.
CONFIRM = 2
#: How many of its deviations an estimate must be beyond a limit to count as outside (and
#: beyond 1 to count as moved, for a note).
SIGMAS = 3.0
#: A part moved (a note) when its factor differs from 1 by more than this and SIGMAS.
NOTE_FRACTION = 0.05
#: The motor friction's allowed factor (ours: the knowledge states no bound on friction).
FRICTION_RANGE = (0.5, 2.0)
#: What a part's alarm tells the operator to do.
MEASURE_HINT = ("measure again (dobtune identify, then adopt the knowledge: the twin and the "
                "gate follow it)")
#: The short low-amplitude measurement offered when a part is not told.
SHORT_MEASUREMENT = ("a short low-amplitude measurement in the loop tells it: dobtune identify "
                     "--connect EP --rig-name R --positions 1 --amplitude 0.5 (one position; "
                     "the watch fits the excitation's window as any other)")


def _band(rate_hz: float) -> FloatArray:
    return np.geomspace(0.05, 0.4 * rate_hz, 120)


def _linear_parts(faults: RigFaults) -> tuple[str, ...]:
    """The parts that move the linear response: gain, stiffness, inertia, and the extra mode's
    frequency and damping when the twin has one."""
    return PARTS[:3] + (MODE_PARTS if faults.resonance_hz > 0.0 else ())


def _part_x(name: str, factor: float, params: RigParams, faults: RigFaults | None = None
            ) -> FloatArray:
    mode = faults is not None and faults.resonance_hz > 0.0
    x = np.array([0.0, 0.0, 0.0, params.motor_coulomb_n_m / friction_scale_n_m(params)]
                 + ([0.0, 0.0] if mode else []))
    x[(PARTS + MODE_PARTS).index(name)] = math.log(factor)
    return x


def _inside(params: RigParams, faults: RigFaults, bound: UncertaintyBound, name: str,
            factor: float, rate_hz: float) -> bool:
    f = _band(rate_hz)
    g0 = rig_response(params, faults, f, 0.0, rate_hz)
    p, fl = drifted(params, faults, _part_x(name, factor, params, faults),
                    params.command_delay_ticks)
    g1 = rig_response(p, fl, f, 0.0, rate_hz)
    return bool(np.all(np.abs(g1 / g0 - 1.0) <= bound.magnitude(f)))


def part_ranges(params: RigParams, faults: RigFaults, bound: UncertaintyBound | None,
                rate_hz: float) -> dict[str, tuple[float, float]]:
    """Each part's factor range inside the bound (None: no bound stated, every linear part
    allowed +-20 %, said by the caller), and the motor friction's `FRICTION_RANGE`. With an
    extra mode in the twin, its frequency's and damping's ranges too (the same bisection)."""
    out: dict[str, tuple[float, float]] = {}
    for name in _linear_parts(faults):
        if bound is None:
            out[name] = (0.8, 1.2)
            continue
        ends = []
        for far in (0.2, 4.0):
            near = 1.0
            if _inside(params, faults, bound, name, far, rate_hz):
                ends.append(far)
                continue
            for _ in range(30):
                mid = math.sqrt(near * far)
                if _inside(params, faults, bound, name, mid, rate_hz):
                    near = mid
                else:
                    far = mid
            ends.append(near)
        out[name] = (ends[0], ends[1])
    # A twin without motor friction: its estimate is in N m, allowed up to twice the scale.
    out["motor_friction"] = (FRICTION_RANGE if params.motor_coulomb_n_m > 0.0
                             else (0.0, FRICTION_RANGE[1] * friction_scale_n_m(params)))
    return out


def gate_on_drift(cfg: LoopConfig, knowledge: PlantKnowledge, params: RigParams,
                  faults: RigFaults, fit: DriftFit, rate_hz: float,
                  told: Collection[str] | None = None) -> Verdict:
    """The gate's verdict on `cfg` with the drifted estimate as the plant's evidence: the
    knowledge's model and bound, its measured responses replaced by the drifted twin's linear
    response (the told parts: `told`, the judge's, or else the fit's; the others as the twin
    has them)."""
    x = _part_x("gain", 1.0, params, faults)
    for name in _linear_parts(faults):
        p = fit.part(name)
        if (p.told if told is None else name in told):
            x[(PARTS + MODE_PARTS).index(name)] = math.log(p.value)
    pd, fd = drifted(params, faults, x, fit.delay_ticks)
    f = np.geomspace(0.1, 0.4 * rate_hz, 80)
    resp = MeasuredResponse("drifted estimate", f, rig_response(pd, fd, f, 0.0, rate_hz))
    plant = PlantKnowledge((resp,), knowledge.bound, knowledge.model, knowledge.version,
                           f"drift estimate of v{knowledge.version}")
    return judge(cfg, plant, recommendation=False)


@dataclass
class PartState:
    """One part as the windows have seen it."""

    name: str
    low: float
    high: float
    value: float = 1.0
    std: float = math.inf
    told: bool = False
    state: str = "not told"
    """"ok", "note" (moved, inside its range), "outside" (not yet confirmed), "alarm",
    "not told"."""
    outside_windows: int = 0
    since_s: float | None = None
    """When the part first left its range (the start of the first window outside)."""

    def reach(self, unit: str) -> float:
        """The distance from the twin's value (a factor 1; for a friction in N m, none: 0) to
        the nearer end of the range: a window whose bias bound is this large or larger cannot
        tell whether the part is inside."""
        ref = 1.0 if unit == "x" else max(0.0, self.low)
        return min(ref - self.low, self.high - ref) if ref > self.low else self.high - ref


@dataclass(frozen=True)
class WindowVerdict:
    """What one window changed: parts that became alarms and the text of each part."""

    new_alarms: tuple[str, ...]
    cleared: tuple[str, ...]
    lines: tuple[str, ...]


@dataclass
class DriftJudge:
    """The parts' states across windows (see the module docstring)."""

    ranges: dict[str, tuple[float, float]]
    parts: dict[str, PartState] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, (lo, hi) in self.ranges.items():
            self.parts.setdefault(name, PartState(name, lo, hi))

    def update(self, fit: DriftFit, t0_s: float) -> WindowVerdict:
        """Take one window's fit; `t0_s` its start (the time a part's `since_s` states)."""
        new, cleared, lines = [], [], []
        for est in fit.parts:
            ps = self.parts[est.name]
            reach = ps.reach(est.unit)
            told = est.told and est.bias < reach
            ps.value, ps.std, ps.told = est.value, est.std, told
            if not told:
                ps.state = "not told" if ps.state != "alarm" else "alarm"
                ps.outside_windows = 0
                why = (f"+-{est.std:.2g}" if not est.told else
                       f"+-{est.std:.2g}, but the residual the twin leaves could move it by "
                       f"{est.bias:.2g}, beyond its reach {reach:.2g}")
                lines.append(f"{est.name}: not told by this window ({why}); "
                             + SHORT_MEASUREMENT)
                continue
            margin = SIGMAS * est.std
            outside = est.value + margin < ps.low or est.value - margin > ps.high
            if outside:
                ps.outside_windows += 1
                if ps.since_s is None:
                    ps.since_s = t0_s
                if ps.outside_windows >= CONFIRM and ps.state != "alarm":
                    ps.state = "alarm"
                    new.append(est.name)
                elif ps.state != "alarm":
                    ps.state = "outside"
            else:
                if ps.state == "alarm":
                    cleared.append(est.name)
                ps.outside_windows = 0
                ps.since_s = None
                moved = abs(est.value - 1.0) > max(NOTE_FRACTION, SIGMAS * est.std)
                ps.state = "note" if moved else "ok"
            lines.append(f"{est.name} x{est.value:.3g} +-{est.std:.2g} ({ps.state}; "
                         f"range {ps.low:.3g}-{ps.high:.3g})")
        return WindowVerdict(tuple(new), tuple(cleared), tuple(lines))
