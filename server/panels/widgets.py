"""Plumbing the panels share: a chart from its `ChartSpec`, HTML text that is only sent when it
changes, and the bordered status boxes (accept / reject / neutral)."""

from __future__ import annotations

import html
from collections.abc import Callable
from typing import Any

from server.charts import ChartSpec, FloatArray

__all__ = ["ACCEPT", "NEUTRAL", "REJECT", "add_chart", "box", "confirm", "esc", "set_html"]

#: (border, background) of a status box.
ACCEPT = ("#2ca02c", "#eaf7ea")
REJECT = ("#d62728", "#fdecea")
NEUTRAL = ("#888", "#f4f4f4")
CAUTION = ("#b26a00", "#fff4e0")


def add_chart(
    gui: Any, spec: ChartSpec, data: tuple[FloatArray, ...], *, aspect: float = 2.0,
    **options: Any,
) -> Any:
    """A uPlot handle built from `spec` (its bands too, if any); afterwards assign `.data`."""
    return gui.add_uplot(
        data=data, series=spec.series, scales=spec.scales, axes=spec.axes, title=spec.title,
        height=spec.height, aspect=aspect, bands=spec.extra.get("bands"), **options,
    )


def set_html(handle: Any, content: str) -> None:
    """Assign an HTML handle's content only when it differs (each assignment is a message to
    every browser)."""
    if handle.content != content:
        handle.content = content


def esc(text: str) -> str:
    """Text for HTML content (quotes stay: the text never goes into an attribute)."""
    return html.escape(text, quote=False)


def box(cls: str, colors: tuple[str, str], content: str, font_px: int | None = 13) -> str:
    """A bordered, tinted block with CSS class `cls` (`colors`: ACCEPT, REJECT, NEUTRAL)."""
    border, background = colors
    size = f";font-size:{font_px}px" if font_px is not None else ""
    return (f"<div class='{cls}' style='border:2px solid {border};background:{background};"
            f"padding:6px;border-radius:4px{size}'>{content}</div>")


def confirm(gui: Any, browser: Any, title: str, body_html: str, ok_label: str,
            on_ok: Callable[[Any], object], ok_color: str = "orange") -> None:
    """A dialog in the browser that asked (`browser`: its viser client; None: every browser,
    on `gui`): `body_html` (already escaped), then `ok_label` calls `on_ok(browser)`, Cancel
    only closes it."""
    g = browser.gui if browser is not None else gui
    with g.add_modal(title) as modal:
        g.add_html(f"<div class='dt-confirm'>{body_html}</div>")
        go = g.add_button(ok_label, color=ok_color)
        cancel = g.add_button("Cancel")

        @go.on_click
        def _go(e: Any) -> None:
            modal.close()
            on_ok(e.client)

        @cancel.on_click
        def _cancel(_e: Any) -> None:
            modal.close()
