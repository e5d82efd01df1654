"""The compiled offline loop (`controller.sim.offline`) against the live loop's Python tick:
the same objects' scenario ticked in Python (`Trajectory.at`, `Ramp.step`, `ServoLoop.tick`,
`SimRig.step`, in the runtime's order) and through `run_ticks` must agree bit for bit: every
recorded signal and every state at the end. The scenario changes everything the runtime can
change between ticks: rig faults, friction changes, coefficient swaps (DOB on/off, Q type,
gains), new trajectories approached by the ramp, a saturating step."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pytest

from controller.core.command_filter import CommandFilter
from controller.core.config import LoopConfig
from controller.core.loop import LoopCoefficients, ServoLoop
from controller.core.ramp import Ramp
from controller.core.trajectory import Trajectory
from controller.sim.linear_rig import BacklashRig, LinearRig, PlantVariant
from controller.sim.offline import ROWS, OfflineRun, run_speed_ticks, run_ticks, supported
from controller.sim.rig_disturbances import ScheduledRig, build_rig, rig_setup
from controller.sim.sim_rig import RigFaults, SimRig

RATE_HZ = 1000.0
TS = 1.0 / RATE_HZ
N = 20_000
LIMIT = 12.0


@dataclass
class World:
    loop: ServoLoop
    rig: SimRig | ScheduledRig
    traj: Trajectory
    ramp: Ramp
    traj_k: int = 0
    log: list[str] = field(default_factory=list)

    @property
    def sim(self) -> SimRig:
        return self.rig.rig if isinstance(self.rig, ScheduledRig) else self.rig


def _world(cfg: LoopConfig) -> World:
    setup = rig_setup(["load-steps", "friction-change", "cogging", "sine-0.5hz"])
    rig = build_rig(setup, rate_hz=RATE_HZ, seed=5, initial_position_deg=30.0)
    w = World(ServoLoop(LoopCoefficients.build(cfg)), rig, Trajectory(), Ramp(TS))
    w.ramp.begin(rig.read()[0])  # Start: approach the sine from 30 deg
    return w


def _new_trajectory(traj: Trajectory) -> Callable[[World], None]:
    def go(w: World) -> None:  # as the runtime: trajectory time restarts, the ramp approaches
        w.traj, w.traj_k = traj, 0
        w.ramp.begin(w.rig.read()[0], w.loop.speed_ref_deg_s)

    return go


def _events(cfg: LoopConfig) -> dict[int, Callable[[World], None]]:
    q_other = "q20" if cfg.q_type == "q31" else "q31"
    return {
        2500: lambda w: w.sim.set_faults(RigFaults(plant_gain=0.7, extra_backlash_deg=0.05)),
        4000: lambda w: w.loop.request(LoopCoefficients.build(
            cfg.with_(dob_on=not cfg.dob_on), 1)),
        6000: lambda w: w.sim.add_resonance(25.0),
        7000: _new_trajectory(Trajectory(kind="step", amplitude_deg=40.0, step_time_s=0.5,
                                         offset_deg=10.0)),
        9500: lambda w: w.loop.request(LoopCoefficients.build(
            cfg.with_(dob_on=True, q_type=q_other, q_cutoff_hz=3.0, cv_kp=1.1), 2)),
        12000: lambda w: w.sim.clear_faults(),
        13000: _new_trajectory(Trajectory(kind="ramp", slope_deg_s=-3.0, offset_deg=20.0)),
        15500: lambda w: w.loop.request(LoopCoefficients.build(cfg, 3)),
        17000: _new_trajectory(Trajectory(kind="hold", offset_deg=0.0)),
    }


def _python_run(cfg: LoopConfig) -> tuple[World, np.ndarray, int]:
    w = _world(cfg)
    events = _events(cfg)
    out = np.empty((len(ROWS), N))
    ramp_ticks = 0
    for k in range(N):
        if k in events:
            events[k](w)
        ref, ref_rate = w.traj.at(w.traj_k * TS)
        w.traj_k += 1
        if w.ramp.active:
            ramp_ticks += 1
            ref = w.ramp.step(ref, ref_rate)
            ref_rate = w.ramp.speed_deg_s
        pos, speed = w.rig.read()
        u = w.loop.tick(ref, ref_rate, pos, speed)
        out[:, k] = (ref, pos, speed, w.loop.speed_ref_deg_s, u, w.loop.d_hat)
        w.rig.step(u)
    return w, out, ramp_ticks


def _compiled_run(cfg: LoopConfig) -> tuple[World, np.ndarray]:
    w = _world(cfg)
    events = _events(cfg)
    run = OfflineRun(np.empty((len(ROWS), N)))
    marks = [0, *sorted(events), N]
    for a, b in itertools.pairwise(marks):
        if a in events:
            events[a](w)
        run_ticks(w.loop, w.rig, w.traj, b - a, traj_tick=w.traj_k, approach=w.ramp,
                  out=run, at=a)
        w.traj_k += b - a
    return w, run.out


def _loop_state(loop: ServoLoop) -> list[float]:
    return [loop.pos_int, loop.e_pos_prev, loop.cv_int, loop.e_speed_prev, loop.u_prev,
            loop.w_prev, loop.d_hat, loop.speed_ref_deg_s, loop.speed_error_deg_s,
            *loop._f1s, *loop._f2s, *loop._cfs]


@pytest.mark.parametrize(
    "cfg",
    [
        LoopConfig(q_type="q31", command_limit_deg_s=LIMIT),
        LoopConfig(q_type="q20", q_cutoff_hz=2.0, command_limit_deg_s=LIMIT),
        LoopConfig(dob_on=False, ff_on=True, command_limit_deg_s=LIMIT),
        LoopConfig(q_type="q31", command_limit_deg_s=LIMIT,
                   command_filter=CommandFilter(kind="notch", notch_hz=31.0)),
        LoopConfig(dob_on=False, command_limit_deg_s=LIMIT,
                   command_filter=CommandFilter(kind="lowpass", lowpass_hz=80.0)),
    ],
    ids=["q31", "q20", "dob-off-ff", "q31-notch", "dob-off-lowpass"],
)
def test_compiled_loop_is_the_python_tick_bit_for_bit(cfg: LoopConfig) -> None:
    wp, ref, ramp_ticks = _python_run(cfg)
    wc, got = _compiled_run(cfg)
    for i, name in enumerate(ROWS):
        assert np.array_equal(got[i], ref[i]), f"{name}: first difference at tick " \
            f"{int(np.argmax(got[i] != ref[i]))}"
    assert _loop_state(wc.loop) == _loop_state(wp.loop)
    assert np.array_equal(wc.sim._x, wp.sim._x) and np.array_equal(wc.sim._p, wp.sim._p)
    assert wc.rig.read() == wp.rig.read() and wc.sim.time_s == wp.sim.time_s
    assert (wc.ramp.active, wc.ramp.pos_deg, wc.ramp.speed_deg_s) == (
        wp.ramp.active, wp.ramp.pos_deg, wp.ramp.speed_deg_s)
    # The scenario did exercise what it claims: approaches, saturation, the DOB on and off,
    # friction changed by the schedule.
    u, d_hat = ref[ROWS.index("command_deg_s")], ref[ROWS.index("d_hat_deg_s")]
    assert ramp_ticks > 1000
    assert np.count_nonzero(np.abs(u) == LIMIT) > 100
    dob_on_then_off = (d_hat[3000:4000], d_hat[5000:9000])
    on, off = dob_on_then_off if cfg.dob_on else dob_on_then_off[::-1]
    assert np.max(np.abs(on)) > 0.01 and np.all(off == 0.0)
    assert np.max(np.abs(d_hat[10000:15000])) > 0.01
    assert wp.sim.friction_n_m[0] > wp.sim.params.coulomb_torque_n_m  # x1.6 at 5 s


def test_a_later_step_continues_exactly() -> None:
    """The objects after `run_ticks` carry on in Python as if they had been ticked there (the
    noise stream across its 4096-sample blocks included)."""
    cfg = LoopConfig()
    traj = Trajectory()
    outs = []
    for compiled in (False, True):
        loop = ServoLoop(LoopCoefficients.build(cfg))
        rig = SimRig(seed=2)
        if compiled:
            run_ticks(loop, rig, traj, 5000)
        else:
            for k in range(5000):
                r, rr = traj.at(k * TS)
                p, w = rig.read()
                rig.step(loop.tick(r, rr, p, w))
        r, rr = traj.at(5000 * TS)
        p, w = rig.read()
        outs.append((loop.tick(r, rr, p, w), p, w))
    assert outs[0] == outs[1]


def test_what_it_runs() -> None:
    from controller.sim.position_dob import PositionDobLoop

    loop = ServoLoop(LoopCoefficients.build(LoopConfig()))
    assert supported(loop, SimRig())
    assert not supported(PositionDobLoop(LoopConfig()), SimRig())
    with pytest.raises(TypeError, match="PositionDobLoop"):
        run_ticks(PositionDobLoop(LoopConfig()), SimRig(), Trajectory(), 10)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="do not fit"):
        run_ticks(loop, SimRig(), Trajectory(), 10, out=OfflineRun(np.empty((len(ROWS), 5))))


def _python_speed_run(
    loop: ServoLoop, rig: BacklashRig | LinearRig, ref: np.ndarray
) -> np.ndarray:
    """As the paper's Figs. 8-9 ticked it before (`ServoLoop.tick_speed`, `BacklashRig.step`)."""
    w = np.empty(len(ref))
    for k in range(len(ref)):
        _, wk = rig.read()
        w[k] = wk
        if not abs(wk) < 1e6:
            w[k:] = np.nan
            break
        rig.step(loop.tick_speed(float(ref[k]), wk))
    return w


