"""Independent fuzz of the stability gate: does it ever accept a loop that is not stable?

    .venv/bin/python tests/bench/fuzz_gate.py [--n 10000] [--seed 0] [--workers 2]
        [--ident-every K] [--csv FAILURES.csv] [--json] [--case I] [--edge]

Each case draws a true plant (M P with gain x0.3-3, natural frequency x0.5-2, damping x0.3-2
of the article's belt mode, half the time an extra resonance 2-60 Hz with damping 0.01-0.2 and
anti-resonance zeros at 0.5-2x its frequency, 0-3 ticks of delay) and a candidate (Q20/Q31,
cut-off log-uniform 0.05-50 Hz, cv_kp 0.1-2, cv_ki 5-200 /s or 0 (15 %), pos_kp 1-30 /s, pos_ki
0.3-20 /s or 0 (20 %), DOB on (75 %) or off, and a `nominal` that is the article model (40 %),
the truth's second-order part (30 %), or a lie: the truth's with its gain x0.1-x10 (30 %)).
The truth comes from tests/fuzz_truth.py (python-control, nothing from the gate); the gate's
verdict is taken with three kinds of plant knowledge, each with the article's Mn Pn as the
commissioning model and its stated bound (COMMISSIONING_BOUND); the candidate's `nominal` is
never evidence (lies included):

    model   the commissioning model and its bound only
    dense   plus the true plant's exact sampled response u[k] -> w[k], 500 points 0.01 Hz..fs/2
    ident   plus what identification hands over: 3 positions, 0.1-20 Hz, 10 points per
            decade, 2 % complex noise, sampling factor divided out (continuous equivalent)

A truth may lie outside what the knowledge states: for `model` when the true plant leaves the
stated bound somewhere, for `ident` when above the measured band it leaves the bound around
the band's edge. Such cases are counted apart ("outside"): no gate can be right about a plant
its evidence excludes. Printed: unstable accepted per evidence kind inside the knowledge (must
be 0) and outside it, share of comfortably stable cases
(true |GM| >= 6 dB and PM >= 30 deg in the speed loop and the whole servo) accepted, share of
stable cases rejected, runtime; `--json` adds a one-line JSON summary. Unstable accepted
cases go to `--csv` for debugging; `--case I` re-runs one case and prints everything.
A "caution" verdict counts as accepted (it is applied after a confirmation).

`--edge`: loops built to sit just past the stability boundary instead. Each case takes the
candidate and plant of a normal case, adds a sharp resonance (even cases: 20-200 Hz, damping
0.005-0.03, between two points of the dense evidence; odd cases: 2-20 Hz, damping 0.01-0.1,
between two points of the identification grid) and scales the plant's gain so that the
largest closed-loop pole radius is 1 + eps, eps log-uniform 1e-6..1e-4, at the boundary
crossing whose critical pole lies nearest the resonance (`fuzz_truth.edge_plant`). Judged on
the evidence the resonance was placed for (dense or ident); printed: edge loops accepted of
those built. Every one is unstable: the count must be 0.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import multiprocessing
import os
import sys
import time
import warnings
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: the truth module

# -- the gate under test and the truth: update these imports (and `gate_verdict`) when the
# -- gate's modules or API change.
from fuzz_truth import (
    Resonance,
    TruePlant,
    Truth,
    edge_plant,
    sampled_response,
    truth,
)

from controller.core.config import LoopConfig, NominalModel
from controller.gate.analysis import analyse
from controller.gate.knowledge import (
    COMMISSIONING_BOUND,
    MIN_ALLOWANCE,
    MeasuredResponse,
    PlantKnowledge,
)

KINDS = ("model", "dense", "ident")
ARTICLE = NominalModel()
RATE_HZ = 1000.0
DENSE_HZ = np.geomspace(0.01, 0.4999 * RATE_HZ, 500)
IDENT_HZ = np.logspace(-1.0, math.log10(20.0), round(10 * math.log10(20.0 / 0.1)) + 1)
IDENT_POSITIONS = 3
IDENT_NOISE = 0.02


# ------------------------------------------------------------------------------ evidence


@dataclass(frozen=True, eq=False)
class Response:
    name: str
    freq_hz: np.ndarray
    response: np.ndarray
    sampled: bool
    """True: the sampled loop's u[k] -> w[k]; False: continuous equivalent G_c(j w)."""


