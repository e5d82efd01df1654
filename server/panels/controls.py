"""The candidate's controls (widgets): Q type, the Q cut-off (a log slider and an Hz field),
the switches and the gains, built once; one callback per control.

viser runs a browser's callbacks on its thread pool, and a value the server sets runs the
control's callbacks at once in the setting thread. So a control's one callback reads what it
needs and asks for the verdict (`changed`) under the candidate's lock, and the echo of the
panel's own setting of a control is told apart by a flag of the setting thread only."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import viser

from controller.core.config import LoopConfig
from controller.core.errors import ConfigError
from server.candidate_store import KeptCandidate
from server.engine import CUTOFF_MAX_HZ, CUTOFF_MIN_HZ
from server.escape import esc
from server.gui import ValueHandle, set_value
from server.panels.filter_controls import (
    FILTER_CONTROLS,
    FilterControls,
    filter_control_problem,
)
from server.panels.widgets import parse_number, set_html
from server.viser_adapter import set_slider_marks

__all__ = ["KEPT_CONTROLS", "SLIDER_SUFFIX", "CandidateControls", "cutoff_marks",
           "gain_errors_html", "kept_problem"]

_Q_LABELS = {"Q31 (3rd order, rel. deg 2)": "q31", "Q20 (2nd order)": "q20"}
_BASE_MARKS: tuple[tuple[float, str], ...] = ((-1.0, "0.1 Hz"), (0.0, "1 Hz"), (1.0, "10 Hz"))
_LOG_LO, _LOG_HI = math.log10(CUTOFF_MIN_HZ), math.log10(CUTOFF_MAX_HZ)
#: The closest a decade mark may sit to 'max' (decades): nearer, their labels overlapped (1.34 Hz
#: next to "1 Hz": 0.13 decade, ~10 px apart on the sidebar's slider), and the decade goes.
_MARK_GAP_DEC = 0.45


def cutoff_marks(rec_hz: float | None) -> tuple[tuple[float, str], ...]:
    """The cut-off slider's marks: decades, and 'max' at the gate's recommendation (a decade
    too close to it left out, so that no two labels overlap)."""
    if rec_hz is not None and CUTOFF_MIN_HZ < rec_hz < CUTOFF_MAX_HZ:
        at = round(math.log10(rec_hz), 3)
        decades = tuple(m for m in _BASE_MARKS if abs(m[0] - at) >= _MARK_GAP_DEC)
        return tuple(sorted((*decades, (at, "max"))))
    return _BASE_MARKS


def _clamp(v: float, lo: float, hi: float) -> float:
    return min(max(v, lo), hi)


def gain_errors_html(errors: dict[str, str]) -> str:
    """The gains' typed values that are none (label -> why), in red, under the gains."""
    if not errors:
        return "<div class='dt-gain-error'></div>"
    lines = "".join(f"<div><b>Rejected</b>: {esc(why)}.</div>" for why in errors.values())
    return ("<div class='dt-gain-error dt-gain-invalid' style='font-size:13px;color:#d62728'>"
            f"{lines}Apply is disabled until each is a number in range.</div>")


def _fmt_gain(v: float) -> str:
    """A gain as its text field shows it (up to 6 significant digits)."""
    return f"{v:.6g}"


def _fmt_hz_value(hz: float) -> str:
    """A cut-off as the Hz field shows it (up to 6 significant digits, no trailing zeros)."""
    return f"{hz:.6g}"


def _cutoff_log(hz: float) -> float:
    """The log slider's position of a cut-off in Hz (clamped to the slider)."""
    return _clamp(math.log10(max(hz, CUTOFF_MIN_HZ)), _LOG_LO, _LOG_HI)


def _label_of(q_type: str) -> str:
    for label, q in _Q_LABELS.items():
        if q == q_type:
            return label
    return next(iter(_Q_LABELS))


@dataclass(frozen=True)
class _Gain:
    """A linear slider for one LoopConfig gain."""

    attr: str  # the control's name (the panel's attribute holding the handle)
    field: str  # the LoopConfig field
    label: str
    lo: float
    hi: float
    step: float
    hint: str | None = None

    def position(self, cfg: LoopConfig) -> float:
        return _clamp(float(getattr(cfg, self.field)), self.lo, self.hi)

    @property
    def slider_label(self) -> str:
        """The slider's label (its own number box is hidden by the page script: it clamped
        and misread what was typed; the text field under it is the value)."""
        return f"{self.label}{SLIDER_SUFFIX}"

    def parse(self, text: str) -> tuple[float | None, str]:
        """The gain typed as `text` (exponents too: "1e-1") or why it is none."""
        return parse_number(text, self.label, self.lo, self.hi)


