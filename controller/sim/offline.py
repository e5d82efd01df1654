"""The compiled offline loop: the controller's own tick and the simulated rig, compiled
together with numba, for runs that need no clock (experiments, `dobtune paper`, the autotune,
Suggest, the gate's nonlinear check).

One definition of the arithmetic: the tick is `controller.core.loop.servo_law` (with
`speed_law` and the DOB filters' `controller.core.discrete.sos_step`), the reference
`controller.core.trajectory.trajectory_at` and `controller.core.ramp.ramp_step`, the rig
`controller.sim.sim_rig.advance_tick`: the plain-float functions the live `ServoLoop`,
`Trajectory` and `Ramp` call (and `SimRig` steps), compiled here into one loop
(`numba.extending.register_jitable` leaves the functions themselves as they are). The live
loop never imports this module. `run_ticks` takes its state from the Python objects and gives
it back: a run can be split anywhere, and between the pieces the Python objects do what the
runtime does between ticks (coefficient swaps, faults, friction changes, a new trajectory or a
ramp), with the same result bit for bit as ticking `ServoLoop` against `SimRig` in Python
(tests/test_offline.py).

The rig's inputs are sampled before each piece: the load torque profile at each tick's time
(compiled through `controller.sim.disturbance.flat_torque`, the profiles' own functions; a
profile of another class through its `torque_n_m`, as `SimRig.step` does) and the encoder
noise (taken from the rig's own stream, `SimRig.take_noise`).

Compiled once per machine and cached (numba `cache=True`, in `__pycache__`). numba checks only
the cached function's own file for changes; the kernel is therefore a closure over a digest
of every function it compiles in (bytecode, constants, the module values they read), which
numba's cache key includes: an edit of any of them compiles afresh.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from types import CodeType, FunctionType
from typing import Any

import numpy as np
from numba.extending import register_jitable

from controller.core import loop as loop_module
from controller.core import ramp, trajectory
from controller.core.arrays import FloatArray
from controller.core.loop import ServoLoop
from controller.core.numba_start import numba
from controller.core.ramp import Ramp
from controller.core.trajectory import KIND_CODE, Trajectory
from controller.sim import sim_rig
from controller.sim.disturbance import FlatProfile, flat_torque, flatten
from controller.sim.linear_rig import BacklashRig, LinearRig, backlash_period, linear_period
from controller.sim.rig_disturbances import ScheduledRig
from controller.sim.sim_rig import SimRig

__all__ = ["OfflineRun", "run_ref_ticks", "run_speed_ticks", "run_ticks", "supported"]


_servo_law = loop_module.servo_law
_speed_law = loop_module.speed_law
_trajectory_at = trajectory.trajectory_at
_ramp_step = ramp.ramp_step
_advance = sim_rig.advance_tick

# Loop state (st) and coefficient (co) arrays: the ServoLoop attributes, in this order.
_STATE = ("pos_int", "e_pos_prev", "cv_int", "e_speed_prev", "u_prev", "w_prev", "d_hat",
          "speed_ref_deg_s", "speed_error_deg_s")
_COEFFS = ("_pos_kp", "_pos_half", "_ff", "_cv_kp", "_cv_half", "_limit", "_dob_on")
#: The trajectory code of a recorded reference: the kernel reads it per tick.
RECORDED = -1
_NO_REF = np.empty(0)
#: Rows of the output array.
ROWS = ("ref_deg", "pos_deg", "speed_deg_s", "speed_ref_deg_s", "command_deg_s", "d_hat_deg_s")


def _compiled_in(roots: tuple[Callable[..., Any], ...]) -> str:
    """Make the plain functions the kernels call, transitively, callable from numba code
    (`register_jitable`: the functions themselves stay as they are); return a digest of all
    of them (their bytecode, constants and names) and of the plain values (numbers, strings,
    tuples) they read from their modules: what numba compiles into the kernels."""
    h = hashlib.sha256()
    seen: set[int] = set()
    todo: list[Any] = list(roots)
    while todo:
        g = todo.pop()
        f = getattr(g, "py_func", g)  # a numba function: its Python source
        if id(f) in seen:
            continue
        seen.add(id(f))
        if f is g:
            register_jitable(f)
        codes = [f.__code__]
        while codes:
            c = codes.pop()
            h.update(c.co_code)
            h.update(repr([k for k in c.co_consts if not isinstance(k, CodeType)]).encode())
            h.update(repr(c.co_names).encode())
            codes += [k for k in c.co_consts if isinstance(k, CodeType)]
            for name in c.co_names:
                v = f.__globals__.get(name)
                if isinstance(getattr(v, "py_func", v), FunctionType):
                    todo.append(v)
                elif isinstance(v, int | float | str | tuple):
                    h.update(f"{name}={v!r}".encode())
    return h.hexdigest()


def _make_kernel(digest: str) -> Callable[..., Any]:
    def kernel(
        x: FloatArray, p: FloatArray, noise: FloatArray, torque: FloatArray, tr: FloatArray,
        k0: int, rp: FloatArray, st: FloatArray, co: FloatArray, f1c: FloatArray,
        f1s: FloatArray, f2c: FloatArray, f2s: FloatArray, cfc: FloatArray, cfs: FloatArray,
        rd: FloatArray, out: FloatArray, j0: int, n: int, ref_in: FloatArray,
        rate_in: FloatArray,
    ) -> None:
        if len(digest) == 0:  # the digest only keys numba's cache
            raise ValueError("no source digest")
        kind = int(tr[0])  # RECORDED: the reference and its rate per tick from ref_in, rate_in
        amp, om, off, slope, t_step, period = tr[1], tr[2], tr[3], tr[4], tr[5], tr[6]
        ramp_on = rp[0] != 0.0
        ramp_pos, ramp_speed = rp[1], rp[2]
        ramp_period, ramp_vmax, ramp_amax = rp[3], rp[4], rp[5]
        pos_int, e_pos_prev, cv_int, e_speed_prev = st[0], st[1], st[2], st[3]
        u_prev, w_prev, d_hat, sref, serr = st[4], st[5], st[6], st[7], st[8]
        pos_kp, pos_half, ff, cv_kp, cv_half, limit = co[0], co[1], co[2], co[3], co[4], co[5]
        dob_on = co[6] != 0.0
        f1n = len(f1c) // 5
        f2n = len(f2c) // 5
        cfn = len(cfc) // 5
        pos, w = rd[0], rd[1]
        for i in range(n):
            if kind == RECORDED:
                ref, ref_rate = ref_in[i], rate_in[i]
            else:
                ref, ref_rate = _trajectory_at(kind, amp, om, off, slope, t_step,
                                               (k0 + i) * period)
            if ramp_on:
                ref, ramp_pos, ramp_speed, ramp_on = _ramp_step(
                    ramp_pos, ramp_speed, ref, ref_rate, ramp_period, ramp_vmax, ramp_amax)
                ref_rate = ramp_speed
            u, d_hat, sref, serr, pos_int, cv_int, e_pos_prev = _servo_law(
                ref, ref_rate, pos, w, pos_int, e_pos_prev, pos_kp, pos_half, ff, u_prev,
                cv_int, e_speed_prev, cv_kp, cv_half, limit, dob_on, f1c, f1s, f1n, f2c, f2s,
                f2n, cfc, cfs, cfn)
            e_speed_prev = serr
            u_prev = u
            w_prev = w
            j = j0 + i
            out[0, j] = ref
            out[1, j] = pos
            out[2, j] = w
            out[3, j] = sref
            out[4, j] = u
            out[5, j] = d_hat
            pos, w = _advance(x, p, u, torque[i], noise[i])
        rp[0] = 1.0 if ramp_on else 0.0
        rp[1] = ramp_pos
        rp[2] = ramp_speed
        st[0], st[1], st[2], st[3] = pos_int, e_pos_prev, cv_int, e_speed_prev
        st[4], st[5], st[6], st[7], st[8] = u_prev, w_prev, d_hat, sref, serr
        rd[0] = pos
        rd[1] = w

    return numba.njit(cache=True)(kernel)  # type: ignore[no-any-return]


def _make_speed_kernel(digest: str, period: Callable[..., float]) -> Callable[..., Any]:
    """The rate loop's kernel on a linear rig whose period is the plain function `period`."""

    def speed_kernel(
        ref: FloatArray, dist: FloatArray, st: FloatArray, co: FloatArray, f1c: FloatArray,
        f1s: FloatArray, f2c: FloatArray, f2s: FloatArray, cfc: FloatArray, cfs: FloatArray,
        rd: FloatArray, w_out: FloatArray, ts: float, args: Any,
    ) -> int:
        if len(digest) == 0:  # the digest only keys numba's cache
            raise ValueError("no source digest")
        cv_int, e_speed_prev = st[2], st[3]
        u_prev, w_prev, d_hat, sref, serr = st[4], st[5], st[6], st[7], st[8]
        cv_kp, cv_half, limit = co[3], co[4], co[5]
        dob_on = co[6] != 0.0
        f1n = len(f1c) // 5
        f2n = len(f2c) // 5
        cfn = len(cfc) // 5
        pos, w = rd[0], rd[1]
        done = len(ref)
        for k in range(len(ref)):
            w_out[k] = w
            if not abs(w) < 1e6:  # diverged
                done = k
                break
            r = ref[k]
            u, d_hat, cv_int, serr = _speed_law(
                r, w, u_prev, cv_int, e_speed_prev, cv_kp, cv_half, limit, dob_on, f1c, f1s,
                f1n, f2c, f2s, f2n, cfc, cfs, cfn)
            e_speed_prev = serr
            u_prev = u
            w_prev = w
            sref = r
            new_pos = period(u, dist[k], pos, args)
            w = (new_pos - pos) / ts
            pos = new_pos
        st[2], st[3] = cv_int, e_speed_prev
        st[4], st[5], st[6], st[7], st[8] = u_prev, w_prev, d_hat, sref, serr
        rd[0] = pos
        rd[1] = w
        return done

    return numba.njit(cache=True)(speed_kernel)  # type: ignore[no-any-return]


