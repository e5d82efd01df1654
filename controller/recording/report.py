"""Metrics and a self-contained HTML report of one or two recordings (inline SVG, no assets).

Metrics follow the article: peak |position error| and RMSE (deg), over the whole recording
and per configuration version (segment), plus the error at velocity reversals (the peak
|error| within `REVERSAL_WINDOW_S` after the reference speed changes sign). The views: error
against time, error against turntable angle (position modulo 360 deg), and the error's
spectrum in orders of rotation (cycles per turntable revolution: belt tooth meshing and pulley
run-out show up as lines at fixed orders whatever the speed), computed by resampling the error
on a uniform grid of unwrapped angle.
"""

from __future__ import annotations

import html
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from controller.recording.mcap_io import Recording

__all__ = ["REVERSAL_WINDOW_S", "Metrics", "html_report", "metrics", "order_spectrum", "to_csv"]

REVERSAL_WINDOW_S = 0.3


@dataclass(frozen=True)
class Metrics:
    samples: int
    duration_s: float
    peak_error_deg: float
    rmse_deg: float
    reversals: int
    reversal_peak_error_deg: float
    """Largest |error| within REVERSAL_WINDOW_S after a reversal (nan: none)."""
    gaps: int
    """Samples lost (gap events)."""
    segments: dict[int, tuple[float, float, int]]
    """Per configuration version: (peak |error|, RMSE, samples)."""


def metrics(rec: Recording) -> Metrics:
    e = rec.state["error_deg"]
    t = rec.state["t_s"]
    ok = np.isfinite(e)
    e_ok = e[ok]
    peak = float(np.max(np.abs(e_ok))) if e_ok.size else math.nan
    rmse = float(np.sqrt(np.mean(e_ok**2))) if e_ok.size else math.nan
    rev_idx = _reversals(rec.state["ref_deg"])
    worst = _reversal_peak(t, e, ok, rev_idx)
    segments = {}
    for v in np.unique(rec.state["config_version"]):
        sel = (rec.state["config_version"] == v) & ok
        if np.any(sel):
            segments[int(v)] = (float(np.max(np.abs(e[sel]))),
                                float(np.sqrt(np.mean(e[sel] ** 2))), int(np.sum(sel)))
    gaps = sum(int(ev.get("to_seq", 0)) - int(ev.get("from_seq", 0)) + 1
               for ev in rec.events if ev.get("kind") == "gap")
    return Metrics(
        samples=rec.n, duration_s=float(t[-1] - t[0]) if t.size > 1 else 0.0,
        peak_error_deg=peak, rmse_deg=rmse, reversals=int(rev_idx.size),
        reversal_peak_error_deg=worst, gaps=gaps, segments=segments,
    )


def _reversals(ref: np.ndarray) -> np.ndarray:
    """Indices (into `ref`) where the reference speed changes sign: the first sample of each
    new direction (zero-speed stretches do not count as a direction)."""
    sign = np.sign(np.diff(ref))
    nz = np.nonzero(sign)[0]
    return nz[1:][sign[nz[1:]] != sign[nz[:-1]]]


def _reversal_peak(t: np.ndarray, e: np.ndarray, ok: np.ndarray, rev_idx: np.ndarray) -> float:
    """Largest |e| over the finite samples within REVERSAL_WINDOW_S after each reversal
    (nan: no reversal has one). Times in order (the usual case): each window is a slice found
    by bisection; otherwise a mask per reversal."""
    worst = math.nan
    ordered = bool(np.all(t[1:] >= t[:-1]))
    for i in rev_idx:
        t0 = t[i]
        if ordered:
            lo = int(np.searchsorted(t, t0, side="left"))
            hi = int(np.searchsorted(t, t0 + REVERSAL_WINDOW_S, side="right"))
            w = e[lo:hi][ok[lo:hi]]
        else:
            w = e[(t >= t0) & (t <= t0 + REVERSAL_WINDOW_S) & ok]
        if w.size:
            peak = float(np.max(np.abs(w)))
            worst = peak if not math.isfinite(worst) else max(worst, peak)
    return worst