@pytest.mark.parametrize(
    ("cfg", "variant"),
    [
        (LoopConfig(), PlantVariant("1.4 Pn R", 1.4, 5.0, 0.05, 4.0, 0.05)),
        (LoopConfig(q_type="q20", q_cutoff_hz=4.0), PlantVariant("0.6 Pn R", 0.6, 5.0, 0.05,
                                                                   4.0, 0.05)),
        (LoopConfig(dob_on=False, command_limit_deg_s=9.0), PlantVariant("Pn")),
        (LoopConfig(cv_kp=40.0), PlantVariant("Pn")),  # kicked past 1e6 deg/s: the stop
    ],
    ids=["q31-1.4", "q20-0.6", "off-saturating", "runaway"],
)
@pytest.mark.parametrize("backlash", [True, False], ids=["backlash", "linear"])
def test_compiled_rate_loop_on_the_linear_rigs_bit_for_bit(
    cfg: LoopConfig, variant: PlantVariant, backlash: bool
) -> None:
    runaway = cfg.cv_kp == 40.0
    step = 5e6 if runaway else 5.0
    n = 2000
    ref = 10.0 * np.sin(2.0 * np.pi * 0.4 * np.arange(n) * TS)
    outs, worlds = [], []
    for compiled in (False, True):
        loop = ServoLoop(LoopCoefficients.build(cfg))
        def dist(t: float) -> float:
            return step if t >= 1.0 else 0.0

        rig: BacklashRig | LinearRig = (
            BacklashRig(variant, cfg.nominal, backlash_deg=0.05, speed_disturbance=dist)
            if backlash else LinearRig(variant, cfg.nominal, speed_disturbance=dist))
        outs.append(run_speed_ticks(loop, rig, ref) if compiled
                    else _python_speed_run(loop, rig, ref))
        worlds.append((loop, rig))
    assert np.array_equal(outs[0], outs[1], equal_nan=True)
    (lp, rp), (lc, rc) = worlds
    assert _loop_state(lc) == _loop_state(lp)
    assert rc.read() == rp.read() or not np.all(np.isfinite(outs[0]))
    if runaway:
        assert np.isnan(outs[0][-1]) and np.isfinite(outs[0][1000])
    else:
        assert np.all(np.isfinite(outs[0])) and np.max(np.abs(outs[0])) > 5.0


