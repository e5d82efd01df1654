"""Recordings panel: the `.mcap` files of a directory (`dobtune record`, the black box) with
their configuration and the article's metrics, and two of them overlaid (before / after):
errors aligned on their reference trajectory, metrics side by side, the configuration diff;
a time scrubber replays the overlay through a window; Record / Stop records the rig into the
directory (the recorder of `dobtune record`, in a thread of this process).

Two places: `build` (the controls' Recordings tab: the directory, Record / Stop, the list,
shared) and the plots panel's wide Compare runs tab (`build_compare`), where each browser gets
a `CompareView` of its own when it connects (`compare_in`): the pickers, the two runs' names and
numbers side by side, the overlay charts of their errors and of their references, the replay
scrubber, the configuration diff. What one browser compares is shown to that browser only, and
any role may compare (it changes nothing); a comparison opens only recordings the list shows,
by name (issue 31: it opened `../` and absolute paths, showed them to every browser, and its
error told whether such a file existed).

Reading and the metrics are `controller.recording` (the same as `dobtune report`); the
alignment and the diff are `controller.recording.compare` (pure). Files are read in the
callback's thread (viser runs callbacks on a pool), and each file's summary is cached by
(size, modification time), so a refresh only reads new or changed files.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import viser

from controller.client import ControllerUnavailable
from controller.client.recorder import Recorder, RecordOptions
from controller.recording.compare import SummaryRow, align_runs, config_diff, summary_row
from controller.recording.mcap_io import Recording, read_recording, read_recordings
from controller.recording.report import REVERSAL_WINDOW_S, metrics
from server.charts import CANDIDATE, NO_DOB, ChartSpec, minmax_decimate, ranged_scales
from server.escape import esc
from server.gui import Browser, on_press, on_press_group, set_scales
from server.http_access import Refused
from server.panels.widgets import NEUTRAL, add_chart, box, set_html

__all__ = ["COMPARE_TAB", "NOT_LISTED", "OVERLAY_CHART", "REFERENCE_CHART", "CompareView",
           "RecordingsPanel", "compare_html", "list_html"]

log = logging.getLogger(__name__)

#: Error of run A and of run B (aligned) against A's time.
OVERLAY_CHART = ChartSpec(
    key="recordings_overlay",
    title="Position error, before (A) and after (B), aligned on the reference",
    series=({"label": "t (s)"},
            {"label": "A", "stroke": CANDIDATE, "width": 1.2, "scale": "y"},
            {"label": "B", "stroke": NO_DOB, "width": 1.2, "scale": "y"}),
    scales={"x": {"time": False, "auto": True}, "y": {"auto": True}},
    axes=({"label": "s", "scale": "x"}, {"label": "deg", "scale": "y"}),
    height=260,
)
#: The references of A and of B shifted by the alignment's lag: how well they were aligned.
REFERENCE_CHART = ChartSpec(
    key="recordings_reference",
    title="Reference trajectory, A and B shifted onto A",
    series=({"label": "t (s)"},
            {"label": "A", "stroke": CANDIDATE, "width": 1.2, "scale": "y"},
            {"label": "B", "stroke": NO_DOB, "width": 1.2, "scale": "y", "dash": (6, 4)}),
    scales={"x": {"time": False, "auto": True}, "y": {"auto": True}},
    axes=({"label": "s", "scale": "x"}, {"label": "deg", "scale": "y"}),
    height=180,
)
#: The plots panel's tab with the comparison (wide: the charts and the table side by side).
COMPARE_TAB = "Compare runs"
_NONE = "-"
_MAX_POINTS = 2000
#: The replay window: the scrubber shows the overlay's last this many seconds up to its time.
REPLAY_WINDOW_S = 10.0
#: A comparison's answer to a name the list does not show (the same whether or not a file of
#: that name exists anywhere).
NOT_LISTED = "Pick two of the recordings listed in the Recordings tab."
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


def _change(va: float, vb: float) -> str:
    """B against A: the difference and its percentage of A."""
    if not (math.isfinite(va) and math.isfinite(vb)):
        return "n/a"
    pct = f" ({100.0 * (vb - va) / abs(va):+.0f} %)" if va != 0.0 else ""
    return f"{vb - va:+.4g} deg{pct}"


def compare_html(a: SummaryRow, b: SummaryRow, lag_s: float, correlation: float) -> str:
    """The two runs' names, their metrics side by side with B's change, per configuration
    version, and the configuration diff (latest configuration of each)."""
    rows = [("peak |error|", a.peak_error_deg, b.peak_error_deg),
            ("RMSE", a.rmse_deg, b.rmse_deg),
            (f"peak |error| at reversals ({REVERSAL_WINDOW_S:g} s)",
             a.reversal_peak_error_deg, b.reversal_peak_error_deg)]
    cell = "style='padding:2px 10px;text-align:right'"
    metrics_rows = "".join(
        f"<tr class='dt-compare-metric'><td>{esc(k)}</td><td {cell}>{_fmt(va)}</td>"
        f"<td {cell}>{_fmt(vb)}</td><td {cell}>{_change(va, vb)}</td></tr>"
        for k, va, vb in rows)
    seg_rows = "".join(
        f"<tr><td>{esc(who)} v{v}</td><td {cell}>{_fmt(peak)}</td><td {cell}>{_fmt(rmse)}</td>"
        f"<td {cell}>{n}</td></tr>"
        for who, row in (("A", a), ("B", b)) for v, peak, rmse, n in row.segments)
    segments = (f"<div><b>Per configuration version</b><table><tr><th>segment</th><th>peak</th>"
                f"<th>RMSE</th><th>samples</th></tr>{seg_rows}</table></div>" if seg_rows else "")
    diff = config_diff(a.config, b.config)
    diff_rows = "".join(
        f"<tr><td>{esc(k)}</td><td {cell}>{esc(str(va))}</td><td {cell}>{esc(str(vb))}</td></tr>"
        for k, va, vb in diff) or "<tr><td colspan='3'>identical configurations</td></tr>"
    names = "".join(
        f"<div class='dt-compare-run'><b style='color:{color}'>{who}</b> {esc(r.name)} "
        f"<span style='color:#555'>({r.duration_s:.1f} s, "
        f"{'no version' if r.config_version is None else f'v{r.config_version}'})</span></div>"
        for who, color, r in (("A (before)", CANDIDATE, a), ("B (after)", NO_DOB, b)))
    return (
        f"<div class='dt-compare' style='font-size:13px'>{names}"
        f"<div style='color:#555'>B shifted by {lag_s:+.2f} s onto A (reference correlation "
        f"{correlation:.3f})</div>"
        "<div style='display:flex;flex-wrap:wrap;gap:8px 28px;align-items:flex-start'>"
        f"<table><tr><th></th><th {cell}>A</th><th {cell}>B</th><th {cell}>B - A</th></tr>"
        f"{metrics_rows}</table>{segments}"
        "<div><b>Configuration difference</b><table>"
        f"<tr><th>field</th><th {cell}>A</th><th {cell}>B</th></tr>{diff_rows}</table></div>"
        "</div></div>")


class RecordingsPanel:
    """`build()` inside the controls' tab, `build_compare()` inside the plots panel's; `refresh()`
    rereads the directory (also the Refresh button)."""

    def __init__(self, gui: viser.GuiApi, directory: str | Path,
                 record: RecordOptions | None = None, rig_name: str = "rig",
                 authorize: Callable[[Browser, str], object] | None = None) -> None:
        """`record`: how the recorder reaches the rig (endpoints, rig name, credentials; its
        `out` is replaced by a new file of the directory); None: no Record button.
        `authorize(browser, action)`: raises `Refused` (told to that browser) unless the user
        at `browser` may start or stop a recording (operators; a viewer watches)."""
        self.gui = gui
        self._authorize = authorize
        self.directory = Path(directory)
        self._record = record
        self._rig_name = rig_name
        self._rec_stop: threading.Event | None = None
        self._rec_thread: threading.Thread | None = None
        self.recording_to: Path | None = None
        self.last_record_output = ""
        self.record_box: Any = None
        self._lock = threading.Lock()
        self._build_lock = threading.Lock()
        self.compare_tab: Any = None
        """The plots panel's Compare runs tab (`build_compare`; None: not built)."""
        self._views: dict[int, CompareView] = {}
        """Each browser's comparison by viser client id (-1: built without a browser)."""
        self._cache: dict[Path, tuple[tuple[int, float], SummaryRow]] = {}
        self.rows: list[SummaryRow] = []
        self.list_box: Any = None

    def build(self, background: bool = True) -> None:
        """The directory, Record / Stop and the list; the directory is then read in a thread
        of its own (`background`: a long recording takes seconds to read) or here."""
        gui = self.gui
        gui.add_html(f"<div class='dt-recordings-dir'>Recordings in <code>"
                     f"{esc(str(self.directory))}</code> (<code>dobtune record</code>, black "
                     "box).</div>")
        if self._record is not None:
            rec = gui.add_button_group("Record", ("Record", "Stop recording"),
                                       hint="record this rig (every tick, status, versions, "
                                       "events) into a new .mcap file in the directory")
            on_press_group(rec, lambda pressed, browser: self.press(pressed, browser))
            self.record_box = gui.add_html("<div class='dt-record'></div>")
        refresh = gui.add_button("Refresh", color="gray", hint="read the directory again")
        on_press(refresh, lambda _browser: self.refresh())
        self.list_box = gui.add_html("")
        gui.add_html(f"<div class='dt-compare-where' style='font-size:12px;color:#555'>Two runs "
                     f"overlaid, their numbers and configuration difference: the plots "
                     f"panel's <b>{COMPARE_TAB}</b> tab.</div>")
        if background:
            set_html(self.list_box, box("dt-recordings", NEUTRAL, "Reading the recordings..."))
            threading.Thread(target=self.refresh, name="recordings-list", daemon=True).start()
        else:
            self.refresh()

    def build_compare(self, plots: viser.PanelHandle) -> None:
        """The plots panel's Compare runs tab; each browser's comparison is built in it when
        the browser connects (`compare_in`)."""
        self.compare_tab = plots.add_tab(COMPARE_TAB)

    def compare_in(self, gui: viser.GuiApi, browser: Browser = None) -> CompareView:
        """A comparison of `browser`'s own, in its `gui` (in the Compare runs tab when
        `build_compare` made one; else where `gui` builds now), offering the files listed."""
        view = CompareView(gui, self)
        with self._build_lock:  # a tab takes one `with` at a time
            if self.compare_tab is not None:
                with self.compare_tab:
                    view.build()
            else:
                view.build()
        key = getattr(browser, "client_id", -1)
        with self._lock:
            self._views[key] = view
            rows = self.rows
        view.show_names(rows)
        return view

    def drop(self, browser_id: int) -> None:
        """The browser left: its comparison goes (its GUI went with it)."""
        with self._lock:
            self._views.pop(browser_id, None)

    def view_of(self, browser: Browser) -> CompareView | None:
        """`browser`'s comparison (None: none; no browser: the one built without one)."""
        with self._lock:
            return self._views.get(getattr(browser, "client_id", -1))

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
        self._show_names(rows)
        return rows

    def _show_names(self, rows: list[SummaryRow]) -> None:
        with self._lock:
            views = list(self._views.values())
        for view in views:
            view.show_names(rows)

    def listed_path(self, name: str) -> Path | None:
        """The file of recording `name` when the list shows it (None: it does not)."""
        with self._lock:
            listed = any(r.name == name for r in self.rows)
        return self.directory / name if listed and Path(name).name == name else None

    # -- recording -----------------------------------------------------------------------------

    def press(self, button: str, browser: Browser = None) -> Path | bool | None:
        """Record or Stop recording pressed in `browser`: refused here, in the server, for a
        user who may not change the rig (a viewer's websocket message reaches this too)."""
        action = "start a recording" if button == "Record" else "stop the recording"
        if self._authorize is not None:
            try:
                self._authorize(browser, action)
            except Refused:
                return None
        return self.start_recording() if button == "Record" else self.stop_recording()

    def start_recording(self) -> Path | None:
        """Record the rig into a new file of the directory until `stop_recording` (None:
        already recording, or no Record button)."""
        if self._record is None:
            return None
        with self._lock:
            if self._rec_thread is not None and self._rec_thread.is_alive():
                self._say_record(f"Already recording to {self.recording_to}.")
                return None
            try:
                self.directory.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                self._say_record(f"Cannot record into {self.directory}: {exc}", error=True)
                return None
            out = self.directory / f"{time.strftime('%Y%m%d-%H%M%S')}-{self._rig_name}.mcap"
            try:
                recorder = Recorder(dataclasses.replace(self._record, out=out))
            except ValueError as exc:
                self._say_record(f"Cannot record: {exc}", error=True)
                return None
            stop = threading.Event()

            def run() -> None:
                try:
                    text, failed = recorder.run(stop).summary(), False
                except ControllerUnavailable as exc:
                    text, failed = f"error: {exc}", True
                except Exception as exc:  # told in the panel and logged; never silent
                    log.exception("recording to %s failed", out)
                    text, failed = f"recording failed: {exc}", True
                self.last_record_output = text
                self._say_record(text, error=failed)
                self.refresh()

            self._rec_stop, self.recording_to = stop, out
            self._rec_thread = threading.Thread(target=run, name="recordings-record",
                                                daemon=True)
            self._rec_thread.start()
        self._say_record(f"Recording to {out.name} (since {time.strftime('%H:%M:%S')}): press "
                         "Stop recording to close the file.")
        return out

    def stop_recording(self, timeout_s: float = 30.0) -> bool:
        """Close the recording (the file is complete when this returns True)."""
        with self._lock:
            stop, thread = self._rec_stop, self._rec_thread
        if stop is None or thread is None:
            self._say_record("Not recording.")
            return False
        stop.set()
        thread.join(timeout_s)
        return not thread.is_alive()

    def _say_record(self, text: str, error: bool = False) -> None:
        if self.record_box is not None:
            color = "color:#d62728;" if error else ""
            set_html(self.record_box, f"<div class='dt-record' style='font-size:12px;{color}'>"
                     f"{esc(text)}</div>")


