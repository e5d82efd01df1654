"""The Trends view's data and charts without a browser (server/trends_data.py,
server/charts_trend.py): a synthetic week read back (tests/trend_week.py), the reduction to a
chart's width against a brute-force reference, what is said about files that cannot be read,
and the charts' scales."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np
import pytest
from trend_week import DAY_S, RANGES, gain_at, write_week

from controller.recording.trend import read_hour
from server.charts_trend import ALARM_DOTS, ALARM_LABEL, readable_range, trend_charts
from server.trends_data import STATES, TrendReader, per_window, time_decimate

RIG = "rigT"


@pytest.fixture(scope="module")
def week(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    root = tmp_path_factory.mktemp("trend")
    end = 1_800_000_000.0  # a fixed week: 2027-01-15
    return root, write_week(root, RIG, end, window_s=120.0)


def _brute(t: np.ndarray, y: np.ndarray, t0: float, t1: float, width: int
           ) -> dict[int, tuple[float, float]]:
    """Per pixel of the chart: (min, max) of the finite values, by a plain loop."""
    out: dict[int, tuple[float, float]] = {}
    for ti, yi in zip(t, y, strict=True):
        if not math.isfinite(yi):
            continue
        px = math.floor((ti - t0) / (t1 - t0) * width)
        lo, hi = out.get(px, (math.inf, -math.inf))
        out[px] = (min(lo, yi), max(hi, yi))
    return out


def test_the_reduction_keeps_every_pixels_min_and_max_and_breaks_at_gaps() -> None:
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(5.0, 15.0, 20000))
    t[12000:] += 5000.0  # the watch off for over an hour
    y = rng.standard_normal(t.size)
    y[rng.integers(0, t.size, 300)] = np.nan
    y[777] = 40.0  # one window's spike
    t0, t1, width = float(t[0]), float(t[-1]), 400
    x, (yd,) = time_decimate(t, [y], t0, t1, width)
    assert x.size <= 2 * width + 2
    assert np.all(np.diff(x) >= 0)
    ref = _brute(t, y, t0, t1, width)
    got: dict[int, tuple[float, float]] = {}
    for xi, yi in zip(x, yd, strict=True):
        if math.isfinite(yi):
            px = min(math.floor((xi - t0) / (t1 - t0) * width), width)
            lo, hi = got.get(px, (math.inf, -math.inf))
            got[px] = (min(lo, yi), max(hi, yi))
    assert got == ref
    assert np.nanmax(yd) == 40.0
    # The gap: one NaN row between the last point before it and the first after.
    before, after = t[11999], t[12000]
    inside = (x > before) & (x < after)
    assert inside.sum() == 1 and np.isnan(yd[inside]).all()


def test_few_points_are_kept_as_they_are_with_their_gaps() -> None:
    t = np.array([0.0, 10.0, 20.0, 200.0, 210.0])
    y = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    x, (yd,) = time_decimate(t, [y], 0.0, 210.0, 1000)
    assert list(x) == [0.0, 10.0, 20.0, 110.0, 200.0, 210.0]
    assert list(yd[[0, 1, 2, 4, 5]]) == [1.0, 2.0, 3.0, 4.0, 5.0] and math.isnan(yd[3])


def test_a_week_reads_back_with_its_known_values(week: tuple[Path, object]) -> None:
    root, wk = week
    reader = TrendReader()
    span = reader.read(root, RIG, wk.t0_epoch_s, wk.t1_epoch_s)  # type: ignore[attr-defined]
    assert span.windows == wk.windows  # type: ignore[attr-defined]
    assert span.problems == []
    assert span.part_names() == ["gain", "stiffness", "inertia", "motor_friction"]
    t = span.parts["t"]
    for i in (0, 100, 2500, span.windows - 1):
        assert span.parts["gain"][i] == pytest.approx(gain_at(float(t[i]), wk), abs=1e-12)
    drop = t >= wk.drop_at  # type: ignore[attr-defined]
    assert set(span.parts["stiffness"][drop]) == {0.6}
    assert set(span.parts["stiffness"][~drop]) == {1.0}
    assert span.parts["stiffness_low"][0] == RANGES["stiffness"][0]
    st = span.part_states["stiffness"]
    assert (st[t >= wk.alarm_at] == STATES.index("alarm")).all()  # type: ignore[attr-defined]
    # The recorded alarm, and no second one made up from the state's entry beside it.
    assert [(a.epoch_s, a.part) for a in span.alarms] == [(wk.alarm_at, "stiffness")]  # type: ignore[attr-defined]
    # Skipped ticks: +1 per window written as a total (the gap's windows counted in it).
    per = span.health["skipped_ticks"][1:]
    assert (per == 1.0).sum() == per.size - 1 and per.max() == 6 * 3600 / 120.0 + 1
    # No window inside the gap.
    g0, g1 = wk.gap  # type: ignore[attr-defined]
    assert not ((t >= g0) & (t < g1)).any()


def test_an_alarm_is_marked_where_it_began_not_where_a_range_begins(
        week: tuple[Path, object], tmp_path: Path) -> None:
    root, wk = week
    reader = TrendReader()
    # The last day: the stiffness in alarm all along, its alarm 2.5 days before: none marked.
    span = reader.read(root, RIG, wk.t1_epoch_s - DAY_S, wk.t1_epoch_s)  # type: ignore[attr-defined]
    assert (span.part_states["stiffness"] == STATES.index("alarm")).all()
    assert span.alarms == []
    # A trend without alarm records (the watch before it wrote them): the entry found from
    # the states, at the first window in alarm.
    bare = tmp_path / "bare"
    w = write_week(bare, RIG, 1_800_000_000.0, window_s=600.0)
    for f in (bare / RIG).glob("*.mcap"):
        hr = read_hour(f)
        if hr.data["/drift/alarm"]:
            f.unlink()  # that hour's file had the record: rewritten without it below
            from controller.recording.trend import TrendWriter
            with TrendWriter(bare, RIG) as tw:
                for topic in ("/drift/residual", "/drift/parts", "/drift/health"):
                    for t, d in zip(hr.epoch_s[topic], hr.data[topic], strict=True):
                        tw.write(topic, t, d)
    span = reader.read(bare, RIG, w.t0_epoch_s, w.t1_epoch_s)
    assert [(a.epoch_s, a.part) for a in span.alarms] == [(w.alarm_at, "stiffness")]
    assert "no alarm record" in span.alarms[0].text


def test_an_hour_is_read_once_until_it_changes(week: tuple[Path, object],
                                               tmp_path: Path) -> None:
    root, wk = week
    reader = TrendReader()
    reader.read(root, RIG, wk.t1_epoch_s - DAY_S, wk.t1_epoch_s)  # type: ignore[attr-defined]
    first = reader.files_read
    assert first >= 24
    reader.read(root, RIG, wk.t1_epoch_s - DAY_S, wk.t1_epoch_s)  # type: ignore[attr-defined]
    assert reader.files_read == first
    newest = sorted((root / RIG).glob("*.mcap"))[-1]
    os.utime(newest, ns=(time.time_ns(), time.time_ns()))
    reader.read(root, RIG, wk.t1_epoch_s - DAY_S, wk.t1_epoch_s)  # type: ignore[attr-defined]
    assert reader.files_read == first + 1


def test_files_that_cannot_be_read_are_said_not_raised(tmp_path: Path) -> None:
    root = tmp_path / "t"
    w = write_week(root, RIG, 1_800_000_000.0, window_s=600.0)
    files = sorted((root / RIG).glob("*.mcap"))
    files[10].write_bytes(b"this is not an mcap file")
    whole = files[20].read_bytes()
    files[20].write_bytes(whole[:300])  # its writer killed mid-hour, in its first chunk
    written = files[20].stat().st_mtime
    span = TrendReader().read(root, RIG, w.t0_epoch_s, w.t1_epoch_s)
    # Just written to: the hour being written (a chunk on its way), not reported.
    assert span.problems == [f"{files[10].name}: not read ({files[10].name}: not a trend file "
                             "(no MCAP magic))"], span.problems
    os.utime(files[20], (written - 3600, written - 3600))  # killed an hour ago
    (root / RIG / "20270101-00.mcap").write_bytes(b"")  # an hour just opened: empty so far
    span = TrendReader().read(root, RIG, w.t0_epoch_s, w.t1_epoch_s)
    assert len(span.problems) == 2, span.problems
    assert files[10].name in span.problems[0] and "not a trend file" in span.problems[0]
    assert files[20].name in span.problems[1] and "cut short" in span.problems[1]
    assert 0 < span.windows < w.windows
    cut = read_hour(files[20])
    assert cut.cut_short and len(cut.data["/drift/parts"]) < 6


def test_the_charts_cover_the_range_with_readable_scales(week: tuple[Path, object]) -> None:
    root, wk = week
    span = TrendReader().read(root, RIG, wk.t0_epoch_s, wk.t1_epoch_s)  # type: ignore[attr-defined]
    charts = trend_charts(span, 900)
    keys = [c.spec.key for c in charts]
    assert keys == ["trend_residuals", "trend_gain", "trend_stiffness", "trend_inertia",
                    "trend_motor_friction", "trend_health"]
    for c in charts:
        assert c.scales["x"]["range"] == (wk.t0_epoch_s, wk.t1_epoch_s)  # type: ignore[attr-defined]
        assert c.scales["x"]["time"] is True
        for name, sc in c.scales.items():
            if name in ("x", "mark"):
                continue
            lo, hi = sc["range"]  # type: ignore[misc]
            assert hi > lo, (c.spec.key, name, lo, hi)
        labels = [s["label"] for s in c.spec.series]
        mark = c.data[labels.index(ALARM_LABEL)]
        at = c.data[0][np.isfinite(mark)]
        assert at.size == ALARM_DOTS and set(at) == {wk.alarm_at}  # type: ignore[attr-defined]
        assert c.data[0].size <= 2 * 900 + ALARM_DOTS + 10
    stiff = charts[2]
    labels = [s["label"] for s in stiff.spec.series]
    lo, hi = stiff.scales["y"]["range"]  # type: ignore[misc]
    assert lo < 0.6 and hi > 1.27  # the value and its whole range
    assert stiff.spec.bands == ({"series": (2, 3), "fill": "rgba(44,160,44,0.12)"},)
    in_alarm = stiff.data[labels.index("in alarm")]
    assert set(in_alarm[np.isfinite(in_alarm)]) == {0.6}


def test_a_flat_trend_still_gets_a_readable_range() -> None:
    assert readable_range(np.array([1.0, 1.0])) == pytest.approx((0.95, 1.05))
    assert readable_range(np.array([0.0, 0.0])) == (-1.0, 1.0)
    assert readable_range(np.array([np.nan])) == (0.0, 1.0)


def test_skipped_ticks_per_window_restart_counts_from_zero() -> None:
    got = per_window(np.array([5.0, 7.0, 7.0, 2.0, 4.0]))
    assert list(got) == [0.0, 2.0, 0.0, 2.0, 2.0]


def test_the_watchs_trend_record_gives_the_range_band_and_the_alarm(tmp_path: Path) -> None:
    """What the watch writes (controller/process/watch.py `_trend`, and each alarm as
    published) is what the Trends tab reads: the parts' ranges and the alarm's part and text."""
    import msgspec

    from controller import protocol as proto
    from controller.process.watch import _trend
    from controller.recording.trend import TrendWriter

    t0 = 1_800_000_000.0
    alarm = proto.DriftAlarm(rig=RIG, seq=1, epoch_s=t0 + 20, part="stiffness", value=0.6,
                             std=0.01, low=0.75, high=1.27, since_epoch_s=t0 + 10,
                             text="stiffness x0.6 below its range", action="measure again")
    with TrendWriter(tmp_path, RIG) as tw:
        for i, (v, state) in enumerate(((1.0, "ok"), (0.6, "outside"), (0.6, "alarm"))):
            part = proto.DriftPart(name="stiffness", value=v, std=0.01, told=True, state=state,
                                   low=0.75, high=1.27)
            msg = proto.DriftState(
                rig=RIG, epoch_s=t0 + 10 * i, window_s=10.0, config_version=1, model="twin",
                parts=[part], delay_ticks=0, twin_delay_ticks=0, plant_residual_rms_deg_s=0.004,
                fitted_residual_rms_deg_s=0.004, loop_measured_rms_deg=0.03,
                loop_predicted_rms_deg=0.03, loop_residual_rms_deg=0.003)
            _trend(tw, msg, None)
        tw.write("/drift/alarm", alarm.epoch_s, msgspec.to_builtins(alarm))
    span = TrendReader().read(tmp_path, RIG, t0 - 1, t0 + 30)
    assert list(span.parts["stiffness_low"]) == [0.75] * 3
    assert list(span.parts["stiffness_high"]) == [1.27] * 3
    assert [(a.epoch_s, a.part, a.text) for a in span.alarms] == [
        (t0 + 20, "stiffness", "stiffness x0.6 below its range")]
    stiff = next(c for c in trend_charts(span, 900) if c.spec.key == "trend_stiffness")
    assert stiff.spec.bands is not None and "allowed range" in stiff.spec.title


def test_the_panel_sends_again_only_what_changed_and_says_what_is_missing(
        week: tuple[Path, object], tmp_path: Path) -> None:
    """The Trends tab in a viser server (no browser): a refresh with the same files and the
    range moved by less than a pixel sends nothing; a changed hour, or a pixel's time later,
    draws again; no trend directory, or none there, is said in words."""
    import viser
    from helpers import free_port

    from server.gui import set_value
    from server.panels.trends import TrendsPanel

    root, wk = week
    clock = [wk.t1_epoch_s]  # type: ignore[attr-defined]
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    panels: list[TrendsPanel] = []
    try:
        panel = TrendsPanel(server.gui, (root,), RIG, 900, refresh_s=3600.0,
                            now=lambda: clock[0])
        panels.append(panel)
        panel.build()
        set_value(panel.range, "last week")
        panel.start()
        panel.reload()
        assert panel.wait_idle(60.0)
        first = panel.charts["trend_gain"].data
        assert "windows in" in panel.status.content, panel.status.content
        clock[0] += 60.0  # a week's pixel is 672 s: nothing to redraw
        panel.reload()
        assert panel.wait_idle(60.0)
        assert panel.charts["trend_gain"].data is first
        clock[0] += 700.0
        panel.reload()
        assert panel.wait_idle(60.0)
        assert panel.charts["trend_gain"].data is not first
        for dirs, words in (((), "No trend directory"), ((tmp_path / "none",), "No trend yet")):
            empty = TrendsPanel(server.gui, dirs, RIG, 900, refresh_s=3600.0)
            panels.append(empty)
            empty.build()
            empty.start()
            empty.reload()
            assert empty.wait_idle(60.0)
            assert words in empty.status.content and empty.charts == {}, empty.status.content
    finally:
        for p in panels:
            p.stop()
        server.stop()
