"""The rig's twin as data (pure): the simulated rig (`RigParams` + `RigFaults` of
`controller.sim.sim_rig`) that stands for the measured plant, what it was fitted to (the plant
knowledge's version and digest), how well it fits (per position, in dB and degrees over the
measured band; a time-domain replay), and what was estimated beside the dynamics (friction,
backlash, noise, the disturbance the DOB has been estimating).

A `RigTwin` is a frozen msgspec Struct: it travels on the wire and in recordings as it is
(`encode` / `decode`), and `sim_rig()` gives the `SimRig` that the compiled offline loop
(`controller.sim.offline.run_ticks`) runs.
"""

from __future__ import annotations

import hashlib
import math

import msgspec

from controller.gate.knowledge import KnowledgeRecord, PlantKnowledge
from controller.sim.disturbance import Disturbance
from controller.sim.sim_rig import RigFaults, RigParams, SimRig

__all__ = ["TWIN_FORMAT", "DisturbanceEstimate", "NonlinearEstimate", "PositionFit",
           "ReplayFit", "RigTwin", "decode", "encode", "from_builtins", "knowledge_digest"]

#: The twin record's format (bumped when a field changes meaning).
TWIN_FORMAT = 1


class _Rec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    pass


class PositionFit(_Rec, frozen=True, kw_only=True):
    """How the twin's linear response at one position matches the response measured there,
    over the measured band [f_lo_hz, f_hi_hz] (`points` frequencies): magnitude error in dB
    and phase error in degrees, rms and worst (twin minus measured)."""

    name: str
    position_deg: float
    f_lo_hz: float
    f_hi_hz: float
    points: int
    rms_db: float
    max_db: float
    rms_deg: float
    max_deg: float
    max_at_hz: float
    """Where the worst magnitude error is."""

    def describe(self) -> str:
        return (f"{self.name}: {self.rms_db:.2f} dB / {self.rms_deg:.1f} deg rms, worst "
                f"{self.max_db:.2f} dB / {self.max_deg:.1f} deg ({self.f_lo_hz:.3g}-"
                f"{self.f_hi_hz:.3g} Hz, {self.points} points)")


class NonlinearEstimate(_Rec, frozen=True, kw_only=True):
    """Friction, backlash and sensor noise of the twin, and where each value came from
    ("estimated: ...", "assumed: the built-in rig's"). A `*_std` is the estimate's standard
    deviation (None: not estimated, the value is the base rig's): `controller.twin.nonlinear`
    for the Coulomb friction, the backlash and the noise (from a recorded window of normal
    running), the responses' fit for the viscous friction."""

    coulomb_torque_n_m: float
    static_torque_n_m: float
    backlash_deg: float
    position_noise_deg: float
    how: tuple[str, ...] = ()
    viscous_n_m_s_rad: float = 0.0
    coulomb_std_n_m: float | None = None
    backlash_std_deg: float | None = None
    position_noise_std_deg: float | None = None
    viscous_std_n_m_s_rad: float | None = None
    rate_noise_deg_s: float = 0.0
    """The speed sensor's noise the encoder's makes (backward difference: sqrt 2 x the
    position noise x the loop rate), deg/s."""
    window: str = ""
    """What the running estimates came from (label and length), "" if none."""

    def describe(self) -> str:
        def pm(v: float, sd: float | None, fmt: str) -> str:
            return (f"{v:{fmt}} +- {sd:{fmt}}" if sd is not None else f"{v:{fmt}} (assumed)")
        return (f"Coulomb {pm(self.coulomb_torque_n_m, self.coulomb_std_n_m, '.3g')} N m, "
                f"viscous {pm(self.viscous_n_m_s_rad, self.viscous_std_n_m_s_rad, '.3g')} "
                f"N m s/rad, backlash {pm(self.backlash_deg, self.backlash_std_deg, '.3g')} "
                f"deg, encoder noise "
                f"{pm(self.position_noise_deg, self.position_noise_std_deg, '.2e')} deg "
                f"(speed {self.rate_noise_deg_s:.3g} deg/s rms)")


class DisturbanceEstimate(_Rec, frozen=True, kw_only=True):
    """The disturbance the DOB has been estimating (its d_hat over a recent window, a rate at
    P's input in deg/s): its rms level and amplitude spectrum (one-sided, per frequency)."""

    window_s: float
    rms_deg_s: float
    mean_deg_s: float
    freq_hz: tuple[float, ...] = ()
    amplitude_deg_s: tuple[float, ...] = ()
    mean_std_deg_s: float | None = None
    """The mean's standard deviation (from the means of ten blocks of the window: d_hat is
    low-passed, its samples are not independent); None: not stated."""
    relative_to: str = ""
    """"": d_hat itself; else what was taken off it (the twin's own d_hat for the same run:
    what remains is the disturbance the twin lacks)."""


