"""The Trends tab (issue 34 item 3): a rig's trend over days as the watch keeps it (MCAP, one
file per hour under the controller's `<state-dir>/trend`), plotted for the people who monitor
from afar: the residuals, each estimated part with its allowed range and state, the loop's
health, and the alarms marked on the time axis and listed.

A time range (last hour, day, week) and a rig (every rig with a trend in the dashboard's trend
directories) are chosen; the reading, the reduction to the chart's width and the charts' data
run on a worker thread (`LatestWins`: a new choice replaces one not started), never in a GUI
callback; the view reads again every `refresh_s` (an hour already read is kept:
`TrendReader`). Whatever could not be read is said in the status line, never raised.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path

import viser

from server.charts_trend import TrendChart, alarm_rows, trend_charts
from server.escape import esc
from server.gui import set_scales, set_value
from server.panels.widgets import CAUTION, NEUTRAL, REJECT, add_chart, box, set_html
from server.trends_data import RANGES, TrendReader, TrendSpan, find_rigs
from server.workers import LatestWins, Periodic

__all__ = ["TrendsPanel"]

log = logging.getLogger(__name__)

NO_RIG = "-"


class TrendsPanel:
    """The Trends tab, shared by every browser (built once; a worker assigns the data)."""

    def __init__(self, gui: viser.GuiApi, dirs: tuple[Path, ...], rig_name: str,
                 width_px: int, refresh_s: float = 30.0,
                 now: Callable[[], float] = time.time) -> None:
        """`dirs`: where the trends are (`<state-dir>/trend` of the controllers); `rig_name`:
        the rig shown first; `width_px`: the charts' width (what a range is reduced to)."""
        self.gui = gui
        self.dirs = dirs
        self.rig_name = rig_name
        self.width_px = width_px
        self._now = now
        self.reader = TrendReader()
        self._worker: LatestWins[tuple[str, str]] = LatestWins(self._load, name="trends-read")
        self._refresher = Periodic(lambda _k: self.reload(), refresh_s, name="trends-refresh")
        self._charts: dict[str, viser.GuiUplotHandle] = {}
        self._keys: tuple[tuple[str, int], ...] = ()
        self.loads = 0
        self.last_load_s = 0.0
        """How long the last load took: read, reduce, assign (the charts' messages queued)."""
        self.span: TrendSpan | None = None

    def build(self) -> None:
        gui = self.gui
        rigs = tuple(find_rigs(self.dirs)) or (NO_RIG,)
        first = self.rig_name if self.rig_name in rigs else rigs[0]
        self.range = gui.add_dropdown("Time range", tuple(RANGES), initial_value="last day",
                                      hint="the trend from this long ago until now")
        self.rig = gui.add_dropdown("Rig", rigs, initial_value=first,
                                    hint="every rig with a trend in the dashboard's trend "
                                    "directories (--trend-dir)")
        self.status = gui.add_html(box("dt-trend-status", NEUTRAL, "Reading the trend..."))
        self.alarms = gui.add_html("<div class='dt-trend-alarms'></div>")
        self.plots = gui.add_folder("Trend plots")
        self.range.on_update(lambda _e: self.reload())
        self.rig.on_update(lambda _e: self.reload())

    @property
    def controls(self) -> tuple[viser.GuiDropdownHandle[str], ...]:
        """What any role may change (it only chooses what is read and shown)."""
        return (self.range, self.rig)

    @property
    def charts(self) -> dict[str, viser.GuiUplotHandle]:
        """The charts drawn now, by key (`server.charts_trend`)."""
        return dict(self._charts)

    def start(self) -> None:
        self._worker.start()
        self._refresher.start()

    def stop(self) -> None:
        self._refresher.stop()
        self._worker.stop()

    def reload(self) -> None:
        """Read the chosen rig and range again (on the worker; returns at once)."""
        self._worker.submit((str(self.rig.value), str(self.range.value)))

    def wait_idle(self, timeout_s: float = 30.0) -> bool:
        return self._worker.wait_idle(timeout_s)

    # -- on the worker ---------------------------------------------------------------------------

    def _rigs(self) -> dict[str, Path]:
        found = find_rigs(self.dirs)
        options = tuple(found) or (NO_RIG,)
        if tuple(self.rig.options) != options:
            keep = self.rig.value if self.rig.value in options else (
                self.rig_name if self.rig_name in options else options[0])
            self.rig.options = options
            set_value(self.rig, keep)  # its callback submits this choice again
        return found

    def _load(self, choice: tuple[str, str]) -> None:
        rig, range_name = choice
        t_start = time.perf_counter()
        try:
            found = self._rigs()
            if rig not in found:
                rig = str(self.rig.value)
            if rig not in found:
                self._clear()
                self._say(REJECT, self._no_trend_text())
                return
            t1 = self._now()
            span = self.reader.read(found[rig], rig, t1 - RANGES[range_name], t1)
            if span.empty:
                self._clear()  # another rig's or range's charts must not stand under it
                self._say(REJECT, f"No trend of rig <b>{esc(rig)}</b> in the {esc(range_name)}"
                          f" ({span.files} hourly files in {esc(str(found[rig] / rig))})."
                          + self._problems(span))
                self._show_alarms(span)
                return
            if self._unchanged(span, range_name):
                return  # a refresh with nothing new: nothing sent to the browsers
            charts = trend_charts(span, self.width_px)
            self._draw(charts)
            self._show_alarms(span)
            self.span = span
            self.last_load_s = time.perf_counter() - t_start
            self._say(CAUTION if span.problems else NEUTRAL, self._summary(span, range_name)
                      + self._problems(span))
        except Exception as exc:  # said plainly in the tab (and logged with its traceback)
            log.exception("the trend of %s was not read", rig)
            self._clear()
            self._say(REJECT, f"The trend of rig <b>{esc(rig)}</b> could not be read: "
                      f"{esc(type(exc).__name__)}: {esc(str(exc))}")
        finally:
            self.loads += 1

    def _unchanged(self, span: TrendSpan, range_name: str) -> bool:
        """The same files as drawn, and the range moved by less than a pixel's time."""
        last = self.span
        if last is None or last.rig != span.rig or last.sources != span.sources:
            return False
        px_s = RANGES[range_name] / self.width_px
        return (abs(span.t1_epoch_s - last.t1_epoch_s) < px_s
                and abs((span.t1_epoch_s - span.t0_epoch_s)
                        - (last.t1_epoch_s - last.t0_epoch_s)) < 1e-6)

    def _clear(self) -> None:
        """No charts (what they showed is not what was asked for)."""
        for handle in self._charts.values():
            handle.remove()
        self._charts = {}
        self._keys = ()
        self.span = None

    def _draw(self, charts: list[TrendChart]) -> None:
        keys = tuple((c.spec.key, len(c.spec.series)) for c in charts)
        if keys != self._keys:  # another set of parts: the charts made again
            for handle in self._charts.values():
                handle.remove()
            self._charts = {}
            with self.plots:
                for c in charts:
                    self._charts[c.spec.key] = add_chart(self.gui, c.spec, c.data, aspect=3.0)
            self._keys = keys
            return
        for c in charts:
            handle = self._charts[c.spec.key]
            set_scales(handle, c.scales)
            handle.data = c.data

    def _say(self, colors: tuple[str, str], html: str) -> None:
        set_html(self.status, box("dt-trend-status", colors, html))

    def _show_alarms(self, span: TrendSpan) -> None:
        rows = alarm_rows(span)
        if not rows:
            set_html(self.alarms, "<div class='dt-trend-alarms'>No alarm in this range.</div>")
            return
        items = "".join(f"<li class='dt-trend-alarm'><b>{esc(when)}</b> {esc(part)}: "
                        f"{esc(text)}</li>" for when, part, text in rows)
        more = len(span.alarms) - len(rows)
        set_html(self.alarms, f"<div class='dt-trend-alarms' style='color:#d62728'>"
                 f"{_count(len(span.alarms), 'alarm')} in this range (red dots on the time axis of "
                 f"every chart):<ul style='margin:2px 0 0 16px;padding:0'>{items}</ul>"
                 + (f"and {more} earlier" if more > 0 else "") + "</div>")

    def _no_trend_text(self) -> str:
        if not self.dirs:
            return ("No trend directory: start the dashboard with --trend-dir DIR (a "
                    "controller keeps its rig's trend in &lt;state-dir&gt;/trend).")
        where = ", ".join(esc(str(d)) for d in self.dirs)
        return (f"No trend yet in {where}: the watch beside the controller writes one window "
                "every 10 s once the loop runs (dobtune controller starts it unless "
                "--no-watch or --auth).")

    @staticmethod
    def _problems(span: TrendSpan) -> str:
        if not span.problems:
            return ""
        items = "".join(f"<li>{esc(p)}</li>" for p in span.problems[:8])
        return (f"<br>{_count(len(span.problems), 'file')} not read whole:<ul "
                f"style='margin:2px 0 0 16px;padding:0' class='dt-trend-problems'>{items}</ul>")

    def _summary(self, span: TrendSpan, range_name: str) -> str:
        t = span.parts.get("t")
        newest = (time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(float(t[-1]))) + " UTC"
                  if t is not None and t.size else "-")
        return (f"Rig <b>{esc(span.rig)}</b>, {esc(range_name)}: {span.windows} windows in "
                f"{span.files} hourly files, newest {newest}; {_count(len(span.alarms), 'alarm')}. "
                f"Each chart draws at most two points per pixel ({self.width_px} px).")


def _count(n: int, what: str) -> str:
    return f"{n} {what}" + ("" if n == 1 else "s")
