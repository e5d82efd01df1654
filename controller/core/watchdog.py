"""The loop watchdog: detectors the tick runs once per period, pure and allocation-free.

Three faults, each a reason to roll back to the previous configuration:

* Oscillation of the speed command u. u goes through a band-pass (2nd-order Butterworth,
  `band_low_hz`..`band_high_hz`, by default 4-150 Hz: from the speed loop's crossover, 4.5 Hz,
  past its phase crossover, 18 Hz, up to where measurement noise takes over); the band's mean
  square through two cascaded first-order lags (`envelope_time_s` each) is the envelope. The
  band-pass removes what the trajectory asks for (tenths of a Hz here; a step is the exception,
  below) and the lags the ripple of a squared sine. Sampled every `window_s`, it trips
  (a) when the band RMS has stayed above `oscillation_rms_deg_s` for `oscillation_duration_s`
      and is not falling by `decay_ratio` per window (a large step fills the band far above
      the threshold for ~0.5 s, but dies out: that is not an oscillation);
  (b) when the band RMS has grown by `growth_ratio` or more in each of the last
      `growth_windows` windows and is above `growth_floor_rms_deg_s`: an instability caught
      while still growing, before it saturates (a transient rises for at most 2-3 windows);
  and in both cases only if the band-passed u crossed zero at least 4 times since its RMS rose
  above half the lower threshold (a command that drifts, e.g. integrators winding up against
  a dead axis, is left to the two detectors below). The thresholds are absolute levels in
  deg/s, not ratios to a long-term level: a loop that had oscillated for a while would raise
  its own reference and stop tripping. On the simulated rig the stiction limit cycle at
  standstill (control.md item 5; ~2 Hz, mostly below the band) peaks at 0.83 deg/s RMS in the
  band and the article's runs at 1.33 (the feedforward sine's start). The frequency reported
  is the zero-crossing rate of the band-passed u over that same stretch.
* Sustained saturation: |u| at the command limit for `saturation_duration_s`.
* Tracking: |position error| above `error_limit_deg` for `error_duration_s`. A step saturates
  the command for about step / limit seconds and keeps the error above the limit a little
  longer: with the defaults (100 deg/s), steps up to ~95 deg pass, larger ones trip.

`Watchdog.step(u, e)` returns 0, or a trip code (`TripCode`) that stays latched until `reset()`;
`Watchdog.trip` then describes it (built only when it trips).
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import Annotated

import msgspec

from controller.core.errors import ConfigError
from controller.core.lti import butter_sos
from controller.core.validate import check_fields, number, positive, within

__all__ = ["TripCode", "Watchdog", "WatchdogLimits", "WatchdogTrip"]


class TripCode(IntEnum):
    NONE = 0
    OSCILLATION = 1
    GROWING_OSCILLATION = 2
    SATURATION = 3
    TRACKING_ERROR = 4


def _windows(value: object, field: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 1000:
        raise ConfigError(field, f"must be an int in 1..1000, got {value!r}")
    return value


class WatchdogLimits(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Thresholds of the watchdog's detectors (units in the names); validated on construction."""

    band_low_hz: Annotated[float, positive] = 4.0
    """Lower edge of the band where the command's oscillation energy is measured."""
    band_high_hz: Annotated[float, positive] = 150.0
    """Upper edge of that band (below the loop's Nyquist frequency)."""
    envelope_time_s: Annotated[float, positive] = 0.05
    """Time constant of each of the two lags smoothing the band's mean square."""
    oscillation_rms_deg_s: Annotated[float, positive] = 2.0
    """Band RMS of the speed command above which the loop counts as oscillating."""
    oscillation_duration_s: Annotated[float, positive] = 1.0
    """How long the oscillation must last to trip..."""
    decay_ratio: Annotated[float, within(1.0, 100.0, lo_open=True)] = 1.12
    """...unless its band RMS is falling by this factor per `window_s` or faster (a transient
    dying out, e.g. after a large step)."""
    growth_floor_rms_deg_s: Annotated[float, positive] = 1.5
    """A growing envelope trips only above this band RMS."""
    growth_ratio: Annotated[float, within(1.0, 100.0, lo_open=True)] = 1.25
    """Minimum growth of the band RMS per window..."""
    window_s: Annotated[float, positive] = 0.05
    """...sampled every this long (the growth and decay tests)..."""
    growth_windows: Annotated[int, _windows] = 4
    """...in this many windows in a row."""
    saturation_duration_s: Annotated[float, positive] = 1.0
    """|u| at the command limit this long trips."""
    error_limit_deg: Annotated[float, positive] = 2.0
    """|theta_ref - theta| above this..."""
    error_duration_s: Annotated[float, positive] = 1.0
    """...this long trips."""

    def __post_init__(self) -> None:
        check_fields(self)
        if not self.band_low_hz < self.band_high_hz:
            raise ConfigError(
                "band_high_hz",
                f"must be above band_low_hz ({self.band_low_hz}), got {self.band_high_hz}",
            )