@dataclass(frozen=True, eq=False)
class Evidence:
    """What the gate is told about the real plant, in neutral form."""

    model: NominalModel | None
    """A commissioning model the controller holds (None: only the candidate's nominal)."""
    responses: tuple[Response, ...] = ()


def gate_verdict(cfg: LoopConfig, ev: Evidence) -> tuple[bool, str]:
    """The adapter to the gate's API: (accepted, reasons). Update when the API changes."""
    measured = [
        MeasuredResponse(r.name, r.freq_hz, r.response, sampled=r.sampled) for r in ev.responses
    ]
    assert ev.model is not None
    knowledge = PlantKnowledge(tuple(measured), COMMISSIONING_BOUND, ev.model)
    a = analyse(cfg, knowledge)
    return a.verdict != "reject", "; ".join(a.reasons)


def inside_knowledge(kind: str, plant: TruePlant) -> bool:
    """Whether the true plant lies within what the knowledge of `kind` states about it."""
    g_true = sampled_response(plant, RATE_HZ, DENSE_HZ)
    g_model = sampled_response(TruePlant(base=ARTICLE), RATE_HZ, DENSE_HZ)
    w = COMMISSIONING_BOUND.magnitude(DENSE_HZ)
    if kind == "model":
        return bool(np.all(np.abs(g_true / g_model - 1.0) <= w))
    if kind == "ident":
        top = IDENT_HZ[-1]
        edge = np.interp(np.log(top), np.log(DENSE_HZ), np.log(g_true / g_model))
        above = top < DENSE_HZ
        err = np.abs(g_true[above] / (g_model[above] * np.exp(edge)) - 1.0)
        return bool(np.all(err <= MIN_ALLOWANCE + w[above]))
    return True


def evidence(kind: str, plant: TruePlant, rng: np.random.Generator) -> Evidence:
    if kind == "model":
        return Evidence(model=ARTICLE)
    if kind == "dense":
        h = sampled_response(plant, RATE_HZ, DENSE_HZ)
        return Evidence(model=ARTICLE, responses=(Response("dense", DENSE_HZ, h, sampled=True),))
    # Identification: the loop measures u[k] -> w[k] and divides out the ZOH + backward
    # difference factor e^{-j w Ts} sinc^2(w Ts / 2) (ident.result.continuous_equivalent).
    x = np.pi * IDENT_HZ / RATE_HZ
    factor = np.exp(-2j * x) * np.sinc(x / np.pi) ** 2
    h = sampled_response(plant, RATE_HZ, IDENT_HZ) / factor
    out = []
    for i in range(IDENT_POSITIONS):
        noise = rng.normal(0.0, IDENT_NOISE, (2, IDENT_HZ.size)) / math.sqrt(2.0)
        out.append(Response(f"pos{i}", IDENT_HZ, h * (1.0 + noise[0] + 1j * noise[1]), False))
    return Evidence(model=ARTICLE, responses=tuple(out))


# ------------------------------------------------------------------------------ cases


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


@dataclass(frozen=True)
class Case:
    index: int
    plant: TruePlant
    config: LoopConfig
    nominal_kind: str
    """"article", "honest" (the truth's second-order part) or "lying" (its gain x0.1-x10)."""
    lie_factor: float


