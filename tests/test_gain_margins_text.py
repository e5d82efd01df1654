"""The verdict's gain margins as an engineer reads them (issue 33 item 2): both positive and
named, in the verdict box, the Decide view, the guide and the history."""

from __future__ import annotations

import math
import re

from controller.core.config import LoopConfig
from controller.core.verdict import VerdictMargins
from server.engine import TuningEngine
from server.panels.bode import decide_html, gain_margin_items
from server.panels.tuning_html import format_gate_html


def _text(html: str) -> str:
    return " ".join(re.sub(r"<[^>]+>", " ", html).split())


def test_the_verdict_headline_reads_both_gain_margins_positive() -> None:
    """Issue 33 item 2: the default loop is conditionally stable; the verdict box and the
    Decide view read "gain margin 26.0 dB up" and "gain-reduction margin 25.8 dB down" (the
    analysis' numbers, checked against python-control in tests/test_analysis.py), never the
    signed -25.8 dB that reads as an unstable loop. A loop without a gain-reduction limit
    (DOB off) shows one gain margin, no "up"/"down"."""
    eng = TuningEngine()
    ev = eng.evaluate(LoopConfig())
    m = ev.verdict.margins
    assert m.gain_margin_db < 0 < m.gain_reduction_margin_db  # the signed pick is the lower
    for page in (format_gate_html(ev), decide_html(ev)):
        text = _text(page)
        assert f"gain margin {m.gain_margin_up_db:.1f} dB up" in text, text
        assert f"gain-reduction margin {m.gain_reduction_margin_db:.1f} dB down" in text, text
        assert f"{m.gain_margin_db:.1f}" not in text, text
    off = eng.evaluate(LoopConfig(dob_on=False)).verdict.margins
    assert off.gain_reduction_margin_db == math.inf and off.gain_margin_db > 0
    text = _text(format_gate_html(eng.evaluate(LoopConfig(dob_on=False))))
    assert f"gain margin {off.gain_margin_db:.1f} dB" in text and "gain-reduction" not in text


def test_a_verdict_recorded_before_both_were_kept_reads_its_signed_pick_by_its_name() -> None:
    """A change-log line or a protocol-1 peer carries python-control's signed pick alone (the
    new fields NaN): a negative one is shown as the gain-reduction margin it is, positive."""
    old = VerdictMargins(gain_margin_db=-25.8, phase_margin_deg=74.8, peak_sensitivity_db=2.9,
                         small_gain_peak=0.26, max_pole_radius=0.998)
    assert gain_margin_items(old) == [("gain-reduction margin", "25.8", "dB down")]
    assert old.gain_margins_text() == "gain-reduction margin 25.8 dB down"
    up = VerdictMargins(gain_margin_db=22.0, phase_margin_deg=58.0, peak_sensitivity_db=2.9,
                        small_gain_peak=0.26, max_pole_radius=0.998)
    assert up.gain_margins_text() == "gain margin 22.0 dB"
    assert math.isnan(old.gain_margin_up_db)
