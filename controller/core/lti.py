"""Linear-system design helpers the product uses, without `scipy.signal` (0.5-0.7 s to import).

Ports of scipy 1.17's `bilinear_zpk`, `zpk2sos` (its 'nearest' pairing), `zpk2tf`, `tf2ss`,
`zpk2ss`, `ss2tf` and the Butterworth design (`butter(..., output="sos")`) for the cases used
here, with the same operations in the same order, so the results are scipy's bit for bit
(tests/test_lti.py checks that against scipy itself); and `sosfilt` (transposed direct form II,
the same arithmetic as scipy's and `discrete.SosFilter.step`), compiled with numba on first
use. Off the
tick; the start path of the controller, the analysis worker and `dobtune check` imports this
instead of scipy.signal.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from controller.core.arrays import FloatArray

_TOL = 100 * np.finfo(np.float64).eps  # scipy's default realness / conjugate tolerance


def bilinear_zpk(
    z: ArrayLike, p: ArrayLike, k: float, fs: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """Bilinear (Tustin) map s -> z of zeros, poles and gain at sample rate `fs`."""
    z = np.atleast_1d(np.asarray(z))
    p = np.atleast_1d(np.asarray(p))
    degree = p.shape[0] - z.shape[0]
    if degree < 0:
        raise ValueError("improper transfer function: more zeros than poles")
    fs2 = 2.0 * fs
    z_z = (fs2 + z) / (fs2 - z)
    p_z = (fs2 + p) / (fs2 - p)
    z_z = np.concatenate((z_z, -np.ones(degree)))  # zeros at infinity go to Nyquist
    k_z = k * np.real(np.prod(fs2 - z) / np.prod(fs2 - p))
    return z_z, p_z, float(k_z)


def _poly(zeros: ArrayLike) -> NDArray[np.generic] | float:
    """Polynomial (highest power first) with the given roots; real when they pair up."""
    seq = np.atleast_1d(np.asarray(zeros))
    if seq.shape[0] == 0:
        return 1.0
    a = np.ones((1,), dtype=seq.dtype)
    one = np.ones_like(seq[0])
    for zero in seq:
        a = np.convolve(a, np.stack((one, -zero)), mode="full")
    if np.iscomplexobj(a):
        roots = np.asarray(seq, dtype=np.complex128)
        if np.all(np.sort(np.imag(roots)) == np.sort(np.imag(np.conj(roots)))):
            a = np.asarray(np.real(a), copy=True)
    return a


def zpk2tf(z: ArrayLike, p: ArrayLike, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Numerator and denominator (highest power first) of zeros, poles, gain (1-D only)."""
    z, p = np.asarray(z), np.asarray(p)
    kk = np.asarray(k, dtype=np.result_type(np.real(z), np.real(p), k))
    if np.issubdtype(kk.dtype, np.integer):
        kk = kk.astype(np.float64)
    z = np.atleast_1d(z)
    kk = np.atleast_1d(kk)
    b = np.multiply(kk, _poly(z))
    a = np.atleast_1d(np.asarray(_poly(p)))
    return b, a


def _normalize(b: ArrayLike, a: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """scipy's `normalize` for one numerator: leading zeros of `a` trimmed, a[0] = 1."""
    den = np.atleast_1d(np.asarray(a))
    num = np.atleast_2d(np.asarray(b))
    if num.ndim > 2 or den.ndim != 1:
        raise ValueError("expected one numerator and a 1-D denominator")
    if np.all(den == 0):
        raise ValueError("denominator must have at least one nonzero element")
    den = np.trim_zeros(den, "f")
    num, den = num / den[0], den / den[0]
    leading = 0
    for j in range(num.shape[-1]):
        if np.all(np.abs(num[:, j]) <= 1e-14):
            leading += 1
        else:
            break
    if leading > 0:  # numerator of lower degree: stripped as scipy does (it also warns)
        if leading == num.shape[1]:
            leading -= 1
        num = num[:, leading:]
    return num, den


def tf2ss(num: ArrayLike, den: ArrayLike) -> tuple[np.ndarray, ...]:
    """Controller canonical form A, B, C, D of num/den (single input, single output)."""
    n, d = _normalize(num, den)
    m, k = n.shape[1], len(d)
    if m > k:
        raise ValueError("improper transfer function: num is longer than den")
    if m == 0 or k == 0:
        raise ValueError("null system")
    n = np.hstack((np.zeros((n.shape[0], k - m), dtype=n.dtype), n))
    dd: np.ndarray = np.atleast_2d(n[:, 0])
    if k == 1:  # a constant gain (one numerator row): no states
        return np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1)), dd.reshape((1, 1))
    frow = -np.array([d[1:]])
    a = np.r_[frow, np.eye(k - 2, k - 1)]
    b = np.eye(k - 1, 1)
    c = n[:, 1:] - np.outer(n[:, 0], d[1:])
    dd = dd.reshape((c.shape[0], b.shape[1]))
    return a, b, c, dd


