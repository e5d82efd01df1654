"""The tuning panel with a nominal-model slot in the candidate (what Identify's "Use as nominal
model" fills)."""

from __future__ import annotations

from collections.abc import Callable

import viser

from controller.core.config import LoopConfig, NominalModel
from server.candidate_apply import CandidateApply
from server.engine import TuningEngine
from server.panels.tuning import TuningPanel

__all__ = ["NominalTuningPanel"]


class NominalTuningPanel(TuningPanel):
    """The tuning panel with a nominal-model slot in the candidate.

    ``nominal_override`` (set by "Use as nominal model") replaces the active configuration's
    nominal in the candidate; the gate evaluates it and Apply sends it like any other change.
    Revert clears it.
    """

    def __init__(self, gui: viser.GuiApi, engine: TuningEngine, applier: CandidateApply,
                 initial: LoopConfig | None = None,
                 on_change: Callable[[TuningPanel], None] | None = None) -> None:
        super().__init__(gui, engine, applier, initial, on_change)
        self.nominal_override: NominalModel | None = None

    def candidate(self) -> LoopConfig:
        cand = super().candidate()
        if self.nominal_override is not None:
            cand = cand.with_(nominal=self.nominal_override)
        return cand

    def set_nominal(self, nominal: NominalModel | None) -> None:
        """Use `nominal` in the candidate (None: the active one) and re-evaluate; no apply."""
        self.nominal_override = nominal
        self.request_update()

    def revert(self, say: bool = True) -> None:
        self.nominal_override = None
        super().revert(say)

    def nominal(self) -> NominalModel | None:
        return self.nominal_override

    def restore_nominal(self, nominal: NominalModel | None) -> None:
        self.nominal_override = nominal

    def cutoff_line_html(self, cutoff_hz: float, rec: float | None, known: bool = True,
                         error: str = "", invalid: bool = False) -> str:
        html = super().cutoff_line_html(cutoff_hz, rec, known, error, invalid)
        n = self.nominal_override
        if n is None:
            return html
        a2, a1, _ = n.pn_den
        return html + (
            "<div class='dt-nominal-fitted' style='font-size:12px;color:#1f77b4'>Candidate "
            f"nominal: <b>fitted by Identify</b> (Pn den {a2:.3g} s&sup2; + {a1:.3g} s + 1); "
            "Revert drops it.</div>"
        )
