"""Plumbing the panels share: a chart from its `ChartSpec` (with its Export row), HTML text
that is only sent when it changes, and the bordered status boxes (accept / reject / neutral)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from typing import Literal

import numpy as np
import viser

from controller.core.arrays import FloatArray
from server import viser_adapter
from server.charts import ChartSpec
from server.escape import esc
from server.export import chart_csv, export_filename
from server.gui import add_uplot

__all__ = ["ACCEPT", "EXPORT_LABEL", "NEUTRAL", "REJECT", "add_chart", "add_export_row", "box",
           "confirm", "parse_number", "reason_list", "send_data", "set_html"]

log = logging.getLogger(__name__)

#: The colours a dialog's OK button is drawn in (viser's names).
ButtonColor = Literal["orange", "green", "red", "blue"]

#: (border, background) of a status box.
ACCEPT = ("#2ca02c", "#eaf7ea")
REJECT = ("#d62728", "#fdecea")
NEUTRAL = ("#888", "#f4f4f4")
CAUTION = ("#b26a00", "#fff4e0")


#: The label of the row under every chart; web_assets/dashboard.js finds the rows by it (and
#: their one "CSV" button) and adds the PNG button beside it.
EXPORT_LABEL = "Export"
EXPORT_HINT = "CSV: this chart's data, from the dashboard; PNG: the chart as drawn here"
#: uPlot's padding (top, right, bottom, left), px: room above the plot for the top tick
#: labels (with 0 at the top, the top label of a scale whose range ends on a tick was cut in
#: half, on the right-hand axes too).
PADDING = (12, 24, 0, 0)


def add_chart(
    gui: viser.GuiApi, spec: ChartSpec, data: tuple[FloatArray, ...], *, aspect: float = 2.0,
    cursor: dict[str, object] | None = None,
) -> viser.GuiUplotHandle:
    """A uPlot handle built from `spec` (its bands too, if any), with its Export row under it;
    afterwards assign `.data`. `gui`: the shared `server.gui` or one browser's `client.gui`;
    either way a CSV goes only to the browser whose button was pressed."""
    chart = add_uplot(
        gui, data=data, series=spec.series, scales=spec.scales, axes=spec.axes,
        title=spec.title, height=spec.height, aspect=aspect, bands=spec.bands,
        cursor=cursor if cursor is not None else spec.cursor, padding=PADDING,
    )
    add_export_row(gui, spec, chart)
    return chart


def add_export_row(gui: viser.GuiApi, spec: ChartSpec,
                   chart: viser.GuiUplotHandle) -> viser.GuiButtonGroupHandle:
    """The compact row under `chart`: "CSV" (made here from the chart's present data and sent
    to the browser that pressed it); the page's script adds "PNG" beside it (drawn in the
    browser from the chart's canvas). `chart.remove()` removes the row too."""
    row = gui.add_button_group(EXPORT_LABEL, ("CSV",), hint=EXPORT_HINT)

    def send_csv(event: viser.GuiEvent[viser.GuiButtonGroupHandle]) -> None:
        # Nothing of the message is used (its value is whatever the sender wrote): a press is
        # a request for this chart's data, for the browser that pressed.
        browser = event.client
        if browser is None:
            log.warning("CSV of %r: the browser that asked is gone", spec.key)
            return
        content = chart_csv(spec, chart.data).encode("utf-8")
        browser.send_file_download(export_filename(spec, "csv"), content,
                                   save_immediately=True)

    row.on_click(send_csv)
    remove_chart = chart.remove

    def remove() -> None:
        row.remove()
        remove_chart()

    # the row goes with its chart (panels re-create charts)
    setattr(chart, "remove", remove)  # noqa: B010 (a method replaced: typed here once)
    return row


def send_data(chart: viser.GuiUplotHandle, data: tuple[FloatArray, ...],
              browsers: Iterable[viser.ClientHandle]) -> None:
    """A uPlot handle's `data` set here (its CSV reads it, in float64) and sent to `browsers`
    only, where an assignment to `chart.data` goes to every browser (and stays in viser's
    buffer for the browsers that connect later: a browser that gets none of these shows the
    data it had). The page gets 32-bit floats: half the bytes of the live charts' ten
    refreshes a second (about 7 significant digits: a chart of a few hundred pixels shows
    three)."""
    viser_adapter.send_prop_to(chart, "data", data, browsers, wire=_float32)


def _float32(data: object) -> tuple[np.ndarray, ...]:
    """A chart's data (viser's cast: a tuple of float64 arrays) as float32 arrays."""
    assert isinstance(data, tuple)
    return tuple(np.asarray(a, dtype=np.float32) for a in data)


def set_html(handle: viser.GuiHtmlHandle, content: str) -> None:
    """Assign an HTML handle's content only when it differs (each assignment is a message to
    every browser)."""
    if handle.content != content:
        handle.content = content


def reason_list(reasons: tuple[str, ...] | list[str], cls: str) -> str:
    """Reasons as a bulleted list, each item of CSS class `cls` (escaped here)."""
    items = "".join(f"<li class='{cls}'>{esc(r)}</li>" for r in reasons)
    return f"<ul style='margin:4px 0 0 16px;padding:0'>{items}</ul>"


def box(cls: str, colors: tuple[str, str], content: str, font_px: int | None = 13) -> str:
    """A bordered, tinted block with CSS class `cls` (`colors`: ACCEPT, REJECT, NEUTRAL)."""
    border, background = colors
    size = f";font-size:{font_px}px" if font_px is not None else ""
    return (f"<div class='{cls}' style='border:2px solid {border};background:{background};"
            f"padding:6px;border-radius:4px{size}'>{content}</div>")


def confirm(gui: viser.GuiApi, browser: viser.ClientHandle | None, title: str, body_html: str,
            ok_label: str, on_ok: Callable[[viser.ClientHandle | None], object],
            ok_color: ButtonColor = "orange") -> None:
    """A dialog in the browser that asked (`browser`: its viser client; None: every browser,
    on `gui`): `body_html` (already escaped), then `ok_label` calls `on_ok(browser)`, Cancel
    only closes it."""
    g = browser.gui if browser is not None else gui
    with g.add_modal(title) as modal:
        g.add_html(f"<div class='dt-confirm'>{body_html}</div>")
        go = g.add_button(ok_label, color=ok_color)
        cancel = g.add_button("Cancel")

        @go.on_click
        def _go(e: viser.GuiEvent[viser.GuiButtonHandle]) -> None:
            modal.close()
            on_ok(e.client)

        @cancel.on_click
        def _cancel(_e: viser.GuiEvent[viser.GuiButtonHandle]) -> None:
            modal.close()


def parse_number(text: str, label: str, lo: float, hi: float,
                 integer: bool = False) -> tuple[float | None, str]:
    """A field's text as a number from `lo` to `hi` (exponents too: "1e1" is 10), or why it
    is none, naming the field."""
    text = text.strip()
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if math.isfinite(v) and lo <= v <= hi and (not integer or v == round(v)):
        return v, ""
    kind = "a whole number" if integer else "a number"
    return None, f"{label}: {text!r} is not {kind} from {lo:g} to {hi:g}"
