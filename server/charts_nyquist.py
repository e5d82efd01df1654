"""The Nyquist chart (pure): the candidate's and the active loop's curves as an SVG
(`server.charts`).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from controller.core.arrays import ComplexArray
from server.charts_base import (
    ACTIVE,
    CANDIDATE,
    GM_COLOR,
    PM_COLOR,
    BodeCurves,
    NyquistLoop,
)

__all__ = [
    "NYQUIST_FOOTER_PX",
    "NYQUIST_HEADER_PX",
    "NYQUIST_INSET_PX",
    "NYQUIST_RADIUS",
    "fmt_margin",
    "nyquist_segments",
    "nyquist_svg",
    "open_loop_response",
]


# -- Nyquist -------------------------------------------------------------------------------------

#: The Nyquist view shows |L| <= this radius (the loop's integrators send L to infinity at
#: low frequency; what matters for margins is near the unit circle and -1).
NYQUIST_RADIUS = 3.0
#: A Nyquist panel's bands (viewBox px): the title and the formula above the square plot, the
#: tick labels inside its edge, the legend below it.
NYQUIST_HEADER_PX = 80
NYQUIST_INSET_PX = 30
NYQUIST_FOOTER_PX = 64


def open_loop_response(c: BodeCurves) -> ComplexArray:
    """L on the grid, back from the drawn magnitude (dB) and unwrapped phase (deg)."""
    return np.asarray(10.0 ** (c.open_loop_db / 20.0) * np.exp(
        1j * np.deg2rad(c.open_loop_phase_deg)), dtype=np.complex128)


def nyquist_segments(z: npt.ArrayLike, radius: float = NYQUIST_RADIUS) -> list[ComplexArray]:
    """The runs of consecutive grid points of the response `z` inside |z| <= radius (one
    polyline each)."""
    z = np.asarray(z, dtype=np.complex128)
    inside = np.isfinite(z) & (np.abs(z) <= radius)
    segments, start = [], None
    for i, ok in enumerate(inside):
        if ok and start is None:
            start = i
        elif not ok and start is not None:
            segments.append(z[start:i])
            start = None
    if start is not None:
        segments.append(z[start:])
    return [s for s in segments if len(s) >= 2]


def fmt_margin(value: float, unit: str) -> str:
    return f"{value:.1f} {unit}" if np.isfinite(value) else "none"


def _nyquist_panel(cand: NyquistLoop | None, active: NyquistLoop | None, title: str,
                   formula: str, cls: str, loop: str, size: int, radius: float) -> str:
    """One Nyquist panel (an SVG): candidate solid, active dashed, unit circle, -1, and the
    candidate's margin points (PM on the unit circle, GM on the negative real axis)."""
    half = size / 2.0
    top = float(NYQUIST_HEADER_PX)
    cx0, cy0 = half, top + half  # the origin
    k = (half - NYQUIST_INSET_PX) / radius  # px per unit
    x0, y0, x1, y1 = cx0 - k * radius, cy0 - k * radius, cx0 + k * radius, cy0 + k * radius

    def xy(z: complex) -> tuple[str, str]:
        return f"{cx0 + k * z.real:.1f}", f"{cy0 - k * z.imag:.1f}"

    height = size + NYQUIST_HEADER_PX + NYQUIST_FOOTER_PX
    parts = [f"<svg class='{cls} dt-nyq-panel' data-loop='{loop}' viewBox='0 0 {size} {height}' "
             f"data-origin='{cx0:.1f} {cy0:.1f}' data-px-per-unit='{k:.4f}' "
             f"width='100%' style='display:block;height:auto;background:#fff'>",
             f"<rect class='dt-nyq-plot' x='{x0:.1f}' y='{y0:.1f}' width='{x1 - x0:.1f}' "
             f"height='{y1 - y0:.1f}' fill='none' stroke='#ccc'/>",
             f"<line x1='{x0:.1f}' y1='{cy0}' x2='{x1:.1f}' y2='{cy0}' stroke='#bbb'/>",
             f"<line x1='{cx0}' y1='{y0:.1f}' x2='{cx0}' y2='{y1:.1f}' stroke='#bbb'/>",
             f"<circle cx='{cx0}' cy='{cy0}' r='{k:.1f}' fill='none' stroke='#999' "
             "stroke-dasharray='4 3'/>"]
    # Ticks at every whole unit on both axes, labelled outside the plot's frame (real: under
    # it, imaginary: left of it), and the axes' names.
    for v in range(-int(radius), int(radius) + 1):
        px, py = cx0 + k * v, cy0 - k * v
        parts.append(f"<line class='dt-nyq-tick' x1='{px:.1f}' y1='{cy0 - 5}' x2='{px:.1f}' "
                     f"y2='{cy0 + 5}' stroke='#888'/>")
        parts.append(f"<line class='dt-nyq-tick' x1='{cx0 - 5}' y1='{py:.1f}' x2='{cx0 + 5}' "
                     f"y2='{py:.1f}' stroke='#888'/>")
        parts.append(f"<text class='dt-nyq-tick-re' x='{px:.1f}' y='{y1 + 15:.1f}' "
                     f"font-size='13' fill='#555' text-anchor='middle'>{v}</text>")
        parts.append(f"<text class='dt-nyq-tick-im' x='{x0 - 4:.1f}' y='{py:.1f}' "
                     f"font-size='13' fill='#555' text-anchor='end' "
                     f"dominant-baseline='central'>{v}</text>")
    parts.append(f"<text x='{x1:.1f}' y='{cy0 - 8}' font-size='13' fill='#555' "
                 "text-anchor='end'>Re L</text>")
    parts.append(f"<text x='{cx0 + 8}' y='{y0 + 13:.1f}' font-size='13' fill='#555'>Im L</text>")
    for nl, color, css, dash in ((active, ACTIVE, "dt-nyq-active", "6 4"),
                                 (cand, CANDIDATE, "dt-nyq-cand", "")):
        if nl is None:
            continue
        for seg in nyquist_segments(nl.response, radius):
            pts = " ".join(",".join(xy(complex(z))) for z in seg)
            parts.append(f"<polyline class='{css}' fill='none' stroke='{color}' "
                         f"stroke-width='2' stroke-dasharray='{dash}' points='{pts}'/>")
    if cand is not None:
        for zs, fs, color, css, what in (
                (cand.gain_crossings, cand.gain_crossover_hz, PM_COLOR, "dt-nyq-pm", "PM"),
                (cand.phase_crossings, cand.phase_crossover_hz, GM_COLOR, "dt-nyq-gm", "GM")):
            for z, f in zip(zs, fs, strict=True):
                if not abs(z) <= radius:
                    continue
                if what == "PM":
                    value = f"PM {np.degrees(np.angle(z)) % 360.0 - 180.0:.1f} deg"
                else:
                    g = -20.0 * np.log10(abs(z))
                    value = (f"gain-reduction margin {-g:.1f} dB down" if g < 0
                             else f"GM {g:.1f} dB up")
                cx, cy = xy(complex(z))
                parts.append(f"<circle class='{css}' cx='{cx}' cy='{cy}' r='6' fill='{color}'>"
                             f"<title>{value} read here ({f:.3g} Hz)</title></circle>")
    cx, cy = xy(-1.0 + 0j)
    parts.append(f"<text class='dt-nyq-critical' x='{cx}' y='{cy}' fill='#d62728' "
                 "font-size='28' text-anchor='middle' dominant-baseline='central'>+</text>")
    if cand is None:
        summary = "not computed"
    else:
        gms = -20.0 * np.log10(np.abs(cand.phase_crossings))
        # The reported GM's point may lie outside the window (a gain-reduction margin).
        outside = bool(np.isfinite(cand.gain_margin_db) and gms.size and abs(
            cand.phase_crossings[int(np.argmin(np.abs(gms - cand.gain_margin_db)))]) > radius)
        # Both gain margins positive and named (issue 33): up where |L| < 1 at a crossing,
        # the gain-reduction margin down where |L| > 1 (a conditionally stable loop).
        ups, downs = gms[gms >= 0], -gms[gms < 0]
        gm_text = (f"GM {fmt_margin(float(ups.min()) if ups.size else math.inf, 'dB')}"
                   + (f" up, gain-reduction margin {float(downs.min()):.1f} dB down"
                      if downs.size else ""))
        summary = (f"PM {fmt_margin(cand.phase_margin_deg, 'deg')}, {gm_text}"
                   + (" (read outside the view)" if outside else ""))
    # Sized for a panel drawn at about half its viewBox width (two side by side in the
    # dashboard's plot column): the title on two lines and the formula above the plot, the
    # legend on two lines under it (never over the curves).
    parts.append(f"<text class='dt-nyq-title' fill='#333'>"
                 f"<tspan x='8' y='24' font-size='22' font-weight='bold'>{title}:</tspan>"
                 f"<tspan x='8' y='48' font-size='19'> {summary}</tspan></text>")
    parts.append(f"<text x='8' y='70' font-size='15' fill='#555'>{formula}</text>")
    foot = y1 + 20
    parts.append(f"<text class='dt-nyq-foot' x='8' y='{foot + 16:.1f}' font-size='15' "
                 f"fill='#555'>|L| &#8804; {radius:g}, unit circle dashed, + = -1</text>")
    parts.append(f"<text class='dt-nyq-foot' x='8' y='{foot + 36:.1f}' font-size='15' "
                 "fill='#555'>candidate solid, active dashed; "
                 f"<tspan fill='{PM_COLOR}'>&#9679; PM</tspan> "
                 f"<tspan fill='{GM_COLOR}'>&#9679; GM</tspan> read here</text></svg>")
    return "".join(parts)


