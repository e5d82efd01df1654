"""Two recordings compared (alignment on the reference, configuration diff, the list's rows)
and the dashboard's Recordings panel on real MCAP files.

References: shifts known by construction (the alignment must find them), numpy's own
peak / RMSE on the samples written.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from helpers import free_port
from sine_recordings import sine_run, write_sine_recording

from controller.core.config import LoopConfig, config_from_builtins
from controller.recording.compare import align_runs, config_diff, flatten, summary_row
from controller.recording.mcap_io import Recording, read_recording
from controller.recording.report import metrics


def test_alignment_finds_a_known_shift_of_a_periodic_reference() -> None:
    a = sine_run(0.0, 40.0, 1.0)
    b = sine_run(3.7, 40.0, 0.5)  # B started 3.7 s later along the trajectory
    al = align_runs(*a, *b)
    assert al.lag_s == pytest.approx(-3.7, abs=0.011)  # one grid step (10 ms)
    assert al.correlation > 0.999
    assert al.t_s.size == pytest.approx((40.0 - 3.7) / 0.01, abs=2)  # the longest overlap
    np.testing.assert_allclose(al.ref_b_deg, al.ref_a_deg, atol=0.03)
    np.testing.assert_allclose(al.error_b_deg, 0.5 * al.error_a_deg, atol=2e-4)


def test_alignment_of_a_random_reference_is_exact() -> None:
    rng = np.random.default_rng(1)
    x = np.cumsum(rng.normal(size=3000))
    t = np.arange(2000) * 0.01
    a = (t, x[:2000], x[:2000] * 1e-3)
    b = (t, x[137:2137], np.zeros(2000))  # B's sample j is A's j + 137
    al = align_runs(*a, *b)
    assert al.lag_s == pytest.approx(-1.37, abs=1e-9)
    assert al.correlation == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(al.ref_b_deg, al.ref_a_deg, atol=1e-9)


def test_alignment_refuses_bad_input() -> None:
    a = sine_run(0.0, 2.0, 1.0)
    with pytest.raises(ValueError, match="fewer than 2 finite samples"):
        align_runs(*a, np.array([0.0]), np.array([1.0]), np.array([0.0]))
    with pytest.raises(ValueError, match="dt_s"):
        align_runs(*a, *a, dt_s=0.0)
    with pytest.raises(ValueError, match="min_overlap"):
        align_runs(*a, *a, min_overlap=1.5)


def test_config_diff_names_nested_fields() -> None:
    a = {"q_type": "q31", "q_cutoff_hz": 0.5, "nominal": {"mn_den": [1.0, 2.0, 1.0]}}
    b = {"q_type": "q31", "q_cutoff_hz": 0.8, "nominal": {"mn_den": [1.0, 3.0, 1.0]}, "x": 1}
    assert config_diff(a, b) == [("nominal.mn_den", (1.0, 2.0, 1.0), (1.0, 3.0, 1.0)),
                                 ("q_cutoff_hz", 0.5, 0.8), ("x", None, 1)]
    assert config_diff(a, a) == []
    assert flatten({"n": {"m": {"k": 1}}}) == {"n.m.k": 1}


def test_summary_row_has_the_latest_configuration_and_numpys_metrics(tmp_path: Path) -> None:
    cfg = LoopConfig().with_(q_cutoff_hz=0.8)
    path = write_sine_recording(tmp_path / "a.mcap", cfg, 0.0, 1.0)
    rec = read_recording(path)
    row = summary_row("a.mcap", rec.configs, metrics(rec))
    e = rec.state["error_deg"]
    assert row.peak_error_deg == pytest.approx(float(np.max(np.abs(e))), rel=1e-12)
    assert row.rmse_deg == pytest.approx(float(np.sqrt(np.mean(e**2))), rel=1e-12)
    assert row.config_version == 1
    assert config_from_builtins(row.config) == cfg
    assert row.samples == 30000 and row.gaps == 0
    # One configuration version: one segment, equal to the whole run.
    assert len(row.segments) == 1
    v, peak, rmse, n = row.segments[0]
    assert (v, n) == (1, 30000)
    assert peak == pytest.approx(row.peak_error_deg, rel=1e-12)
    assert rmse == pytest.approx(row.rmse_deg, rel=1e-12)




@pytest.fixture
def gui() -> Iterator[object]:
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        yield server.gui
    finally:
        server.stop()


@pytest.mark.slow
def test_the_panel_lists_and_compares_two_runs(gui: object, tmp_path: Path) -> None:
    from server.panels.recordings import NOT_LISTED, RecordingsPanel

    before = LoopConfig()
    after = before.with_(q_cutoff_hz=0.8)
    write_sine_recording(tmp_path / "1-before.mcap", before, 0.0, 1.0)
    write_sine_recording(tmp_path / "2-after.mcap", after, 3.7, 0.5)
    (tmp_path / "3-broken.mcap").write_bytes(b"not an mcap file")
    panel = RecordingsPanel(gui, tmp_path)
    panel.build(background=False)
    view = panel.compare_in(gui)  # after the list was read: the pickers offer its files
    assert [r.name for r in panel.rows] == ["1-before.mcap", "2-after.mcap"]
    listing = panel.list_box.content
    assert "1-before.mcap" in listing and "3-broken.mcap" in listing  # named, not hidden
    assert f"{panel.rows[1].peak_error_deg:.4g} deg" in listing
    assert view.pick_b.value == "2-after.mcap"
    html = view.compare("1-before.mcap", "2-after.mcap")
    assert "q_cutoff_hz" in html and "0.8" in html and "-3.70 s" in html
    assert "Per configuration version" in html and "B v1" in html
    assert "1-before.mcap" in html and "2-after.mcap" in html  # both runs named
    # B's change against A: its peak is half of A's (-50 %), computed here from the rows.
    a, b = panel.rows
    assert f"{b.peak_error_deg - a.peak_error_deg:+.4g} deg (-50 %)" in html
    x, ea, eb = view.chart.data
    assert len(x) <= 2000 and np.max(np.abs(eb)) == pytest.approx(
        0.5 * np.max(np.abs(ea)), rel=0.05)
    # The references overlaid: B shifted by the lag lies on A.
    xr, ra, rb = view.ref_chart.data
    np.testing.assert_array_equal(xr, x)
    np.testing.assert_allclose(rb, ra, atol=0.05)
    # A file the list shows as unreadable is not one of its recordings: not opened.
    assert NOT_LISTED in view.compare("1-before.mcap", "3-broken.mcap")


def _reversal_metrics_by_loops(t: np.ndarray, ref: np.ndarray,
                               e: np.ndarray) -> tuple[int, float]:
    """The reversal count and peak |error| written out sample by sample: a reversal is where
    the sign of the reference's step differs from the last non-zero one; its window is every
    finite sample with t0 <= t <= t0 + 0.3 s."""
    reversals, worst, last = 0, math.nan, 0.0
    for k in range(len(ref) - 1):
        step = ref[k + 1] - ref[k]
        if step == 0.0:
            continue
        if last != 0.0 and (step > 0) != (last > 0):
            reversals += 1
            w = [abs(x) for tt, x in zip(t, e, strict=True)
                 if t[k] <= tt <= t[k] + 0.3 and math.isfinite(x)]
            if w:
                worst = max(w) if math.isnan(worst) else max(worst, max(w))
        last = step
    return reversals, worst


@pytest.mark.parametrize("case", ["sine", "flat stretches", "non-finite errors",
                                  "times out of order", "no finite error after reversals",
                                  "error rising (the window's end counts)",
                                  "error falling (the window's start counts)"])
def test_reversal_metrics_equal_a_sample_by_sample_count(case: str) -> None:
    rng = np.random.default_rng(abs(hash(case)) % 2**32)
    n = 4000
    t = np.arange(n) / 1000.0
    ref = 5.0 * np.sin(2 * np.pi * 1.3 * t)
    e = 0.01 * rng.standard_normal(n)
    if case == "flat stretches":
        ref = np.round(ref, 1)  # zero steps around every reversal
    if case == "non-finite errors":
        e[rng.choice(n, 600, replace=False)] = np.nan
        e[rng.choice(n, 50, replace=False)] = np.inf
    if case == "times out of order":
        t = t.copy()
        t[1000:1100] = t[1000:1100][::-1]
    if case == "no finite error after reversals":
        e[:] = np.nan
    if case.startswith("error rising"):
        e = t.copy()
    if case.startswith("error falling"):
        e = 10.0 - t
    rec = Recording(state={"seq": np.arange(n), "t_s": t, "ref_deg": ref, "error_deg": e,
                           "config_version": np.ones(n, dtype=np.int64)},
                    log_time_s=t.copy())
    m = metrics(rec)
    reversals, worst = _reversal_metrics_by_loops(t, ref, e)
    assert reversals >= 9
    assert m.reversals == reversals
    if math.isnan(worst):
        assert math.isnan(m.reversal_peak_error_deg)
    else:
        assert m.reversal_peak_error_deg == worst