def _make_torque_sampler(digest: str) -> Callable[..., Any]:
    def sample_torques(
        kinds: Any, params: FloatArray, times_s: FloatArray, levels_n_m: FloatArray,
        summed: bool, k0: int, ts: float, out: FloatArray,
    ) -> None:
        if len(digest) == 0:  # the digest only keys numba's cache
            raise ValueError("no source digest")
        for i in range(len(out)):
            out[i] = flat_torque(kinds, params, times_s, levels_n_m, summed, (k0 + i) * ts)

    return numba.njit(cache=True)(sample_torques)  # type: ignore[no-any-return]


_DIGEST = _compiled_in((_servo_law, _speed_law, _trajectory_at, _ramp_step, _advance,
                        backlash_period, linear_period, flat_torque))
_kernel = _make_kernel(_DIGEST)
_sample_torques = _make_torque_sampler(_DIGEST)
_speed_kernels = {rig: _make_speed_kernel(_DIGEST, rig.period)
                  for rig in (BacklashRig, LinearRig)}


@dataclass
class OfflineRun:
    """The recorded signals of a run (one column per tick; `ROWS` names the rows)."""

    out: FloatArray

    @property
    def ref_deg(self) -> FloatArray:
        return self.out[0]

    @property
    def pos_deg(self) -> FloatArray:
        return self.out[1]

    @property
    def speed_deg_s(self) -> FloatArray:
        return self.out[2]

    @property
    def speed_ref_deg_s(self) -> FloatArray:
        return self.out[3]

    @property
    def command_deg_s(self) -> FloatArray:
        return self.out[4]

    @property
    def d_hat_deg_s(self) -> FloatArray:
        return self.out[5]