def make_case(seed: int, index: int) -> Case:
    rng = np.random.default_rng([seed, index])
    res = None
    if rng.uniform() < 0.5:
        res = Resonance(
            freq_hz=_log_uniform(rng, 2.0, 60.0),
            damping=_log_uniform(rng, 0.01, 0.2),
            zero_ratio=_log_uniform(rng, 0.5, 2.0),
        )
    plant = TruePlant(
        gain=_log_uniform(rng, 0.3, 3.0),
        wn_scale=_log_uniform(rng, 0.5, 2.0),
        damping_scale=_log_uniform(rng, 0.3, 2.0),
        resonance=res,
        delay_ticks=int(rng.integers(0, 4)),
    )
    u = rng.uniform()
    kind, lie = ("article", 1.0) if u < 0.4 else ("honest", 1.0) if u < 0.7 else ("lying", 0.0)
    if kind == "lying":
        lie = _log_uniform(rng, 0.1, 10.0)
    nominal = ARTICLE if kind == "article" else _second_order_part(plant, lie)
    cfg = LoopConfig(
        rate_hz=RATE_HZ,
        nominal=nominal,
        q_type=str(rng.choice(["q20", "q31"])),
        q_cutoff_hz=_log_uniform(rng, 0.05, 50.0),
        cv_kp=_log_uniform(rng, 0.1, 2.0),
        cv_ki_per_s=0.0 if rng.uniform() < 0.15 else _log_uniform(rng, 5.0, 200.0),
        pos_kp_per_s=_log_uniform(rng, 1.0, 30.0),
        pos_ki_per_s=0.0 if rng.uniform() < 0.2 else _log_uniform(rng, 0.3, 20.0),
        dob_on=bool(rng.uniform() < 0.75),
        ff_on=bool(rng.uniform() < 0.5),
    )
    return Case(index, plant, cfg, kind, lie)


def _second_order_part(plant: TruePlant, lie: float) -> NominalModel:
    """The article's form with the truth's gain and belt mode (no resonance, no delay)."""
    a2, a1, a0 = ARTICLE.pn_den
    k, d = plant.wn_scale, plant.damping_scale
    g = plant.gain * lie
    return NominalModel(
        mn_den=ARTICLE.mn_den,
        pn_num=(g * ARTICLE.pn_num[0], g * ARTICLE.pn_num[1], g * ARTICLE.pn_num[2]),
        pn_den=(a2 / (k * k), d * a1 / k, a0),
    )


@dataclass(frozen=True)
class EdgeCase:
    index: int
    kind: str
    """The evidence the resonance was placed for: "dense" or "ident"."""
    plant: TruePlant
    config: LoopConfig
    radius: float


def make_edge_case(seed: int, index: int) -> EdgeCase | None:
    """A normal case's candidate and plant, plus a sharp resonance between two measured
    points, the gain scaled to put the loop just past the boundary (None: no gain in
    x1/30..x30 crosses it)."""
    base = make_case(seed, index)
    rng = np.random.default_rng([seed, index, 2])
    kind = "dense" if index % 2 == 0 else "ident"
    grid, (lo, hi), damping = (
        (DENSE_HZ, (20.0, 200.0), (0.005, 0.03)) if kind == "dense"
        else (IDENT_HZ, (2.0, 20.0), (0.01, 0.1))
    )
    k = int(rng.integers(np.searchsorted(grid, lo), np.searchsorted(grid, hi) - 1))
    x = math.log(grid[k]) + rng.uniform(0.2, 0.8) * math.log(grid[k + 1] / grid[k])
    res = Resonance(
        freq_hz=math.exp(x),
        damping=_log_uniform(rng, *damping),
        zero_ratio=_log_uniform(rng, 0.5, 2.0),
    )
    eps = _log_uniform(rng, 1e-6, 1e-4)
    plant = TruePlant(
        gain=base.plant.gain, wn_scale=base.plant.wn_scale,
        damping_scale=base.plant.damping_scale, resonance=res,
        delay_ticks=base.plant.delay_ticks,
    )
    found = edge_plant(plant, base.config, 1.0 + eps, near_hz=res.freq_hz)
    if found is None:
        return None
    return EdgeCase(index, kind, found[0], base.config, found[1])


