"""`dobtune identify`: measure the plant on the loop, fit Mn Pn, recommend Q cut-offs (command
body, no argv).

Writes into ``out_dir``: ``pos<k>_<deg>deg.csv`` per position (``freq_hz,mag_db,phase_deg,
coherence``, the continuous-equivalent response u -> w, readable by ``dobtune check --frd``),
``raw_pos<k>.npz`` (every tick: t_s, u, w, x, pos, offset, phase, exc_index) and
``summary.json``. With ``--connect`` the run executes inside the controller's loop (see
`controller.process.node`); the same files are written except the raw records. Exit codes: 0 done,
1 aborted by a limit (partial data written, marked incomplete), 2 bad input (the message
names the flag or field).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from controller.core.config import LoopConfig, config_to_builtins
from controller.core.errors import ConfigError
from controller.ident.estimate import write_frd_csv
from controller.ident.identify import (
    IdentifyAborted,
    IdentifyResult,
    IdentifySpec,
    PositionRecord,
    RigLike,
    run_identification,
)

__all__ = ["EXIT_ABORTED", "EXIT_BAD_INPUT", "EXIT_OK", "identify_main", "summary_json"]

EXIT_OK, EXIT_ABORTED, EXIT_BAD_INPUT = 0, 1, 2

#: IdentifySpec field -> command-line flag, for error messages.
_FLAGS = {
    "mode": "--mode",
    "signal": "--signal",
    "f_min_hz": "--f-min",
    "f_max_hz": "--f-max",
    "positions": "--positions",
    "amplitude_deg_s": "--amplitude",
}


def _finite(v: float | None) -> float | None:
    return v if v is not None and math.isfinite(v) else None


def csv_name(p: PositionRecord) -> str:
    return f"{p.name}.csv"


def _raw_name(p: PositionRecord) -> str:
    return f"raw_pos{p.index}.npz"


def summary_json(
    result: IdentifyResult,
    files: dict[int, tuple[str | None, str]],
    wall_s: float,
    files_config: str | None = None,
) -> dict[str, Any]:
    """The object written to summary.json and printed by ``--json``."""
    spec = result.spec
    exc = result.excitation
    fit = result.fit
    agree = result.agreement
    unc = result.uncertainty
    positions = []
    for i, p in enumerate(result.positions):
        est = p.estimate
        entry: dict[str, Any] = {
            "index": p.index,
            "center_deg": p.center_deg,
            "complete": p.complete,
            "points_done": p.points_done,
            "points_total": p.points_total,
            "csv": files.get(p.index, (None, ""))[0],
            "raw": files.get(p.index, (None, ""))[1],
            "min_coherence": None if est is None else float(np.min(est.coherence)),
        }
        if unc is not None and p.complete and i < unc.delta.shape[0]:
            k = int(np.argmax(np.abs(unc.delta[i])))
            entry["delta_peak"] = float(np.abs(unc.delta[i][k]))
            entry["delta_peak_hz"] = float(unc.freq_hz[k])
        positions.append(entry)
    fit_obj = None
    if fit is not None:
        fit_obj = {
            "model": "Mn Pn = 1 / (a2 s^2 + a1 s + 1)",
            "a2": fit.params["a2"],
            "a2_std": fit.param_std["a2"],
            "a1": fit.params["a1"],
            "a1_std": fit.param_std["a1"],
            "natural_freq_hz": _finite(fit.natural_freq_hz),
            "natural_freq_std_hz": _finite(fit.natural_freq_std_hz),
            "zeta": _finite(fit.zeta),
            "zeta_std": _finite(fit.zeta_std),
            "band_hz": [fit.f_lo_hz, fit.f_hi_hz],
            "n_points": fit.n_points,
            "residual_rms_db": fit.residual_rms_db,
            "residual_rms_deg": fit.residual_rms_deg,
            "converged": fit.converged,
        }
    freqs = exc.freq_hz
    return {
        "complete": result.complete,
        "abort_reason": result.abort_reason,
        "plant": "sim",
        "mode": spec.mode,
        "signal": spec.signal,
        "f_min_hz": spec.f_min_hz,
        "f_max_hz": spec.f_max_hz,
        "n_frequencies": int(freqs.size),
        "amplitude_deg_s": spec.amplitude_deg_s,
        "window_deg": spec.window_deg,
        "simulated_s": result.simulated_s,
        "wall_s": wall_s,
        "positions": positions,
        "fit": fit_obj,
        "nominal": None
        if result.nominal is None
        else {
            "mn_den": list(result.nominal.mn_den),
            "pn_num": list(result.nominal.pn_num),
            "pn_den": list(result.nominal.pn_den),
        },
        "agreement": None
        if agree is None
        else {
            "agree_below_hz": agree.agree_below_hz,
            "first_disagree_hz": agree.first_disagree_hz,
            "tol_db": agree.tol_db,
            "tol_deg": agree.tol_deg,
        },
        "agreement_freq_hz": None if agree is None else agree.agree_below_hz,
        "recommended_cutoff_hz": dict(result.recommended_cutoff_hz),
        "recommended_cutoff_hz_config_nominal": dict(result.recommended_cutoff_hz_config),
        "search_limit_hz": 0.1 * result.config.rate_hz,
        "fitted_config": files_config,
        "gate_checks": [
            {
                "q_type": g.q_type,
                "cutoff_hz": g.cutoff_hz,
                "accepted": g.accepted,
                "small_gain_peak": _finite(g.small_gain_peak),
                "reasons": list(g.reasons),
            }
            for g in result.gate_checks
        ],
        "notes": list(result.notes),
        "config": config_to_builtins(result.config),
    }


def _write(result: IdentifyResult, out_dir: Path) -> dict[int, tuple[str | None, str]]:
    out_dir.mkdir(parents=True, exist_ok=True)
    files: dict[int, tuple[str | None, str]] = {}
    for p in result.positions:
        csv: str | None = None
        est = p.estimate
        if est is not None:
            csv = csv_name(p)
            write_frd_csv(out_dir / csv, est.freq_hz, est.response, est.coherence)
        raw = _raw_name(p)
        np.savez_compressed(
            out_dir / raw,
            center_deg=np.float64(p.center_deg),
            complete=np.bool_(p.complete),
            **p.raw.as_arrays(),  # type: ignore[arg-type]
        )
        files[p.index] = (csv, raw)
    return files


def _write_config(result: IdentifyResult, out_dir: Path) -> str | None:
    """The run's LoopConfig with the fitted nominal, for `dobtune check <it> --frd ...`."""
    cfg = result.fitted_config
    if cfg is None:
        return None
    name = "config_fitted.json"
    (out_dir / name).write_text(
        json.dumps(config_to_builtins(cfg), indent=2) + "\n", encoding="utf-8"
    )
    return name