class ReplayFit(_Rec, frozen=True, kw_only=True):
    """A recorded run replayed on the twin: the measured position error against the one the
    twin predicts for the same reference and configuration."""

    label: str
    duration_s: float
    measured_rmse_deg: float
    predicted_rmse_deg: float
    measured_peak_deg: float
    predicted_peak_deg: float

    @property
    def rmse_ratio(self) -> float:
        """predicted / measured RMSE (1 = exact)."""
        m = self.measured_rmse_deg
        return self.predicted_rmse_deg / m if m > 0.0 else math.nan


class RigTwin(_Rec, frozen=True, kw_only=True):
    """A simulated rig that stands for the measured one. See the module docstring.

    `params` and `faults` are the simulated rig (its belt stiffness varying with the angle
    stands for the per-position dynamics; an extra mode in `faults` for a measured resonance;
    `params.command_delay_ticks` for the measured delay, `faults.plant_gain` for the drive's
    gain); `fitted` the factors fitted against the built-in rig (name -> value);
    `positions` the fit per measured position; `nonlinear`, `disturbance`, `replay` what was
    estimated beside the dynamics (None: not estimated)."""

    format: int = TWIN_FORMAT
    knowledge_version: int
    knowledge_digest: str
    source: str
    rate_hz: float
    params: RigParams
    faults: RigFaults
    fitted: dict[str, float] = {}
    positions: tuple[PositionFit, ...] = ()
    nonlinear: NonlinearEstimate | None = None
    disturbance: DisturbanceEstimate | None = None
    replay: ReplayFit | None = None
    notes: tuple[str, ...] = ()

    def sim_rig(self, *, seed: int = 0, initial_position_deg: float = 0.0,
                disturbance: Disturbance | None = None, rate_hz: float | None = None) -> SimRig:
        """A fresh `SimRig` of the twin at rest at `initial_position_deg`, with the external
        load torque `disturbance` (None: none), its faults staged for the first step: what
        `controller.sim.offline.run_ticks` runs."""
        rig = SimRig(self.params, rate_hz=rate_hz or self.rate_hz, seed=seed,
                     disturbance=disturbance, initial_position_deg=initial_position_deg)
        if self.faults.active:
            rig.set_faults(self.faults)
        return rig

    def matches(self, knowledge: PlantKnowledge) -> bool:
        """Whether this twin was built from `knowledge` (version and digest)."""
        return (self.knowledge_version == knowledge.version
                and self.knowledge_digest == knowledge_digest(knowledge))

    @property
    def worst_fit(self) -> PositionFit | None:
        return max(self.positions, key=lambda p: p.rms_db, default=None)

    def describe(self) -> str:
        """One line: what it stands for and how well it fits."""
        w = self.worst_fit
        each = ", ".join(f"{p.rms_db:.2f} dB/{p.rms_deg:.1f} deg" for p in self.positions)
        fit = f"fit per position {each} rms" if w is not None else "no measured position"
        fac = ", ".join(f"{k} {v:.3g}" for k, v in self.fitted.items())
        return (f"twin of plant knowledge v{self.knowledge_version} ({self.source}; {fac}; "
                f"{fit})")


def knowledge_digest(knowledge: PlantKnowledge) -> str:
    """A digest of the knowledge's content (model, bound, measured responses; not its version
    number nor source): a twin built from other data does not match, whatever the version
    number says."""
    rec = msgspec.structs.replace(KnowledgeRecord.of(knowledge), version=0, source="")
    raw = msgspec.msgpack.encode(rec)
    return hashlib.sha256(raw).hexdigest()[:16]


def encode(twin: RigTwin) -> bytes:
    """The twin as JSON (recordings, files)."""
    return msgspec.json.encode(twin)


def from_builtins(obj: object) -> RigTwin:
    """A twin from plain data (a recording's `twin` event); ValueError naming the field."""
    try:
        return msgspec.convert(obj, type=RigTwin)
    except msgspec.ValidationError as exc:
        raise ValueError(f"twin: {exc}") from None


def decode(data: bytes | str) -> RigTwin:
    """A twin from `encode`'s JSON; ValueError naming the field for a bad one."""
    try:
        return msgspec.json.decode(data, type=RigTwin)
    except msgspec.ValidationError as exc:
        raise ValueError(f"twin: {exc}") from None