class WatchdogTrip(msgspec.Struct, frozen=True, kw_only=True):
    """Why and when the watchdog tripped, with the figures it saw."""

    code: int
    """A `TripCode` value."""
    kind: str
    """"oscillation", "growing oscillation", "saturation" or "tracking error"."""
    reason: str
    """One line for people, with the figures below."""
    tick: int
    """Ticks since the last reset, counting the tripping one (1 = the first tick)."""
    time_s: float
    """The same in seconds."""
    duration_s: float
    """How long the condition had lasted."""
    frequency_hz: float | None
    """Oscillation frequency (zero crossings of the band-passed command); None if not one."""
    command_amplitude_deg_s: float
    """Oscillation: amplitude (sqrt 2 x band RMS) of the command; otherwise |u| at the trip."""
    error_deg: float
    """|position error| at the trip."""


#: An oscillation crosses zero: fewer crossings of the band-passed command since its RMS rose
#: above half the lower of the two thresholds is a drift, not an oscillation.
_MIN_CROSSINGS = 4

_KIND = {
    TripCode.OSCILLATION: "oscillation",
    TripCode.GROWING_OSCILLATION: "growing oscillation",
    TripCode.SATURATION: "saturation",
    TripCode.TRACKING_ERROR: "tracking error",
}


def _biquad_steady(c: tuple[float, float, float, float, float], x: float) -> tuple[float, ...]:
    """(s1, s2, y) of a transposed-direct-form-II section held at a constant input x."""
    b0, b1, b2, a1, a2 = c
    y = x * (b0 + b1 + b2) / (1.0 + a1 + a2)
    return y - b0 * x, b2 * x - a2 * y, y


