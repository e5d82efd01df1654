"""The dashboard's Identify panel without a browser.

Offline on the simulated rig (no controller: the dashboard shows its 'not reachable' banner):
a short run fills the charts and shows the fit and the recommended cut-offs; Abort mid-run
keeps the measured positions, marked incomplete; "Use as nominal model" changes the tuning
candidate's nominal and re-evaluates it, and sends nothing.

On a real controller process (integration): the same short run inside its loop through
IdentifyStart and the identify queryable; Abort through IdentifyAbort keeps the partial data.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from collections.abc import Iterator

import numpy as np
import pytest
from helpers import free_port, spawn, wait_for

from controller import protocol as proto
from controller.core.config import LoopConfig
from controller.ident.spec import IdentifySpec
from server import charts
from server.dashboard.app import Dashboard, DashboardOptions
from server.dashboard.demo import controller_command, stop_process
from server.panels.identify import (
    ABORTED,
    DASHBOARD_FIELDS,
    DONE,
    WHERE_CONTROLLER,
    IdentifyPanel,
    IdentifySettings,
)
from server.panels.nominal_tuning import NominalTuningPanel

SHORT = IdentifySettings(dict(mode="open", signal="multisine", f_min_hz=1.0, f_max_hz=8.0,
                              points_per_decade=4, positions=1, amplitude_deg_s=10.0))






@pytest.fixture(scope="module")
def short_run(dash: Dashboard) -> IdentifyPanel:
    p = dash.identify
    assert p is not None
    t0 = time.perf_counter()
    assert p.start(SHORT)
    assert p.wait_done(30.0)
    print(f"short identification: {time.perf_counter() - t0:.2f} s wall")
    return p


def _finite(a: np.ndarray) -> int:
    return int(np.isfinite(a).sum())


def test_short_identification_fills_charts_and_shows_fit_and_cutoffs(
    short_run: IdentifyPanel,
) -> None:
    p = short_run
    assert p.state == DONE, p.text
    r = p.result
    assert r is not None and r.complete and r.fit is not None and r.nominal is not None
    # charts: 1 position -> |G|, +std, -std, fit; phase + fit; coherence
    mag = p.responses.charts["identify_mag"].data
    assert len(mag) == 1 + 3 + 1
    n_meas = r.positions[0].estimate.freq_hz.size  # type: ignore[union-attr]
    assert n_meas >= 4
    assert _finite(mag[1]) == n_meas
    assert _finite(mag[2]) == n_meas and np.all(mag[2][np.isfinite(mag[2])]
                                                 >= mag[1][np.isfinite(mag[2])])
    assert _finite(mag[4]) >= 50  # the fit on a dense grid
    assert np.all(np.diff(mag[0]) > 0)
    coh = p.responses.charts["identify_coherence"].data
    assert _finite(coh[1]) == n_meas and np.nanmin(coh[1]) > 0.9
    # the simulated rig's M(s)P(s): about 7.1 Hz, zeta about 0.73
    assert 6.4 < r.fit.natural_freq_hz < 7.8
    html = p.result_html.content
    assert "Fit Mn Pn" in html and "&zeta;" in html and "residual" in html
    assert "Q31" in html and "Q20" in html and "recommended" in html
    assert r.recommended_cutoff_hz["q31"] is not None
    assert f"{r.recommended_cutoff_hz['q31']:.3g} Hz" in html
    assert "two positions" in html  # agreement needs >= 2
    assert float(p.progress_bar.value) == 100.0
    assert "dt-id-done" in p.status.content and "offline on the simulated rig" in p.status.content
    assert not p.use.button.disabled and not p.start_button.disabled and p.abort_button.disabled


def test_use_as_nominal_changes_candidate_and_reevaluates_without_apply(
    dash: Dashboard, short_run: IdentifyPanel, monkeypatch: pytest.MonkeyPatch,
) -> None:
    t = dash.panel_of(None)
    assert isinstance(t, NominalTuningPanel)
    applied: list[LoopConfig] = []
    monkeypatch.setattr(t.applier, "submit",
                        lambda _panel, c, _confirm=False, _browser=None: applied.append(c))
    assert t.wait_idle(5.0)
    r = short_run.result
    assert r is not None and r.nominal is not None
    assert t.candidate().nominal != r.nominal
    before = t.update_count
    assert short_run.use_as_nominal()
    wait_for(lambda: t.update_count > before and t.wait_idle(0.1))
    assert t.candidate().nominal == r.nominal
    ev = t.last_evaluation
    assert ev is not None and ev.config.nominal == r.nominal  # the gate saw the fitted model
    assert t.active.nominal != r.nominal  # nothing reached the controller's config
    assert applied == []
    # No controller here: its plant knowledge (the only one judged on) cannot take the
    # responses, and the dashboard says so instead of judging on knowledge of its own.
    assert not dash.engine.measured
    assert "Apply" in short_run.use.result.content
    assert "dt-nominal-fitted" in t.cutoff_text.content  # the Tune tab says so
    wait_for(lambda: "not adopted by the controller" in dash.knowledge.text.content, 15.0)
    # Revert drops it
    t.revert()
    assert t.wait_idle(5.0)
    assert t.candidate().nominal == t.active.nominal
    assert "dt-nominal-fitted" not in t.cutoff_text.content
    assert applied == []


def test_abort_mid_run_keeps_partial_data_marked_incomplete(dash: Dashboard) -> None:
    p = dash.identify
    assert p is not None
    slow = IdentifySettings(dict(mode="open", signal="multisine", f_min_hz=1.0, f_max_hz=8.0,
                                 points_per_decade=4, positions=3), pace=4.0)
    assert p.start(slow)
    assert not p.start(slow)  # a second start while running is refused (server-side check)
    assert "already" in p.status.content
    try:
        # the first position is on the chart: its curve is appended, then the chart published
        # (waiting on the list alone raced the publish: 'assert 0 > 0' under load)
        wait_for(lambda: len(p.responses.curves) >= 1
                 and _finite(p.responses.charts["identify_mag"].data[1]) > 0, 120.0)
    finally:  # never leave the module's panel running for the next test
        aborted = p.abort()
    assert aborted
    assert p.wait_done(10.0)
    assert p.state == ABORTED
    r = p.result
    assert r is not None and not r.complete and r.fit is None
    assert 1 <= sum(1 for q in r.positions if q.complete) < 3
    mag = p.responses.charts["identify_mag"].data
    assert len(mag) == 1 + 3 * 3 + 1
    assert _finite(mag[1]) > 0  # position 1 still drawn
    assert _finite(mag[-1]) == 0  # no fit
    assert "INCOMPLETE" in p.result_html.content and "INCOMPLETE" in p.status.content
    assert "dt-id-aborted" in p.status.content and "INCOMPLETE" in p.responses.note.content
    assert p.use.button.disabled and not p.use_as_nominal()
    assert not p.abort()  # nothing running any more


def test_bad_settings_are_refused_before_anything_runs(dash: Dashboard) -> None:
    p = dash.identify
    assert p is not None
    assert not p.start(IdentifySettings(dict(f_min_hz=5.0, f_max_hz=2.0)))
    assert "f_min_hz" in p.status.content and p.state != "running"
    assert not p.start(IdentifySettings(dict(seed=3)))  # not a field of the panel's spec
    assert "seed" in p.status.content and p.state != "running"


def test_the_panels_fields_are_generated_from_the_spec(dash: Dashboard) -> None:
    """Labels, units, ranges and defaults of the Identify fields come from IdentifySpec."""
    shown = {f.name: (f.title, f.default, f.param.choices or f.limits) for f in DASHBOARD_FIELDS}
    assert shown == {
        "mode": ("Mode", "open", ("open", "closed")),
        "signal": ("Signal", "multisine", ("sine", "multisine")),
        "f_min_hz": ("f min (Hz)", 0.1, (0.01, 200.0, 0.01)),
        "f_max_hz": ("f max (Hz)", 20.0, (0.02, 400.0, 0.01)),
        "points_per_decade": ("Points per decade", 10, (1, 200, 1.0)),
        "positions": ("Positions", 3, (1, 36, 1.0)),
        "amplitude_deg_s": ("Amplitude (deg/s)", 10.0, (0.1, 100.0, 0.1)),
    }
    p = dash.identify
    assert p is not None
    assert p.settings().spec() == IdentifySpec()  # the panel starts at the spec's defaults
    for f in DASHBOARD_FIELDS:
        assert p.form.fields[f.name].hint == f.param.help, f.name  # the spec's help text


def test_identify_chart_data_pure() -> None:
    f = np.array([1.0, 2.0, 4.0])
    c = charts.MeasuredCurve("a", f, np.array([0.0, -1.0, -3.0]), np.array([-5.0, -10.0, -20.0]),
                             np.array([0.1, np.nan, 0.2]), np.array([0.99, 0.98, 0.97]))
    d = charts.identify_data(2, [c, None], np.array([1.5, 3.0]), np.array([1.0 + 0j, 0.5j]))
    x = d["identify_mag"][0]
    assert list(x) == [1.0, 1.5, 2.0, 3.0, 4.0]
    assert len(d["identify_mag"]) == 1 + 6 + 1 and len(d["identify_phase"]) == 1 + 2 + 1
    assert np.isnan(d["identify_mag"][4]).all()  # position 2 not measured yet
    assert d["identify_mag"][2][2] == -1.0  # NaN std -> no band width
    specs = charts.identify_chart_specs(2)
    for s in specs:
        assert len(s.series) == len(d[s.key])
    assert specs[0].bands[1]["series"]  # type: ignore[index] == (5, 6)


def test_partial_controller_status_is_drawn_with_its_band(dash: Dashboard) -> None:
    p = dash.identify
    assert p is not None and p.state != "running"
    n = p.responses.n
    pos = proto.PositionResponse(
        index=0, center_deg=0.0, complete=False, points_done=2, points_total=5,
        freq_hz=[0.5, 1.0], mag_db=[-1.0, -3.0], phase_deg=[-20.0, -45.0],
        coherence=[0.99, 0.98], mag_std_db=[0.2, 0.4], phase_std_deg=[1.0, 2.0],
    )
    st = proto.IdentifyStatus(rig="r", state="running", run_id=1, progress=0.3,
                              positions=[pos])
    st = proto.decode(proto.encode(st), proto.IdentifyStatus)  # as it comes over the wire
    before = p.responses.updates
    drawn = p.show_partial(st, n, LoopConfig().nominal)
    assert drawn == (2,) and p.responses.updates == before + 1
    mag = p.responses.charts["identify_mag"].data
    x = list(mag[0])
    assert x == [0.5, 1.0]
    np.testing.assert_allclose(mag[1], [-1.0, -3.0])  # the curve
    np.testing.assert_allclose(mag[2], [-0.8, -2.6])  # band: + std
    np.testing.assert_allclose(mag[3], [-1.2, -3.4])  # band: - std
    assert charts.identify_chart_specs(n)[0].bands  # drawn as a band
    np.testing.assert_allclose(p.responses.charts["identify_coherence"].data[1], [0.99, 0.98])
    # the same status again: nothing redrawn
    assert p.show_partial(st, n, LoopConfig().nominal, drawn) == drawn
    assert p.responses.updates == before + 1


# -- on the controller ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def remote_dash() -> Iterator[Dashboard]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory(prefix="dobtune-identify-") as state:
        from pathlib import Path

        proc = spawn(controller_command(endpoint, "idtest", Path(state)))
        try:
            opts = DashboardOptions(connect=(endpoint,), rig_name="idtest", port=free_port(),
                                    verbose=False)
            with Dashboard(opts) as d:
                d.panel_in(d.server.gui)  # a candidate panel without a browser
                wait_for(lambda: d.client.status is not None
                         and d.client.status.mode == "running", 30.0)
                yield d
        finally:
            stop_process(proc)


@pytest.mark.integration
def test_short_identification_on_the_controller(
    remote_dash: Dashboard, monkeypatch: pytest.MonkeyPatch,
) -> None:
    d = remote_dash
    p, t = d.identify, d.panel_of(None)
    assert p is not None and isinstance(t, NominalTuningPanel)
    assert p.settings().where == WHERE_CONTROLLER  # the default when a controller is known
    applied: list[LoopConfig] = []
    monkeypatch.setattr(t.applier, "submit",
                        lambda _panel, c, _confirm=False, _browser=None: applied.append(c))
    before = d.client.get_config()
    t0 = time.perf_counter()
    assert p.start(dataclasses.replace(SHORT, where=WHERE_CONTROLLER))
    wait_for(lambda: p.progress > 0.1, 20.0)  # progress comes from the controller's status
    assert "on the controller" in p.status.content
    assert p.wait_done(90.0)
    print(f"short identification on the controller: {time.perf_counter() - t0:.1f} s wall")
    assert p.state == DONE, p.text
    v = p.view
    assert v is not None and v.complete and v.fit is not None and v.nominal is not None
    assert 6.4 < v.fit.natural_freq_hz < 7.8
    assert v.recommended_cutoff_hz.get("q31") is not None
    mag = p.responses.charts["identify_mag"].data
    assert _finite(mag[1]) >= 4 and _finite(mag[-1]) >= 50
    html = p.result_html.content
    assert "Fit Mn Pn" in html and "Q31" in html and "Q20" in html
    assert p.result is None  # the controller's run: no offline result
    assert p.use_as_nominal()
    wait_for(lambda: t.wait_idle(0.1) and t.candidate().nominal == v.nominal)
    assert applied == []
    after = d.client.get_config()
    assert after.version == before.version and after.config == before.config
    t.revert()


@pytest.mark.integration
def test_abort_on_the_controller_keeps_partial_data(remote_dash: Dashboard) -> None:
    p = remote_dash.identify
    assert p is not None
    two = IdentifySettings(dict(mode="open", signal="multisine", f_min_hz=1.0, f_max_hz=8.0,
                                points_per_decade=4, positions=2), where=WHERE_CONTROLLER)
    assert p.start(two)
    wait_for(lambda: p.progress > 0.6, 60.0)  # into the second position
    assert p.abort()
    assert p.wait_done(30.0)
    assert p.state == ABORTED, p.text
    v = p.view
    assert v is not None and not v.complete and v.fit is None and v.nominal is None
    assert v.positions_done == 1
    assert _finite(p.responses.charts["identify_mag"].data[1]) >= 4  # position 1 still drawn
    assert "INCOMPLETE" in p.result_html.content and "INCOMPLETE" in p.status.content
    assert not p.use_as_nominal()
    st = remote_dash.client.status
    assert st is not None and st.mode == "stopped"  # the controller holds (stopped); no fault


@pytest.mark.integration
def test_an_identifications_positions_are_adopted_as_one_knowledge(remote_dash: Dashboard) -> None:
    """Use fit adopts every position's response in one request: one new plant knowledge on
    the controller (one by one it made a version, a verdict and a twin build per position:
    v2, v3, v4 after a Measure at 3 positions), with each response and its uncertainty."""
    from controller.gate.knowledge import MeasuredResponse

    d = remote_dash
    before = d.client.knowledge().record
    assert before is not None
    f = np.geomspace(0.5, 8.0, 6)
    h = 1.0 / (1.0 + 1j * f / 7.0)
    ms = [MeasuredResponse(f"identify pos{i}_{120 * i}deg", f, (1.0 + 0.01 * i) * h,
                           spread=np.full(f.size, 0.02)) for i in range(3)]
    d.knowledge.add_identified(ms, None)
    after = d.client.knowledge().record
    assert after is not None and after.version == before.version + 1
    got = {m.name: m for m in after.to_knowledge().measured}
    for m in ms:
        assert m.name in got
        np.testing.assert_allclose(got[m.name].response, m.response, rtol=1e-12)
        assert got[m.name].spread is not None
        np.testing.assert_allclose(got[m.name].spread, m.spread, rtol=1e-12)
    assert d.engine.plant.version == after.version
    assert f"v{after.version}: " in d.knowledge.text.content