def _fmt(v: float | None, spec: str = ".3g", unit: str = "") -> str:
    if v is None or not math.isfinite(v):
        return "none"
    return f"{v:{spec}}{unit}"


def report_text(summary: dict[str, Any], out_dir: Path) -> str:
    """The readable table printed without ``--json``."""
    lines = [
        f"dobtune identify: {summary['mode']} loop, "
        f"{'stepped sine' if summary['signal'] == 'sine' else 'multisine'} "
        f"{summary['f_min_hz']:g}-{summary['f_max_hz']:g} Hz ({summary['n_frequencies']} "
        f"frequencies), {len(summary['positions'])} position(s); "
        f"{summary['simulated_s']:.0f} s simulated in {summary['wall_s']:.1f} s",
        f"  {'position':<16}{'points':>8}{'min coh.':>10}{'max |Delta|':>13}  at",
    ]
    for p in summary["positions"]:
        lines.append(
            f"  {p['center_deg']:>8g} deg     {p['points_done']:>3}/{p['points_total']:<3}"
            f"{_fmt(p['min_coherence'], '.4f'):>10}{_fmt(p.get('delta_peak'), '.3g'):>13}"
            f"  {_fmt(p.get('delta_peak_hz'), '.3g', ' Hz')}"
            + ("" if p["complete"] else "  INCOMPLETE")
        )
    fit = summary["fit"]
    if fit is not None:
        lines.append(
            f"  fit Mn Pn = 1/(a2 s^2 + a1 s + 1), {fit['band_hz'][0]:.3g}-{fit['band_hz'][1]:.3g}"
            f" Hz: natural frequency {_fmt(fit['natural_freq_hz'], '.3f')} +- "
            f"{_fmt(fit['natural_freq_std_hz'], '.2g')} Hz, damping {_fmt(fit['zeta'], '.3f')} +- "
            f"{_fmt(fit['zeta_std'], '.2g')}; residual {fit['residual_rms_db']:.2f} dB / "
            f"{fit['residual_rms_deg']:.2f} deg rms"
        )
    agree = summary["agreement"]
    if agree is not None:
        first = agree["first_disagree_hz"]
        lines.append(
            f"  curves agree within {agree['tol_db']:g} dB / {agree['tol_deg']:g} deg below "
            f"{agree['agree_below_hz']:.3g} Hz"
            + (f" (spread from {first:.3g} Hz)" if first is not None else " (whole band)")
        )
    top = summary["search_limit_hz"]

    def cutoffs(rec: dict[str, float | None]) -> str:
        def one(v: float | None) -> str:
            if v is None:
                return "none (even the lowest is rejected)"
            return f">= {top:g} Hz (search limit)" if v >= 0.999 * top else f"{v:.3g} Hz"

        return ", ".join(f"{q.upper()} {one(v)}" for q, v in rec.items())

    if summary["recommended_cutoff_hz"]:
        lines.append(
            "  recommended max Q cut-off, fitted model + measured responses: "
            + cutoffs(summary["recommended_cutoff_hz"])
        )
    if summary["recommended_cutoff_hz_config_nominal"]:
        lines.append(
            "  (with the configured nominal instead: "
            + cutoffs(summary["recommended_cutoff_hz_config_nominal"])
            + ")"
        )
    for g in summary["gate_checks"]:
        verdict = "accept" if g["accepted"] else "REJECT"
        why = f" ({g['reasons'][0]})" if g["reasons"] else ""
        lines.append(f"  gate at {g['q_type'].upper()} {g['cutoff_hz']:.3g} Hz: {verdict}{why}")
    lines += [f"  note: {n}" for n in summary["notes"]]
    if not summary["complete"]:
        lines.append(f"ABORTED: {summary['abort_reason']} (partial data kept)")
    lines.append(
        f"  files in {out_dir}"
        + (
            f"; check: dobtune check {out_dir / summary['fitted_config']} --frd "
            f"{out_dir}/pos*.csv --cutoff-hz HZ"
            if summary["fitted_config"]
            else ""
        )
    )
    return "\n".join(lines) + "\n"