class Watchdog:
    """Per-tick detectors; `step` is the hot path (plain floats, no allocation until a trip).

    `command_limit_deg_s` must follow the active configuration's limit (a plain attribute:
    assign it when a configuration is swapped in).
    """

    trip: WatchdogTrip | None
    """What tripped (None until a trip)."""

    __slots__ = (
        "_c1",
        "_c2",
        "_crossings",
        "_decay_sq",
        "_episode",
        "_episode_ms",
        "_episode_start",
        "_err_lim",
        "_err_n",
        "_err_ticks",
        "_floor_ms",
        "_grow_n",
        "_grow_need",
        "_k_env",
        "_m1",
        "_m2",
        "_m_prev",
        "_osc_ms",
        "_osc_n",
        "_osc_ticks",
        "_positive",
        "_ratio_sq",
        "_s1",
        "_s2",
        "_s3",
        "_s4",
        "_sat_n",
        "_sat_ticks",
        "_tick",
        "_win_i",
        "_win_n",
        "code",
        "command_limit_deg_s",
        "limits",
        "rate_hz",
        "trip",
    )

    def __init__(
        self,
        limits: WatchdogLimits | None = None,
        *,
        rate_hz: float = 1000.0,
        command_limit_deg_s: float = 100.0,
    ) -> None:
        lim = WatchdogLimits() if limits is None else limits
        if not isinstance(lim, WatchdogLimits):
            raise ConfigError("limits", f"must be WatchdogLimits, got {type(lim).__name__}")
        rate = positive(rate_hz, "rate_hz")
        positive(command_limit_deg_s, "command_limit_deg_s")
        if not lim.band_high_hz < rate / 2.0:
            raise ConfigError(
                "band_high_hz", f"{lim.band_high_hz} Hz is not below the Nyquist limit {rate / 2}"
            )
        self.limits = lim
        self.rate_hz = rate
        self.command_limit_deg_s = float(command_limit_deg_s)
        sos = butter_sos(2, (lim.band_low_hz, lim.band_high_hz), "bandpass", rate)
        self._c1, self._c2 = (
            (float(b0), float(b1), float(b2), float(a1), float(a2))
            for b0, b1, b2, _a0, a1, a2 in sos
        )
        self._k_env = -math.expm1(-1.0 / (rate * lim.envelope_time_s))
        self._osc_ms = lim.oscillation_rms_deg_s**2
        self._floor_ms = lim.growth_floor_rms_deg_s**2
        self._episode_ms = 0.25 * min(self._osc_ms, self._floor_ms)
        self._ratio_sq = lim.growth_ratio**2
        self._decay_sq = lim.decay_ratio**2
        self._osc_ticks = max(1, round(lim.oscillation_duration_s * rate))
        self._win_n = max(1, round(lim.window_s * rate))
        self._grow_need = lim.growth_windows
        self._sat_ticks = max(1, round(lim.saturation_duration_s * rate))
        self._err_ticks = max(1, round(lim.error_duration_s * rate))
        self._err_lim = lim.error_limit_deg
        self.reset()

    def reset(self, command_deg_s: float = 0.0) -> None:
        """Clear every detector and the trip (after a rollback); the band-pass starts as if the
        command had been `command_deg_s` forever (no start-up transient)."""
        self._s1, self._s2, y = _biquad_steady(self._c1, number(command_deg_s, "command_deg_s"))
        self._s3, self._s4, _ = _biquad_steady(self._c2, y)
        self._m1 = self._m2 = self._m_prev = 0.0
        self._positive = False
        self._crossings = 0
        self._episode = False
        self._episode_start = 0
        self._osc_n = self._grow_n = self._sat_n = self._err_n = 0
        self._win_i = self._win_n
        self._tick = 0
        self.code = 0
        self.trip = None

    # -- the hot path ----------------------------------------------------------------------

    def step(self, command_deg_s: float, error_deg: float) -> int:
        """One tick: the command sent (after saturation) and the position error (deg).
        Returns 0, or the latched trip code."""
        if self.code:
            return self.code
        tick = self._tick + 1
        self._tick = tick
        b0, b1, b2, a1, a2 = self._c1
        y = b0 * command_deg_s + self._s1
        self._s1 = b1 * command_deg_s - a1 * y + self._s2
        self._s2 = b2 * command_deg_s - a2 * y
        b0, b1, b2, a1, a2 = self._c2
        x = y
        y = b0 * x + self._s3
        self._s3 = b1 * x - a1 * y + self._s4
        self._s4 = b2 * x - a2 * y
        k = self._k_env
        m1 = self._m1
        m1 += k * (y * y - m1)
        m2 = self._m2
        m2 += k * (m1 - m2)
        self._m1 = m1
        self._m2 = m2

        # Zero crossings, counted only while the band holds more than noise (an episode).
        if m2 > self._episode_ms:
            if not self._episode:
                self._episode = True
                self._episode_start = tick
                self._crossings = 0
                self._positive = y > 0.0
            elif (y > 0.0) is not self._positive:
                self._positive = y > 0.0
                self._crossings += 1
        elif self._episode:
            self._episode = False
        if m2 > self._osc_ms:
            self._osc_n += 1
        else:
            self._osc_n = 0
        self._win_i -= 1
        if self._win_i == 0:
            self._win_i = self._win_n
            m_prev = self._m_prev
            self._m_prev = m2
            if m2 > self._ratio_sq * m_prev and m_prev > 0.0:
                self._grow_n += 1
            else:
                self._grow_n = 0
            if self._crossings >= _MIN_CROSSINGS:
                if self._grow_n >= self._grow_need and m2 > self._floor_ms:
                    n = self._grow_n * self._win_n
                    return self._trip(TripCode.GROWING_OSCILLATION, n, command_deg_s, error_deg)
                if self._osc_n >= self._osc_ticks and m2 * self._decay_sq >= m_prev:
                    n = self._osc_n
                    return self._trip(TripCode.OSCILLATION, n, command_deg_s, error_deg)

        # Written so that NaN counts as out of bounds (it fails every comparison).
        limit = self.command_limit_deg_s
        if -limit < command_deg_s < limit:
            self._sat_n = 0
        else:
            self._sat_n += 1
            if self._sat_n >= self._sat_ticks:
                return self._trip(TripCode.SATURATION, self._sat_n, command_deg_s, error_deg)
        limit = self._err_lim
        if -limit <= error_deg <= limit:
            self._err_n = 0
        else:
            self._err_n += 1
            if self._err_n >= self._err_ticks:
                return self._trip(TripCode.TRACKING_ERROR, self._err_n, command_deg_s, error_deg)
        return 0

    # -- off the hot path: only when it trips -------------------------------------------------

    def _trip(self, code: TripCode, ticks: int, command_deg_s: float, error_deg: float) -> int:
        rate = self.rate_hz
        duration = ticks / rate
        lim = self.limits
        freq = None
        amp = abs(command_deg_s)
        if code in (TripCode.OSCILLATION, TripCode.GROWING_OSCILLATION):
            amp = math.sqrt(2.0 * self._m2)
            span = (self._tick - self._episode_start + 1) / rate
            freq = self._crossings / (2.0 * span)
            rms = math.sqrt(self._m2)
            if code == TripCode.OSCILLATION:
                why = (
                    f"speed command oscillates at {freq:.3g} Hz, {rms:.3g} deg/s RMS in "
                    f"{lim.band_low_hz:g}-{lim.band_high_hz:g} Hz (limit "
                    f"{lim.oscillation_rms_deg_s:g}) for {duration:.3g} s"
                )
            else:
                growth = lim.growth_ratio**lim.growth_windows
                why = (
                    f"speed command oscillation at {freq:.3g} Hz growing: >= x{growth:.3g} in "
                    f"{duration:.3g} s, now {rms:.3g} deg/s RMS in "
                    f"{lim.band_low_hz:g}-{lim.band_high_hz:g} Hz"
                )
        elif code == TripCode.SATURATION and not math.isfinite(command_deg_s):
            why = f"speed command not finite ({command_deg_s}) for {duration:.3g} s"
        elif code == TripCode.SATURATION:
            why = (
                f"speed command at its limit {self.command_limit_deg_s:g} deg/s for "
                f"{duration:.3g} s"
            )
        elif not math.isfinite(error_deg):
            why = f"position error not finite ({error_deg}) for {duration:.3g} s"
        else:
            why = (
                f"position error {abs(error_deg):.3g} deg beyond {lim.error_limit_deg:g} deg for "
                f"{duration:.3g} s"
            )
        self.trip = WatchdogTrip(
            code=int(code),
            kind=_KIND[code],
            reason=why,
            tick=self._tick,
            time_s=self._tick / rate,
            duration_s=duration,
            frequency_hz=freq,
            command_amplitude_deg_s=amp,
            error_deg=abs(error_deg),
        )
        self.code = int(code)
        return self.code