_GAINS = (
    _Gain("cv_kp", "cv_kp", "Cv Kp", 0.05, 3.0, 0.01, "speed loop Cv = Kp (1 + Ki/s)"),
    _Gain("cv_ki", "cv_ki_per_s", "Cv Ki (1/s)", 0.0, 200.0, 1.0),
    _Gain("pos_kp", "pos_kp_per_s", "Pos Kp (1/s)", 0.5, 40.0, 0.1,
          "position loop Cp = Kp (1 + Ki/s)"),
    _Gain("pos_ki", "pos_ki_per_s", "Pos Ki (1/s)", 0.0, 20.0, 0.1),
)
#: The end of a gain slider's label (the page script hides the number box of such sliders).
SLIDER_SUFFIX = ", drag"
#: (control name = LoopConfig field, label) of the switches.
_SWITCHES = (("dob_on", "DOB on"), ("ff_on", "Velocity feedforward"))
#: The controls a kept candidate holds (their names; `kept`, `restore`).
KEPT_CONTROLS = ("q_type", "cutoff_hz_input", *(a for a, _ in _SWITCHES),
                 *(g.attr for g in _GAINS))


def kept_problem(k: KeptCandidate) -> str:
    """Why `k` (read from a file) cannot be put back into the controls ("" : it can): its
    controls must be these, each once, with a value of the control's kind (the speed-command
    filter's controls too, or none of them: a candidate kept before they were)."""
    names = [n for n, _ in k.controls]
    if sorted(names) not in (sorted(KEPT_CONTROLS), sorted(KEPT_CONTROLS + FILTER_CONTROLS)):
        return (f"controls: expected {', '.join(KEPT_CONTROLS + FILTER_CONTROLS)}, got "
                f"{', '.join(names)}")
    for name, value in k.controls:
        if name in FILTER_CONTROLS:
            problem = filter_control_problem(name, value)
            if problem:
                return problem
            continue
        if name == "q_type":
            ok = value in _Q_LABELS
        elif name == "cutoff_hz_input":
            ok = isinstance(value, str) and len(value) <= 64
        elif name in dict(_SWITCHES):
            ok = isinstance(value, bool)
        else:
            g = next(g for g in _GAINS if g.attr == name)
            ok = isinstance(value, float) and g.lo <= value <= g.hi
        if not ok:
            return f"controls.{name}: {value!r} is not a value of this control"
    return ""