def _torques(rig: SimRig, profile: FlatProfile | None, n: int) -> FloatArray:
    """The load torque of the rig's next `n` steps: compiled for the profiles of
    `controller.sim.disturbance`, else the profile's own Python (`SimRig.torques`)."""
    if profile is None or rig.disturbance is None:
        return rig.torques(n)
    out = np.empty(n)
    _sample_torques(profile.kinds, profile.params, profile.times_s, profile.levels_n_m,
                    profile.summed, rig.tick, rig.period_s, out)
    return out


def _take_pending(loop: ServoLoop) -> None:
    """The coefficient swap `ServoLoop.tick` would make first."""
    pending = loop._pending
    if pending is not None:
        loop._pending = None
        loop._swap(pending)


def _loop_arrays(loop: ServoLoop) -> tuple[FloatArray, ...]:
    """The loop's state, coefficients, DOB filters and command filter as the kernels take
    them (the command filter's arrays are empty when it is off)."""
    st = np.array([getattr(loop, a) for a in _STATE], dtype=np.float64)
    co = np.array([getattr(loop, a) for a in _COEFFS], dtype=np.float64)
    return (st, co, np.array(loop._f1c), np.array(loop._f1s), np.array(loop._f2c),
            np.array(loop._f2s), np.array(loop._cfc, dtype=np.float64),
            np.array(loop._cfs, dtype=np.float64))


