"""What Suggest and the Time tab's comparison say (issue 33): a difference inside the
prediction's accuracy (`SIGNIFICANT_REL`) is "no significant difference", never a win; and
Suggest's "The candidate now has this setting" goes once the candidate is changed. A real
dashboard panel (no browser: the HTML handles a browser is sent)."""

from __future__ import annotations

import html
import re
from typing import Any

from controller.core.config import LoopConfig
from controller.core.trajectory import Trajectory
from controller.tune.autotune import SIGNIFICANT_REL, differs
from server.engine import PreviewComparison
from server.panels.tuning_html import preview_html


def _text(page: str) -> str:
    return " ".join(re.sub(r"<[^>]+>", " ", html.unescape(page)).split())


def test_the_time_tab_calls_a_difference_inside_the_band_none(dash: Any) -> None:
    """Q31 at 0.1 Hz against the DOB off on the default sine: the runs the Time tab makes
    differ by a fraction of a percent (RMSE -0.2 % in the issue): "No significant difference",
    not "DOB beats DOB off"; Q20 at 6.43 Hz (Suggest's pick on the demo) is outside it."""
    eng, traj = dash.engine, Trajectory()
    off = eng.preview(LoopConfig(dob_on=False), traj)
    said = []
    for cfg in (LoopConfig(q_cutoff_hz=0.1), LoopConfig(q_type="q20", q_cutoff_hz=6.43)):
        cand = eng.preview(cfg, traj)
        change = cand.rmse_deg / off.rmse_deg - 1.0
        text = _text(preview_html(traj, PreviewComparison(cand, off, (), no_dob=off)))
        want = {-1: "DOB beats DOB off here", 0: "No significant difference from DOB off here",
                1: "DOB does not beat DOB off here"}[differs(cand.rmse_deg, off.rmse_deg)]
        assert want in text and f"RMSE {change:+.1%}" in text, text
        said.append((abs(change) < SIGNIFICANT_REL, want))
    print(f"\n  {said}")
    assert said[0] == (True, "No significant difference from DOB off here"), said


def test_suggest_stops_saying_the_candidate_has_its_setting_once_changed(dash: Any) -> None:
    t = dash.panel_of(None)
    t.suggest.request()
    assert t.suggest.wait_idle(300.0)
    res = t.suggest.last
    assert res is not None
    text = _text(t.suggest_text.content)
    assert "The candidate now has" in text, text
    assert "changed since" not in text
    # The user edits the candidate: the sentence goes, the result stays said as Suggest's.
    t.cv_kp.value = float(t.cv_kp.value) * 0.9
    assert t.wait_idle(30.0)
    text = _text(t.suggest_text.content)
    assert "The candidate now has" not in text, text
    assert "The candidate has been changed since" in text and res.summary()[:40] in text, text