def zpk2ss(z: ArrayLike, p: ArrayLike, k: float) -> tuple[np.ndarray, ...]:
    return tf2ss(*zpk2tf(z, p, k))


def ss2tf(a: ArrayLike, b: ArrayLike, c: ArrayLike, d: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """num (one row per output) and den of a single-input state-space system (n >= 1 states)."""
    a, b, c, d = (np.atleast_2d(np.asarray(m)) for m in (a, b, c, d))
    n = a.shape[0]
    if a.shape != (n, n) or b.shape != (n, 1) or c.shape[1] != n or d.shape != (c.shape[0], 1):
        raise ValueError(f"ss2tf: inconsistent shapes {a.shape} {b.shape} {c.shape} {d.shape}")
    den = np.poly(a)
    type_test = a[:, 0] + b[:, 0] + c[0, :] + d + 0.0
    num = np.empty((c.shape[0], n + 1), type_test.dtype)
    for i in range(c.shape[0]):
        num[i] = np.poly(a - np.dot(b, np.atleast_2d(c[i, :]))) + (d[i] - 1) * den
    return num, den


def _cplxreal(z: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Conjugate pairs (one per pair, positive imaginary part) and the real values, sorted."""
    z = np.atleast_1d(np.asarray(z))
    if z.size == 0:
        return z, z
    z = z[np.lexsort((abs(z.imag), z.real))]
    real_indices = abs(z.imag) <= _TOL * abs(z)
    zr = z[real_indices].real
    if len(zr) == len(z):
        return np.array([]), zr
    z = z[~real_indices]
    zp = z[z.imag > 0]
    zn = z[z.imag < 0]
    if len(zp) != len(zn):
        raise ValueError("a complex value has no matching conjugate")
    same_real = np.diff(zp.real) <= _TOL * abs(zp[:-1])
    diffs = np.diff(np.concatenate(([0], same_real, [0])))
    run_starts = np.nonzero(diffs > 0)[0]
    run_stops = np.nonzero(diffs < 0)[0]
    for start, stop in zip(run_starts, run_stops + 1, strict=True):
        for chunk in (zp[start:stop], zn[start:stop]):
            chunk[...] = chunk[np.lexsort([abs(chunk.imag)])]
    if any(abs(zp - zn.conj()) > _TOL * abs(zn)):
        raise ValueError("a complex value has no matching conjugate")
    return (zp + zn.conj()) / 2, zr


def _nearest(fro: np.ndarray, to: complex, which: str) -> int:
    order = np.argsort(np.abs(fro - to))
    if which == "any":
        return int(order[0])
    mask = np.isreal(fro[order])
    if which == "complex":
        mask = ~mask
    return int(order[np.nonzero(mask)[0][0]])


def _section(z: list[complex], p: list[complex]) -> FloatArray:
    sos = np.zeros(6)
    b, a = zpk2tf(z, p, 1)
    sos[3 - len(b) : 3] = b
    sos[6 - len(a) : 6] = a
    return sos


def zpk2sos(z: ArrayLike, p: ArrayLike, k: float) -> FloatArray:
    """Second-order sections of a digital zpk, scipy's 'nearest' pairing (poles closest to the
    unit circle last, each with the zeros nearest to it)."""
    z, p = np.asarray(z), np.asarray(p)
    kk = np.asarray(k)
    if len(z) == len(p) == 0:
        return np.asarray([[kk, 0.0, 0.0, 1.0, 0.0, 0.0]], dtype=np.float64)
    p = np.concatenate((p, np.zeros(max(len(z) - len(p), 0))))
    z = np.concatenate((z, np.zeros(max(len(p) - len(z), 0))))
    n_sections = (max(len(p), len(z)) + 1) // 2
    if len(p) % 2 == 1:
        p = np.concatenate((p, [0.0]))
        z = np.concatenate((z, [0.0]))
    z = np.concatenate(_cplxreal(z))
    p = np.concatenate(_cplxreal(p))
    if not np.isreal(kk):
        raise ValueError("k must be real")
    kk = kk.real

    def idx_worst(q: np.ndarray) -> int:
        return int(np.argmin(np.abs(1 - np.abs(q))))

    sos = np.zeros((n_sections, 6))
    for si in range(n_sections - 1, -1, -1):
        p1_idx = idx_worst(p)
        p1 = p[p1_idx]
        p = np.delete(p, p1_idx)
        if np.isreal(p1) and np.isreal(p).sum() == 0:
            z1_idx = _nearest(z, p1, "real")
            z1 = z[z1_idx]
            z = np.delete(z, z1_idx)
            sos[si] = _section([z1, 0], [p1, 0])
        elif (len(p) + 1 == len(z) and not np.isreal(p1)
              and np.isreal(p).sum() == 1 and np.isreal(z).sum() == 1):
            z1_idx = _nearest(z, p1, "complex")
            z1 = z[z1_idx]
            z = np.delete(z, z1_idx)
            sos[si] = _section([z1, z1.conj()], [p1, p1.conj()])
        else:
            if np.isreal(p1):
                prealidx = np.flatnonzero(np.isreal(p))
                p2_idx = prealidx[idx_worst(p[prealidx])]
                p2 = p[p2_idx]
                p = np.delete(p, p2_idx)
            else:
                p2 = p1.conj()
            if len(z) > 0:
                z1_idx = _nearest(z, p1, "any")
                z1 = z[z1_idx]
                z = np.delete(z, z1_idx)
                if not np.isreal(z1):
                    sos[si] = _section([z1, z1.conj()], [p1, p2])
                elif len(z) > 0:
                    z2_idx = _nearest(z, p1, "real")
                    z2 = z[z2_idx]
                    z = np.delete(z, z2_idx)
                    sos[si] = _section([z1, z2], [p1, p2])
                else:
                    sos[si] = _section([z1], [p1, p2])
            else:
                sos[si] = _section([], [p1, p2])
    if len(p) or len(z):
        raise AssertionError("zpk2sos: poles or zeros left unpaired")
    sos[0][:3] *= kk
    return sos


def butter_sos(order: int, cutoff_hz: float | tuple[float, float], btype: str,
               rate_hz: float) -> FloatArray:
    """Digital Butterworth low-, high- or band-pass as sections: scipy's
    `butter(order, cutoff_hz, btype, fs=rate_hz, output="sos")`."""
    if order < 1 or int(order) != order:
        raise ValueError(f"order: must be a positive integer, got {order!r}")
    wn = np.asarray(cutoff_hz, dtype=np.float64) / (rate_hz / 2)
    if np.any(wn <= 0) or np.any(wn >= 1):
        raise ValueError(f"cutoff_hz: {cutoff_hz!r} is not within 0 < f < {rate_hz / 2} Hz")
    z = np.asarray([], dtype=np.float64)
    m = np.arange(-order + 1, order, 2, dtype=np.float64)
    p = -np.exp(1j * np.pi * m / (2 * order))  # analog prototype (buttap)
    k = 1.0
    fs = 2.0
    warped = 2 * fs * np.tan(np.pi * wn / fs)
    if btype in ("lowpass", "highpass"):
        if wn.size != 1:
            raise ValueError("cutoff_hz: one frequency for a low- or high-pass")
        wo = float(warped)
        if btype == "lowpass":
            z, p, k = wo * z, wo * p, k * wo ** (len(p) - len(z))
        else:
            degree = len(p) - len(z)
            z_hp = np.concatenate((wo / z, np.zeros(degree)))
            k = k * np.real(np.prod(-z) / np.prod(-p))
            z, p = z_hp, wo / p
    elif btype == "bandpass":
        if wn.size != 2 or not wn[0] < wn[1]:
            raise ValueError("cutoff_hz: (low, high) with low < high for a band-pass")
        bw = float(warped[1] - warped[0])
        wo = float(np.sqrt(warped[0] * warped[1]))
        degree = len(p) - len(z)
        z_lp = (z * bw / 2).astype(np.complex128)
        p_lp = (p * bw / 2).astype(np.complex128)
        z = np.concatenate((z_lp + np.sqrt(z_lp**2 - wo**2), z_lp - np.sqrt(z_lp**2 - wo**2)))
        p = np.concatenate((p_lp + np.sqrt(p_lp**2 - wo**2), p_lp - np.sqrt(p_lp**2 - wo**2)))
        z = np.concatenate((z, np.zeros(degree)))
        k = k * bw**degree
    else:
        raise ValueError(f"btype: 'lowpass', 'highpass' or 'bandpass', got {btype!r}")
    zd, pd, kd = bilinear_zpk(z, p, k, fs=fs)
    return zpk2sos(zd, pd, kd)


def _sosfilt_py(sos: FloatArray, x: FloatArray, y: FloatArray) -> None:
    n = sos.shape[0]
    s = np.zeros((n, 2))
    for i in range(x.shape[0]):
        v = x[i]
        for j in range(n):
            out = sos[j, 0] * v + s[j, 0]
            s[j, 0] = sos[j, 1] * v - sos[j, 4] * out + s[j, 1]
            s[j, 1] = sos[j, 2] * v - sos[j, 5] * out
            v = out
        y[i] = v


_sosfilt: Callable[[FloatArray, FloatArray, FloatArray], None] | None = None


def sosfilt(sos: ArrayLike, x: ArrayLike) -> FloatArray:
    """Filter `x` through the sections from rest (scipy's `sosfilt`, 1-D float64)."""
    s = np.ascontiguousarray(sos, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 6 or not np.all(s[:, 3] == 1.0):
        raise ValueError("sos: expected an (n, 6) array with a0 = 1")
    xa = np.ascontiguousarray(x, dtype=np.float64)
    if xa.ndim != 1:
        raise ValueError("x: expected a 1-D array")
    global _sosfilt
    if _sosfilt is None:  # numba compiled on first use (cached on disk), not at import
        import numba

        _sosfilt = numba.njit(cache=True)(_sosfilt_py)
    y = np.empty_like(xa)
    _sosfilt(s, xa, y)
    return y
