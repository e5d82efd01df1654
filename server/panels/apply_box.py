"""A candidate's Apply box: the button, why it is off, and the outcome, from "sending" to the
controller's reply (`StepState`: what the guided path shows of it)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import viser

from controller.core.config import LoopConfig
from controller.core.verdict import Verdict
from server.escape import esc
from server.panels.tuning_html import apply_why_html
from server.panels.widgets import ACCEPT, CAUTION, NEUTRAL, REJECT, box, set_html
from server.panels.widgets import reason_list as _reason_list

__all__ = ["ApplyBox", "StepState"]


@dataclass(frozen=True)
class StepState:
    """Where one step of the work stands (the guided path shows it: server/panels/guide.py)."""

    state: str  # "todo" | "running" | "done" | "failed"
    progress: float | None = None
    """0..1 while running (None: unknown)."""
    text: str = ""
    version: int | None = None
    """Apply: the active version the controller answered with."""
    at_s: float = 0.0
    """Apply: when it was accepted (time.monotonic())."""


class ApplyBox:
    """The Apply button and the outcome box of one candidate (built by `build_button` and
    `build_result`, where the panel puts them)."""

    button: viser.GuiButtonHandle
    why: viser.GuiHtmlHandle
    result: viser.GuiHtmlHandle

    def __init__(self) -> None:
        self.state = StepState("todo")
        """The last Apply: sending (running), accepted (done, `version`), not sent or refused
        (failed, with the reason)."""
        self.reply_version: int | None = None
        """The active version the box last announced (None: it announces none)."""

    def build_button(self, gui: viser.GuiApi) -> None:
        self.button = gui.add_button("Apply candidate", color="gray", disabled=True,
                                     hint="send to the controller; its gate decides")
        self.why = gui.add_html(apply_why_html("computing the verdict"))

    def build_result(self, gui: viser.GuiApi) -> None:
        self.result = gui.add_html('<div class="dt-apply">No change sent yet.</div>')

    def refresh(self, why: str, verdict_color: str) -> None:
        """Off (gray) with the reason `why`, or on in the verdict's colour ("" : on)."""
        disabled = bool(why)
        if self.button.disabled != disabled:
            self.button.disabled = disabled
        color = "gray" if disabled else verdict_color
        if self.button.color != color:
            self.button.color = color  # type: ignore[assignment]
        set_html(self.why, apply_why_html(why))

    def not_sent(self, cls: str, color: tuple[str, str], html: str, reason: str) -> None:
        """The dashboard did not send the candidate: `html` in the box, `reason` in the
        state."""
        self.result.content = box(cls, color, html)
        self.state = StepState("failed", None, reason)

    def sending(self, confirmed: bool) -> None:
        self.reply_version = None
        self.state = StepState("running", None, "sending to the controller"
                               + (" (caution confirmed)" if confirmed else ""))
        self.result.content = box("dt-apply", NEUTRAL, "Sending the candidate (confirmed)..."
                                  if confirmed else "Sending the candidate...")

    def say(self, text: str) -> None:
        """A note of the panel's own (a revert): a reply box from an earlier candidate no
        longer applies."""
        self.reply_version = None
        self.result.content = box("dt-apply", NEUTRAL, esc(text))

    def superseded(self, version: int | None) -> None:
        """The controller's active version is now `version`: a success text about an older
        one no longer stands."""
        shown = self.reply_version
        if shown is not None and version is not None and version > shown:
            # The box spoke of v{shown}; the controller has moved on (a rollback, or another
            # browser): no success text stands for a state that is gone.
            self.reply_version = None
            self.result.content = box(
                "dt-apply dt-apply-superseded", CAUTION,
                f"<b>Active config is now v{version}</b>, no longer v{shown} of your last "
                "apply: changed since (a watchdog rollback or another client; see the alarms "
                "and History).")

    def show_reply(self, accepted: bool, version: int, reasons: list[str], note: str = "") -> None:
        """The controller's reply to this candidate's Apply."""
        self.reply_version = version
        self.state = (
            StepState("done", None, f"accepted: the active configuration is v{version}",
                      version, time.monotonic()) if accepted else
            StepState("failed", None, "rejected by the controller: "
                      + "; ".join(reasons[:1] or ["no reason given"]), version))
        if accepted:
            self.result.content = box(
                "dt-apply", ACCEPT, f"<b>Accepted</b>: active config is now version {version}."
            )
        else:
            self.result.content = box(
                "dt-apply dt-apply-rejected", REJECT,
                f"<b>Rejected by the controller</b> (active stays version {version}):"
                f"{_reason_list(reasons, 'dt-reject-reason')}{esc(note)}",
            )

    def note_refused(self, why: str) -> None:
        """The dashboard refused to send (the browser was told): nothing is under way."""
        self.state = StepState("failed", None, f"refused in the dashboard: {why}")

    def show_error(self, text: str) -> None:
        self.state = StepState("failed", None, f"error: {text}")
        self.result.content = box("dt-apply", REJECT, f"<b>Error</b>: {esc(text)}")

    def checked(self, cand: LoopConfig, active: LoopConfig, stale: bool, stale_by_reset: bool,
                base_version: int | None, judge: Callable[[LoopConfig], Verdict]
                ) -> Verdict | None:
        """The dashboard's own checks before it sends `cand` (whatever the browser's button
        showed): the gate's verdict on it (accept or caution), or None when it is not sent
        (said in the box and the state): made against a version since reset (the controller
        would take it: its version number matches), the active configuration itself (a new
        version of it changes nothing on the rig), rejected by the gate."""
        if stale_by_reset:
            self.not_sent(
                "dt-apply dt-apply-rejected", REJECT,
                f"<b>Not sent</b>: made against v{base_version} as it was before the "
                "controller's state was reset; Revert first.",
                "not sent: made against a version since reset")
            return None
        if cand == active and not stale:
            self.not_sent(
                "dt-apply dt-apply-same", NEUTRAL,
                "<b>Not sent</b>: the candidate is the active configuration.",
                "not sent: the candidate is the active configuration")
            return None
        verdict = judge(cand)
        if verdict.verdict == "reject":
            self.not_sent(
                "dt-apply dt-apply-rejected", REJECT,
                "<b>Not sent</b>: the gate rejects this candidate"
                f"{_reason_list(verdict.reasons, 'dt-reject-reason')}",
                "not sent: the gate rejects it: " + "; ".join(verdict.reasons[:1]))
            return None
        return verdict