class _Progress:
    """A one-line terminal progress indicator (carriage return, at most every 1 %)."""

    def __init__(self, err: TextIO) -> None:
        self.err = err
        self.last = -1
        self.text = ""

    def __call__(self, fraction: float, text: str) -> None:
        pct = int(fraction * 100)
        if pct == self.last and text == self.text:
            return
        self.last, self.text = pct, text
        self.err.write(f"\r[{pct:3d}%] {text[:70]:<70}")
        self.err.flush()

    def done(self) -> None:
        if self.last >= 0:
            self.err.write("\n")
            self.err.flush()


def _bad(msg: str, as_json: bool, out: TextIO, err: TextIO) -> int:
    if as_json:
        out.write(json.dumps({"error": msg}) + "\n")
    else:
        err.write(f"error: {msg}\n")
    return EXIT_BAD_INPUT


def identify_main(
    plant: str | None,
    connect: str | None,
    rig_name: str | None,
    mode: str,
    signal: str,
    f_min_hz: float,
    f_max_hz: float,
    positions: int,
    amplitude_deg_s: float,
    out_dir: Path,
    as_json: bool,
    out: TextIO,
    err: TextIO,
    *,
    cfg: LoopConfig | None = None,
    spec_overrides: dict[str, Any] | None = None,
    rig_factory: Callable[[], RigLike] | None = None,
) -> int:
    """Run the identification and report; returns the exit code (0 ok, 1 aborted, 2 bad input).

    ``spec_overrides`` sets further `IdentifySpec` fields (tests use it for short runs);
    ``rig_factory`` replaces the simulated rig (tests: a faulty rig).
    """
    if connect is not None:
        if plant is not None:
            return _bad("--plant and --connect are exclusive", as_json, out, err)
        if not rig_name:
            return _bad("--connect needs --rig-name", as_json, out, err)
        return _remote(
            connect,
            rig_name,
            mode,
            signal,
            f_min_hz,
            f_max_hz,
            positions,
            amplitude_deg_s,
            out_dir,
            as_json,
            out,
            err,
            spec_overrides or {},
        )
    if plant not in (None, "sim"):
        return _bad(f"--plant: only 'sim' is supported here (got {plant!r})", as_json, out, err)
    try:
        spec = IdentifySpec(
            mode=mode,
            signal=signal,
            f_min_hz=f_min_hz,
            f_max_hz=f_max_hz,
            positions=positions,
            amplitude_deg_s=amplitude_deg_s,
            **(spec_overrides or {}),
        )
    except ConfigError as exc:
        flag = _FLAGS.get(exc.field, exc.field)
        return _bad(f"{flag}: {exc}", as_json, out, err)
    except TypeError as exc:  # an unknown override name
        return _bad(str(exc), as_json, out, err)
    loop_cfg = cfg if cfg is not None else LoopConfig()
    progress = _Progress(err)
    t0 = time.perf_counter()
    code = EXIT_OK
    try:
        result = run_identification(spec, loop_cfg, rig_factory, progress)
    except ConfigError as exc:
        progress.done()
        flag = _FLAGS.get(exc.field, exc.field)
        return _bad(f"{flag}: {exc}", as_json, out, err)
    except IdentifyAborted as exc:
        progress.done()
        result = exc.result
        code = EXIT_ABORTED
    else:
        progress.done()
    wall = time.perf_counter() - t0
    try:
        files = _write(result, out_dir)
        summary = summary_json(result, files, wall, _write_config(result, out_dir))
        (out_dir / "summary.json").write_text(
            json.dumps(summary, indent=2, allow_nan=False) + "\n", encoding="utf-8"
        )
    except OSError as exc:
        return _bad(f"--out: cannot write to {out_dir}: {exc}", as_json, out, err)
    if as_json:
        out.write(json.dumps(summary, allow_nan=False) + "\n")
    else:
        out.write(report_text(summary, out_dir))
    if code == EXIT_ABORTED:
        err.write(f"error: identification aborted: {result.abort_reason}\n")
    return code


