"""Predicted, then measured (issue 35 item 5), as the History tab shows it (pure): the
watch's check of the latest version (`controller.process.prediction_check`), each figure
predicted beside measured with its tolerance, the verdict in plain words, what it means, and
when the prediction failed badly the rollback offered (through the History's "Use as
candidate" and Apply: the gate judges it again)."""

from __future__ import annotations

from controller import protocol as proto
from server.escape import esc

__all__ = ["prediction_html", "state_of"]

_COLOUR = {"held": "#1a7f37", "failed": "#b35900", "failed badly": "#c62828"}
_NAMES = {"rmse_deg": "RMSE (deg)", "peak_error_deg": "peak |error| (deg)",
          "command_noise_deg_s": "command noise (deg/s)"}


def state_of(checks: list[proto.PredictionCheck], version: int) -> str:
    """The check's state for `version` ("" when the watch has none)."""
    for k in checks:
        if k.config_version == version:
            return k.state
    return ""


def _row(f: proto.PredictionFigure) -> str:
    name = _NAMES.get(f.name, f.name.replace("error_rms_deg", "error RMS (deg)"))
    if f.measured is None:
        meas = off = "-"
    else:
        meas = f"{f.measured:.4g}"
        off = (f"{(f.measured - f.predicted) / abs(f.predicted):+.1%}"
               if f.predicted != 0.0 else "-")
    tol = f"&plusmn;{f.tolerance_rel:.0%}" if f.tolerance_rel else "shown"
    return (f"<tr><td>{esc(name)}</td><td>{f.predicted:.4g}</td><td>{meas}</td>"
            f"<td>{off}</td><td>{tol}</td></tr>")


def prediction_html(checks: list[proto.PredictionCheck], running_version: int | None) -> str:
    """The box: the check of the running version (else the newest)."""
    if not checks:
        return ("<div class='dt-prediction'><b>Predicted, then measured</b>: no check yet. The "
                "watch beside the loop (the controller starts it unless --no-watch) predicts "
                "each applied version on the twin, then measures the rig; its first check "
                "follows the loop's first run.</div>")
    k = next((c for c in checks if c.config_version == running_version), checks[-1])
    colour = _COLOUR.get(k.state, "#555")
    if k.state == "predicted":
        verdict = (f"predicted; the rig's window ({k.settle_s:g} s settling, then "
                   f"{k.window_s:.3g} s) is not complete yet")
    else:
        verdict = k.state.upper()
    offer = ""
    if k.state == "failed badly" and k.rollback_to is not None:
        offer = (f"<div class='dt-prediction-offer'><b>Roll back to v{k.rollback_to}</b> (its "
                 f"prediction held): choose v{k.rollback_to} under Version below, <i>Use as "
                 "candidate</i>, then Apply (the gate judges it again).</div>")
    rows = "".join(_row(f) for f in [*k.figures, *k.bands])
    return (
        f"<div class='dt-prediction' style='font-size:12px'><b>Predicted, then measured: "
        f"v{k.config_version}</b> on {esc(k.trajectory.kind)} &mdash; <span "
        f"class='dt-prediction-state' style='color:{colour};font-weight:bold'>{esc(verdict)}"
        f"</span><div>{esc(k.meaning)}</div>{offer}<table><tr><th>figure</th><th>predicted"
        f"</th><th>measured</th><th>off</th><th>tolerance</th></tr>{rows}</table>"
        f"<div style='color:#666'>predicted on {esc(k.model)}</div></div>")
