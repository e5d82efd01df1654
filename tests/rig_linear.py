"""The simulated rig's linear reference, shared by tests/test_ident_accuracy.py,
tests/test_experiment.py and tests/bench/bench_identify.py: its analytic linearisation, its
parameters with the nonlinearities switched off, and the rig with nonlinearities and noise off."""

from __future__ import annotations

import numpy as np

from controller.sim.sim_rig import RigParams, SimRig

__all__ = ["NONLINEAR", "linear_params", "linear_response", "linear_rig"]

#: The rig's nonlinear parameters (friction, backlash, tooth effects): zero in the linear regime.
NONLINEAR = ("backlash_deg", "coulomb_torque_n_m", "static_torque_n_m", "bias_torque_n_m",
             "transmission_error_deg", "ripple_torque_n_m")


def linear_params(**overrides: float) -> RigParams:
    """The rig's parameters with every one of `NONLINEAR` zero; `overrides` set any field."""
    return RigParams(**{**dict.fromkeys(NONLINEAR, 0.0), **overrides})


def linear_response(freq_hz: np.ndarray, p: RigParams | None = None) -> np.ndarray:
    """u -> w of the simulated rig linearised about a one-way motion (belt loaded, friction
    constant, no ripple): G = Ki T / A with T = (k + c s) / (Jl s^2 + (bl + c) s + k) the belt
    and load, A = Jm s^2 + bm s + (k + c s)(1 - T) / N^2 + (Ki + Kp s) D the motor with the
    drive's I-P loop, D = (1 - e^{-s Tw}) / (s Tw) its speed estimate over the window Tw."""
    p = p or RigParams()
    s = 2j * np.pi * np.asarray(freq_hz, dtype=np.float64)
    n, k, c = p.gear_ratio, p.belt_stiffness_n_m_rad, p.belt_damping_n_m_s_rad
    t = (k + c * s) / (p.load_inertia_kg_m2 * s**2 + (p.load_viscous_n_m_s_rad + c) * s + k)
    tw = p.drive_speed_window_s
    d = (1.0 - np.exp(-s * tw)) / (s * tw)
    a = (
        p.motor_inertia_kg_m2 * s**2
        + p.motor_viscous_n_m_s_rad * s
        + (k + c * s) * (1.0 - t) / n**2
        + (p.drive_ki_n_m_rad + p.drive_kp_n_m_s_rad * s) * d
    )
    return np.asarray(p.drive_ki_n_m_rad * t / a)


def linear_rig() -> SimRig:
    """The simulated rig with its nonlinearities and noise switched off (the reference check)."""
    return SimRig(linear_params(position_noise_deg=0.0, load_encoder_bits=48,
                                motor_encoder_counts_per_rev=2**30))
