"""Recordings panel: the `.mcap` files of a directory (`dobtune record`, the black box) with
their configuration and the article's metrics, and two of them overlaid (before / after):
errors aligned on their reference trajectory, metrics side by side, the configuration diff.

Reading and the metrics are `controller.recording` (the same as `dobtune report`); the
alignment and the diff are `controller.recording.compare` (pure). Files are read in the
callback's thread (viser runs callbacks on a pool), and each file's summary is cached by
(size, modification time), so a refresh only reads new or changed files.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import Any

import numpy as np

from controller.recording.compare import SummaryRow, align_runs, config_diff, summary_row
from controller.recording.mcap_io import Recording, read_recording
from controller.recording.report import REVERSAL_WINDOW_S, metrics
from server.charts import CANDIDATE, NO_DOB, ChartSpec, minmax_decimate
from server.panels.widgets import NEUTRAL, add_chart, box, esc, set_html

__all__ = ["OVERLAY_CHART", "RecordingsPanel", "compare_html", "list_html"]

#: Error of run A and of run B (aligned) against A's time.
OVERLAY_CHART = ChartSpec(
    key="recordings_overlay",
    title="Position error, before (A) and after (B), aligned on the reference",
    series=({"label": "t (s)"},
            {"label": "A", "stroke": CANDIDATE, "width": 1.2, "scale": "y"},
            {"label": "B", "stroke": NO_DOB, "width": 1.2, "scale": "y"}),
    scales={"x": {"time": False, "auto": True}, "y": {"auto": True}},
    axes=({"label": "s", "scale": "x"}, {"label": "deg", "scale": "y"}),
    height=220,
)
_NONE = "-"
_MAX_POINTS = 2000
#: Configuration fields shown in the list (the rest are in the diff).
_SHOWN = ("dob_on", "q_type", "q_cutoff_hz", "ff_on")


def _fmt(v: float, unit: str = "deg") -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v:.4g} {unit}"


def list_html(rows: list[SummaryRow], directory: Path) -> str:
    """The table of recordings (newest name last, as listed)."""
    if not rows:
        return box("dt-recordings", NEUTRAL, f"No .mcap files in {esc(str(directory))}.")
    head = ("<tr><th>file</th><th>s</th><th>config</th><th>peak |e|</th><th>RMSE</th>"
            f"<th>reversals ({REVERSAL_WINDOW_S:g} s)</th><th>lost</th></tr>")
    body = []
    for r in rows:
        shown = ", ".join(f"{k}={r.config[k]}" for k in _SHOWN if k in r.config)
        version = _NONE if r.config_version is None else f"v{r.config_version}"
        body.append(
            f"<tr><td>{esc(r.name)}</td><td>{r.duration_s:.1f}</td>"
            f"<td>{version} {esc(shown)}</td><td>{_fmt(r.peak_error_deg)}</td>"
            f"<td>{_fmt(r.rmse_deg)}</td><td>{_fmt(r.reversal_peak_error_deg)}</td>"
            f"<td>{r.gaps}</td></tr>")
    return (f"<div class='dt-recordings' style='font-size:12px'><table>{head}{''.join(body)}"
            "</table></div>")


def compare_html(a: SummaryRow, b: SummaryRow, lag_s: float, correlation: float) -> str:
    """Metrics side by side and the configuration diff (latest configuration of each)."""
    rows = [("peak |error|", a.peak_error_deg, b.peak_error_deg),
            ("RMSE", a.rmse_deg, b.rmse_deg),
            (f"peak |error| at reversals ({REVERSAL_WINDOW_S:g} s)",
             a.reversal_peak_error_deg, b.reversal_peak_error_deg)]
    metrics_rows = "".join(
        f"<tr><td>{esc(k)}</td><td>{_fmt(va)}</td><td>{_fmt(vb)}</td></tr>"
        for k, va, vb in rows)
    diff = config_diff(a.config, b.config)
    diff_rows = "".join(
        f"<tr><td>{esc(k)}</td><td>{esc(str(va))}</td><td>{esc(str(vb))}</td></tr>"
        for k, va, vb in diff) or "<tr><td colspan='3'>identical configurations</td></tr>"
    return (
        f"<div class='dt-compare' style='font-size:12px'><b>A</b> {esc(a.name)} &nbsp; "
        f"<b>B</b> {esc(b.name)}<br>B shifted by {lag_s:+.2f} s onto A (reference "
        f"correlation {correlation:.3f})<table><tr><th></th><th>A</th><th>B</th></tr>"
        f"{metrics_rows}</table><b>Configuration difference</b><table>"
        f"<tr><th>field</th><th>A</th><th>B</th></tr>{diff_rows}</table></div>")


class RecordingsPanel:
    """`build()` inside a tab; `refresh()` rereads the directory (also the Refresh button)."""

    def __init__(self, gui: Any, directory: str | Path) -> None:
        self.gui = gui
        self.directory = Path(directory)
        self._lock = threading.Lock()
        self._cache: dict[Path, tuple[tuple[int, float], SummaryRow]] = {}
        self.rows: list[SummaryRow] = []
        self.chart: Any = None
        self.list_box: Any = None
        self.compare_box: Any = None
        self.pick_a: Any = None
        self.pick_b: Any = None

    def build(self, background: bool = True) -> None:
        """The widgets; the directory is then read in a thread of its own (`background`: a
        long recording takes seconds to read) or here."""
        gui = self.gui
        gui.add_markdown(f"Recordings in `{self.directory}` (`dobtune record`, black box).")
        refresh = gui.add_button("Refresh", color="gray", hint="read the directory again")
        refresh.on_click(lambda _e: self.refresh())
        self.list_box = gui.add_html("")
        self.pick_a = gui.add_dropdown("A (before)", (_NONE,), initial_value=_NONE)
        self.pick_b = gui.add_dropdown("B (after)", (_NONE,), initial_value=_NONE)
        compare = gui.add_button("Compare", hint="overlay B's error on A's, aligned on the "
                                 "reference trajectory; metrics and configuration diff")
        compare.on_click(lambda _e: self.compare(self.pick_a.value, self.pick_b.value))
        self.compare_box = gui.add_html("")
        self.chart = add_chart(gui, OVERLAY_CHART, OVERLAY_CHART.placeholder([0.0, 1.0]))
        if background:
            set_html(self.list_box, box("dt-recordings", NEUTRAL, "Reading the recordings..."))
            threading.Thread(target=self.refresh, name="recordings-list", daemon=True).start()
        else:
            self.refresh()

    # -- the list ------------------------------------------------------------------------------

    def _row(self, path: Path) -> SummaryRow:
        st = path.stat()
        key = (st.st_size, st.st_mtime)
        hit = self._cache.get(path)
        if hit is not None and hit[0] == key:
            return hit[1]
        rec = read_recording(path)
        row = summary_row(path.name, rec.configs, metrics(rec))
        self._cache[path] = (key, row)
        return row

    def refresh(self) -> list[SummaryRow]:
        """Read the directory (new or changed files only); update the list and the pickers.
        A file that cannot be read is listed as such, never hidden."""
        with self._lock:
            files = sorted(self.directory.glob("*.mcap")) if self.directory.is_dir() else []
            rows, bad = [], []
            for f in files:
                try:
                    rows.append(self._row(f))
                except (OSError, ValueError) as exc:
                    bad.append(f"{f.name}: {exc}")
            self.rows = rows
        if self.list_box is not None:
            html = list_html(rows, self.directory)
            if bad:
                html += "".join(f"<div style='color:#d62728'>{esc(b)}</div>" for b in bad)
            set_html(self.list_box, html)
        names = tuple(r.name for r in rows) or (_NONE,)
        for pick in (self.pick_a, self.pick_b):
            if pick is not None and tuple(pick.options) != names:
                pick.options = names
        if self.pick_b is not None and len(rows) >= 2 and self.pick_b.value == rows[0].name:
            self.pick_b.value = rows[-1].name
        return rows

    # -- two runs ------------------------------------------------------------------------------

    def compare(self, name_a: str, name_b: str) -> str:
        """Overlay B on A; returns (and shows) the comparison's HTML, or why not."""
        if _NONE in (name_a, name_b):
            return self._say("Pick two recordings.")
        try:
            rec_a = read_recording(self.directory / name_a)
            rec_b = read_recording(self.directory / name_b)
            al = align_runs(*_columns(rec_a), *_columns(rec_b))
        except (OSError, ValueError) as exc:
            return self._say(f"Cannot compare: {exc}")
        row_a = summary_row(name_a, rec_a.configs, metrics(rec_a))
        row_b = summary_row(name_b, rec_b.configs, metrics(rec_b))
        html = compare_html(row_a, row_b, al.lag_s, al.correlation)
        if self.chart is not None:
            x, (ea, eb) = minmax_decimate(al.t_s, [al.error_a_deg, al.error_b_deg], _MAX_POINTS)
            self.chart.data = (x, ea, eb)
        return self._say(html, raw=True)

    def _say(self, text: str, raw: bool = False) -> str:
        html = text if raw else box("dt-compare", NEUTRAL, esc(text))
        if self.compare_box is not None:
            set_html(self.compare_box, html)
        return html


def _columns(rec: Recording) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return rec.state["t_s"], rec.state["ref_deg"], rec.state["error_deg"]
