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
        from controller.core.numba_start import numba

        _sosfilt = numba.njit(cache=True)(_sosfilt_py)
    y = np.empty_like(xa)
    _sosfilt(s, xa, y)
    return y


# --------------------------------------------------------------------------- matrix exponential

# Al-Mohy & Higham (2009), "A new scaling and squaring algorithm for the matrix exponential",
# as scipy 1.17's `linalg.expm` runs it for a real matrix below 400 x 400: the same Padé degree
# m and scaling s from the same norms, the same U, V sums, (V - U) X = U solved by LU, squared s
# times. Its parameters (theta_m, and the bound coefficients of the backward-error test):
_THETA = (1.495585217958292e-002, 2.539398330063230e-001, 9.504178996162932e-001,
          2.097847961257068e+000, 4.250000000000000e+000)
_ELL_COEFF = (1.1191048088221578e-11, 1.1167770708198077e-06, 4.9826124310493469e-01,
              6.5662862500000000e+05, 1.2573361865339437e+19)
_PADE_B = {
    3: (120.0, 60.0, 12.0),
    5: (30240.0, 15120.0, 3360.0, 420.0, 30.0),
    7: (17297280.0, 8648640.0, 1995840.0, 277200.0, 25200.0, 1512.0, 56.0),
    9: (17643225600.0, 8821612800.0, 2075673600.0, 302702400.0, 30270240.0, 2162160.0,
        110880.0, 3960.0, 90.0),
    13: (64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0,
         129060195264000.0, 10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0,
         40840800.0, 960960.0, 16380.0, 182.0),
}


def _norm1(m: FloatArray) -> float:
    return float(np.max(np.sum(np.abs(m), axis=0)))


def _ell(spun: FloatArray, norm_a: float, coeff: float, degree: int) -> int:
    """max(0, ceil(log2(||A|^(2m+1)|_1 / ||A||_1 / coeff) / (2m))): the extra scaling the
    backward-error bound asks for (`spun`: |A|^T applied 2m+1 times to ones)."""
    top = float(np.max(spun))
    if top == 0.0:  # |A| nilpotent: no bound to meet
        return 0
    return max(0, int(np.ceil(np.log2(top / norm_a / coeff) / degree)))


def _pade_structure(a: FloatArray) -> tuple[int, int, list[FloatArray]]:
    """Padé degree m, scaling s and the powers [A, A^2, A^4, A^6, A^8 or None] (scipy's
    `pick_pade_structure` for n < 400), the powers already scaled by 2^-s."""
    abs_t = np.abs(a).T
    v = abs_t @ np.ones(a.shape[0])
    norm_a = float(np.max(v))
    a2 = a @ a
    a4 = a2 @ a2
    a6 = a4 @ a2
    d4 = _norm1(a4) ** 0.25
    d6 = _norm1(a6) ** (1.0 / 6.0)
    eta1 = max(d4, d6)
    powers: list[FloatArray] = [a, a2, a4, a6]

    def spin(times: int) -> FloatArray:
        nonlocal v
        for _ in range(times):
            v = abs_t @ (abs_t @ v)
        return v

    # The bound's vector is spun on whether or not eta passes (the next test goes on from it).
    if _ell(spin(3), norm_a, _ELL_COEFF[0], 6) == 0 and eta1 < _THETA[0]:
        return 3, 0, powers
    if _ell(spin(2), norm_a, _ELL_COEFF[1], 10) == 0 and eta1 < _THETA[1]:
        return 5, 0, powers
    a8 = a4 @ a4
    d8 = _norm1(a8) ** 0.125
    eta2 = max(d6, d8)
    if _ell(spin(2), norm_a, _ELL_COEFF[2], 14) == 0 and eta2 < _THETA[2]:
        return 7, 0, powers
    if _ell(spin(2), norm_a, _ELL_COEFF[3], 18) == 0 and eta2 < _THETA[3]:
        return 9, 0, [*powers, a8]
    d10 = _norm1(a6 @ a4) ** 0.1
    eta4 = min(eta2, max(d8, d10))
    s = max(0, int(np.ceil(np.log2(eta4 / _THETA[4]))))
    if s:
        abs_t = abs_t * 2.0**-s
        v = v * 2.0 ** (-19.0 * s)
        norm_a *= 2.0**-s
    s += _ell(spin(4), norm_a, _ELL_COEFF[4], 26)
    if s:
        powers = [p * f ** -s for p, f in zip(powers, (2.0, 4.0, 16.0, 64.0), strict=True)]
    return 13, s, powers


def expm(a: ArrayLike) -> FloatArray:
    """The matrix exponential of a real square matrix (without scipy.linalg, 0.2-0.3 s to
    import with the numpy modules its array-API layer loads). Agrees with `scipy.linalg.expm`
    to rounding (tests/test_lti.py)."""
    m_in = np.asarray(a, dtype=np.float64)
    if m_in.ndim != 2 or m_in.shape[0] != m_in.shape[1] or m_in.shape[0] == 0:
        raise ValueError(f"expm: expected a non-empty square matrix, got shape {m_in.shape}")
    n = m_in.shape[0]
    if not np.any(m_in - np.diag(np.diag(m_in))):  # diagonal (1 x 1 included)
        return np.diag(np.exp(np.diag(m_in)))
    m, s, p = _pade_structure(m_in)
    b = _PADE_B[m]
    eye = np.eye(n)
    if m == 3:
        u = p[0] @ p[1] + b[1] * p[0]
        v = b[2] * p[1] + b[0] * eye
    elif m == 5:
        u = p[0] @ (p[2] + b[3] * p[1] + b[1] * eye)
        v = b[4] * p[2] + b[2] * p[1] + b[0] * eye
    elif m == 7:
        u = p[0] @ (p[3] + b[5] * p[2] + b[3] * p[1] + b[1] * eye)
        v = b[6] * p[3] + b[4] * p[2] + b[2] * p[1] + b[0] * eye
    elif m == 9:
        u = p[0] @ (p[4] + b[7] * p[3] + b[5] * p[2] + b[3] * p[1] + b[1] * eye)
        v = b[8] * p[4] + b[6] * p[3] + b[4] * p[2] + b[2] * p[1] + b[0] * eye
    else:
        a2, a4, a6 = p[1], p[2], p[3]
        u = p[0] @ (a6 @ (a6 + b[11] * a4 + b[9] * a2)
                    + (b[7] * a6 + b[5] * a4 + b[3] * a2 + b[1] * eye))
        v = (a6 @ (b[12] * a6 + b[10] * a4 + b[8] * a2)
             + (b[6] * a6 + b[4] * a4 + b[2] * a2 + b[0] * eye))
    e = 2.0 * np.linalg.solve(v - u, u) + eye  # (V - U)^-1 (V + U) = I + 2 (V - U)^-1 U
    for _ in range(s):
        e = e @ e
    return e