def run_edge_case(seed: int, index: int) -> tuple[EdgeCase, bool | None, str] | None:
    case = make_edge_case(seed, index)
    if case is None:
        return None
    rng = np.random.default_rng([seed, index, 1])
    try:
        ok, why = gate_verdict(case.config, evidence(case.kind, case.plant, rng))
    except Exception as exc:  # a gate that raises applies nothing: not accepted
        return case, None, f"error: {type(exc).__name__}: {exc}"
    return case, ok, why


def _edge_work(job: tuple[int, int, int]) -> tuple[EdgeCase, bool | None, str] | None:
    return run_edge_case(job[0], job[1])


def main_edge(cfg: FuzzConfig) -> dict[str, Any]:
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    t0 = time.perf_counter()
    done: list[tuple[EdgeCase, bool | None, str]] = []
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(cfg.workers, initializer=_quiet) as pool:
        jobs = [(cfg.seed, i, 1) for i in range(cfg.n)]
        for r in pool.imap_unordered(_edge_work, jobs, chunksize=4):
            if r is not None:
                done.append(r)
    out: dict[str, Any] = {"seconds": round(time.perf_counter() - t0, 1), "kinds": {}}
    for kind in ("dense", "ident"):
        rs = [r for r in done if r[0].kind == kind]
        acc = sorted((r for r in rs if r[1]), key=lambda r: r[0].index)
        out["kinds"][kind] = {"built": len(rs), "accepted": len(acc),
                              "errors": sum(r[1] is None for r in rs)}
        for case, _, why in acc:
            res = case.plant.resonance
            assert res is not None
            print(f"  accepted {kind} case {case.index}: radius 1{case.radius - 1:+.2e}, "
                  f"resonance {res.freq_hz:.4g} Hz damping {res.damping:.3g}, "
                  f"gain x{case.plant.gain:.4g}; {why[:160]}")
    total = sum(k["built"] for k in out["kinds"].values())
    bad = sum(k["accepted"] for k in out["kinds"].values())
    print(f"{cfg.n} edge cases tried, {total} built (radius 1 + 1e-6..1e-4) in "
          f"{out['seconds']} s: {bad} accepted "
          + ", ".join(f"{k} {v['accepted']}/{v['built']}" for k, v in out["kinds"].items()))
    if cfg.json:
        print(json.dumps(out, sort_keys=True))
    return out


# ------------------------------------------------------------------------------ one case


@dataclass
class Result:
    index: int
    nominal_kind: str
    lie_factor: float
    stable: bool
    comfortable: bool
    radius: float
    verdicts: dict[str, bool | None]
    """Accepted per evidence kind; None: gate error (counted as not accepted); absent: the
    kind was not run for this case."""
    inside: dict[str, bool]
    """Per evidence kind: the truth lies within what that knowledge states."""
    reasons: dict[str, str]
    row: dict[str, Any]


PLANT_FIELDS = ("gain", "wn_scale", "damping_scale", "delay_ticks")
CONFIG_FIELDS = (
    "q_type", "q_cutoff_hz", "cv_kp", "cv_ki_per_s", "pos_kp_per_s", "pos_ki_per_s", "dob_on",
)  # fmt: skip


def _row(case: Case, t: Truth) -> dict[str, Any]:
    """One CSV row: the case's parameters and its truth."""
    r = case.plant.resonance
    row: dict[str, Any] = {"case": case.index}
    row |= {k: getattr(case.plant, k) for k in PLANT_FIELDS}
    row |= {
        "res_hz": r.freq_hz if r else "",
        "res_damping": r.damping if r else "",
        "res_zero_ratio": r.zero_ratio if r else "",
        "nominal": case.nominal_kind,
        "lie_factor": case.lie_factor,
    }
    row |= {k: getattr(case.config, k) for k in CONFIG_FIELDS}
    row |= {"radius_speed": t.radius_speed, "radius_full": t.radius_full}
    for loop, m in (("speed", t.margins_speed), ("full", t.margins_full)):
        row[f"gm_{loop}_db"] = m.gain_margin_db if m else ""
        row[f"pm_{loop}_deg"] = m.phase_margin_deg if m else ""
    return row