def nyquist_svg(cand: BodeCurves, active: BodeCurves | None, size: int = 460,
                radius: float = NYQUIST_RADIUS) -> str:
    """The speed loop's Nyquist plots (positive frequencies) side by side, as inline SVG:
    with the DOB (class `dt-nyquist`) and without it (class `dt-nyquist-nodob`); each draws
    the candidate and the active configuration, the unit circle, the critical point -1 and
    the candidate's own points where its PM and GM are read. The panels wrap one under the
    other when the container is narrower than two."""
    act_dob = active.nyquist_dob if active is not None else None
    act_nodob = active.nyquist_nodob if active is not None else None
    panels = (
        _nyquist_panel(cand.nyquist_dob, act_dob, "with DOB",
                       "speed loop L = G (Cv + F1) / (1 - F2 z^-1)", "dt-nyquist", "dob",
                       size, radius),
        _nyquist_panel(cand.nyquist_nodob, act_nodob, "without DOB", "speed loop L = G Cv",
                       "dt-nyquist-nodob", "nodob", size, radius),
    )
    return ("<div class='dt-nyq-pair' style='display:flex;flex-wrap:wrap;gap:8px'>"
            + "".join(f"<div style='flex:1 1 260px;max-width:{size}px'>{p}</div>"
                      for p in panels)
            + "</div>")
