"""Identification above the first band (pure): a scan that finds a mode, a zoomed pass that
resolves it, and the passes merged into one response per position.

A first identification stops at 20 Hz (the fit's band); a belt or coupling mode between 20 and
~60 Hz then lies where the speed loop still has gain but the gate knows the plant only within
the commissioning bound, and a lightly damped one (damping 0.01: a half-power band of 2 % of
its frequency) slips between the points of a 10-per-decade grid (the gate then asks to
"measure denser"). As an engineer would, the band is extended in two cheap multisine passes:

1. the scan: `SCAN_BAND_HZ` at `SCAN_POINTS_PER_DECADE` (resolution `SCAN_RESOLUTION_HZ`), the
   excitation raised to `SCAN_AMPLITUDE_DEG_S` (the position barely moves there), to find the
   lowest resonance (`controller.gate.knowledge.measured_modes_hz`: a peak >= 3 dB above the
   lowest magnitude below it);
2. the zoom: `ZOOM_SPAN` about that peak at 200 points per decade (1.2 % apart: two points in
   the half-power band of a damping-0.006 mode) on a resolution of
   `ZOOM_RESOLUTION_FRACTION` of its low end.

Above the scan's band the rig's response is below the encoder's noise on this excitation (at
~60 Hz the spread per point passes 0.15, above ~80 Hz it is 0.4-4): a mode there stays under
the commissioning bound, and the responses say where they end.
"""

from __future__ import annotations

import numpy as np

from controller.gate.knowledge import MeasuredResponse, PlantKnowledge, measured_modes_hz
from controller.ident.spec import IdentifySpec

__all__ = ["SCAN_BAND_HZ", "ZOOM_SPAN", "merge_responses", "scan_spec", "zoom_band_hz",
           "zoom_spec"]

SCAN_BAND_HZ = (18.0, 60.0)
SCAN_POINTS_PER_DECADE = 40
SCAN_RESOLUTION_HZ = 0.5
SCAN_AMPLITUDE_DEG_S = 20.0
#: The zoom's band about the scan's peak f: f / ZOOM_SPAN[0] to f x ZOOM_SPAN[1] (the scan's
#: points are 6 % apart: the true peak lies within one step of the one found).
ZOOM_SPAN = (1.3, 1.4)
ZOOM_POINTS_PER_DECADE = 200
#: The zoom's resolution as a fraction of its band's low end: odd lines 1 % apart there,
#: finer than the 1.16 % of 200 points per decade (0.1 Hz at 20 Hz: a 10 s period).
ZOOM_RESOLUTION_FRACTION = 0.005


def scan_spec(first: IdentifySpec) -> IdentifySpec:
    """The scan above `first`'s band, at its positions."""
    lo, hi = SCAN_BAND_HZ
    return first.with_(f_min_hz=lo, f_max_hz=hi, points_per_decade=SCAN_POINTS_PER_DECADE,
                       resolution_hz=SCAN_RESOLUTION_HZ,
                       amplitude_deg_s=SCAN_AMPLITUDE_DEG_S)


def zoom_band_hz(scan: tuple[MeasuredResponse, ...]) -> tuple[float, float] | None:
    """The zoom's band about the lowest resonance the scan shows at any position (None: the
    scan shows none)."""
    modes = measured_modes_hz(PlantKnowledge(measured=scan))
    if not modes:
        return None
    f = min(m[0] for m in modes)
    lo = max(SCAN_BAND_HZ[0], f / ZOOM_SPAN[0])
    hi = min(SCAN_BAND_HZ[1], f * ZOOM_SPAN[1])
    return (lo, hi) if hi > lo * 1.05 else None


def zoom_spec(first: IdentifySpec, band_hz: tuple[float, float]) -> IdentifySpec:
    """The zoomed pass over `band_hz`, at `first`'s positions."""
    lo, hi = band_hz
    return first.with_(f_min_hz=lo, f_max_hz=hi, points_per_decade=ZOOM_POINTS_PER_DECADE,
                       resolution_hz=lo * ZOOM_RESOLUTION_FRACTION,
                       amplitude_deg_s=SCAN_AMPLITUDE_DEG_S)


def merge_responses(*passes: tuple[MeasuredResponse, ...]) -> tuple[MeasuredResponse, ...]:
    """One response per position from several passes over the same positions (the k-th
    response of each pass is the k-th position; the first pass names it): every point, sorted
    by frequency; where two passes measured the same frequency, the later pass's point (the
    finer one) is kept."""
    n = len(passes[0])
    if any(len(p) != n for p in passes):
        raise ValueError("merge_responses: every pass must hold one response per position")
    out = []
    for k in range(n):
        parts = [p[k] for p in passes]
        f = np.concatenate([m.freq_hz for m in parts])
        h = np.concatenate([m.response for m in parts])
        s = np.concatenate([m.spread if m.spread is not None else np.zeros(m.freq_hz.size)
                            for m in parts])
        order = np.argsort(f, kind="stable")
        f, h, s = f[order], h[order], s[order]
        # the later of equal frequencies: reverse, take the first of each, reverse back
        _, first_rev = np.unique(f[::-1], return_index=True)
        keep = np.sort(f.size - 1 - first_rev)
        out.append(MeasuredResponse(parts[0].name, f[keep], h[keep], parts[0].sampled,
                                    s[keep]))
    return tuple(out)
