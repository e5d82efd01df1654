"""`dobtune paper --out DIR`: every experiment of the article on the simulated rig, as a report.

Runs `controller.sim.paper.run_paper` and writes DIR/report.md (one section per figure: our
plot, our numbers, the article's reported numbers, a plain statement of agreement or
disagreement with the reason) and one PNG per figure (matplotlib, Agg backend). The
frequency-domain results (Fig. 11, eqs. 28-29) are checked against python-control here and
the differences written into the report. Progress goes to stderr, one line per run.

Exit codes: 0 written, 2 bad input or an unwritable directory.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TextIO

import numpy as np

from controller.core.config import LoopConfig, config_to_builtins
from controller.core.errors import ConfigError
from controller.sim.linear_rig import PlantVariant

__all__ = ["figure_file", "paper_main", "python_control_check"]


def figure_file(figure: str) -> str:
    """'Fig. 8' -> 'fig8.png', 'Eqs. 28-29' -> 'eqs28-29.png'."""
    return figure.lower().replace(".", "").replace(" ", "") + ".png"


def python_control_check(cfg: LoopConfig) -> dict[str, float]:
    """Eq. 23 and eqs. 28-29 computed again with python-control's transfer-function algebra
    (and the sensitivity as a finite difference of W2 and W1 in P, not from its formula);
    returns the largest difference in dB to `controller.sim.paper_freq`'s curves."""
    import control as ct

    from controller.core.qfilter import design_q
    from controller.sim.paper import VARIANTS_40
    from controller.sim.paper_freq import sensitivity_curves, suppression_curve

    nom = cfg.nominal
    s = ct.tf("s")
    m = ct.tf([1.0], list(nom.mn_den))
    pn = ct.tf(list(nom.pn_num), list(nom.pn_den))
    cv = cfg.cv_kp * (1 + cfg.cv_ki_per_s / s)
    f = np.geomspace(0.01, 50.0, 300)
    jw = 2j * math.pi * f
    out = {"eq23_max_diff_db": 0.0, "eqs28_29_max_diff_db": 0.0}

    def mag_db(sys_: ct.TransferFunction) -> np.ndarray:
        return 20.0 * np.log10(np.abs(np.asarray(sys_(jw)).ravel()))

    variants: Sequence[PlantVariant] = (PlantVariant("nominal"), VARIANTS_40[1])
    for qt in ("q20", "q31"):
        q = ct.tf(*design_q(qt, cutoff_hz=cfg.q_cutoff_hz).tf())  # type: ignore[arg-type]
        for v in variants:
            p = ct.tf(*v.p_polys(nom))
            loop = cv * m * p
            d = 1 + loop + (p / pn - 1) * q
            ours = suppression_curve(cfg, qt, cfg.q_cutoff_hz, v, f).gain_db
            # eq. 23 with the article's names: E1 (eq. 18, no DOB) over E2 (eq. 16, DOB)
            e1 = p / (1 + loop)
            e2 = p * (1 - q) / d
            diff = float(np.max(np.abs(mag_db(e1 / e2) - ours)))
            out["eq23_max_diff_db"] = max(out["eq23_max_diff_db"], diff)
    # Sensitivity: relative change of W per relative change of P, by finite difference.
    q = ct.tf(*design_q(cfg.q_type, cutoff_hz=cfg.q_cutoff_hz).tf())  # type: ignore[arg-type]
    qj = np.asarray(q(jw)).ravel()
    cvj = np.asarray(cv(jw)).ravel()
    mj = np.asarray(m(jw)).ravel()
    pnj = np.asarray(pn(jw)).ravel()
    eps = 1e-6
    for v in variants:
        pj = np.asarray(ct.tf(*v.p_polys(nom))(jw)).ravel()

        def w1(p_: np.ndarray) -> np.ndarray:
            return np.asarray(cvj * mj * p_ / (1 + cvj * mj * p_))

        def w2(p_: np.ndarray) -> np.ndarray:
            return np.asarray(cvj * mj * p_ / (1 + cvj * mj * p_ + (p_ / pnj - 1) * qj))

        ours_c = sensitivity_curves(cfg.with_(dob_on=True), v, f)
        for w, ref in ((w1, ours_c.s1_db), (w2, ours_c.s2_db)):
            sens = (w(pj * (1 + eps)) - w(pj)) / w(pj) / eps
            diff = float(np.max(np.abs(20.0 * np.log10(np.abs(sens)) - ref)))
            out["eqs28_29_max_diff_db"] = max(out["eqs28_29_max_diff_db"], diff)
    return out


