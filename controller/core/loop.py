"""The three-loop servo tick: position loop -> speed loop Cv -> rate-difference DOB.

Per tick (plain float arithmetic on preallocated state, no allocation, no I/O):

    e_pos = theta_ref - theta
    r     = Cp(e_pos) + ff_gain * dtheta_ref/dt          (feedforward only when ff_on)
    e     = r - w
    v     = N(Cv(e))                                     N: the command filter, when on
    d_hat = F1(z) w[k] - F2(z) u[k-1]                    (0 when the DOB is off)
    u     = sat(v - d_hat, +-command_limit_deg_s)         the DOB sees this saturated u

Cp and Cv are PI controllers discretised by Tustin (trapezoidal integration); their integrators
stop integrating while the command is saturated in the direction they push (anti-windup by
conditional integration). New coefficients are designed off the tick (`LoopCoefficients.build`)
and prepared off the tick (`PreparedCoefficients`: the tick's scalars and fresh filter objects,
made in the requesting thread); the swap at the next tick boundary only takes the prepared
objects and re-initialises the new DOB states from the present d_hat and speed (a few float
operations per filter section), so that d_hat and u do not jump (bumpless transfer).

The arithmetic is in two plain-float functions, `servo_law` (the whole tick) and `speed_law`
(Cv and the DOB, the position loop open); `ServoLoop` keeps the state and calls them. The
compiled offline loop (`controller.sim.offline`) compiles these same functions with numba, and
is tested bit for bit against `ServoLoop` (tests/test_offline.py).
"""

from __future__ import annotations

from dataclasses import dataclass

from controller.core.command_filter import command_filter_sos
from controller.core.config import LoopConfig
from controller.core.discrete import SosCoefficients, SosFilter, SosStates, sos_step
from controller.core.dob import DobDesign, design_dob

# -- the tick's arithmetic: plain-float functions (no state of their own, no allocation
# beyond the returned tuple) that `ServoLoop` calls per tick and that the compiled offline
# loop (`controller.sim.offline`) compiles with numba: one definition for both.


def speed_law(
    r: float,
    w: float,
    u_prev: float,
    cv_int: float,
    e_speed_prev: float,
    cv_kp: float,
    cv_half: float,
    limit: float,
    dob_on: bool,
    f1c: SosCoefficients,
    f1s: SosStates,
    f1n: int,
    f2c: SosCoefficients,
    f2s: SosStates,
    f2n: int,
    cfc: SosCoefficients,
    cfs: SosStates,
    cfn: int,
) -> tuple[float, float, float, float]:
    """Cv and the DOB for one period: (u, d_hat, new cv_int, speed error e). The DOB filters'
    states (f1s, f2s) are updated in place; u is saturated at +-limit, and Cv's integrator
    does not integrate further into a saturated command. Cv's output goes through the
    command filter's `cfn` sections (cfc, cfs; none when the filter is off)."""
    e = r - w
    cv_int_new = cv_int + cv_half * (e + e_speed_prev)
    v = cv_kp * e + cv_int_new
    if cfn > 0:
        v = sos_step(cfc, cfs, cfn, v)
    if dob_on:
        d_hat = sos_step(f1c, f1s, f1n, w) - sos_step(f2c, f2s, f2n, u_prev)
    else:
        d_hat = 0.0
    u = v - d_hat
    if u > limit:
        u = limit
        if cv_int_new > cv_int:
            cv_int_new = cv_int
    elif u < -limit:
        u = -limit
        if cv_int_new < cv_int:
            cv_int_new = cv_int
    return u, d_hat, cv_int_new, e


def servo_law(
    ref_deg: float,
    ref_rate_deg_s: float,
    pos_deg: float,
    speed_deg_s: float,
    pos_int: float,
    e_pos_prev: float,
    pos_kp: float,
    pos_half: float,
    ff: float,
    u_prev: float,
    cv_int: float,
    e_speed_prev: float,
    cv_kp: float,
    cv_half: float,
    limit: float,
    dob_on: bool,
    f1c: SosCoefficients,
    f1s: SosStates,
    f1n: int,
    f2c: SosCoefficients,
    f2s: SosStates,
    f2n: int,
    cfc: SosCoefficients,
    cfs: SosStates,
    cfn: int,
) -> tuple[float, float, float, float, float, float, float]:
    """The whole servo for one period (position PI with feedforward, then `speed_law`):
    (u, d_hat, speed reference r, speed error e, new pos_int, new cv_int, position error)."""
    e_pos = ref_deg - pos_deg
    pos_int_new = pos_int + pos_half * (e_pos + e_pos_prev)
    r = pos_kp * e_pos + pos_int_new + ff * ref_rate_deg_s
    u, d_hat, cv_int_new, e = speed_law(
        r, speed_deg_s, u_prev, cv_int, e_speed_prev, cv_kp, cv_half, limit, dob_on,
        f1c, f1s, f1n, f2c, f2s, f2n, cfc, cfs, cfn,
    )
    # Anti-windup: no integration further into a saturated command.
    if (u >= limit and pos_int_new > pos_int) or (u <= -limit and pos_int_new < pos_int):
        pos_int_new = pos_int
    return u, d_hat, r, e, pos_int_new, cv_int_new, e_pos


