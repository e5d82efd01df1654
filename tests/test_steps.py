"""Step responses of the linear loop against an independent python-control closed loop
(tests/fuzz_truth.py: the same discrete loop built from control.ss blocks)."""

from __future__ import annotations

import control as ct
import numpy as np
import pytest
from fuzz_truth import TruePlant, disturbance_loop

from controller.core.config import LoopConfig, NominalModel
from controller.tune.steps import step_responses


@pytest.mark.parametrize("cfg", [LoopConfig(), LoopConfig(q_type="q20", q_cutoff_hz=2.0),
                                 LoopConfig(dob_on=False), LoopConfig(pos_ki_per_s=0.0)])
def test_load_step_matches_python_control(cfg: LoopConfig) -> None:
    t, _ref, load = step_responses(cfg, NominalModel(), duration_s=1.5)
    sys = disturbance_loop(TruePlant(), cfg, position=True)  # d at the plant input -> [w, theta]
    resp = ct.forced_response(sys, T=t, U=np.ones_like(t))
    theta = np.asarray(resp.outputs)[1]
    # The tick measures before it commands: our theta[k] is the truth's theta at step k.
    np.testing.assert_allclose(load, theta, atol=1e-6 * max(1.0, np.max(np.abs(theta))))


def test_reference_step_settles_at_one_degree() -> None:
    _, ref, _ = step_responses(LoopConfig(), NominalModel(), duration_s=4.0)
    assert ref[-1] == pytest.approx(1.0, abs=2e-3)  # integral action: no static error
    assert np.max(ref) > 1.0  # the PI position loop overshoots
