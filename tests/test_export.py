"""Export of a chart: the CSV (pure, server/export.py), the Export row that add_chart puts under
every chart (server/panels/widgets.py) and the page script the gate puts into the page.

The CSV is read back with the csv module and float(), independently of how it was written."""

from __future__ import annotations

import csv
import io
import math
from typing import Any

import numpy as np
import pytest

from server import charts
from server.charts import BODE_CHARTS, LIVE_CHARTS, ChartSpec
from server.export import MARK_UNIT, chart_csv, column_header, export_filename
from server.http_access import PAGE_SCRIPT_FILE, HttpAccess, page_script_html
from server.panels.widgets import EXPORT_LABEL, add_chart

SPECS = {s.key: s for s in (*BODE_CHARTS, *LIVE_CHARTS, charts.PREVIEW_CHART,
                            charts.STEP_CHART)}


def _read(text: str) -> tuple[list[str], list[list[str]]]:
    rows = list(csv.reader(io.StringIO(text)))
    return rows[0], rows[1:]


def _floats(rows: list[list[str]]) -> np.ndarray:
    return np.array([[float(c) if c != "" else math.nan for c in r] for r in rows])


def _random_data(spec: ChartSpec, n: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    x = np.sort(rng.uniform(0.01, 100.0, n))
    cols = [rng.normal(0.0, 1e3, n) * 10.0 ** rng.integers(-12, 12, n)
            for _ in spec.series[1:]]
    return (x, *cols)


@pytest.mark.parametrize("key", sorted(SPECS))
def test_csv_round_trips_every_chart_exactly(key: str) -> None:
    spec = SPECS[key]
    data = _random_data(spec, 257)
    header, rows = _read(chart_csv(spec, data))
    assert len(header) == len(spec.series)  # one column per series, x first
    assert len(rows) == 257 and all(len(r) == len(spec.series) for r in rows)
    back = _floats(rows)
    np.testing.assert_array_equal(back, np.column_stack(data))  # shortest repr: bit-exact


def test_nan_is_an_empty_cell_and_infinities_survive() -> None:
    spec = charts.PREVIEW_CHART  # t, candidate, active, candidate with the DOB off
    t = np.array([0.0, 0.5, 1.0, 1.5])
    cand = np.array([1.0, math.nan, -math.inf, 2.5e-300])
    act = np.array([math.nan, 3.0, math.nan, math.inf])
    off = np.array([0.25, 0.5, 0.75, 1.0])
    _, rows = _read(chart_csv(spec, (t, cand, act, off)))
    assert [r[1] for r in rows] == ["1.0", "", "-inf", "2.5e-300"]
    assert [r[2] for r in rows] == ["", "3.0", "", "inf"]
    back = _floats(rows)
    np.testing.assert_array_equal(back[:, 1], cand)
    np.testing.assert_array_equal(back[:, 2], act)
    np.testing.assert_array_equal(back[:, 3], off)


def test_header_carries_the_units_of_the_axes() -> None:
    loop_mag = next(s for s in BODE_CHARTS if s.key == "loop_mag")
    assert column_header(loop_mag) == [
        "f (Hz)", "|L| candidate (dB)", "|L| active (dB)", "0 dB line (dB)",
        "gain margin (up) (dB)", "gain-reduction margin (down) (dB)"]
    loop_phase = next(s for s in BODE_CHARTS if s.key == "loop_phase")
    assert column_header(loop_phase)[3:] == ["-180 deg line (deg)", "phase margin (deg)"]
    plant = next(s for s in BODE_CHARTS if s.key == "plant")
    assert column_header(plant)[-1] == f"responses diverge (> 1 dB) ({MARK_UNIT})"
    error = next(s for s in LIVE_CHARTS if s.key == "error")
    # The version series is its own unit ("config v"): not repeated.
    assert column_header(error) == ["t (s)", "error (deg)", "config v"]
    steps = charts.STEP_CHART
    assert column_header(steps)[3] == "load step candidate (deg (load step))"
    coherence = charts.identify_chart_specs(1)[2]
    assert column_header(coherence) == ["f (Hz)", "pos 1 coherence"]  # dimensionless


def test_bad_data_is_refused_naming_the_chart_and_series() -> None:
    spec = charts.PREVIEW_CHART
    assert len(spec.series) == 4  # t, candidate, active, candidate with the DOB off
    with pytest.raises(ValueError, match=r"data: 2 columns for the 4 series of chart 'preview'"):
        chart_csv(spec, (np.zeros(3), np.zeros(3)))
    with pytest.raises(ValueError, match=r"series 'active' of chart 'preview'"):
        chart_csv(spec, (np.zeros(3), np.zeros(3), np.zeros(4), np.zeros(3)))


def test_file_names_follow_the_title() -> None:
    loop_mag = next(s for s in BODE_CHARTS if s.key == "loop_mag")
    assert export_filename(loop_mag, "csv") == (
        "dobtune-open-loop-l-speed-loop-magnitude-gain-margin-0-db-l-where-the-phase-is-180-deg"
        ".csv")
    long = next(s for s in BODE_CHARTS if s.key == "rejection")
    name = export_filename(long, "png")
    # The whole title (a cut at 48 characters left out "where the DOB helps").
    assert name == ("dobtune-dob-rejection-gain-tracking-error-without-dob-with-dob-article-eq-23-"
                    "0-db-where-the-dob-helps-0-db-where-it-costs-waterbed.png")
    assert export_filename(ChartSpec("k", "!!!", ({"label": "x"},), {}, ()), "csv") == (
        "dobtune-chart.csv")


# -- the Export row (add_chart), with stand-ins for viser's GUI ------------------------------


class _Handle:
    def __init__(self, **kw: Any) -> None:
        self.__dict__.update(kw)
        self.removed = False
        self.clicks: list[Any] = []

    def on_click(self, fn: Any) -> None:
        self.clicks.append(fn)

    def remove(self) -> None:
        assert not self.removed
        self.removed = True


class _Gui:
    def __init__(self) -> None:
        self.made: list[_Handle] = []

    def add_uplot(self, **kw: Any) -> _Handle:
        self.made.append(_Handle(kind="uplot", **kw))
        return self.made[-1]

    def add_button_group(self, label: str, options: tuple[str, ...], **kw: Any) -> _Handle:
        self.made.append(_Handle(kind="row", label=label, options=options, **kw))
        return self.made[-1]


class _Browser:
    def __init__(self) -> None:
        self.files: list[tuple[str, bytes, bool]] = []

    def send_file_download(self, name: str, content: bytes, save_immediately: bool) -> None:
        self.files.append((name, content, save_immediately))


class _Event:
    def __init__(self, client: Any, value: Any) -> None:
        self.client = client
        self.target = type("T", (), {"value": value})()


def test_every_chart_gets_an_export_row_whose_csv_goes_to_the_browser_that_asked() -> None:
    spec = charts.PREVIEW_CHART
    gui = _Gui()
    chart = add_chart(gui, spec, spec.placeholder([0.0, 1.0]))
    assert [h.kind for h in gui.made] == ["uplot", "row"]  # the row right under its chart
    row = gui.made[1]
    assert row.label == EXPORT_LABEL and row.options == ("CSV",) and len(row.clicks) == 1
    data = (np.array([0.0, 1.0, 2.0]), np.array([0.1, 0.2, math.nan]), np.array([1.0, 2.0, 3.0]),
            np.array([0.3, 0.2, 0.1]))
    chart.data = data  # what the panels do afterwards
    asker, other = _Browser(), _Browser()
    # Whatever a (forged) message carried as the value, a press sends this chart's data.
    for value in ("CSV", "PNG", "../../etc/passwd", ""):
        row.clicks[0](_Event(asker, value))
    assert other.files == []
    assert len(asker.files) == 4
    for name, content, now in asker.files:
        assert name == export_filename(spec, "csv") and now
        assert content.decode() == chart_csv(spec, data)
    row.clicks[0](_Event(None, "CSV"))  # the browser left: nothing to send, no error
    assert len(asker.files) == 4


def test_removing_a_chart_removes_its_export_row() -> None:
    gui = _Gui()
    chart = add_chart(gui, charts.PREVIEW_CHART, charts.PREVIEW_CHART.placeholder([0.0, 1.0]))
    chart.remove()
    assert all(h.removed for h in gui.made)


# -- the page script ---------------------------------------------------------------------------


def test_the_gate_puts_the_page_script_into_the_page_only() -> None:
    from websockets.datastructures import Headers
    from websockets.http11 import Request, Response

    script = page_script_html()
    assert script.startswith("<script>") and "dobtune" in script
    assert PAGE_SCRIPT_FILE.read_text() in script
    page = b"<!doctype html><html><body><div id=root></div></body></html>"

    def viser(_conn: Any, req: Any) -> Response:
        return Response(200, "OK", Headers({"Content-Type": "text/html",
                                            "Content-Length": str(len(page))}), page)

    g = HttpAccess("127.0.0.1", token="t" * 32, proven=True)
    g.page_extra = "<a class='x'>E</a>"
    gated = g.wrap(viser)
    got = gated(None, Request(f"/?token={'t' * 32}", Headers({"Host": "127.0.0.1"})))
    body = bytes(got.body)
    assert body.index(b"<a class='x'>E</a>") < body.index(b"<script>") < body.index(b"</body>")
    assert int(got.headers["Content-Length"]) == len(body)
    other = gated(None, Request(f"/other?token={'t' * 32}", Headers({"Host": "127.0.0.1"})))
    assert b"<script>" not in bytes(other.body)


def test_a_missing_page_script_is_said_not_hidden(tmp_path: Any,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    assert page_script_html(tmp_path / "nothing.js") == ""
    assert "unreadable" in caplog.text
    bad = tmp_path / "bad.js"
    bad.write_text("let s = '</script>';")
    with pytest.raises(ValueError, match="page script"):
        page_script_html(bad)