def test_torque_profiles_sampled_compiled_as_in_python() -> None:
    """Every profile class, alone and summed, sampled by the compiled loop's sampler equals
    `torque_n_m` at each tick's time; another class and a sum of sums (float addition is not
    associative) fall back to Python."""
    from controller.sim.disturbance import (
        NoDisturbance,
        SineTorque,
        StepsTorque,
        StepTorque,
        SumTorque,
        flatten,
    )
    from controller.sim.offline import _torques

    class Custom:
        def torque_n_m(self, time_s: float) -> float:
            return 0.3 * time_s

    sine = SineTorque(0.7, 1.3, phase_deg=33.0)
    steps = StepsTorque((0.5, 1.0, 2.5), (1.0, -2.0, 0.25))
    profiles = [sine, StepTorque(-0.5, 1.2), steps, NoDisturbance(),
                SumTorque((sine, steps, StepTorque(0.1, 0.0), NoDisturbance())),
                SumTorque(()), Custom(),
                SumTorque((sine, SumTorque((steps, StepTorque(0.1, 0.0))), NoDisturbance()))]
    for d in profiles:
        rig = SimRig(disturbance=d)  # type: ignore[arg-type]
        for _ in range(7):
            rig.step(0.0)
        ts = rig.period_s
        want = np.array([d.torque_n_m(k * ts) for k in range(7, 3007)], dtype=np.float64)
        nested = isinstance(d, SumTorque) and any(isinstance(p, SumTorque) for p in d.parts)
        assert (flatten(d) is None) == (isinstance(d, Custom) or nested)  # type: ignore[arg-type]
        got = _torques(rig, flatten(d), 3000)  # type: ignore[arg-type]
        assert np.array_equal(got, want), d
        zero = isinstance(d, NoDisturbance) or d == SumTorque(())
        assert np.count_nonzero(want) == 0 if zero else np.count_nonzero(want) > 1000
