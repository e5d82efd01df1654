"""`dobtune check`: the gate's verdict on a configuration file (command body, no argv).

The same function as the controller's gate (`controller.gate.verdict.judge`), judged on plant
knowledge: `--knowledge FILE` (the record a controller keeps, `dobtune ctl knowledge --json`
or its state directory's knowledge.json), else the simulated rig's model with the
commissioning bound; `--frd FILE` adds measured responses. Every reason names its evidence.

Exit codes: 0 accept, 3 caution (applies only with confirmation), 1 reject, 2 bad input (the
message names the file and line, or the field).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

from controller.cli.frd_files import load_measured
from controller.cli.inputs import BadInput, load_config, load_knowledge
from controller.core.config import config_to_builtins
from controller.core.errors import ConfigError
from controller.core.verdict import Verdict, gain_margins_text
from controller.gate.analysis import Analysis, analyse
from controller.gate.knowledge import PlantKnowledge
from controller.gate.margins import Margins
from controller.gate.search import Recommendation, recommend
from controller.gate.verdict import EXIT_CODES, verdict_of
from controller.sim.nonlinear_check import findings

__all__ = ["check_main"]

EXIT_BAD_INPUT = 2


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _margins_json(m: Margins) -> dict[str, float | None]:
    return {
        "gain_margin_db": _finite(m.gain_margin_db),
        "phase_crossover_hz": _finite(m.phase_crossover_hz),
        "gain_margin_up_db": _finite(m.gain_margin_up_db),
        "gain_margin_up_hz": _finite(m.gain_margin_up_hz),
        "gain_reduction_margin_db": _finite(m.gain_reduction_margin_db),
        "gain_reduction_margin_hz": _finite(m.gain_reduction_margin_hz),
        "phase_margin_deg": _finite(m.phase_margin_deg),
        "gain_crossover_hz": _finite(m.gain_crossover_hz),
        "delay_margin_s": _finite(m.delay_margin_s),
        "peak_sensitivity_db": _finite(m.peak_sensitivity_db),
        "peak_sensitivity_hz": _finite(m.peak_sensitivity_hz),
    }


def _recommendation_json(r: Recommendation | None) -> dict[str, Any]:
    """The recommended cut-off's parts: the gate alone, the position spread's limit."""
    if r is None:
        return {}
    sp = r.spread
    return {
        "recommended_gate_only_hz": r.gate_hz,
        "spread_limited_cutoff_hz": r.spread_hz,
        "spread_figure_max": None if sp is None else 1.0 / r.margin,
        "position_spread": None if sp is None else {
            "responses": list(sp.names),
            "divergence_hz": sp.divergence_hz,
            "freq_hz": sp.freq_hz.tolist(),
            "relative": sp.relative.tolist(),
            "mag_db": sp.mag_db.tolist(),
        },
    }


def report_json(a: Analysis, j: Verdict, rec: Recommendation | None = None) -> dict[str, Any]:
    """The JSON object printed by `dobtune check --json` (`j`: the verdict from analysis
    `a`)."""
    recommended_hz = j.recommended_max_cutoff_hz
    config = config_to_builtins(a.config)
    config["q_tau_s"] = a.tau_s  # derived from q_type and q_cutoff_hz (not a LoopConfig field)
    return {
        "verdict": j.verdict,
        "reasons": list(j.reasons),
        "rejections": list(j.rejections),
        "cautions": list(j.cautions),
        "knowledge": a.knowledge,
        **_margins_json(a.margins),
        "bandwidth_hz": _finite(a.bandwidth_hz),
        "small_gain_peak": _finite(a.small_gain_peak),
        "max_pole_radius": a.max_pole_radius,
        "noise_to_command_peak_db": _finite(a.noise_to_command_peak_db),
        "recommended_max_cutoff_hz": recommended_hz,
        "recommended_for_q_type": a.config.q_type,
        **_recommendation_json(rec),
        "sources": [
            {
                "name": s.name,
                "kind": s.kind,
                "small_gain_peak": _finite(s.small_gain_peak),
                "small_gain_freq_hz": _finite(s.small_gain_freq_hz),
                "small_gain_with_position_loop": _finite(s.small_gain_full_peak),
                "small_gain_with_position_loop_freq_hz": _finite(s.small_gain_full_freq_hz),
                "delta_q_peak": _finite(s.delta_q_peak),
                "base_loop_stable": s.base_loop_stable,
                "margins": _margins_json(s.margins) if s.margins is not None else None,
                "margins_whole_servo": (
                    _margins_json(s.margins_full) if s.margins_full is not None else None
                ),
                "band_hz": list(s.band_hz) if s.band_hz is not None else None,
            }
            for s in a.sources
        ],
        "config": config,
    }


def _fmt(v: float, unit: str, spec: str = ".1f") -> str:
    return f"{v:{spec}} {unit}" if math.isfinite(v) else "none"


def _gain_text(m: Margins) -> str:
    """The speed loop's gain margins in one line, both positive and named
    (`gain_margins_text`)."""
    return gain_margins_text(m.gain_margin_up_db, m.gain_reduction_margin_db)


def report_text(a: Analysis, j: Verdict, rec: Recommendation | None = None) -> str:
    """The readable table printed by `dobtune check` (`j`: the verdict from analysis `a`)."""
    recommended_hz = j.recommended_max_cutoff_hz
    c, m = a.config, a.margins
    dob = f"{c.q_type} at {c.q_cutoff_hz:g} Hz (tau {a.tau_s:.4g} s)" if c.dob_on else "off"

    def row(label: str, value: str, at: float | None = None) -> str:
        where = f"  at {_fmt(at, 'Hz', '.3g')}" if at is not None else ""
        return f"  {label:<28}{value:>12}{where}"

    lines = [
        f"dobtune check: DOB {dob}, Cv {c.cv_kp:g} (1 + {c.cv_ki_per_s:g}/s), "
        f"Cp {c.pos_kp_per_s:g} (1 + {c.pos_ki_per_s:g}/s), {c.rate_hz:g} Hz loop",
        f"  judged on {a.knowledge}",
        f"  speed loop: {_gain_text(m)}",
        row("gain margin (up)", _fmt(m.gain_margin_up_db, "dB"),
            m.gain_margin_up_hz if math.isfinite(m.gain_margin_up_db) else None),
        row("gain-reduction margin (down)", _fmt(m.gain_reduction_margin_db, "dB"),
            m.gain_reduction_margin_hz if m.conditionally_stable else None),
        row("phase margin", _fmt(m.phase_margin_deg, "deg"), m.gain_crossover_hz),
        row("delay margin", _fmt(m.delay_margin_s * 1e3, "ms")),
        row("peak sensitivity", _fmt(m.peak_sensitivity_db, "dB"), m.peak_sensitivity_hz),
        row("speed-loop bandwidth", _fmt(a.bandwidth_hz, "Hz", ".3g")),
        row("max closed-loop pole radius", f"{a.max_pole_radius:.5f}"),
        row("noise -> command peak", _fmt(a.noise_to_command_peak_db, "dB")),
    ]
    for s in a.sources:
        if s.kind in ("bound", "model"):
            lines.append(
                f"  plant model, {s.name}: |W T| {_fmt(s.small_gain_peak, '', '.3g').strip()} at "
                f"{_fmt(s.small_gain_freq_hz, 'Hz', '.3g')}, whole servo "
                f"{_fmt(s.small_gain_full_peak, '', '.3g').strip()}"
                + ("" if s.base_loop_stable else "; UNSTABLE")
            )
            continue
        sm, sf = s.margins, s.margins_full
        assert sm is not None and sf is not None
        band = f" ({s.band_hz[0]:.3g}-{s.band_hz[1]:.3g} Hz)" if s.band_hz else ""
        lines.append(
            f"  response {s.name!r}{band}: |a T| {_fmt(s.small_gain_peak, '', '.3g').strip()} at "
            f"{_fmt(s.small_gain_freq_hz, 'Hz', '.3g')}, whole servo "
            f"{_fmt(s.small_gain_full_peak, '', '.3g').strip()}; PM "
            f"{_fmt(sm.phase_margin_deg, 'deg')} / {_fmt(sf.phase_margin_deg, 'deg')}, GM up "
            f"{_fmt(sm.gain_margin_up_db, 'dB')} / {_fmt(sf.gain_margin_up_db, 'dB')}, "
            f"gain-reduction margin down {_fmt(sm.gain_reduction_margin_db, 'dB')} / "
            f"{_fmt(sf.gain_reduction_margin_db, 'dB')} (speed / whole)"
            + ("" if s.base_loop_stable else "; NOT proven stable")
        )
    rec_text = (
        f"{recommended_hz:.3g} Hz"
        if recommended_hz is not None
        else "none (even the lowest is rejected)"
    )
    lines.append(f"  recommended max cut-off ({c.q_type}): {rec_text}")
    if rec is not None and rec.spread is not None:
        lines.append(f"    {rec.describe()}")
    lines.append(f"verdict: {j.verdict.upper()}")
    lines += [f"  - reject: {r}" for r in j.rejections]
    lines += [f"  - caution: {r}" for r in j.cautions]
    return "\n".join(lines) + "\n"


def check_main(
    config_path: Path | None,
    q_type: str | None,
    cutoff_hz: float | None,
    frd_paths: Sequence[Path],
    as_json: bool,
    out: TextIO,
    knowledge_path: Path | None = None,
) -> int:
    """Load, override, check; print a table (or one JSON object). Returns the exit code."""
    try:
        cfg = load_config(config_path)
        try:
            if q_type is not None:
                cfg = cfg.with_(q_type=q_type)
            if cutoff_hz is not None:
                cfg = cfg.with_(q_cutoff_hz=cutoff_hz)
        except ConfigError as exc:
            flag = "--q" if exc.field == "q_type" else "--cutoff-hz"
            raise BadInput(f"{flag}: {exc}") from exc
        try:
            measured = load_measured(list(frd_paths))
        except OSError as exc:
            raise BadInput(f"cannot read response file: {exc}") from exc
        except ValueError as exc:
            raise BadInput(str(exc)) from exc
        plant = load_knowledge(knowledge_path)
        if measured:
            names = {m.name for m in plant.measured}
            clash = [m.name for m in measured if m.name in names]
            if clash:
                raise BadInput(f"--frd: response {clash[0]!r} is already in the knowledge")
            plant = PlantKnowledge(
                (*plant.measured, *measured), plant.bound, plant.model, plant.version,
                f"{plant.source} + --frd",
            )
        a = analyse(cfg, plant)
        j = verdict_of(a, plant, nonlinear=findings)
        rec = recommend(cfg, plant) if len(plant.measured) >= 2 else None
    except BadInput as exc:
        if as_json:
            out.write(json.dumps({"error": str(exc)}) + "\n")
        else:
            out.write(f"error: {exc}\n")
        return EXIT_BAD_INPUT
    if as_json:
        out.write(json.dumps(report_json(a, j, rec), allow_nan=False) + "\n")
    else:
        out.write(report_text(a, j, rec))
    return EXIT_CODES[j.verdict]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", type=Path, default=None, help="LoopConfig JSON file")
    p.add_argument("--q", dest="q_type", default=None, metavar="q20|q31")
    p.add_argument("--cutoff-hz", type=float, default=None)
    p.add_argument(
        "--frd",
        type=Path,
        action="append",
        default=[],
        metavar="FILE",
        help="measured response CSV freq_hz,mag_db,phase_deg (repeatable)",
    )
    p.add_argument(
        "--knowledge",
        type=Path,
        default=None,
        metavar="FILE",
        help="plant knowledge record (JSON; default: the simulated rig's model with the "
        "commissioning bound)",
    )
    p.add_argument("--json", action="store_true")


def run(args: argparse.Namespace) -> int:
    return check_main(
        args.config, args.q_type, args.cutoff_hz, args.frd, args.json, sys.stdout, args.knowledge
    )