def _loop_back(loop: ServoLoop, st: FloatArray, f1s: FloatArray, f2s: FloatArray,
               cfs: FloatArray) -> None:
    """The kernels' final state back into the loop."""
    for a, v in zip(_STATE, st.tolist(), strict=True):
        setattr(loop, a, v)
    loop._f1s[:] = f1s.tolist()
    loop._f2s[:] = f2s.tolist()
    loop._cfs[:] = cfs.tolist()


def run_speed_ticks(
    loop: ServoLoop, rig: BacklashRig | LinearRig, ref_deg_s: FloatArray
) -> FloatArray:
    """The rate loop alone on a linear rig (with or without backlash), as the paper's
    Figs. 8-9 tick it:
    per tick the rig's rate w is recorded, then `loop.tick_speed(ref[k], w)` and `rig.step`.
    Stops when |w| reaches 1e6 deg/s (diverged): the rest of the record is NaN. The objects'
    states are taken and given back."""
    kernel = _speed_kernels.get(type(rig))
    if type(loop) is not ServoLoop or kernel is None:
        raise TypeError(f"run_speed_ticks: needs ServoLoop and a linear rig, got "
                        f"{type(loop).__name__} and {type(rig).__name__}")
    ref = np.ascontiguousarray(ref_deg_s, dtype=np.float64)
    n = len(ref)
    w_out = np.full(n, math.nan)
    if n == 0:
        return w_out
    _take_pending(loop)
    st, co, f1c, f1s, f2c, f2s, cfc, cfs = _loop_arrays(loop)
    rd = np.array(rig.read())
    dist = rig.disturbances(n)
    done = kernel(ref, dist, st, co, f1c, f1s, f2c, f2s, cfc, cfs, rd, w_out, rig.period_s,
                  rig.args)
    rig.advanced(done, float(rd[0]), float(rd[1]))
    _loop_back(loop, st, f1s, f2s, cfs)
    if done < n:
        w_out[done:] = math.nan
    return w_out


def supported(loop: object, rig: object) -> bool:
    """Whether `run_ticks` can run this pair (the runtime's `ServoLoop` itself, not a variant;
    the simulated rig, with or without scheduled friction changes)."""
    return type(loop) is ServoLoop and type(rig) in (SimRig, ScheduledRig)


