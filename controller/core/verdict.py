"""The gate's verdict on one configuration, as plain data: the one type (and its wire form) the
controller's gate, its worker process, `dobtune check`, the dashboard and the protocol carry.

`controller.gate.verdict.judge` makes it; `controller.protocol` sends it (MessagePack maps,
msgspec). Plain data only (no analysis here), so that the wire contract can import it.
"""

from __future__ import annotations

import math
from typing import Literal

import msgspec

__all__ = ["VERDICT_KINDS", "Verdict", "VerdictKind", "VerdictMargins", "gain_margins_text",
           "kind_of", "margins_dict"]

VerdictKind = Literal["accept", "caution", "reject"]
VERDICT_KINDS: tuple[VerdictKind, ...] = ("accept", "caution", "reject")


class VerdictMargins(msgspec.Struct, frozen=True, kw_only=True):
    """The figures a verdict shows, on the plant model (NaN: not computed, e.g. refused before
    the analysis ran)."""

    gain_margin_db: float
    phase_margin_deg: float
    peak_sensitivity_db: float
    small_gain_peak: float
    """The robust-stability figure: max over the evidence of |a T| (|W T| for the bound)."""
    max_pole_radius: float
    noise_to_command_peak_db: float = math.nan
    """Peak gain from speed-measurement noise to the command, |(Cv + F1) / D|."""
    gain_margin_up_db: float = math.nan
    """How far the loop gain may rise before instability (>= 0; inf: no limit). NaN: not
    known (a verdict recorded before it was kept: then `gain_margin_db` alone)."""
    gain_reduction_margin_db: float = math.nan
    """How far the loop gain may fall before instability, in a conditionally stable loop
    (> 0; inf: no such limit). `gain_margin_db` (python-control's pick of the two, negative
    for this one) stays for the records, the protocol and `dobtune check --json`."""

    def gain_margins_text(self) -> str:
        """`gain_margins_text` of these margins."""
        return gain_margins_text(self.gain_margin_up_db, self.gain_reduction_margin_db,
                                 self.gain_margin_db)

    @classmethod
    def unknown(cls) -> VerdictMargins:
        nan = math.nan
        return cls(gain_margin_db=nan, phase_margin_deg=nan, peak_sensitivity_db=nan,
                   small_gain_peak=nan, max_pole_radius=nan)


class Verdict(msgspec.Struct, frozen=True, kw_only=True):
    """accept / caution / reject on one configuration, with the reasons that name their
    evidence, the margins, the recommended maximum Q cut-off and the knowledge judged on."""

    verdict: VerdictKind
    rejections: tuple[str, ...] = ()
    cautions: tuple[str, ...] = ()
    margins: VerdictMargins
    recommended_max_cutoff_hz: float | None = None
    """For the candidate's Q type (None: even the lowest cut-off is not accepted, or the
    candidate was rejected before the search was worth running)."""
    knowledge: str = ""
    """The plant knowledge judged on, in one line (`PlantKnowledge.describe`)."""
    knowledge_version: int = 0

    @property
    def reasons(self) -> tuple[str, ...]:
        """The rejections, then the cautions."""
        return self.rejections + self.cautions

    @property
    def applicable(self) -> bool:
        """May be applied: accept, or caution (then only after the user confirms)."""
        return self.verdict != "reject"

    @classmethod
    def refused(cls, reason: str, knowledge_version: int = 0) -> Verdict:
        """A rejection before (or without) an analysis: margins unknown."""
        return cls(verdict="reject", rejections=(reason,), margins=VerdictMargins.unknown(),
                   knowledge_version=knowledge_version)


def gain_margins_text(up_db: float, down_db: float, signed_db: float = math.nan) -> str:
    """The gain margins as an engineer reads them, both positive and named: "gain margin
    26.0 dB up, gain-reduction margin 25.8 dB down" for a conditionally stable loop, "gain
    margin 22.0 dB" for a loop without a gain-reduction limit. Without both (a record from
    before they were kept), python-control's signed pick `signed_db`, said to be signed."""
    if math.isnan(up_db) and math.isnan(down_db):
        if math.isnan(signed_db):
            return "gain margin n/a"
        if signed_db < 0:
            return f"gain-reduction margin {-signed_db:.1f} dB down"
        return f"gain margin {signed_db:.1f} dB" if math.isfinite(signed_db) else \
            "gain margin none (no -180 deg crossing)"
    up = "unlimited" if up_db == math.inf else ("n/a" if math.isnan(up_db) else f"{up_db:.1f} dB")
    if not math.isfinite(down_db):
        if up_db == math.inf:
            return "gain margin none (no -180 deg crossing)"
        return f"gain margin {up}"
    return f"gain margin {up} up, gain-reduction margin {down_db:.1f} dB down"


def margins_dict(m: VerdictMargins | None) -> dict[str, float] | None:
    """The margins as a plain dict (the change log's JSON)."""
    return None if m is None else msgspec.structs.asdict(m)


def kind_of(v: Verdict | None) -> str:
    """The verdict's kind for a line of text: accept, caution, reject; "-" when there is none
    (a refused request, a change logged without one)."""
    return "-" if v is None else v.verdict