def run_case(seed: int, index: int, kinds: tuple[str, ...]) -> Result:
    case = make_case(seed, index)
    t = truth(case.plant, case.config, margins="if_stable")
    rng = np.random.default_rng([seed, index, 1])
    verdicts: dict[str, bool | None] = {}
    reasons: dict[str, str] = {}
    inside = {kind: inside_knowledge(kind, case.plant) for kind in kinds}
    for kind in kinds:
        try:
            verdicts[kind], reasons[kind] = gate_verdict(
                case.config, evidence(kind, case.plant, rng)
            )
        except Exception as exc:  # a gate that raises applies nothing: not accepted
            verdicts[kind], reasons[kind] = None, f"error: {type(exc).__name__}: {exc}"
    return Result(
        index=index,
        nominal_kind=case.nominal_kind,
        lie_factor=case.lie_factor,
        stable=t.stable,
        comfortable=t.comfortable(),
        radius=t.max_pole_radius,
        verdicts=verdicts,
        inside=inside,
        reasons=reasons,
        row=_row(case, t),
    )


def _work(job: tuple[int, int, int]) -> Result:
    seed, index, ident_every = job
    kinds = KINDS if index % ident_every == 0 else KINDS[:-1]
    return run_case(seed, index, kinds)


def _quiet() -> None:
    warnings.simplefilter("ignore")
    np.seterr(all="ignore")


# ------------------------------------------------------------------------------ summary


def summarise(results: list[Result], seconds: float) -> dict[str, Any]:
    n = len(results)
    stable = [r for r in results if r.stable]
    comfy = [r for r in stable if r.comfortable]
    out: dict[str, Any] = {
        "cases": n,
        "unstable": n - len(stable),
        "stable": len(stable),
        "comfortable": len(comfy),
        "nominal_kinds": dict(Counter(r.nominal_kind for r in results)),
        "seconds": round(seconds, 1),
        "kinds": {},
    }
    for kind in KINDS:
        ran = [r for r in results if kind in r.verdicts]
        if not ran:
            continue
        bad = [r for r in ran if not r.stable and r.verdicts[kind]]
        st = [r for r in ran if r.stable]
        cf = [r for r in st if r.comfortable]
        out["kinds"][kind] = {
            "cases": len(ran),
            "outside": sum(not r.inside[kind] for r in ran),
            "accepted": sum(bool(r.verdicts[kind]) for r in ran),
            "unstable_accepted": sum(r.inside[kind] for r in bad),
            "unstable_accepted_outside": sum(not r.inside[kind] for r in bad),
            "comfortable_accepted": _share(sum(bool(r.verdicts[kind]) for r in cf), len(cf)),
            "stable_rejected": _share(sum(not r.verdicts[kind] for r in st), len(st)),
            "errors": sum(r.verdicts[kind] is None for r in ran),
        }
    return out


def _share(k: int, n: int) -> float:
    return round(k / n, 4) if n else math.nan


def report(s: dict[str, Any]) -> str:
    lines = [
        f"{s['cases']} cases in {s['seconds']} s: {s['unstable']} unstable, {s['stable']} stable"
        f" ({s['comfortable']} comfortably: |GM| >= 6 dB, PM >= 30 deg in both loops);"
        f" nominal {s['nominal_kinds']}",
        f"{'evidence':<8} {'cases':>6} {'outside':>7} {'accepted':>8} {'unstable acc.':>13}"
        f" {'(outside)':>9} {'comfortable acc.':>16} {'stable rej.':>11} {'errors':>6}",
    ]
    for kind, k in s["kinds"].items():
        lines.append(
            f"{kind:<8} {k['cases']:>6} {k['outside']:>7} {k['accepted']:>8}"
            f" {k['unstable_accepted']:>13} {k['unstable_accepted_outside']:>9}"
            f" {k['comfortable_accepted']:>16.1%}"
            f" {k['stable_rejected']:>11.1%} {k['errors']:>6}"
        )
    return "\n".join(lines)


