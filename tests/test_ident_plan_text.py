"""What the Identify confirmation states (issue 33): the same band and amplitude as the run's
progress text (the demo asked 10 deg/s and moved at 3: the confirmation said 10), and the
planned duration."""

from __future__ import annotations

import re

import numpy as np
import pytest

from controller.core.config import LoopConfig
from controller.ident.plan import plan_program, plan_text
from controller.ident.spec import IdentifySpec


@pytest.mark.parametrize("spec", [IdentifySpec(), IdentifySpec(signal="sine", positions=1),
                                  IdentifySpec(amplitude_deg_s=1.0, positions=2)],
                         ids=["multisine-default", "stepped-sine", "small-amplitude"])
def test_the_plan_text_states_what_the_progress_text_will(spec: IdentifySpec) -> None:
    cfg = LoopConfig()
    text = plan_text(spec, cfg, 0.0)
    plan = plan_program(spec, cfg, 0.0)
    runs = [label.split(": ", 1)[1] for _, label in plan.labels if label.endswith("deg/s")]
    # Every excitation segment's amplitude, as its progress text gives it, is in the text.
    amps = {r.rsplit(", ", 1)[1] for r in runs}
    shown = re.search(r", ([0-9.]+(?:-[0-9.]+)? deg/s)", text)
    assert shown is not None, text
    lo_hi = [float(v) for v in shown[1].split()[0].split("-")]
    got = sorted(float(a.split()[0]) for a in amps)
    assert [got[0], got[-1]] == pytest.approx([lo_hi[0], lo_hi[-1]]), (text, amps)
    if spec.signal == "multisine":  # the band as the progress names it
        (band,) = {r.rsplit(", ", 1)[0] for r in runs}
        assert text.startswith(band + ", "), (text, band)
    # Asked more than planned: both said, the asked one as asked, never as the excitation.
    lowered = got[-1] < spec.amplitude_deg_s
    assert (f"{spec.amplitude_deg_s:g} deg/s asked" in text) == lowered, text
    # The duration: the planned ticks.
    m = re.search(r"about (\d+) s", text)
    assert m is not None and int(m[1]) == round(plan.seg_end[-1] / cfg.rate_hz), text
    assert len(plan.kind) == plan.seg_end[-1]
    assert f"at {len(spec.centers_deg)} position(s)" in text


def test_the_demo_default_names_3_deg_s_not_10() -> None:
    text = plan_text(IdentifySpec(), LoopConfig(), 0.0)
    assert text.startswith("multisine 0.1-19.9 Hz, 3 deg/s (10 deg/s asked"), text
    assert np.isfinite(float(re.search(r"about (\d+) s", text)[1]))  # type: ignore[index]
