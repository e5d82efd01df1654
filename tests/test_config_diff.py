"""The candidate's difference from the active configuration as an engineer reads it (issue 33:
the diff printed raw Python, "nominal: {'mn_den': (1.013e-05, ...)}")."""

from __future__ import annotations

import control
import numpy as np

from controller.core.config import LoopConfig, NominalModel
from server.panels.tuning_html import config_diff_html, nominal_summary

FITTED = NominalModel(mn_den=(1.2e-05, 0.0051, 1.0), pn_num=(1.013e-05, 0.004501, 2.0),
                      pn_den=(0.0006, 0.035, 1.0))


def test_the_nominal_model_is_summarised_against_python_control() -> None:
    text = nominal_summary(FITTED)
    g = control.tf(list(FITTED.pn_num), list(np.polymul(FITTED.mn_den, FITTED.pn_den)))
    gain_db = 20 * np.log10(abs(g(2j * np.pi)))
    hz = sorted(abs(p) / (2 * np.pi) for p in control.poles(g))
    assert text == (f"gain {gain_db:.1f} dB at 1 Hz, poles at "
                    + ", ".join(f"{f:.3g}" for f in hz) + " Hz")
    # By hand: Mn's poles (a complex pair) at its natural frequency 1 / sqrt(1.2e-5) rad/s.
    assert f"{1 / np.sqrt(1.2e-05) / (2 * np.pi):.3g}" in text


def test_the_diff_has_no_raw_python() -> None:
    old = LoopConfig()
    new = old.with_(nominal=FITTED, cv_kp=1.2345678, q_cutoff_hz=2.0)
    html = config_diff_html(old, new, "active v3", "Candidate")
    assert "nominal model Mn Pn: gain" in html and "poles at" in html
    assert "{" not in html and "mn_den" not in html and "&#x27;" not in html
    assert "cv_kp: 1.35 &rarr; <b>1.235</b>" in html
    assert "q_cutoff_hz: 0.5 &rarr; <b>2</b>" in html
