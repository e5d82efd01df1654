"""The tuning panel's HTML (pure: values in, HTML out): the gate's verdict, the candidate's
difference from the active configuration, the preview's numbers, the cut-off line, the stale
and Apply notes. Every text from elsewhere is escaped (`server.escape.esc`)."""

from __future__ import annotations

import numpy as np

from controller.core.config import LoopConfig, NominalModel
from controller.core.trajectory import Trajectory
from controller.gate.knowledge import PositionSpread
from controller.tune.autotune import SIGNIFICANT_REL, differs
from server.engine import Evaluation, PreviewComparison, PreviewResult
from server.escape import esc
from server.panels.bode import margin_items as _margin_items
from server.panels.widgets import ACCEPT, CAUTION, REJECT, box
from server.panels.widgets import reason_list as _reason_list

__all__ = [
    "active_html",
    "apply_why_html",
    "computing_html",
    "config_diff_html",
    "cutoff_html",
    "diff_html",
    "divergence_html",
    "format_gate_html",
    "kept_problem_html",
    "preview_html",
    "stale_html",
]


def format_gate_html(ev: Evaluation | None, error: str | None = None) -> str:
    """Margins and verdict as a small HTML block; a red box when the gate would reject."""
    if error is not None:
        return box("dt-verdict dt-reject", REJECT, f"<b>Invalid candidate</b><br>{esc(error)}",
                   font_px=None)
    assert ev is not None
    g = ev.verdict
    rows = "".join(
        f"<tr><td>{label}</td><td style='text-align:right'>{value} {unit}</td></tr>"
        for label, value, unit in _margin_items(g.margins)
    )
    table = f"<table style='width:100%;font-size:12px'>{rows}</table>"
    judged = (f"<div class='dt-knowledge' style='font-size:11px;color:#555'>judged on "
              f"{esc(g.knowledge)}</div>" if g.knowledge else "")
    if g.verdict == "accept":
        return box("dt-verdict dt-accept", ACCEPT, f"<b>Verdict: accept</b>{table}{judged}",
                   font_px=None)
    reasons = _reason_list(g.reasons, "dt-reason")
    if g.verdict == "caution":
        return box("dt-verdict dt-caution", CAUTION,
                   f"<b>Verdict: CAUTION</b> (applies only after you confirm){table}{reasons}"
                   f"{judged}", font_px=None)
    return box("dt-verdict dt-reject", REJECT,
               f"<b>Verdict: REJECT</b> (cannot be sent){table}{reasons}{judged}", font_px=None)


def diff_html(cand: LoopConfig, active: LoopConfig, version: int | None) -> str:
    """The fields the candidate changes against the active configuration (always shown)."""
    against = f"active v{version}" if version is not None else "the active configuration"
    return config_diff_html(active, cand, against, "Candidate")


def _value_text(v: object) -> str:
    """A configuration value as read: numbers to 4 significant digits, nested ones by name."""
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return "(" + ", ".join(_value_text(x) for x in v) + ")"
    if isinstance(v, dict):
        return ", ".join(f"{k} {_value_text(x)}" for k, x in v.items())
    return str(v)


def nominal_summary(n: NominalModel) -> str:
    """The nominal model Mn Pn = pn_num / (mn_den pn_den) in an engineer's terms: its gain at
    1 Hz and its poles' frequencies (a raw 'mn_den: (1.013e-05, ...)' told nobody anything)."""
    num = np.asarray(n.pn_num, dtype=float)
    den = np.polymul(np.asarray(n.mn_den, dtype=float), np.asarray(n.pn_den, dtype=float))
    s = 2j * np.pi
    gain_db = 20 * np.log10(abs(np.polyval(num, s) / np.polyval(den, s)))
    poles = np.roots(np.trim_zeros(den, "f"))
    hz = sorted(float(abs(p)) / (2 * np.pi) for p in poles)
    where = ", ".join("0 (integrator)" if f < 1e-12 else f"{f:.3g}" for f in hz)
    return f"gain {round(gain_db, 1) + 0.0:.1f} dB at 1 Hz, poles at {where} Hz"


