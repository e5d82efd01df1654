"""`dobtune check`: run the stability check on a configuration file (command body, no argv).

Exit codes: 0 the gate accepts, 1 it rejects, 2 bad input (the message names the file and
line, or the field).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

from controller.cli import Command
from controller.core.config import LoopConfig, config_from_builtins, config_to_builtins
from controller.core.errors import ConfigError
from controller.gate.analysis import Analysis, analyse
from controller.gate.frd import load_measured
from controller.gate.knowledge import PlantKnowledge
from controller.gate.margins import Margins
from controller.gate.search import recommended_max_cutoff_hz

__all__ = ["check_main"]

EXIT_ACCEPT, EXIT_REJECT, EXIT_BAD_INPUT = 0, 1, 2


class _BadInput(Exception):
    pass


def _field_line(text: str, field: str) -> int | None:
    """Line (1-based) where the top-level key of `field` ("nominal.mn_den[2]") appears."""
    key = field.split(".", 1)[0].split("[", 1)[0]
    needle = f'"{key}"'
    for i, line in enumerate(text.splitlines(), start=1):
        if needle in line:
            return i
    return None


def _load_config(path: Path | None) -> LoopConfig:
    if path is None:
        return LoopConfig()
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise _BadInput(f"{path}: cannot read config: {exc}") from exc
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise _BadInput(f"{path}:{exc.lineno}: invalid JSON: {exc.msg}") from exc
    try:
        return config_from_builtins(data)
    except ConfigError as exc:
        line = _field_line(text, exc.field)
        where = f"{path}:{line}" if line is not None else str(path)
        raise _BadInput(f"{where}: field {exc.field!r}: {exc}") from exc


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _margins_json(m: Margins) -> dict[str, float | None]:
    return {
        "gain_margin_db": _finite(m.gain_margin_db),
        "phase_crossover_hz": _finite(m.phase_crossover_hz),
        "phase_margin_deg": _finite(m.phase_margin_deg),
        "gain_crossover_hz": _finite(m.gain_crossover_hz),
        "delay_margin_s": _finite(m.delay_margin_s),
        "peak_sensitivity_db": _finite(m.peak_sensitivity_db),
        "peak_sensitivity_hz": _finite(m.peak_sensitivity_hz),
    }


def report_json(a: Analysis, recommended_hz: float | None) -> dict[str, Any]:
    """The JSON object printed by `dobtune check --json`."""
    config = config_to_builtins(a.config)
    config["q_tau_s"] = a.tau_s  # derived from q_type and q_cutoff_hz (not a LoopConfig field)
    return {
        "verdict": a.verdict,
        "reasons": list(a.reasons),
        **_margins_json(a.margins),
        "bandwidth_hz": _finite(a.bandwidth_hz),
        "small_gain_peak": _finite(a.small_gain_peak),
        "max_pole_radius": a.max_pole_radius,
        "noise_to_command_peak_db": _finite(a.noise_to_command_peak_db),
        "recommended_max_cutoff_hz": recommended_hz,
        "recommended_for_q_type": a.config.q_type,
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
            }
            for s in a.sources
        ],
        "config": config,
    }


def _fmt(v: float, unit: str, spec: str = ".1f") -> str:
    return f"{v:{spec}} {unit}" if math.isfinite(v) else "none"


def report_text(a: Analysis, recommended_hz: float | None) -> str:
    """The readable table printed by `dobtune check`."""
    c, m = a.config, a.margins
    dob = f"{c.q_type} at {c.q_cutoff_hz:g} Hz (tau {a.tau_s:.4g} s)" if c.dob_on else "off"

    def row(label: str, value: str, at: float | None = None) -> str:
        where = f"  at {_fmt(at, 'Hz', '.3g')}" if at is not None else ""
        return f"  {label:<28}{value:>12}{where}"

    lines = [
        f"dobtune check: DOB {dob}, Cv {c.cv_kp:g} (1 + {c.cv_ki_per_s:g}/s), "
        f"Cp {c.pos_kp_per_s:g} (1 + {c.pos_ki_per_s:g}/s), {c.rate_hz:g} Hz loop",
        row("gain margin", _fmt(m.gain_margin_db, "dB"), m.phase_crossover_hz),
        row("phase margin", _fmt(m.phase_margin_deg, "deg"), m.gain_crossover_hz),
        row("delay margin", _fmt(m.delay_margin_s * 1e3, "ms")),
        row("peak sensitivity", _fmt(m.peak_sensitivity_db, "dB"), m.peak_sensitivity_hz),
        row("speed-loop bandwidth", _fmt(a.bandwidth_hz, "Hz", ".3g")),
        row("max closed-loop pole radius", f"{a.max_pole_radius:.5f}"),
        row("noise -> command peak", _fmt(a.noise_to_command_peak_db, "dB")),
    ]
    for s in a.sources:
        if s.kind == "bound":
            lines.append(
                f"  bound {s.name!r}: ||W T|| {s.small_gain_peak:.3g} at "
                f"{s.small_gain_freq_hz:.3g} Hz, with position loop {s.small_gain_full_peak:.3g}; "
                f"||W Q|| {s.delta_q_peak:.3g}"
            )
            continue
        sm = s.margins
        assert sm is not None
        lines.append(
            f"  response {s.name!r}: eq. 21 {_fmt(s.small_gain_peak, '', '.3g').strip()} at "
            f"{_fmt(s.small_gain_freq_hz, 'Hz', '.3g')}, with position loop "
            f"{_fmt(s.small_gain_full_peak, '', '.3g').strip()}; ||Delta Q|| "
            f"{_fmt(s.delta_q_peak, '', '.3g').strip()}; PM {_fmt(sm.phase_margin_deg, 'deg')}, "
            f"GM {_fmt(sm.gain_margin_db, 'dB')}, Ms {_fmt(sm.peak_sensitivity_db, 'dB')}"
            + ("" if s.base_loop_stable else "; loop without DOB NOT proven stable")
        )
    rec = (
        f"{recommended_hz:.3g} Hz"
        if recommended_hz is not None
        else "none (even the lowest is rejected)"
    )
    lines.append(f"  recommended max cut-off ({c.q_type}): {rec}")
    lines.append(f"verdict: {a.verdict.upper()}")
    lines += [f"  - {r}" for r in a.reasons]
    return "\n".join(lines) + "\n"


def check_main(
    config_path: Path | None,
    q_type: str | None,
    cutoff_hz: float | None,
    frd_paths: Sequence[Path],
    as_json: bool,
    out: TextIO,
) -> int:
    """Load, override, check; print a table (or one JSON object). Returns the exit code."""
    try:
        cfg = _load_config(config_path)
        try:
            if q_type is not None:
                cfg = cfg.with_(q_type=q_type)
            if cutoff_hz is not None:
                cfg = cfg.with_(q_cutoff_hz=cutoff_hz)
        except ConfigError as exc:
            flag = "--q" if exc.field == "q_type" else "--cutoff-hz"
            raise _BadInput(f"{flag}: {exc}") from exc
        try:
            measured = load_measured(list(frd_paths))
        except OSError as exc:
            raise _BadInput(f"cannot read response file: {exc}") from exc
        except ValueError as exc:
            raise _BadInput(str(exc)) from exc
        plant = PlantKnowledge(measured=measured)
        a = analyse(cfg, plant)
        rec = recommended_max_cutoff_hz(cfg, plant, q_type=cfg.q_type)
    except _BadInput as exc:
        if as_json:
            out.write(json.dumps({"error": str(exc)}) + "\n")
        else:
            out.write(f"error: {exc}\n")
        return EXIT_BAD_INPUT
    if as_json:
        out.write(json.dumps(report_json(a, rec), allow_nan=False) + "\n")
    else:
        out.write(report_text(a, rec))
    return EXIT_ACCEPT if a.accepted else EXIT_REJECT


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
    p.add_argument("--json", action="store_true")


def run(args: argparse.Namespace) -> int:
    return check_main(args.config, args.q_type, args.cutoff_hz, args.frd, args.json, sys.stdout)


COMMAND = Command("check", "stability check of a configuration", add_arguments, run)
