""""Use as nominal model" of the Identify panel: a complete run's fitted Mn Pn, and its measured
responses as the gate's plant knowledge, put into the tuning candidate of the browser that
pressed it. It never talks to the controller: the candidate is judged like any other change
and sent only by the Tune tab's Apply."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import viser

from controller.gate.knowledge import MeasuredResponse
from server.identify_view import IdentifyView
from server.panels.nominal_tuning import NominalTuningPanel

__all__ = ["UseFit"]

EMPTY = "<div class='dt-id-use' style='font-size:12px'></div>"


class UseFit:
    """The button and the line under it, built in `gui` at once. `tuning_for(browser)`: that
    browser's candidate panel; `add_measured(responses, browser)`: the measured responses into
    the knowledge that browser's candidate is judged on."""

    def __init__(
        self, gui: viser.GuiApi,
        tuning_for: Callable[[viser.ClientHandle | None], NominalTuningPanel | None] | None,
        add_measured: Callable[[Sequence[MeasuredResponse], viser.ClientHandle | None], None]
        | None,
    ) -> None:
        self._tuning_for = tuning_for
        self._add_measured = add_measured
        self.button = gui.add_button("Use as nominal model", color="blue", disabled=True,
                                     hint="put the fitted Mn Pn into the tuning candidate "
                                          "(checked by the gate; Apply sends it)")
        self.result = gui.add_html(EMPTY)

    def clear(self) -> None:
        """A run starts: nothing to use yet."""
        self.button.disabled = True
        self.result.content = EMPTY

    def put(self, view: IdentifyView | None, browser: viser.ClientHandle | None) -> bool:
        """Put `view`'s fit (a complete run's; None: none) into `browser`'s candidate."""
        if view is None or view.nominal is None or not view.complete:
            self.result.content = (
                "<div class='dt-id-use' style='color:#d62728;font-size:12px'>No complete "
                "identification with a usable fit: nothing to use.</div>")
            return False
        tuning = self._tuning_for(browser) if self._tuning_for is not None else None
        if tuning is None:
            self.result.content = (
                "<div class='dt-id-use' style='color:#d62728;font-size:12px'>This browser has "
                "no tuning candidate to put the fit into.</div>")
            return False
        if self._add_measured is not None and view.measured:
            self._add_measured([dataclasses.replace(m, name=f"identify {m.name}")
                                for m in view.measured], browser)
        tuning.set_nominal(view.nominal)
        fit = view.fit
        wn = f" (f<sub>n</sub> {fit.natural_freq_hz:.3f} Hz, &zeta; {fit.zeta:.3f})" if fit else ""
        self.result.content = (
            "<div class='dt-id-use dt-id-used' style='font-size:12px;border:2px solid #1f77b4;"
            "padding:4px;border-radius:4px'>The tuning candidate of the browser that pressed "
            "<i>Use as nominal model</i> now uses the fitted Mn Pn"
            f"{wn} and the measured responses. Check the verdict on the <b>Tune</b> tab; "
            "<b>Apply</b> there sends it (the controller's gate decides). Revert drops it."
            "</div>")
        return True
