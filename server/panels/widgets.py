"""Plumbing the panels share: a chart from its `ChartSpec`, HTML text that is only sent when it
changes, and the bordered status boxes (accept / reject / neutral)."""

from __future__ import annotations

import html
from typing import Any

from server.charts import ChartSpec, FloatArray

__all__ = ["ACCEPT", "NEUTRAL", "REJECT", "add_chart", "box", "esc", "set_html"]

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
