"""A thin typed layer over the viser GUI calls the project makes that viser's own type hints
do not carry: a handle's `value` assigned (viser's setter exists and sends the value to the
browsers, but its handles' `value` reads as a read-only property to a type checker)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, TypeVar

import viser

from controller.core.arrays import FloatArray

__all__ = ["Browser", "NumberShown", "ValueHandle", "add_uplot", "on_press", "on_press_group",
           "set_scales", "set_value"]

T = TypeVar("T")

#: The browser that pressed a control or asked (None: no browser: a script, a test, the API).
Browser = viser.ClientHandle | None

#: The value controls the dashboard builds.
ValueHandle = (viser.GuiDropdownHandle[str] | viser.GuiTextHandle | viser.GuiCheckboxHandle
               | viser.GuiSliderHandle[float])


class NumberShown(Protocol):
    """A handle that shows a number (a progress bar: viser does not export its class)."""

    @property
    def value(self) -> float: ...



def set_value(handle: ValueHandle | NumberShown, value: object) -> None:
    """`handle.value = value` (viser runs the handle's callbacks at once in this thread and
    sends the value to the browsers)."""
    setattr(handle, "value", value)  # noqa: B010 (the setter, typed here once)


def set_scales(chart: viser.GuiUplotHandle, scales: dict[str, dict[str, object]]) -> None:
    """A uPlot chart's scales as the charts build them (plain dicts: `server.charts`), which
    viser types as its own `Scale` TypedDict."""
    setattr(chart, "scales", scales)  # noqa: B010 (typed here once)


def on_press(button: viser.GuiButtonHandle,
             act: Callable[[viser.ClientHandle | None], object]) -> None:
    """`act(browser)` when `button` is pressed, in the browser that pressed it (what `act`
    returns is dropped: viser's button callbacks return nothing)."""

    def pressed(event: viser.GuiEvent[viser.GuiButtonHandle]) -> None:
        act(event.client)

    button.on_click(pressed)


def on_press_group(group: viser.GuiButtonGroupHandle,
                   act: Callable[[str, viser.ClientHandle | None], object]) -> None:
    """`act(option, browser)` when an option of the button group `group` is pressed."""

    def pressed(event: viser.GuiEvent[viser.GuiButtonGroupHandle]) -> None:
        act(str(event.target.value), event.client)

    group.on_click(pressed)


def add_uplot(gui: viser.GuiApi, *, data: tuple[FloatArray, ...],
              series: tuple[dict[str, object], ...], scales: dict[str, dict[str, object]],
              axes: tuple[dict[str, object], ...], title: str | None, height: float | None,
              aspect: float, bands: object, cursor: object,
              padding: tuple[int, int, int, int]) -> viser.GuiUplotHandle:
    """`gui.add_uplot(...)` with a chart's series, scales, axes, bands and cursor as the charts
    build them (plain dicts: `server.charts`), which viser types as its own TypedDicts."""
    add: Callable[..., viser.GuiUplotHandle] = gui.add_uplot  # (the TypedDicts: typed here once)
    return add(data=data, series=series, scales=scales, axes=axes, title=title, height=height,
               aspect=aspect, bands=bands, cursor=cursor, padding=padding)
