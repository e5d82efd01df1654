"""The Suggest chart and choice (server/suggest.py) on hand-made search results."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from controller.core.config import LoopConfig
from controller.tune.autotune import SIGNIFICANT_REL, Point, TuneResult
from server.charts import ranged_scales
from server.suggest import SUGGEST_CHART, suggest_data, suggested_config


def _p(q: str, hz: float, verdict: str, rmse: float) -> Point:
    cfg = LoopConfig().with_(q_type=q, q_cutoff_hz=hz)
    return Point(cfg, verdict, rmse, 2 * rmse, 0.0, rmse if verdict != "reject" else math.inf)


def test_columns_follow_the_points_and_start_finite() -> None:
    curve = (_p("q31", 0.1, "reject", math.nan), _p("q31", 1.0, "accept", 0.02),
             _p("q20", 0.1, "accept", 0.03), _p("q20", 5.0, "caution", 0.01))
    res = TuneResult(best=curve[1], baseline=_p("q31", 0.5, "accept", 0.025), curve=curve)
    data = suggest_data(res)
    assert len(data) == len(SUGGEST_CHART.series)
    x, q31, q20, caution, off, bar, mark = data
    np.testing.assert_array_equal(x, [0.1, 1.0, 5.0])
    # q31 at 0.1 Hz was rejected: not drawn (NaN: the y scale is fixed, no stand-in value).
    assert math.isnan(q31[0]) and q31[1] == 0.02 and math.isnan(q31[2])
    # q20 at 5 Hz is the gate's caution: not counted, so drawn apart (hollow), not on its line.
    assert q20[0] == 0.03 and math.isnan(q20[1]) and math.isnan(q20[2])
    assert caution[2] == 0.01 and np.isnan(caution[:2]).all()
    np.testing.assert_array_equal(off, [0.025] * 3)
    np.testing.assert_allclose(bar, [0.025 * (1 - SIGNIFICANT_REL)] * 3)
    # The suggested dot only at the suggested cut-off (a stand-in at 0.1 Hz drew a second one).
    assert mark[1] == 0.02 and math.isnan(mark[0]) and math.isnan(mark[2])
    lo, hi = ranged_scales(SUGGEST_CHART, data)["y"]["range"]
    assert lo < 0.01 and hi > 0.03 and hi - lo < 0.03


def test_the_dob_goes_off_when_no_setting_beats_it() -> None:
    base = LoopConfig()
    worse = _p("q31", 1.0, "accept", 0.05)
    res = TuneResult(best=worse, baseline=_p("q31", 0.5, "accept", 0.02), curve=(worse,))
    assert not res.dob_helps
    assert suggested_config(base, res) == base.with_(dob_on=False)
    better = _p("q20", 2.0, "accept", 0.01)
    res = TuneResult(best=better, baseline=_p("q31", 0.5, "accept", 0.02), curve=(better,))
    assert suggested_config(base, res) == base.with_(dob_on=True, q_type="q20", q_cutoff_hz=2.0)
    assert suggested_config(base, res).cv_kp == base.cv_kp  # the gains are kept


def test_no_result_draws_nothing_but_has_a_finite_scale() -> None:
    data = suggest_data(None)
    x, *cols = data
    assert len(cols) == len(SUGGEST_CHART.series) - 1
    for c in cols:
        assert not np.isfinite(c).any()
    scale = ranged_scales(SUGGEST_CHART, data)["y"]
    assert scale["auto"] is False and scale["range"] == pytest.approx((-0.05, 1.05))
    assert x[0] == pytest.approx(0.1)


def test_the_text_names_what_the_chart_shows_beating_the_dob_off() -> None:
    """Issue 33: the chart showed Q20 at 20 Hz far below the DOB off while the text said no DOB
    setting beats it (a caution: drawn, not counted, not said). Now the text names it, why it
    is not counted, and that it is hollow on the chart."""
    off = _p("q31", 0.5, "accept", 0.037)
    worse = _p("q31", 1.0, "accept", 0.05)
    caution = dataclasses.replace(_p("q20", 20.0, "caution", 0.014),
                                  why="noise to command 23 dB > 20 dB")
    res = TuneResult(best=worse, baseline=off, curve=(worse, caution))
    assert not res.dob_helps and res.not_counted == (caution,)
    text = res.summary()
    assert "no accepted DOB setting beats the DOB off" in text, text
    assert ("q20 at 20 Hz would score lower (0.014 deg, RMSE 0.014 deg) but is not counted: "
            "the gate's caution: noise to command 23 dB > 20 dB (hollow on the chart)") in text
    x, _q31, q20, hollow, *_ = suggest_data(res)
    assert hollow[list(x).index(20.0)] == 0.014 and np.isnan(q20).all()
    assert suggested_config(LoopConfig(), res) == LoopConfig().with_(dob_on=False)


def test_a_difference_inside_the_band_is_no_win() -> None:
    """Issue 33: Suggest offered Q31 at 0.1 Hz for a 0.16 % lower error. Inside
    SIGNIFICANT_REL (1 %: the prediction's own accuracy) it is "no significant difference":
    the DOB stays off, no suggested dot; just outside the band it is a win."""
    off = _p("q31", 0.5, "accept", 0.02888)
    tiny = _p("q31", 0.1, "accept", 0.02888 * (1 - 0.0016))
    res = TuneResult(best=tiny, baseline=off, curve=(tiny,))
    assert not res.dob_helps
    assert res.summary().startswith("no significant difference: the best accepted DOB "
                                    "setting, q31 at 0.1 Hz, scores -0.2% against the DOB off")
    assert suggested_config(LoopConfig(), res) == LoopConfig().with_(dob_on=False)
    assert np.isnan(suggest_data(res)[-1]).all()
    win = _p("q31", 0.1, "accept", 0.02888 * (1 - 1.5 * SIGNIFICANT_REL))
    res = TuneResult(best=win, baseline=off, curve=(win,))
    assert res.dob_helps and "beyond the +-1% band" in res.summary()
    assert suggest_data(res)[-1][0] == pytest.approx(win.score)