def write_failures(path: Path, results: list[Result]) -> int:
    rows = []
    for r in sorted(results, key=lambda r: r.index):
        kinds = [k for k in KINDS if not r.stable and r.verdicts.get(k) and r.inside.get(k)]
        if kinds:
            rows.append({**r.row, "accepted_with": " ".join(kinds)})
    fields = [*_row_fields(), "accepted_with"]
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)
    return len(rows)


def _row_fields() -> list[str]:
    case = make_case(0, 0)
    return list(_row(case, truth(case.plant, case.config, margins="never")).keys())


def show_case(seed: int, index: int) -> None:
    case = make_case(seed, index)
    print(case.plant)
    print(case.config)
    print(f"nominal: {case.nominal_kind} (lie factor {case.lie_factor:.3g})")
    t = truth(case.plant, case.config)
    print(asdict(t), "stable:", t.stable, "comfortable:", t.comfortable())
    r = run_case(seed, index, KINDS)
    for kind in KINDS:
        print(f"{kind}: accepted={r.verdicts[kind]} {r.reasons[kind]}")


# ------------------------------------------------------------------------------ main


@dataclass(frozen=True)
class FuzzConfig:
    n: int = 10000
    seed: int = 0
    workers: int = 2
    ident_every: int = 1
    csv_path: Path | None = None
    json: bool = False
    edge: bool = False


def main(cfg: FuzzConfig) -> dict[str, Any]:
    jobs = [(cfg.seed, i, cfg.ident_every) for i in range(cfg.n)]
    # One BLAS thread per worker: the matrices are small and threads only contend (1.5x
    # faster). Spawned workers import numpy afresh and see the setting.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    t0 = time.perf_counter()
    results: list[Result] = []
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(cfg.workers, initializer=_quiet) as pool:
        for r in pool.imap_unordered(_work, jobs, chunksize=16):
            results.append(r)
            if len(results) % 1000 == 0:
                rate = len(results) / (time.perf_counter() - t0)
                print(f"  {len(results)} cases, {rate:.1f}/s", file=sys.stderr, flush=True)
    summary = summarise(results, time.perf_counter() - t0)
    summary.update(seed=cfg.seed, ident_every=cfg.ident_every)
    print(report(summary))
    if cfg.csv_path is not None:
        k = write_failures(cfg.csv_path, results)
        print(f"{k} unstable accepted case(s) written to {cfg.csv_path}")
    if cfg.json:
        print(json.dumps(summary, sort_keys=True))
    return summary


def _parse(argv: list[str]) -> tuple[FuzzConfig, int | None]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=10000, help="number of cases")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--ident-every",
        type=int,
        default=1,
        help="run the identification-like evidence on every K-th case only (it is the costly one)",
    )
    ap.add_argument("--csv", type=Path, default=None, help="write unstable accepted cases here")
    ap.add_argument("--json", action="store_true", help="print a one-line JSON summary")
    ap.add_argument("--case", type=int, default=None, help="show one case in detail and exit")
    ap.add_argument("--edge", action="store_true",
                    help="loops built just past the stability boundary (see the docstring)")
    a = ap.parse_args(argv)
    fc = FuzzConfig(a.n, a.seed, a.workers, max(1, a.ident_every), a.csv, a.json, a.edge)
    return fc, a.case


if __name__ == "__main__":
    fuzz_cfg, one = _parse(sys.argv[1:])
    if one is not None:
        _quiet()
        show_case(fuzz_cfg.seed, one)
    elif fuzz_cfg.edge:
        main_edge(fuzz_cfg)
    else:
        main(fuzz_cfg)