@dataclass(frozen=True)
class LoopCoefficients:
    """A validated configuration and the filters built from it, ready to swap in."""

    config: LoopConfig
    version: int
    dob: DobDesign

    @staticmethod
    def build(config: LoopConfig, version: int = 0) -> LoopCoefficients:
        return LoopCoefficients(config=config, version=version, dob=design_dob(config))


def tick_gains(c: LoopConfig) -> tuple[float, float, float, float, float, float]:
    """The tick's scalars of a configuration: (pos_kp, pos_half, cv_kp, cv_half, ff, limit).

    `*_half` is kp * ki * Ts / 2, the trapezoidal (Tustin) integrator's step on the sum of this
    and the previous error; ff is 0 while the feedforward is off; limit is the command limit.
    """
    ts = c.period_s
    return (
        c.pos_kp_per_s,
        c.pos_kp_per_s * c.pos_ki_per_s * ts * 0.5,
        c.cv_kp,
        c.cv_kp * c.cv_ki_per_s * ts * 0.5,
        c.ff_gain if c.ff_on else 0.0,
        c.command_limit_deg_s,
    )


class PreparedCoefficients:
    """`LoopCoefficients` in the form the tick uses: scalar gains and new filter objects.

    Built off the tick (in the thread that requests the swap); the swap only takes these
    objects over. Single use: the loop that swaps it in owns its filters.
    """

    __slots__ = (
        "cf",
        "coefficients",
        "cv_half",
        "cv_kp",
        "dob_on",
        "f1",
        "f2",
        "f2_dc_gain",
        "ff",
        "limit",
        "pos_half",
        "pos_kp",
    )

    def __init__(self, coefficients: LoopCoefficients) -> None:
        c = coefficients.config
        self.coefficients = coefficients
        self.pos_kp, self.pos_half, self.cv_kp, self.cv_half, self.ff, self.limit = tick_gains(c)
        self.dob_on = c.dob_on
        self.f1 = SosFilter(coefficients.dob.f1_sos)
        self.f2 = SosFilter(coefficients.dob.f2_sos)
        self.f2_dc_gain = self.f2.dc_gain()
        # The command filter: no sections when off (the tick then skips it).
        self.cf = SosFilter(command_filter_sos(c.command_filter, c.rate_hz))