class CompareView:
    """One browser's comparison in the Compare runs tab: its pickers (the files listed), the
    two runs' names and numbers, the overlay charts, the replay scrubber."""

    def __init__(self, gui: viser.GuiApi, panel: RecordingsPanel) -> None:
        self.gui = gui
        self.panel = panel
        self._aligned: Any = None
        self.pick_a: Any = None
        self.pick_b: Any = None
        self.compare_button: Any = None
        self.compare_box: Any = None
        self.chart: Any = None
        self.ref_chart: Any = None
        self.scrub: Any = None

    def build(self) -> None:
        gui = self.gui
        self.pick_a = gui.add_dropdown("A (before)", (_NONE,), initial_value=_NONE)
        self.pick_b = gui.add_dropdown("B (after)", (_NONE,), initial_value=_NONE)
        self.compare_button = gui.add_button(
            "Compare", hint="overlay B's error on A's, aligned on the reference trajectory; "
            "metrics and configuration diff (in this browser)")
        self.compare_button.on_click(
            lambda _e: self.compare(self.pick_a.value, self.pick_b.value))
        self.compare_box = gui.add_html(box(
            "dt-compare", NEUTRAL, "Pick two recordings (the list: the controls' Recordings "
            "tab) and press Compare."))
        # Empty: NaN on a fixed y scale draws nothing (zeros drew a flat line that read as data).
        for attr, spec in (("chart", OVERLAY_CHART), ("ref_chart", REFERENCE_CHART)):
            empty = (np.array([0.0, 1.0]), np.full(2, np.nan), np.full(2, np.nan))
            handle = add_chart(gui, spec, empty)
            set_scales(handle, ranged_scales(spec, empty))
            setattr(self, attr, handle)
        self.scrub = gui.add_slider(
            "Replay at (s)", min=0.0, max=1.0, step=0.1, initial_value=1.0,
            hint=f"the overlay's last {REPLAY_WINDOW_S:g} s up to this time; the end shows the "
            "whole run")
        self.scrub.on_update(lambda _e: self.replay(float(self.scrub.value)))

    def show_names(self, rows: list[SummaryRow]) -> None:
        """The pickers offer the files listed (B: the newest when A and B are the same)."""
        names = tuple(r.name for r in rows) or (_NONE,)
        for pick in (self.pick_a, self.pick_b):
            if pick is not None and tuple(pick.options) != names:
                pick.options = names
        if self.pick_b is not None and len(rows) >= 2 and self.pick_b.value == rows[0].name:
            self.pick_b.value = rows[-1].name

    def compare(self, name_a: str, name_b: str) -> str:
        """Overlay B on A; returns (and shows, in this browser) the comparison's HTML, or why
        not. Only recordings the list shows are opened: any other name (a path, `../`, a file
        not listed) gets `NOT_LISTED`, whether or not such a file exists."""
        if _NONE in (name_a, name_b):
            return self._say("Pick two recordings.")
        path_a, path_b = self.panel.listed_path(name_a), self.panel.listed_path(name_b)
        if path_a is None or path_b is None:
            return self._say(NOT_LISTED)
        try:
            rec_a, rec_b = read_recordings((path_a, path_b))
            al = align_runs(*_columns(rec_a), *_columns(rec_b))
        except (OSError, ValueError) as exc:
            return self._say(f"Cannot compare: {exc}")
        row_a = summary_row(name_a, rec_a.configs, metrics(rec_a))
        row_b = summary_row(name_b, rec_b.configs, metrics(rec_b))
        html = compare_html(row_a, row_b, al.lag_s, al.correlation)
        self._aligned = al
        if self.scrub is not None:
            end = float(al.t_s[-1]) if len(al.t_s) else 1.0
            self.scrub.max = round(max(end, 0.1), 1)
            self.scrub.value = self.scrub.max  # the whole run
        self.replay(math.inf)
        return self._say(html, raw=True)

    def replay(self, t_s: float) -> tuple[np.ndarray, ...] | None:
        """The overlay up to `t_s` in a REPLAY_WINDOW_S window (inf, or the end: all of it);
        returns the error chart's data (None: nothing compared yet). The reference chart
        shows the same window."""
        al = self._aligned
        if al is None or len(al.t_s) == 0:
            return None
        t, ea, eb, ra, rb = al.t_s, al.error_a_deg, al.error_b_deg, al.ref_a_deg, al.ref_b_deg
        if t_s < float(t[-1]) - 1e-9:
            keep = (t >= t_s - REPLAY_WINDOW_S) & (t <= t_s)
            if np.count_nonzero(keep) >= 2:
                t, ea, eb, ra, rb = t[keep], ea[keep], eb[keep], ra[keep], rb[keep]
        x, (da, db) = minmax_decimate(t, [ea, eb], _MAX_POINTS)
        data = (x, da, db)
        xr, (dra, drb) = minmax_decimate(t, [ra, rb], _MAX_POINTS)
        for handle, spec, d in ((self.chart, OVERLAY_CHART, data),
                                (self.ref_chart, REFERENCE_CHART, (xr, dra, drb))):
            if handle is not None:
                scales = ranged_scales(spec, d)
                if scales != handle.scales:  # a new scale re-creates the chart
                    handle.scales = scales
                handle.data = d
        return data

    def _say(self, text: str, raw: bool = False) -> str:
        html = text if raw else box("dt-compare", NEUTRAL, esc(text))
        if self.compare_box is not None:
            set_html(self.compare_box, html)
        return html


def _columns(rec: Recording) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return rec.state["t_s"], rec.state["ref_deg"], rec.state["error_deg"]
