"""Two recordings side by side, and a directory's list of them: pure computation on arrays
and dictionaries (no I/O; the dashboard's Recordings panel and tests call it).

- `align_runs`: the lag that puts run B's reference trajectory on run A's (both sampled on a
  common uniform grid; the lag maximising the correlation coefficient of the references over
  their overlap, which must be at least `min_overlap` of the shorter run), then both errors on the
  overlap, so "before" and "after" are compared at the same points of the trajectory.
- `config_diff`: the fields that differ between two configurations (nested fields dotted).
- `summary_row`: one recording as a row of the list (its latest configuration and the
  article's metrics from `controller.recording.report.metrics`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.recording.report import Metrics

#: Correlations within this of the best count as equally good (see `align_runs`).
CORR_TIE = 1e-3

__all__ = ["Alignment", "SummaryRow", "align_runs", "config_diff", "flatten", "summary_row"]


@dataclass(frozen=True, eq=False)
class Alignment:
    """Run B shifted onto run A: B's sample at time t_b overlays A's at t_b - lag_s."""

    lag_s: float
    correlation: float
    """Correlation coefficient of the references over the overlap (1: identical shapes;
    0 when a reference is constant, e.g. a hold: then the runs are aligned by their starts)."""
    t_s: np.ndarray
    """The overlap on A's time axis (from A's first sample), uniform."""
    ref_a_deg: np.ndarray
    ref_b_deg: np.ndarray
    error_a_deg: np.ndarray
    error_b_deg: np.ndarray


def _uniform(t: np.ndarray, ref: np.ndarray, err: np.ndarray, dt: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t from the first sample, ref, err) on a uniform grid of step dt (finite samples)."""
    t, ref, err = (np.asarray(v, dtype=np.float64) for v in (t, ref, err))
    ok = np.isfinite(t) & np.isfinite(ref) & np.isfinite(err)
    t, ref, err = t[ok], ref[ok], err[ok]
    if t.size < 2 or t[-1] <= t[0]:
        raise ValueError("a run has fewer than 2 finite samples")
    grid = np.arange(t[0], t[-1], dt)
    return grid - t[0], np.interp(grid, t, ref), np.interp(grid, t, err)


def align_runs(
    t_a: np.ndarray, ref_a: np.ndarray, err_a: np.ndarray,
    t_b: np.ndarray, ref_b: np.ndarray, err_b: np.ndarray,
    *, dt_s: float = 0.01, min_overlap: float = 0.5,
) -> Alignment:
    """Align run B on run A by their references (see the module docstring). `t_*` in seconds
    (any origin), references and errors in degrees. ValueError naming the problem for runs
    too short or without any overlap."""
    if not (dt_s > 0.0 and math.isfinite(dt_s)):
        raise ValueError(f"dt_s: must be finite and > 0 (got {dt_s!r})")
    if not 0.0 < min_overlap <= 1.0:
        raise ValueError(f"min_overlap: must be in (0, 1] (got {min_overlap!r})")
    ta, ra, ea = _uniform(t_a, ref_a, err_a, dt_s)
    _, rb, eb = _uniform(t_b, ref_b, err_b, dt_s)
    na, nb = ra.size, rb.size
    need = max(2, math.ceil(min_overlap * min(na, nb)))
    # lag k (samples): B[j] overlays A[j - k]; k from -(na - need) to nb - need
    xa = ra - np.mean(ra)
    xb = rb - np.mean(rb)
    size = 1 << (na + nb - 1).bit_length()
    full = np.fft.irfft(np.fft.rfft(xb, size) * np.conj(np.fft.rfft(xa, size)), size)
    # Pearson correlation over each lag's overlap (sums over the window from cumulative sums)
    s1a = np.concatenate([[0.0], np.cumsum(xa)])
    s2a = np.concatenate([[0.0], np.cumsum(xa * xa)])
    s1b = np.concatenate([[0.0], np.cumsum(xb)])
    s2b = np.concatenate([[0.0], np.cumsum(xb * xb)])
    ks = np.arange(-(na - need), nb - need + 1)
    a0s = np.maximum(0, -ks)
    b0s = a0s + ks
    ms = np.minimum(na - a0s, nb - b0s)
    suma, sumb = s1a[a0s + ms] - s1a[a0s], s1b[b0s + ms] - s1b[b0s]
    cov = full[ks % size] - suma * sumb / ms
    var = ((s2a[a0s + ms] - s2a[a0s]) - suma**2 / ms) * ((s2b[b0s + ms] - s2b[b0s]) - sumb**2 / ms)
    ok = var > 1e-24 * (float(np.sum(xa * xa)) * float(np.sum(xb * xb)) + 1e-300)
    corr = np.where(ok, cov / np.sqrt(np.where(ok, var, 1.0)), 0.0)
    # A periodic reference matches at every period: of the peaks (local maxima) within
    # CORR_TIE of the best, the one with the longest overlap.
    padded = np.concatenate([[-np.inf], corr, [-np.inf]])
    peak = (corr >= padded[:-2]) & (corr >= padded[2:])
    near = np.nonzero(peak & (corr >= np.max(corr) - CORR_TIE))[0]
    pick = int(near[np.argmax(ms[near])])
    best_k, best_c = int(ks[pick]), float(corr[pick])
    a0 = max(0, -best_k)
    b0 = a0 + best_k
    m = min(na - a0, nb - b0)
    return Alignment(
        lag_s=best_k * dt_s,
        correlation=float(best_c),
        t_s=ta[a0 : a0 + m],
        ref_a_deg=ra[a0 : a0 + m],
        ref_b_deg=rb[b0 : b0 + m],
        error_a_deg=ea[a0 : a0 + m],
        error_b_deg=eb[b0 : b0 + m],
    )


def flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dictionaries as one level with dotted keys; lists become tuples."""
    out: dict[str, Any] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(flatten(v, f"{prefix}{k}."))
        return out
    out[prefix[:-1]] = tuple(obj) if isinstance(obj, list) else obj
    return out


def config_diff(a: dict[str, Any], b: dict[str, Any]) -> list[tuple[str, Any, Any]]:
    """(field, value in a, value in b) of every field that differs (None: absent), sorted."""
    fa, fb = flatten(a), flatten(b)
    return [(k, fa.get(k), fb.get(k)) for k in sorted(set(fa) | set(fb))
            if fa.get(k) != fb.get(k)]


@dataclass(frozen=True)
class SummaryRow:
    """One recording in the list."""

    name: str
    duration_s: float
    samples: int
    config_version: int | None
    """The latest configuration version seen (None: the recording has none)."""
    config: dict[str, Any]
    peak_error_deg: float
    rmse_deg: float
    reversal_peak_error_deg: float
    gaps: int
    segments: tuple[tuple[int, float, float, int], ...] = ()
    """Per configuration version, in order: (version, peak |error|, RMSE, samples)."""


def summary_row(name: str, configs: dict[int, dict[str, Any]], m: Metrics) -> SummaryRow:
    version = max(configs) if configs else None
    return SummaryRow(
        name=name,
        duration_s=m.duration_s,
        samples=m.samples,
        config_version=version,
        config=configs[version] if version is not None else {},
        peak_error_deg=m.peak_error_deg,
        rmse_deg=m.rmse_deg,
        reversal_peak_error_deg=m.reversal_peak_error_deg,
        gaps=m.gaps,
        segments=tuple((v, *m.segments[v]) for v in sorted(m.segments)),
    )