class ServoLoop:
    """The controller state; `tick` is the hot path, `request` swaps coefficients (any thread)."""

    __slots__ = (
        "_cf",
        "_cfc",
        "_cfn",
        "_cfs",
        "_cv_half",
        "_cv_kp",
        "_dob_on",
        "_f1",
        "_f1c",
        "_f1n",
        "_f1s",
        "_f2",
        "_f2c",
        "_f2n",
        "_f2s",
        "_ff",
        "_limit",
        "_pending",
        "_pos_half",
        "_pos_kp",
        "active",
        "cv_int",
        "d_hat",
        "e_pos_prev",
        "e_speed_prev",
        "pos_int",
        "speed_error_deg_s",
        "speed_ref_deg_s",
        "u_prev",
        "w_prev",
    )

    def __init__(self, coefficients: LoopCoefficients) -> None:
        self._pending: PreparedCoefficients | None = None
        self.speed_ref_deg_s = self.speed_error_deg_s = 0.0
        self._take(PreparedCoefficients(coefficients))
        self.reset()

    def reset(self) -> None:
        """Zero every state (e.g. after a fault, before re-enabling the drive)."""
        self.u_prev = self.w_prev = self.d_hat = 0.0
        self.pos_int = self.cv_int = self.e_pos_prev = self.e_speed_prev = 0.0
        self._f1.set_steady(0.0)
        self._f2.set_steady(0.0)
        self._cf.set_steady(0.0)

    # -- coefficient handling (off the hot path except the swap at the tick boundary) --------

    def _take(self, p: PreparedCoefficients) -> None:
        """Take over prepared coefficients: assignments only."""
        self.active = p.coefficients
        self._pos_kp = p.pos_kp
        self._pos_half = p.pos_half
        self._cv_kp = p.cv_kp
        self._cv_half = p.cv_half
        self._ff = p.ff
        self._limit = p.limit
        self._dob_on = p.dob_on
        self._f1 = p.f1
        self._f2 = p.f2
        self._f1c, self._f1s, self._f1n = p.f1.coefficients, p.f1.states, p.f1.n_sections
        self._f2c, self._f2s, self._f2n = p.f2.coefficients, p.f2.states, p.f2.n_sections
        self._cf = p.cf
        self._cfc, self._cfs, self._cfn = p.cf.coefficients, p.cf.states, p.cf.n_sections

    def request(self, coefficients: LoopCoefficients | PreparedCoefficients) -> None:
        """Ask for `coefficients` to take effect at the next tick boundary (thread-safe).
        Plain coefficients are prepared here, in the caller's thread."""
        if isinstance(coefficients, LoopCoefficients):
            coefficients = PreparedCoefficients(coefficients)
        self._pending = coefficients

    def _swap(self, p: PreparedCoefficients) -> None:
        old_pos_kp, old_cv_kp, old_dob_on = self._pos_kp, self._cv_kp, self._dob_on
        d_hat = self.d_hat if old_dob_on else 0.0
        self._take(p)
        # Proportional-gain changes: move the difference into the integrators so that the
        # controller outputs are continuous for the error they last saw.
        self.pos_int += (old_pos_kp - p.pos_kp) * self.e_pos_prev
        self.cv_int += (old_cv_kp - p.cv_kp) * self.e_speed_prev
        # A new command filter starts in the steady state for Cv's present output (unity DC
        # gain: the filtered command does not jump).
        p.cf.set_steady(p.cv_kp * self.e_speed_prev + self.cv_int)
        if p.dob_on:
            # New DOB filters start in the steady state that reproduces the present estimate:
            # F1 as if w had been constant, F2 with the constant input that gives d_hat.
            f1_out = p.f1.set_steady(self.w_prev)
            p.f2.set_steady((f1_out - d_hat) / p.f2_dc_gain)
            self.d_hat = d_hat
        else:
            # DOB switched off: its last correction moves into the speed integrator.
            self.cv_int -= d_hat
            self.d_hat = 0.0

    # -- the hot path --------------------------------------------------------------------------

    def tick(
        self, ref_deg: float, ref_rate_deg_s: float, pos_deg: float, speed_deg_s: float
    ) -> float:
        """One control period; returns the (saturated) load-side speed command in deg/s."""
        pending = self._pending
        if pending is not None:
            self._pending = None
            self._swap(pending)

        u, d_hat, r, e, pos_int, cv_int, e_pos = servo_law(
            ref_deg, ref_rate_deg_s, pos_deg, speed_deg_s, self.pos_int, self.e_pos_prev,
            self._pos_kp, self._pos_half, self._ff, self.u_prev, self.cv_int,
            self.e_speed_prev, self._cv_kp, self._cv_half, self._limit, self._dob_on,
            self._f1c, self._f1s, self._f1n, self._f2c, self._f2s, self._f2n,
            self._cfc, self._cfs, self._cfn,
        )
        self.pos_int = pos_int
        self.e_pos_prev = e_pos
        self.cv_int = cv_int
        self.e_speed_prev = e
        self.w_prev = speed_deg_s
        self.u_prev = u
        self.d_hat = d_hat
        self.speed_ref_deg_s = r
        self.speed_error_deg_s = e
        return u

    def tick_speed(self, speed_ref_deg_s: float, speed_deg_s: float) -> float:
        """One period with the position loop open: Cv + DOB track `speed_ref_deg_s` (used for
        frequency-response measurement in closed loop and to check eqs. 15-18)."""
        pending = self._pending
        if pending is not None:
            self._pending = None
            self._swap(pending)
        return self._speed(speed_ref_deg_s, speed_deg_s)

    def _speed(self, r: float, speed_deg_s: float) -> float:
        u, d_hat, cv_int, e = speed_law(
            r, speed_deg_s, self.u_prev, self.cv_int, self.e_speed_prev, self._cv_kp,
            self._cv_half, self._limit, self._dob_on,
            self._f1c, self._f1s, self._f1n, self._f2c, self._f2s, self._f2n,
            self._cfc, self._cfs, self._cfn,
        )
        self.cv_int = cv_int
        self.e_speed_prev = e
        self.w_prev = speed_deg_s
        self.u_prev = u
        self.d_hat = d_hat
        self.speed_ref_deg_s = r
        self.speed_error_deg_s = e
        return u