def run_ticks(
    loop: ServoLoop,
    rig: SimRig | ScheduledRig,
    traj: Trajectory,
    n: int,
    *,
    traj_tick: int = 0,
    approach: Ramp | None = None,
    out: OfflineRun | None = None,
    at: int = 0,
    period_s: float | None = None,
) -> OfflineRun:
    """Run `n` ticks as the runtime does with the clock taken away: per tick the reference is
    `traj` at (traj_tick + i) x `period_s` (default: the loop's period), through `approach`
    while it is active, then `loop.tick` on the rig's reading, then `rig.step` with the
    command. The objects' states are taken and given back (they continue exactly as if they
    had been ticked); a pending coefficient swap is taken at the first tick, as
    `ServoLoop.tick` does. Records into `out` (a new one with n columns if None) from column
    `at` on."""
    if not supported(loop, rig):
        raise TypeError(f"run_ticks: needs ServoLoop and SimRig, got {type(loop).__name__} "
                        f"and {type(rig).__name__}")
    if out is None:
        out = OfflineRun(np.empty((len(ROWS), n)))
    if n < 0 or at < 0 or at + n > out.out.shape[1]:
        raise ValueError(f"run_ticks: {n} ticks from column {at} do not fit the output")
    if n > 0:
        _take_pending(loop)
    period = loop.active.config.period_s if period_s is None else period_s
    tr = np.array([KIND_CODE[traj.kind], traj.amplitude_deg, traj.omega_rad_s, traj.offset_deg,
                   traj.slope_deg_s, traj.step_time_s, period])
    if approach is not None:
        rp = np.array([float(approach.active), approach.pos_deg, approach.speed_deg_s,
                       approach.period_s, approach.speed_max_deg_s, approach.accel_max_deg_s2])
    else:
        rp = np.zeros(6)
    st, co, f1c, f1s, f2c, f2s, cfc, cfs = _loop_arrays(loop)
    sim = rig.rig if isinstance(rig, ScheduledRig) else rig
    d = sim.disturbance
    profile = None if d is None else flatten(d)
    done = 0
    while done < n:
        # A ScheduledRig's friction changes fall between pieces, exactly where its step
        # would make them.
        m = n - done
        base = rig
        if isinstance(rig, ScheduledRig):
            rig.apply_due()
            nxt = rig.next_event_tick()
            if nxt is not None:
                m = min(m, nxt - rig.tick)
            base = rig.rig
        assert isinstance(base, SimRig)
        torque = _torques(base, profile, m)
        noise = base.take_noise(m)
        rd = np.array(base.read())
        _kernel(base._x, base._p, noise, torque, tr, traj_tick + done, rp, st, co, f1c, f1s,
                f2c, f2s, cfc, cfs, rd, out.out, at + done, m, _NO_REF, _NO_REF)
        base.advanced(m, float(rd[0]), float(rd[1]))
        if isinstance(rig, ScheduledRig):
            rig.tick += m
        done += m
    _loop_back(loop, st, f1s, f2s, cfs)
    if approach is not None:
        approach.active = bool(rp[0] != 0.0)
        approach.pos_deg = float(rp[1])
        approach.speed_deg_s = float(rp[2])
    return out


def run_ref_ticks(loop: ServoLoop, rig: SimRig, ref_deg: FloatArray,
                  ref_rate_deg_s: FloatArray) -> OfflineRun:
    """`run_ticks` on a given reference: per tick k `loop.tick(ref_deg[k], ref_rate_deg_s[k],
    *rig.read())`, then `rig.step` with the command (its load torque profile and noise
    sampled as `run_ticks` does); the same result bit for bit as that Python loop. The
    objects' states are taken and given back."""
    if type(loop) is not ServoLoop or type(rig) is not SimRig:
        raise TypeError(f"run_ref_ticks: needs ServoLoop and SimRig, got {type(loop).__name__} "
                        f"and {type(rig).__name__}")
    ref = np.ascontiguousarray(ref_deg, dtype=np.float64)
    rate = np.ascontiguousarray(ref_rate_deg_s, dtype=np.float64)
    if ref.ndim != 1 or rate.shape != ref.shape:
        raise ValueError(f"run_ref_ticks: reference {ref.shape} and rate {rate.shape} differ")
    n = ref.size
    out = OfflineRun(np.empty((len(ROWS), n)))
    if n == 0:
        return out
    _take_pending(loop)
    st, co, f1c, f1s, f2c, f2s, cfc, cfs = _loop_arrays(loop)
    d = rig.disturbance
    torque = _torques(rig, None if d is None else flatten(d), n)
    noise = rig.take_noise(n)
    rd = np.array(rig.read())
    tr = np.array([float(RECORDED), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    _kernel(rig._x, rig._p, noise, torque, tr, 0, np.zeros(6), st, co, f1c, f1s, f2c, f2s, cfc,
            cfs, rd, out.out, 0, n, ref, rate)
    rig.advanced(n, float(rd[0]), float(rd[1]))
    _loop_back(loop, st, f1s, f2s, cfs)
    return out