def order_spectrum(rec: Recording, points_per_rev: int = 720) -> tuple[np.ndarray, np.ndarray]:
    """(orders, amplitude deg) of the error resampled on unwrapped angle; empty if the
    turntable travelled less than one revolution (no order is resolved then)."""
    pos = rec.state["pos_deg"]
    e = rec.state["error_deg"]
    ok = np.isfinite(pos) & np.isfinite(e)
    pos, e = pos[ok], e[ok]
    if pos.size < 16:
        return np.empty(0), np.empty(0)
    # Travel along the path (turning back counts): the cumulative absolute angle.
    s = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(pos)))])
    travel = float(s[-1])
    if travel < 360.0:
        return np.empty(0), np.empty(0)
    keep = np.concatenate([[True], np.diff(s) > 0])
    s, e = s[keep], e[keep]
    n = int(travel / 360.0 * points_per_rev)
    grid = np.linspace(0.0, travel, n, endpoint=False)
    x = np.interp(grid, s, e)
    x = x - np.mean(x)
    amp = 2.0 * np.abs(np.fft.rfft(x * np.hanning(n))) / (0.5 * n)
    orders = np.fft.rfftfreq(n, d=1.0 / points_per_rev)  # cycles per 360 deg
    return orders, amp


def to_csv(rec: Recording, path: str | Path) -> Path:
    cols = ["seq", "t_s", "ref_deg", "pos_deg", "speed_deg_s", "speed_ref_deg_s",
            "command_deg_s", "d_hat_deg_s", "error_deg", "config_version"]
    path = Path(path)
    data = np.column_stack([rec.state[c].astype(np.float64) for c in cols])
    np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt="%.9g")
    return path


# -- the HTML ----------------------------------------------------------------------------------

_COLORS = ("#1f77b4", "#d62728")


def _svg(series: list[tuple[np.ndarray, np.ndarray, str]], title: str, xlabel: str,
         ylabel: str, *, log_y: bool = False, w: int = 760, h: int = 260) -> str:
    pad_l, pad_b, pad_t = 60, 36, 24
    xs = [x for x, _, _ in series if x.size]
    ys = [np.log10(np.maximum(y, 1e-12)) if log_y else y for _, y, _ in series if y.size]
    if not xs:
        return f"<p><i>{html.escape(title)}: no data</i></p>"
    x0, x1 = min(float(np.min(x)) for x in xs), max(float(np.max(x)) for x in xs)
    y0, y1 = min(float(np.nanmin(y)) for y in ys), max(float(np.nanmax(y)) for y in ys)
    if x1 <= x0:
        x1 = x0 + 1.0
    if y1 <= y0:
        y1 = y0 + 1.0
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" '
             f'class="plot"><text x="{w / 2}" y="16" text-anchor="middle">'
             f"{html.escape(title)}</text>"]
    pw, ph = w - pad_l - 10, h - pad_b - pad_t
    parts.append(f'<rect x="{pad_l}" y="{pad_t}" width="{pw}" height="{ph}" fill="none" '
                 'stroke="#999"/>')
    for (x, y, label), color in zip(series, _COLORS * 4, strict=False):
        if not x.size:
            continue
        yy = np.log10(np.maximum(y, 1e-12)) if log_y else y
        step = max(1, x.size // 2000)
        px = pad_l + (x[::step] - x0) / (x1 - x0) * pw
        py = pad_t + ph - (yy[::step] - y0) / (y1 - y0) * ph
        pts = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(px, py, strict=True) if math.isfinite(b))
        parts.append(f'<polyline fill="none" stroke="{color}" stroke-width="1" points="{pts}">'
                     f"<title>{html.escape(label)}</title></polyline>")
    ylo = f"1e{y0:.1f}" if log_y else f"{y0:.4g}"
    yhi = f"1e{y1:.1f}" if log_y else f"{y1:.4g}"
    parts.append(f'<text x="{pad_l - 4}" y="{pad_t + ph}" text-anchor="end">{ylo}</text>'
                 f'<text x="{pad_l - 4}" y="{pad_t + 10}" text-anchor="end">{yhi}</text>'
                 f'<text x="{pad_l}" y="{h - 8}">{x0:.4g}</text>'
                 f'<text x="{pad_l + pw}" y="{h - 8}" text-anchor="end">{x1:.4g}</text>'
                 f'<text x="{pad_l + pw / 2}" y="{h - 8}" text-anchor="middle">'
                 f"{html.escape(xlabel)}</text>"
                 f'<text x="12" y="{pad_t + ph / 2}" transform="rotate(-90 12 {pad_t + ph / 2})" '
                 f'text-anchor="middle">{html.escape(ylabel)}</text></svg>')
    return "".join(parts)


def _fmt(v: float, unit: str = "deg") -> str:
    return "n/a" if not math.isfinite(v) else f"{v:.4g} {unit}"


