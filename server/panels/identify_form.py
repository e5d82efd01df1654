"""The Identify panel's settings: where the run happens (with a controller), the spec's fields,
generated from the metadata of `controller.ident.spec.IdentifySpec` (label, unit, range, help),
and the offline pace. Each field's text is read here; one that is none of its values is named
under the fields, and Start refuses until each is one."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import viser

from controller.core.errors import ConfigError
from controller.ident.spec import IDENTIFY_FIELDS, IdentifySpec
from server.escape import esc
from server.panels.widgets import parse_number

__all__ = [
    "DASHBOARD_FIELDS",
    "OFFLINE_NOTE",
    "PACE_LABEL",
    "WHERE_CONTROLLER",
    "WHERE_OFFLINE",
    "IdentifyForm",
    "IdentifySettings",
]

OFFLINE_NOTE = "offline on the simulated rig"
WHERE_CONTROLLER, WHERE_OFFLINE = "controller", "offline simulation"

#: The IdentifySpec fields on the panel (those with a `Param.label`), in order.
DASHBOARD_FIELDS = tuple(f for f in IDENTIFY_FIELDS if f.param.label)

PACE_LABEL = "Pace (x real time, 0 = fastest)"
PACE_MAX = 1000.0

#: A spec field's value as the panel reads it (a choice's text, or a number).
FieldValue = str | float | int


@dataclasses.dataclass(frozen=True)
class IdentifySettings:
    """What the panel's controls ask for."""

    values: Mapping[str, FieldValue] = dataclasses.field(default_factory=dict)
    """IdentifySpec fields by name (`DASHBOARD_FIELDS`; a missing one takes its default)."""
    pace: float = 0.0
    """Simulated seconds per wall second (0: as fast as possible); offline only."""
    where: str = WHERE_OFFLINE
    """WHERE_CONTROLLER or WHERE_OFFLINE."""

    def spec(self) -> IdentifySpec:
        """The validated spec; raises ConfigError naming the field."""
        try:
            return IdentifySpec(**self.values)  # type: ignore[arg-type]
        except TypeError as exc:  # not a spec field
            raise ConfigError("settings", str(exc)) from exc


def field_errors_html(errors: list[str] | tuple[str, ...]) -> str:
    if not errors:
        return "<div class='dt-identify-field-error'></div>"
    lines = "".join(f"<div>{esc(e)}</div>" for e in errors)
    return ("<div class='dt-identify-field-error dt-identify-field-invalid' "
            f"style='font-size:12px;color:#d62728'><b>Not a value:</b>{lines}"
            "Start refuses until each is one.</div>")


class IdentifyForm:
    """The settings' controls, built in `gui` at once: "Run on" (with a controller), a note on
    what moves, the spec's fields, the pace and the line naming a field that is not a value."""

    def __init__(self, gui: viser.GuiApi, with_controller: bool) -> None:
        self.where: viser.GuiDropdownHandle[str] | None = None
        if with_controller:
            self.where = gui.add_dropdown(
                "Run on", (WHERE_CONTROLLER, WHERE_OFFLINE), initial_value=WHERE_CONTROLLER,
                hint="controller: the excitation runs in its loop and the rig moves; offline "
                     "simulation: the built-in simulated rig in this dashboard")
        gui.add_html(
            "<div class='dt-identify-note' style='font-size:12px;color:#b36b00'>"
            + ("On the controller the <b>rig moves</b> (limits: amplitude, position window, "
               "duration; E-STOP aborts). " if with_controller else "")
            + f"Offline: <b>{OFFLINE_NOTE}</b>.</div>"
        )
        self.fields: dict[str, viser.GuiDropdownHandle[str] | viser.GuiTextHandle] = {}
        for f in DASHBOARD_FIELDS:
            if f.param.choices:
                self.fields[f.name] = gui.add_dropdown(
                    f.title, f.param.choices, initial_value=f.default, hint=f.param.help)
            else:
                # A text field read here (a number box clamped, and dropped the "e" of
                # "1e9": 19 deg/s was then offered); a wrong value is refused naming the field.
                self.fields[f.name] = gui.add_text(f.title, f"{f.default:g}", hint=f.param.help)
        self.pace = gui.add_text(PACE_LABEL, f"{IdentifySettings().pace:g}", hint="offline only")
        self.field_errors = gui.add_html(field_errors_html(()))
        for h in (*self.fields.values(), self.pace):
            h.on_update(lambda _e: self.show_errors())

    def _values(self) -> tuple[dict[str, FieldValue], float, list[str]]:
        """The fields' values, the pace, and why a field's text is none of its values."""
        values: dict[str, FieldValue] = {}
        errors: list[str] = []
        for f in DASHBOARD_FIELDS:
            v = self.fields[f.name].value
            if f.param.choices:
                values[f.name] = f.type(v)
                continue
            lo, hi, _step = f.limits
            num, why = parse_number(str(v), f.title, lo, hi, integer=f.type is int)
            if num is None:
                errors.append(why)
            else:
                values[f.name] = round(num) if f.type is int else num
        pace, why = parse_number(str(self.pace.value), PACE_LABEL, 0.0, PACE_MAX)
        if pace is None:
            errors.append(why)
        return values, pace or 0.0, errors

    def show_errors(self) -> None:
        self.field_errors.content = field_errors_html(self._values()[2])

    def settings(self) -> IdentifySettings:
        """What the controls ask for; raises ConfigError naming a field whose text is none of
        its values."""
        values, pace, errors = self._values()
        if errors:
            raise ConfigError("settings", "; ".join(errors))
        return IdentifySettings(
            values=values, pace=pace,
            where=str(self.where.value) if self.where is not None else WHERE_OFFLINE)