def config_diff_html(old: LoopConfig, new: LoopConfig, old_label: str, new_label: str,
                     cls: str = "dt-diff") -> str:
    """The fields in which `new` differs from `old`, one per line (old &rarr; new)."""
    from controller.core.config import config_to_builtins

    a, c = config_to_builtins(old), config_to_builtins(new)
    rows = []
    for k in c:
        if c[k] == a.get(k):
            continue
        if k == "nominal":  # a model, as an engineer reads one (not its raw coefficients)
            rows.append(f"<li>nominal model Mn Pn: {esc(nominal_summary(old.nominal))} &rarr; "
                        f"<b>{esc(nominal_summary(new.nominal))}</b></li>")
        elif k == "command_filter":  # the filter in words, not its raw fields
            rows.append(f"<li>speed-command filter: {esc(old.command_filter.describe())} "
                        f"&rarr; <b>{esc(new.command_filter.describe())}</b></li>")
        else:
            rows.append(f"<li>{esc(k)}: {esc(_value_text(a.get(k)))} &rarr; "
                        f"<b>{esc(_value_text(c[k]))}</b></li>")
    if not rows:
        return (f"<div class='{cls}' style='font-size:12px;color:#555'>{esc(new_label)}: same "
                f"as {esc(old_label)}.</div>")
    return (f"<div class='{cls}' style='font-size:12px'>{esc(new_label)} vs {esc(old_label)}:"
            f"<ul style='margin:2px 0 0 16px;padding:0'>{''.join(rows)}</ul></div>")


def preview_html(traj: Trajectory, p: PreviewComparison) -> str:
    """The preview's numbers: the candidate, the same gains with the DOB off (the DOB's value
    and its price: the command noise above 20 Hz), the active configuration."""
    pc, pa, pn = p.candidate, p.active, p.no_dob

    def run(label: str, r: PreviewResult, cls: str) -> str:
        return (f"<li class='{cls}'>{label}: peak <b>{r.peak_error_deg:.4f}</b> deg, RMSE "
                f"<b>{r.rmse_deg:.4f}</b> deg, command noise &gt;20 Hz "
                f"{r.command_noise_deg_s:.3g} deg/s</li>")

    c = pc.config
    dob = f"DOB {c.q_type.upper()} at {c.q_cutoff_hz:.3g} Hz" if c.dob_on else "DOB off"
    rows = [run(f"candidate ({dob})", pc, "dt-preview-cand")]
    if pn is not None:
        rows.append(run("candidate, DOB off", pn, "dt-preview-nodob"))
    rows.append(run("active", pa, "dt-preview-active"))
    verdict = ""
    if pn is not None and c.dob_on:
        # A difference inside the prediction's own accuracy is none (`SIGNIFICANT_REL`).
        said = {-1: "DOB beats DOB off here",
                0: (f"No significant difference from DOB off here (RMSE within "
                    f"&plusmn;{SIGNIFICANT_REL:.0%}, what the prediction is good to)"),
                1: "DOB does not beat DOB off here"}[differs(pc.rmse_deg, pn.rmse_deg)]
        verdict = (f"<div class='dt-preview-verdict'>{said}"
                   f": RMSE {pc.rmse_deg / pn.rmse_deg - 1.0:+.1%}, peak "
                   f"{pc.peak_error_deg / pn.peak_error_deg - 1.0:+.1%}, command noise "
                   f"x{pc.command_noise_deg_s / max(pn.command_noise_deg_s, 1e-12):.2g}</div>")
    return (
        "<div class='dt-preview' style='font-size:13px'>"
        f"<b>Preview</b> ({esc(traj.kind)}, {pc.t_s[-1] + pc.t_s[1]:.1f} s simulated, "
        f"disturbances: {esc(pc.disturbances)}) "
        f"<span style='color:#888'>({pc.elapsed_s * 1e3:.0f} ms)</span>"
        + (f"<div class='dt-preview-plant' style='color:#555'>on the "
           f"{esc(pc.plant_source)}</div>" if pc.plant_source else "") +
        f"<ul style='margin:2px 0 0 16px;padding:0'>{''.join(rows)}</ul>{verdict}</div>"
    )