# -- through a running controller -------------------------------------------------------------


def _remote(
    endpoint: str,
    rig_name: str,
    mode: str,
    signal: str,
    f_min_hz: float,
    f_max_hz: float,
    positions: int,
    amplitude_deg_s: float,
    out_dir: Path,
    as_json: bool,
    out: TextIO,
    err: TextIO,
    overrides: dict[str, Any],
    poll_s: float = 0.2,
) -> int:
    """Start the run in the controller's loop, follow it, fetch the results, write the files
    (as offline, without the raw records: those stay in the state stream)."""
    import msgspec

    from controller import protocol as proto
    from controller.zenoh_session import check_endpoint, open_session

    try:
        check_endpoint(endpoint)
        proto.check_rig_name(rig_name)
    except ValueError as exc:
        return _bad(f"--connect/--rig-name: {exc}", as_json, out, err)
    fields = {
        "mode": mode,
        "signal": signal,
        "f_min_hz": f_min_hz,
        "f_max_hz": f_max_hz,
        "positions": positions,
        "amplitude_deg_s": amplitude_deg_s,
        **overrides,
    }
    try:
        IdentifySpec(**fields)  # the same checks as the controller's, before connecting
        msg = msgspec.convert(fields, proto.IdentifySpecMsg)
    except ConfigError as exc:
        return _bad(f"{_FLAGS.get(exc.field, exc.field)}: {exc}", as_json, out, err)
    except (TypeError, msgspec.ValidationError) as exc:
        return _bad(f"spec: {exc}", as_json, out, err)
    timeout_s = 5.0

    def query(session: Any, key: str, payload: bytes | None) -> bytes | None:
        kw: dict[str, Any] = {"timeout": timeout_s}
        if payload is not None:
            kw["payload"] = payload
        for reply in session.get(key, **kw):
            if reply.ok is not None:
                data: bytes = reply.ok.payload.to_bytes()
                return data
            return None
        return None

    t0 = time.perf_counter()
    progress = _Progress(err)
    with open_session(listen=(), connect=[endpoint]) as session:
        cmd = proto.encode(proto.Command(body=proto.IdentifyStart(spec=msg), client="identify"))
        raw = None
        deadline = time.monotonic() + 10.0
        while raw is None and time.monotonic() < deadline:  # the session may still connect
            raw = query(session, proto.key_command(rig_name), cmd)
        if raw is None:
            return _bad(
                f"--connect: no reply from rig {rig_name!r} at {endpoint}", as_json, out, err
            )
        reply = proto.decode(raw, proto.CommandReply)
        if not reply.ok:
            return _bad(f"controller refused: {reply.message}", as_json, out, err)
        deadline = time.monotonic() + msg.max_duration_s + 300.0
        status: proto.IdentifyStatus | None = None
        while time.monotonic() < deadline:
            data = query(session, proto.key_identify(rig_name), None)
            if data is not None:
                status = proto.decode(data, proto.IdentifyStatus)
                progress(min(status.progress, 0.99), status.text)
                if status.state in ("done", "aborted"):
                    break
            time.sleep(poll_s)
        progress.done()
    if status is None or status.state not in ("done", "aborted"):
        return _bad("controller: no result before the deadline", as_json, out, err)
    try:
        summary = _write_remote(status, out_dir, time.perf_counter() - t0)
    except OSError as exc:
        return _bad(f"--out: cannot write to {out_dir}: {exc}", as_json, out, err)
    if as_json:
        out.write(json.dumps(summary, allow_nan=False) + "\n")
    else:
        out.write(report_text(summary, out_dir))
    if status.state == "aborted":
        err.write(f"error: identification aborted: {status.abort_reason}\n")
        return EXIT_ABORTED
    return EXIT_OK