class CandidateControls:
    """The candidate's controls in `gui` (built by `build`), read as LoopConfig field values,
    set from a configuration or a kept candidate."""

    q_type: viser.GuiDropdownHandle[str]
    cutoff_log: viser.GuiSliderHandle[float]
    cutoff_hz_input: viser.GuiTextHandle
    cutoff_text: viser.GuiHtmlHandle

    def __init__(self, gui: viser.GuiApi, lock: threading.RLock,
                 changed: Callable[[], None]) -> None:
        """`lock`: the candidate's (held while a control's change is read and judged, and
        while the controls are set as a whole); `changed()`: ask for the verdict."""
        self.gui = gui
        self._lock = lock
        self._changed = changed
        self._writing = threading.local()
        self.cutoff_hz = 1.0
        """The candidate's cut-off: as typed in the Hz field, or where the slider was dragged
        (rounded to 3 significant digits)."""
        self.cutoff_error = ""
        """Why the Hz field's text is no cut-off ("" : it is one)."""
        self._marks: tuple[tuple[float, str], ...] = ()
        self.switches: dict[str, viser.GuiCheckboxHandle] = {}
        self.gains: dict[str, viser.GuiSliderHandle[float]] = {}
        self.gain_inputs: dict[str, viser.GuiTextHandle] = {}
        """Each gain's text field (the value; typed, never written back by the server while
        typed), by the gain's control name + "_input"."""
        self.gain_errors: dict[str, str] = {}
        """A gain's label -> why its text field's text is no value of it."""
        self.gain_text: viser.GuiHtmlHandle | None = None
        self.filter = FilterControls(gui, self._echo, self._on_filter)
        """The speed-command filter's controls (after the gains)."""

    def build(self, a: LoopConfig, cutoff_text: str) -> None:
        """Every control, at `a`; `cutoff_text`: the cut-off line's first HTML."""
        gui = self.gui
        self.q_type = gui.add_dropdown(
            "Q type", tuple(_Q_LABELS), initial_value=_label_of(a.q_type),
            hint="Q31: 3rd-order Q-filter (3 tau s + 1)/(tau s + 1)^3; Q20: 1/(tau s + 1)^2",
        )
        self.cutoff_log = gui.add_slider(
            "Q cut-off, log scale", min=round(_LOG_LO, 3), max=round(_LOG_HI, 3), step=0.005,
            initial_value=_cutoff_log(a.q_cutoff_hz), marks=_BASE_MARKS,
            hint="-3 dB cut-off of Q: drag on a log scale (the Hz field below is the value). "
            "The mark 'max' is the gate's recommendation.",
        )
        # A text field, not a number field: the server never writes into it while the user
        # types (a number field's limits made the server clamp the first typed "0" and send
        # it back), and "1e-1" or "2.5" parse as typed.
        self.cutoff_hz_input = gui.add_text(
            "Q cut-off (Hz)", initial_value=_fmt_hz_value(a.q_cutoff_hz),
            hint=f"type the -3 dB cut-off in Hz ({CUTOFF_MIN_HZ:g} to {CUTOFF_MAX_HZ:g}); "
            "the slider follows",
        )
        self.cutoff_hz = float(a.q_cutoff_hz)
        self.cutoff_error = ""
        self.cutoff_hz_input.on_update(self._on_cutoff_typed)
        self.cutoff_log.on_update(self._on_cutoff_slider)
        self.cutoff_text = gui.add_html(cutoff_text)
        for attr, label in _SWITCHES:
            self.switches[attr] = gui.add_checkbox(label, bool(getattr(a, attr)))
        for g in _GAINS:
            self.gains[g.attr] = gui.add_slider(g.slider_label, g.lo, g.hi, g.step,
                                                g.position(a), hint=g.hint)
            # A text field as the cut-off's (a number box clamped "-1" to the minimum, dropped
            # the "e" of "1e1" and kept the old value for "abc", all silently).
            self.gain_inputs[g.attr + "_input"] = gui.add_text(
                g.label, initial_value=_fmt_gain(g.position(a)),
                hint=f"type {g.label} ({g.lo:g} to {g.hi:g}); the slider follows")
        self.gain_errors = {}
        self.gain_text = gui.add_html(gain_errors_html({}))
        self.filter.build(a)
        self.q_type.on_update(self._on_control)
        for c in self.switches.values():
            c.on_update(self._on_control)
        for g in _GAINS:
            self.gains[g.attr].on_update(self._gain_slider_cb(g))
            self.gain_inputs[g.attr + "_input"].on_update(self._gain_typed_cb(g))

    def handles(self) -> dict[str, ValueHandle]:
        """Every value control by name (the names of `KEPT_CONTROLS`, and `cutoff_log`)."""
        return {"q_type": self.q_type, "cutoff_log": self.cutoff_log,
                "cutoff_hz_input": self.cutoff_hz_input, **self.switches, **self.gains,
                **self.gain_inputs, **self.filter.handles()}

    # -- the candidate's own settings: their callbacks are echoes -----------------------------

    @contextmanager
    def setting(self) -> Iterator[None]:
        """This thread sets controls: their callbacks (run at once, in this thread) are
        echoes, not a user's change."""
        prev = getattr(self._writing, "on", False)
        self._writing.on = True
        try:
            yield
        finally:
            self._writing.on = prev

    def _echo(self) -> bool:
        return bool(getattr(self._writing, "on", False))

    # -- callbacks (viser's thread pool: short) -------------------------------------------------

    def _on_cutoff_typed(self, _event: viser.GuiEvent[viser.GuiTextHandle]) -> None:
        """The Hz field is the value (never written back while typed); the slider follows."""
        if self._echo():
            return
        with self._lock:
            self.read_cutoff_text()
            self._changed()

    def _on_cutoff_slider(self, _event: viser.GuiEvent[viser.GuiSliderHandle[float]]) -> None:
        """A drag of the slider (its one callback): the cut-off (3 significant digits) and the
        Hz field follow, then the verdict is asked for, in that order and under the lock
        (with the request in a callback of its own, which viser may run first, a drag could
        be judged before its cut-off was read)."""
        if self._echo():
            return
        with self._lock:
            self.cutoff_hz = float(f"{10.0 ** float(self.cutoff_log.value):.3g}")
            self.cutoff_error = ""
            with self.setting():
                set_value(self.cutoff_hz_input, _fmt_hz_value(self.cutoff_hz))
            self._changed()

    def _on_control(self, _event: object) -> None:
        if not self._echo():
            self._changed()

    def _on_filter(self) -> None:
        """A user's change of the filter's controls: judged under the candidate's lock."""
        with self._lock:
            self._changed()

    def _gain_slider_cb(self, g: _Gain) -> Callable[[object], None]:
        def dragged(_event: object) -> None:
            """A drag: the gain's text field follows (its error, if any, goes)."""
            if self._echo():
                return
            with self._lock:
                self.gain_errors.pop(g.label, None)
                with self.setting():
                    set_value(self.gain_inputs[g.attr + "_input"],
                              _fmt_gain(float(self.gains[g.attr].value)))
                self._show_gain_errors()
                self._changed()
        return dragged

    def _gain_typed_cb(self, g: _Gain) -> Callable[[object], None]:
        def typed(_event: object) -> None:
            """The text field is the value (never written back while typed); the slider
            follows."""
            if self._echo():
                return
            with self._lock:
                self._read_gain_text(g)
                self._show_gain_errors()
                self._changed()
        return typed

    def _read_gain_text(self, g: _Gain) -> None:
        text = str(self.gain_inputs[g.attr + "_input"].value).strip()
        v, why = g.parse(text)
        if v is None:
            self.gain_errors[g.label] = why
            return
        self.gain_errors.pop(g.label, None)
        with self.setting():
            set_value(self.gains[g.attr], v)

    def _show_gain_errors(self) -> None:
        if self.gain_text is not None:
            set_html(self.gain_text, gain_errors_html(self.gain_errors))

    # -- reading and setting ---------------------------------------------------------------------

    def read_cutoff_text(self) -> None:
        """The cut-off from the Hz field's text (or why it is none); the slider follows."""
        text = str(self.cutoff_hz_input.value).strip()
        try:
            hz = float(text)
        except ValueError:
            hz = math.nan
        if not (math.isfinite(hz) and CUTOFF_MIN_HZ <= hz <= CUTOFF_MAX_HZ):
            self.cutoff_error = (
                f"{text!r} is not a cut-off in Hz between {CUTOFF_MIN_HZ:g} and {CUTOFF_MAX_HZ:g}"
            )
        else:
            self.cutoff_error = ""
            self.cutoff_hz = hz
            with self.setting():
                set_value(self.cutoff_log, _cutoff_log(hz))

    def values(self) -> dict[str, object]:
        """The LoopConfig fields the controls set; raises ConfigError (the cut-off's text)."""
        if self.cutoff_error:
            raise ConfigError("q_cutoff_hz", self.cutoff_error)
        for g in _GAINS:
            if g.label in self.gain_errors:
                raise ConfigError(g.field, self.gain_errors[g.label])
        values: dict[str, object] = {
            "q_type": _Q_LABELS.get(self.q_type.value, "q31"),
            "q_cutoff_hz": self.cutoff_hz,
        }
        for attr, h in self.switches.items():
            values[attr] = bool(h.value)
        for g in _GAINS:
            values[g.field] = float(self.gains[g.attr].value)
        values.update(self.filter.values())
        return values

    def show(self, a: LoopConfig) -> None:
        """Every control set to `a` (no verdict asked for: the caller does, once)."""
        with self._lock, self.setting():
            set_value(self.q_type, _label_of(a.q_type))
            set_value(self.cutoff_log, _cutoff_log(a.q_cutoff_hz))
            set_value(self.cutoff_hz_input, _fmt_hz_value(a.q_cutoff_hz))
            self.cutoff_hz = float(a.q_cutoff_hz)
            self.cutoff_error = ""
            for attr, h in self.switches.items():
                set_value(h, bool(getattr(a, attr)))
            for g in _GAINS:
                set_value(self.gains[g.attr], g.position(a))
            self._gains_from_sliders()
            self.filter.show(a)

    def _gains_from_sliders(self) -> None:
        """Each gain's text field at its slider (errors gone); under `setting`."""
        for g in _GAINS:
            set_value(self.gain_inputs[g.attr + "_input"],
                      _fmt_gain(float(self.gains[g.attr].value)))
        self.gain_errors = {}
        self._show_gain_errors()

    def kept(self) -> tuple[tuple[str, object], ...]:
        """The controls' values as a kept candidate holds them."""
        handles = self.handles()
        return tuple((n, handles[n].value) for n in KEPT_CONTROLS + FILTER_CONTROLS)

    def restore(self, controls: tuple[tuple[str, object], ...]) -> None:
        """The controls as kept (`kept_problem` found nothing wrong with them)."""
        handles = self.handles()
        with self._lock, self.setting():
            for name, value in controls:
                set_value(handles[name], value)
            self.read_cutoff_text()
            self._gains_from_sliders()
            self.filter.restored()

    def update_marks(self, rec: float | None) -> None:
        """The slider's 'max' mark at the gate's recommendation."""
        marks = cutoff_marks(rec)
        if marks != self._marks:
            self._marks = marks
            set_slider_marks(self.cutoff_log, marks)  # viser takes marks only at creation
