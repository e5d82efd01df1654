"""A thin typed layer over the viser GUI calls the project makes that viser's own type hints
do not carry: a handle's `value` assigned (viser's setter exists and sends the value to the
browsers, but its handles' `value` reads as a read-only property to a type checker)."""

from __future__ import annotations

from typing import TypeVar

import viser

__all__ = ["ValueHandle", "set_scales", "set_value"]

T = TypeVar("T")

#: The value controls the dashboard builds.
ValueHandle = (viser.GuiDropdownHandle[str] | viser.GuiTextHandle | viser.GuiCheckboxHandle
               | viser.GuiSliderHandle[float])


def set_value(handle: ValueHandle, value: object) -> None:
    """`handle.value = value` (viser runs the handle's callbacks at once in this thread and
    sends the value to the browsers)."""
    setattr(handle, "value", value)  # noqa: B010 (the setter, typed here once)


def set_scales(chart: viser.GuiUplotHandle, scales: dict[str, dict[str, object]]) -> None:
    """A uPlot chart's scales as the charts build them (plain dicts: `server.charts`), which
    viser types as its own `Scale` TypedDict."""
    setattr(chart, "scales", scales)  # noqa: B010 (typed here once)
