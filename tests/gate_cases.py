"""Random gate cases and a bit-exact digest of what the gate answers: for the tests and the
bench (tests/bench/gate_answers_ab.py) that check a speed-up of the gate changes nothing.

Only the gate's public types are used, so an older tree judges the same cases."""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Callable

import numpy as np

from controller.core.config import LoopConfig, NominalModel
from controller.gate.knowledge import COMMISSIONING_BOUND, MeasuredResponse, PlantKnowledge
from controller.gate.loop_model import nominal_continuous_response


def json_form(v: object, leaf: Callable[[object], object]) -> object:
    """`v` (dataclasses, tuples, lists, numpy scalars, plain values) as JSON-able values;
    `leaf(x)` gives the form of a number or array, or NotImplemented for anything else."""
    done = leaf(v)
    if done is not NotImplemented:
        return done
    if isinstance(v, (np.floating, np.complexfloating)):
        return json_form(v.item(), leaf)
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: json_form(getattr(v, f.name), leaf) for f in dataclasses.fields(v)}
    if isinstance(v, (tuple, list)):
        return [json_form(x, leaf) for x in v]
    if v is None or isinstance(v, (str, int, bool)):
        return v
    return repr(v)


def _bits(v: object) -> object:
    if isinstance(v, np.ndarray):
        return [str(v.dtype), list(v.shape),
                hashlib.sha256(np.ascontiguousarray(v).tobytes()).hexdigest()]
    if isinstance(v, float):
        return float.hex(v)
    if isinstance(v, complex):
        return [float.hex(v.real), float.hex(v.imag)]
    return NotImplemented


def canon(v: object) -> object:
    """A JSON-able form of `v` that holds every bit of its numbers (arrays by a hash of their
    bytes, floats in hex)."""
    return json_form(v, _bits)


def random_configs(n: int, seed: int) -> list[tuple[LoopConfig, int]]:
    """(candidate, index into `knowledge_set()`): gains, integrators on and off, both Q types,
    cut-offs 0.02-40 Hz, the DOB mostly on; about half rejected, the rest accepted or
    cautioned."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        cfg = LoopConfig(
            cv_kp=float(rng.uniform(0.15, 1.6)),
            cv_ki_per_s=float(rng.choice([0.0, rng.uniform(5.0, 120.0)])),
            pos_kp_per_s=float(rng.uniform(1.0, 16.0)),
            pos_ki_per_s=float(rng.choice([0.0, rng.uniform(0.5, 6.0)])),
            q_type=str(rng.choice(["q31", "q20"])),
            q_cutoff_hz=float(np.exp(rng.uniform(math.log(0.02), math.log(40.0)))),
            dob_on=bool(rng.random() < 0.85),
            ff_on=bool(rng.random() < 0.3),
        )
        out.append((cfg, int(rng.integers(0, 5))))
    return out


def knowledge_set() -> list[PlantKnowledge]:
    """Measured at three positions as identification hands them over; the model with its
    bound; the model alone; two positions of a plant 30 % stronger with a mode at 6 Hz; one
    dense sampled response with a mode at 40 Hz."""
    model = NominalModel()

    def positions(f: np.ndarray, gain: float, mode_hz: float | None, seed: int,
                  sampled: bool = False) -> tuple[MeasuredResponse, ...]:
        h = gain * nominal_continuous_response(model, f)
        if mode_hz is not None:  # a lightly damped pole pair with its zeros a little above
            s = 1j * 2 * np.pi * f
            wp, wz = 2 * np.pi * mode_hz, 2 * np.pi * mode_hz * 1.15
            h = h * (s**2 + 2 * 0.03 * wz * s + wz**2) / (s**2 + 2 * 0.02 * wp * s + wp**2) \
                * wp**2 / wz**2
        if sampled:
            x = np.pi * f / 1000.0
            h = h * np.exp(-2j * x) * np.sinc(x / np.pi) ** 2
        rng = np.random.default_rng(seed)
        return tuple(
            MeasuredResponse(f"pos{i}", f, h * (1.0 + 0.02 * rng.standard_normal(f.size)
                                                 + 0.02j * rng.standard_normal(f.size)),
                             sampled=sampled, spread=np.full(f.size, 0.04))
            for i in range(3))

    ident = np.logspace(-1.0, math.log10(20.0), 24)
    dense = np.geomspace(0.05, 300.0, 160)
    return [
        PlantKnowledge(positions(ident, 1.0, None, 0), COMMISSIONING_BOUND, model),
        PlantKnowledge((), COMMISSIONING_BOUND, model),
        PlantKnowledge((), None, model),
        PlantKnowledge(positions(ident, 1.3, 6.0, 1)[:2], COMMISSIONING_BOUND, model),
        PlantKnowledge(positions(dense, 0.8, 40.0, 2, sampled=True)[:1], COMMISSIONING_BOUND,
                       model),
    ]
