"""The guided path's pieces that are pure (server/panels/guide.py): the watch after an apply,
and the steps' HTML."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import statuses

from controller import protocol as proto
from server.panels.guide import GUIDE_STEPS, Watch, guide_html
from server.panels.tuning import StepState


def status(**kw: Any) -> proto.Status:
    """The shared status, at configuration version 5."""
    return statuses.status(**{"config_version": 5, **kw})


def samples(t_apply: float, t_end: float, before: float, after: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.arange(0.0, t_end, 1e-3)
    rng = np.random.default_rng(1)
    err = np.where(t < t_apply, before, after) * rng.standard_normal(len(t))
    ver = np.where(t < t_apply, 4.0, 5.0)
    return t, err, ver


def test_the_watch_compares_the_error_before_and_after_over_its_length() -> None:
    t, err, ver = samples(20.0, 26.0, 0.03, 0.01)
    w = Watch(version=5, length_s=10.0, rollbacks_before=0)
    w.see(status(), t, err, ver)
    assert not w.finished and w.step().state == "running"
    assert math.isclose(w.step().progress or 0.0, 0.6, abs_tol=1e-3)
    # Independent: numpy on the same selections (the 10 s before the first v5 sample).
    before = err[(ver == 4) & (t >= 10.0)]
    assert math.isclose(w.before_rms_deg, float(np.sqrt(np.mean(before**2))), rel_tol=1e-12)
    t, err, ver = samples(20.0, 30.5, 0.03, 0.01)
    w.see(status(), t, err, ver)
    assert w.finished
    after = err[ver == 5]
    assert math.isclose(w.after_rms_deg, float(np.sqrt(np.mean(after**2))), rel_tol=1e-12)
    s = w.step()
    assert s.state == "done" and "no rollback" in s.text and "-67%" in s.text
    assert f"before {w.before_rms_deg:.4f} deg, after {w.after_rms_deg:.4f} deg" in s.text


def test_a_rollback_fails_the_watch_with_its_reason() -> None:
    t, err, ver = samples(20.0, 22.0, 0.03, 0.2)
    w = Watch(version=5, length_s=10.0, rollbacks_before=2)
    w.see(status(rollbacks=2), t, err, ver)
    assert w.step().state == "running"
    why = "watchdog: oscillates at 11 Hz; rolled back from v5 to the previous configuration as v6"
    w.see(status(rollbacks=3, config_version=6, watchdog=why), t, err, ver)
    s = w.step()
    assert w.finished and s.state == "failed"
    assert s.text.startswith("ROLLED BACK to v6: " + why)
    # Another client's apply (no rollback) is not one.
    w2 = Watch(version=5, length_s=10.0, rollbacks_before=2)
    w2.see(status(rollbacks=2, config_version=7), t, err, ver)
    assert w2.rolled_back_to is None


def test_the_steps_html_shows_each_state_progress_and_text() -> None:
    states = [StepState("done", 1.0, "3 position(s)"), StepState("failed", None, "no <fit>"),
              StepState("todo"), StepState("running", 0.42, "searching"), StepState("todo"),
              StepState("todo"), StepState("todo")]
    html = guide_html([(k, t, s) for (k, t), s in zip(GUIDE_STEPS, states, strict=True)])
    assert html.count("<li") == 7
    assert "dt-step-measure dt-step-done" in html and "[done]" in html
    assert "no &lt;fit&gt;" in html and "dt-step-fit dt-step-failed" in html
    assert "[running 42 %]" in html and html.count("[not started]") == 4