def html_report(recs: list[tuple[str, Recording]]) -> str:
    """One recording, or two compared (before / after)."""
    names = [html.escape(n) for n, _ in recs]
    ms = [metrics(r) for _, r in recs]
    rows = [("samples", [str(m.samples) for m in ms]),
            ("duration", [_fmt(m.duration_s, "s") for m in ms]),
            ("peak |error|", [_fmt(m.peak_error_deg) for m in ms]),
            ("RMSE", [_fmt(m.rmse_deg) for m in ms]),
            ("reversals", [str(m.reversals) for m in ms]),
            (f"peak |error| within {REVERSAL_WINDOW_S:g} s of a reversal",
             [_fmt(m.reversal_peak_error_deg) for m in ms]),
            ("samples lost", [str(m.gaps) for m in ms])]
    table = ("<table><tr><th></th>" + "".join(f"<th>{n}</th>" for n in names) + "</tr>"
             + "".join(f"<tr><td>{html.escape(k)}</td>" + "".join(f"<td>{v}</td>" for v in vs)
                       + "</tr>" for k, vs in rows) + "</table>")
    seg = []
    for (name, _), m in zip(recs, ms, strict=True):
        for v, (pk, rm, count) in sorted(m.segments.items()):
            seg.append(f"<tr><td>{html.escape(name)}</td><td>v{v}</td><td>{_fmt(pk)}</td>"
                       f"<td>{_fmt(rm)}</td><td>{count}</td></tr>")
    seg_table = ("<table><tr><th>recording</th><th>config</th><th>peak |error|</th>"
                 "<th>RMSE</th><th>samples</th></tr>" + "".join(seg) + "</table>")
    diff = ""
    if len(recs) == 2:
        a = recs[0][1].configs.get(max(recs[0][1].configs, default=-1), {})
        b = recs[1][1].configs.get(max(recs[1][1].configs, default=-1), {})
        keys = sorted(set(a) | set(b))
        changed = [k for k in keys if a.get(k) != b.get(k)]
        diff = ("<h2>Configuration difference (latest of each)</h2><table><tr><th>field</th>"
                f"<th>{names[0]}</th><th>{names[1]}</th></tr>"
                + "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(str(a.get(k)))}</td>"
                          f"<td>{html.escape(str(b.get(k)))}</td></tr>" for k in changed)
                + "</table>" + ("" if changed else "<p>identical</p>"))
    t_series = [(r.state["t_s"] - r.state["t_s"][0], r.state["error_deg"], n)
                for n, r in recs if r.n]
    a_series = []
    for n, r in recs:
        angle = np.mod(r.state["pos_deg"], 360.0)
        order = np.argsort(angle)
        a_series.append((angle[order], r.state["error_deg"][order], n))
    spectra = [(*order_spectrum(r), n) for n, r in recs]
    spec_note = "" if all(s[0].size for s in spectra) else (
        "<p><i>A recording whose turntable travelled less than one revolution has no order "
        "spectrum.</i></p>")
    events = []
    for n, r in recs:
        for ev in r.events:
            events.append(f"<tr><td>{html.escape(n)}</td><td>{ev.get('log_time_s', 0):.3f}</td>"
                          f"<td>{html.escape(str(ev.get('kind')))}</td>"
                          f"<td>{html.escape(str(ev.get('text', '')))}</td></tr>")
    return f"""<!doctype html><html><head><meta charset="utf-8">
<title>dobtune report: {' vs '.join(names)}</title>
<style>body{{font:14px sans-serif;margin:24px;max-width:900px}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}svg.plot text{{font-size:11px}}
</style></head><body>
<h1>dobtune report</h1><p>{' vs '.join(names)} (blue{', red' if len(recs) == 2 else ''})</p>
<h2>Metrics</h2>{table}<h2>Per configuration version</h2>{seg_table}{diff}
<h2>Position error</h2>{_svg(t_series, "error against time", "t (s)", "error (deg)")}
{_svg(a_series, "error against turntable angle", "angle (deg, mod 360)", "error (deg)")}
{_svg([(o[1:], a[1:], n) for o, a, n in spectra if o.size > 1],
      "error spectrum in orders of rotation", "order (cycles per revolution)",
      "amplitude (deg)", log_y=True)}{spec_note}
<h2>Events</h2><table><tr><th>recording</th><th>time (s)</th><th>kind</th><th>text</th></tr>
{''.join(events)}</table></body></html>
"""