def _plot(fig_result: object, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from controller.sim.paper import FigureResult

    assert isinstance(fig_result, FigureResult)
    panels = fig_result.panels
    fig = Figure(figsize=(10.0, 3.3 * len(panels)), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(panels), 1, squeeze=False)[:, 0]
    for ax, panel in zip(axes, panels, strict=True):
        for ser in panel.series:
            ax.plot(ser.x, ser.y, label=ser.label, lw=1.0,
                    marker="o" if len(ser.x) <= 20 else None, ms=3)
        for label, y in panel.hlines:
            ax.axhline(y, ls="--", lw=0.8, color="0.4", label=label)
        if panel.vspan is not None:
            ax.axvspan(*panel.vspan, color="0.9", zorder=0)
        if panel.logx:
            ax.set_xscale("log")
        if panel.xticks:
            ax.set_xticks(range(len(panel.xticks)), panel.xticks, rotation=15, fontsize=8)
        ax.set_title(f"{fig_result.figure}: {panel.title}", fontsize=10)
        ax.set_xlabel(panel.xlabel)
        ax.set_ylabel(panel.ylabel)
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.savefig(path, dpi=90)


def _report(
    figures: Sequence[object], cfg: LoopConfig, names: tuple[str, ...], quick: bool,
    checks: dict[str, float], wall_s: float,
) -> str:
    from controller.cli.common import markdown_table
    from controller.sim.paper import FigureResult

    figs = [f for f in figures if isinstance(f, FigureResult)]
    c = config_to_builtins(cfg)
    lines = [
        "# The article's experiments on the simulated rig",
        "",
        "Yu, Yang, Ruan, Xu, Tang, \"A Rate-Difference Disturbance Observer Control for a "
        "Timing-Belt Servo System\", IEEE TIE 2022. The article's numbers are those restated "
        "in /work/shared/design/control.md (the table `ARTICLE` in controller/sim/paper.py); "
        "where control.md gives none the report says \"not reported\". control.md describes "
        "no experiment for the other figures (1-7, 12-13), so they have no section.",
        "",
        f"Made by `dobtune paper`{' --quick (shorter runs, fewer points)' if quick else ''} "
        f"in {wall_s:.0f} s. Loop: Cv = {c['cv_kp']:g} (1 + {c['cv_ki_per_s']:g}/s), "
        f"position PI {c['pos_kp_per_s']:g} (1 + {c['pos_ki_per_s']:g}/s), "
        f"{cfg.q_type.upper()} at {cfg.q_cutoff_hz:g} Hz, {cfg.rate_hz:g} Hz; "
        + ("added disturbances: " + ", ".join(names) if names else "no added disturbance")
        + ". Plots: PNG (matplotlib).",
        "",
        "## Summary",
        "",
        markdown_table(("figure", "what", "agreement"),
                       [(f.figure, f.title, f.agreement) for f in figs]),
        *_in_short(figs),
    ]
    for f in figs:
        lines += [
            f"## {f.figure}: {f.title}",
            "",
            f"![{f.figure}]({figure_file(f.figure)})",
            "",
            f"**What we ran.** {f.setup}",
            "",
            "**Ours.**",
            "",
            markdown_table(f.columns, f.rows),
            "**The article (control.md).**",
            "",
            markdown_table(("quantity", "run", "reported"),
                           [(a.quantity, a.run, a.text) for a in f.article])
            if f.article else "Nothing reported: this section is ours (where the DOB helps).\n",
            f"**Agreement: {f.agreement}.** {f.reason}",
            "",
        ]
        if f.figure == "Fig. 11":
            lines += [f"Independent check: python-control's transfer-function algebra gives "
                      f"the same |E1/E2| within {checks['eq23_max_diff_db']:.2g} dB "
                      f"(0.01-50 Hz, Q20 and Q31, nominal and perturbed plant).", ""]
        if f.figure == "Eqs. 28-29":
            lines += [f"Independent check: the sensitivities as finite differences of W1, W2 "
                      f"in P (python-control responses) match eqs. 28-29 within "
                      f"{checks['eqs28_29_max_diff_db']:.2g} dB.", ""]
    return "\n".join(lines)


def _in_short(figs: Sequence[object]) -> list[str]:
    """A few plain sentences with the numbers that decide the question "does the DOB help?"."""
    from controller.sim.paper import FigureResult

    by = {f.figure: f for f in figs if isinstance(f, FigureResult)}
    out = []
    f14, f16, dist, sens = (by.get(k) for k in ("Fig. 14", "Fig. 16", "Disturbances",
                                                "Eqs. 28-29"))
    if f14 is not None:
        n = f14.numbers
        out.append(
            f"On the article's sine the DOB changes the RMSE from {n['rmse_off']:.4f} to "
            f"{n['rmse_dob']:.4f} deg (article: 0.0231 to 0.0207) and the peak from "
            f"{n['peak_off']:.4f} to {n['peak_dob']:.4f} deg (article: 0.1 to 0.05); velocity "
            f"feedforward brings the RMSE to {n['rmse_ff']:.4f} deg (article: 0.0052).")
    if f16 is not None:
        n = f16.numbers
        out.append(f"The best Q31 cut-off on that sine is {n['best_hz']:g} Hz (RMSE "
                   f"{n['best_rmse']:.4f} deg, DOB off {n['off_rmse']:.4f} deg).")
    if dist is not None:
        first = dist.reason.split(". At hold")[0]
        out.append("With the timing-belt disturbances: " + first[:1].lower() + first[1:] + ".")
    if sens is not None:
        out.append("Where the DOB does what the article says: " + sens.reason.split(
            "Ours: ", 1)[-1])
    return ["**In short.** " + " ".join(out), ""] if out else []


def paper_main(
    out_dir: Path, *, quick: bool, config_path: Path | None, disturbances: Sequence[str],
    seed: int, err: TextIO,
) -> int:
    from controller.cli.inputs import BadInput, load_config
    from controller.ident.paper_fig13 import run_paper
    from controller.sim.paper import Options
    from controller.sim.rig_disturbances import rig_setup

    t0 = time.perf_counter()

    def say(what: str) -> None:
        err.write(f"[{time.perf_counter() - t0:6.1f} s] {what}\n")
        err.flush()

    try:
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError("seed", f"must be an int >= 0, got {seed!r}")
        cfg = load_config(config_path)
        names = rig_setup(tuple(disturbances)).names
        out_dir.mkdir(parents=True, exist_ok=True)
    except (BadInput, ConfigError) as exc:
        err.write(f"dobtune paper: error: {exc}\n")
        return 2
    except OSError as exc:
        err.write(f"dobtune paper: error: cannot create {out_dir}: {exc}\n")
        return 2
    figures = run_paper(Options(cfg=cfg, disturbances=names, quick=quick, seed=seed,
                                progress=say))
    say("checking eq. 23 and eqs. 28-29 against python-control")
    checks = python_control_check(cfg)
    try:
        for f in figures:
            say(f"plotting {f.figure}")
            _plot(f, out_dir / figure_file(f.figure))
        report = _report(figures, cfg, names, quick, checks, time.perf_counter() - t0)
        (out_dir / "report.md").write_text(report, encoding="utf-8")
    except OSError as exc:
        err.write(f"dobtune paper: error: cannot write into {out_dir}: {exc}\n")
        return 2
    say(f"wrote {out_dir / 'report.md'} and {len(figures)} PNG files")
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="directory for report.md and the PNG plots (created)")
    p.add_argument("--quick", action="store_true",
                   help="shorter runs and fewer points (a smoke run, under 30 s)")
    p.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="a LoopConfig JSON (as dobtune check takes); default the article's")
    p.add_argument("--disturbance", action="append", default=[], metavar="NAME",
                   help="timing-belt disturbance on the rig for every figure (repeatable)")
    p.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    return paper_main(args.out, quick=args.quick, config_path=args.config,
                      disturbances=args.disturbance, seed=args.seed, err=sys.stderr)