def divergence_html(sp: PositionSpread | None) -> str:
    """Where the measured responses part (the recommendation keeps Q below it)."""
    if sp is None:
        return ""
    n = len(sp.names)
    if sp.divergence_hz is None:
        return f" &middot; the {n} measured responses agree within 1 dB on their band"
    return (f" &middot; the {n} measured responses diverge above "
            f"<b>{sp.divergence_hz:.2f} Hz</b>")


def kept_problem_html(text: str) -> str:
    if not text:
        return "<div class='dt-kept-problem'></div>"
    # A file's path is long and has no spaces: broken anywhere rather than cut off.
    return box("dt-kept-problem", REJECT,
               f"<span style='overflow-wrap:anywhere'>{esc(text)}</span>")


def apply_why_html(why: str) -> str:
    if not why:
        return "<div class='dt-apply-why'></div>"
    return ("<div class='dt-apply-why dt-apply-blocked' style='font-size:12px;color:#555'>"
            f"Apply is off: {esc(why)}.</div>")


def computing_html(on: bool) -> str:
    if not on:
        return "<div class='dt-computing'></div>"
    return ("<div class='dt-computing dt-computing-on' style='font-size:12px;color:#555;"
            "font-style:italic'>computing the verdict...</div>")


def cutoff_html(cutoff_hz: float, rec: float | None, known: bool, error: str,
                spread: PositionSpread | None, invalid: bool = False) -> str:
    """The cut-off line under the slider: the value, the gate's recommended maximum (or why
    there is none yet), where the measured responses diverge; the error of a typed value.
    `invalid`: another field of the candidate is rejected (no recommendation is searched)."""
    if error:
        return ("<div class='dt-cutoff dt-cutoff-invalid' style='font-size:13px;"
                "color:#d62728'><b>Q cut-off (Hz) rejected</b>: "
                f"{esc(error)}. Apply is disabled until it is a number in range.</div>")
    if invalid:
        rec_txt = (" &middot; no recommended max: another field of the candidate is rejected "
                   "(see the verdict)")
    elif not known:
        rec_txt = " &middot; recommended max: computing..."
    elif rec is None:
        rec_txt = " &middot; <span style='color:#d62728'>the gate accepts no cut-off with " \
            "these gains</span>"
    else:
        rec_txt = f" &middot; gate's recommended max <b>{rec:.2f} Hz</b>"
    rec_txt += divergence_html(spread)
    warn = ""
    if rec is not None and cutoff_hz > rec:
        warn = " <span style='color:#d62728'>(above the recommendation)</span>"
    return (f"<div class='dt-cutoff' style='font-size:13px'>Q cut-off "
            f"<b>{cutoff_hz:.3f} Hz</b>{rec_txt}{warn}</div>")


def stale_html(stale: bool, by_reset: bool, base_version: int | None,
               active_version: int | None) -> str:
    """Why a candidate made against another version is not sent ("" box when it is not)."""
    if not stale:
        return "<div class='dt-stale'></div>"
    if by_reset:
        return box(
            "dt-stale", CAUTION,
            f"<b>Based on v{base_version} as it was</b>: the controller's "
            f"v{active_version} is another configuration now (its state was reset "
            "since this candidate was made). Apply is off; <b>Revert</b> loads "
            f"v{active_version}.")
    return box(
        "dt-stale", CAUTION,
        f"<b>Based on v{base_version}</b>: the active configuration is now "
        f"v{active_version} (changed since: another client, or a watchdog rollback). "
        f"Apply would be refused (it carries "
        f"v{base_version}); <b>Revert</b> loads v{active_version}.")


def active_html(a: LoopConfig, version: int | None) -> str:
    """The active configuration in one line."""
    v = "?" if version is None else str(version)
    return (
        f"<div class='dt-active' style='font-size:12px;color:#555'>Active (v{v}): "
        f"{a.q_type.upper()} {a.q_cutoff_hz:.3g} Hz, DOB {'on' if a.dob_on else 'off'}, "
        f"FF {'on' if a.ff_on else 'off'}, Cv {a.cv_kp:g}(1+{a.cv_ki_per_s:g}/s), "
        f"Cp {a.pos_kp_per_s:g}(1+{a.pos_ki_per_s:g}/s)"
        + (f", speed-command filter: {esc(a.command_filter.describe())}"
           if a.command_filter.kind != "off" else "") + "</div>"
    )
