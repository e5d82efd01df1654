"""The candidate's speed-command filter controls (`LoopConfig.command_filter`: off, a notch or
a low-pass on Cv's output): a dropdown for the kind and one text field per number, the
fields of the other kind hidden. A field is the value as typed (never written back while
typed, never clamped): a word or a number out of range makes the candidate invalid, refused
naming the field (`command_filter.notch_hz`, ...), as the gains' fields are."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import msgspec
import viser

from controller.core.command_filter import (
    LOWPASS_DAMPING_RANGE,
    NOTCH_DEPTH_DB_RANGE,
    NOTCH_WIDTH_RANGE,
    CommandFilter,
)
from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from server.gui import ValueHandle, set_value

__all__ = ["FILTER_CONTROLS", "FILTER_LABELS", "FilterControls", "filter_control_problem"]

#: The dropdown's labels -> `CommandFilter.kind`.
FILTER_LABELS = {"off": "off", "notch": "notch", "low-pass": "lowpass"}


@dataclass(frozen=True)
class _Field:
    name: str
    """The CommandFilter field (its control: name + "_input")."""
    label: str
    kind: str
    """The filter kind the field belongs to."""
    hint: str


_FIELDS = (
    _Field("notch_hz", "Notch (Hz)", "notch",
           "the notch's centre in Hz (at the resonance; below 0.45 x the loop rate)"),
    _Field("notch_depth_db", "Notch depth (dB)", "notch",
           f"attenuation at the centre, {NOTCH_DEPTH_DB_RANGE[0]:g} to "
           f"{NOTCH_DEPTH_DB_RANGE[1]:g} dB"),
    _Field("notch_width", "Notch width", "notch",
           f"the notch's pole damping ({NOTCH_WIDTH_RANGE[0]:g} to {NOTCH_WIDTH_RANGE[1]:g}): "
           "wider covers a mode that moves with position"),
    _Field("lowpass_hz", "Low-pass (Hz)", "lowpass",
           "the 2nd-order low-pass's corner in Hz (below 0.45 x the loop rate)"),
    _Field("lowpass_damping", "Low-pass damping", "lowpass",
           f"{LOWPASS_DAMPING_RANGE[0]:g} to {LOWPASS_DAMPING_RANGE[1]:g}"),
)
#: The controls a kept candidate holds for the filter (their names).
FILTER_CONTROLS = ("filter_kind", *(f.name + "_input" for f in _FIELDS))
KIND_HINT = ("a notch or 2nd-order low-pass on the speed controller's output, before the DOB "
             "(for a resonance that limits the speed loop); off: no filter")


def _label_of(kind: str) -> str:
    return next((label for label, k in FILTER_LABELS.items() if k == kind), "off")


def _fmt(v: float) -> str:
    """A number as its field shows it: the shortest text that reads back as the same float
    (a loaded filter's value is the configuration's, not a rounding of it)."""
    return repr(float(v))


def filter_control_problem(name: str, value: object) -> str:
    """Why `value` (read from a kept candidate's file) is no value of the filter control
    `name` ("" : it is one)."""
    ok = (value in FILTER_LABELS if name == "filter_kind"
          else isinstance(value, str) and len(value) <= 64)
    return "" if ok else f"controls.{name}: {value!r} is not a value of this control"


class FilterControls:
    """The filter's controls in `gui` (built by `build`), read as `LoopConfig.command_filter`
    (`values`), set from a configuration (`show`). `echo()`: the controls are being set by the
    panel (their callbacks are not a user's change); `changed()`: ask for the verdict."""

    kind: viser.GuiDropdownHandle[str]

    def __init__(self, gui: viser.GuiApi, echo: Callable[[], bool],
                 changed: Callable[[], None]) -> None:
        self.gui = gui
        self._echo = echo
        self._changed = changed
        self.inputs: dict[str, viser.GuiTextHandle] = {}
        self._shown = CommandFilter()
        """The filter the controls were last set to (`build`, `show`)."""

    def build(self, a: LoopConfig) -> None:
        cf = self._shown = a.command_filter
        self.kind = self.gui.add_dropdown("Speed-command filter", tuple(FILTER_LABELS),
                                          initial_value=_label_of(cf.kind), hint=KIND_HINT)
        for f in _FIELDS:
            self.inputs[f.name] = self.gui.add_text(
                f.label, initial_value=_fmt(getattr(cf, f.name)), hint=f.hint,
                visible=f.kind == cf.kind)
        self.kind.on_update(self._on_kind)
        for h in self.inputs.values():
            h.on_update(self._on_typed)

    def handles(self) -> dict[str, ValueHandle]:
        """Every control by the name it is kept under (`FILTER_CONTROLS`)."""
        return {"filter_kind": self.kind,
                **{f.name + "_input": self.inputs[f.name] for f in _FIELDS}}

    def _show_fields(self) -> None:
        kind = FILTER_LABELS.get(str(self.kind.value), "off")
        for f in _FIELDS:
            self.inputs[f.name].visible = f.kind == kind

    def _on_kind(self, _event: object) -> None:
        self._show_fields()
        if not self._echo():
            self._changed()

    def _on_typed(self, _event: object) -> None:
        if not self._echo():
            self._changed()

    def values(self) -> dict[str, object]:
        """{"command_filter": the filter as the controls show it}; raises ConfigError naming
        the field of the chosen kind whose text is no number (its range is CommandFilter's,
        also by name). The other kind's numbers (and all of them when off) are those last
        shown (`show`): off is the shown filter switched off, so that a candidate switched
        back to off is the configuration it came from."""
        kind = FILTER_LABELS.get(str(self.kind.value))
        if kind is None:
            raise ConfigError("command_filter.kind", f"{self.kind.value!r} is not a filter")
        typed: dict[str, float] = {}
        for f in _FIELDS:
            if f.kind != kind:
                continue
            text = str(self.inputs[f.name].value).strip()
            try:
                v = float(text)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise ConfigError(f"command_filter.{f.name}", f"{text!r} is not a number")
            typed[f.name] = v
        return {"command_filter": msgspec.structs.replace(self._shown, kind=kind, **typed)}

    def show(self, a: LoopConfig) -> None:
        """Every control at `a`'s filter (the caller holds the panel's `setting`)."""
        cf = self._shown = a.command_filter
        set_value(self.kind, _label_of(cf.kind))
        for f in _FIELDS:
            set_value(self.inputs[f.name], _fmt(getattr(cf, f.name)))
        self._show_fields()

    def restored(self) -> None:
        """After a kept candidate's values were set: the fields of its kind shown."""
        self._show_fields()