def _write_remote(status: Any, out_dir: Path, wall_s: float) -> dict[str, Any]:
    from controller.core.config import NominalModel, config_from_builtins

    out_dir.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = json.loads(status.summary_json) if status.summary_json else {}
    if not summary:
        raise OSError(f"the controller sent no summary ({status.text})")
    summary["wall_s"] = wall_s
    by_index = {p["index"]: p for p in summary["positions"]}
    for p in status.positions:
        if p.freq_hz:
            name = f"pos{p.index}_{p.center_deg:g}deg.csv"
            resp = 10.0 ** (np.asarray(p.mag_db) / 20.0) * np.exp(1j * np.radians(p.phase_deg))
            write_frd_csv(out_dir / name, p.freq_hz, resp, p.coherence)
            by_index[p.index]["csv"] = name
        by_index[p.index]["raw"] = None
    if summary.get("nominal") is not None:
        n = summary["nominal"]
        cfg = config_from_builtins(summary["config"]).with_(
            nominal=NominalModel(
                mn_den=tuple(n["mn_den"]), pn_num=tuple(n["pn_num"]), pn_den=tuple(n["pn_den"])
            )
        )
        name = "config_fitted.json"
        (out_dir / name).write_text(
            json.dumps(config_to_builtins(cfg), indent=2) + "\n", encoding="utf-8"
        )
        summary["fitted_config"] = name
    (out_dir / "summary.json").write_text(
        json.dumps(summary, indent=2, allow_nan=False) + "\n", encoding="utf-8"
    )
    return summary
