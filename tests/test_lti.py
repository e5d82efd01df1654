"""controller.core.lti (the product's own filter design, no scipy.signal on the start path)
against scipy.signal itself: bit for bit (array_equal) on every case the product builds and on
random ones; sosfilt bit for bit too (the same float64 operations in the same order)."""

from __future__ import annotations

import itertools
import subprocess
import sys
import warnings

import numpy as np
import pytest
from scipy import linalg, signal

from controller.core import lti
from controller.core.config import NominalModel
from controller.core.discrete import prewarped_fs
from controller.core.dob import f1_continuous_zpk
from controller.core.qfilter import design_q
from controller.gate.loop_model import discrete_plant, mp_zpk


def _same(a: object, b: object) -> None:
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape, (a.shape, b.shape)
    assert np.array_equal(a, b), (a, b)  # bit for bit (no tolerance)


def _random_zpk(rng: np.random.Generator, n_pairs: int, n_real: int, n_zero_pairs: int,
                n_zero_real: int) -> tuple[np.ndarray, np.ndarray, float]:
    def roots(pairs: int, reals: int) -> np.ndarray:
        c = -rng.uniform(0.1, 300, pairs) + 1j * rng.uniform(0.1, 500, pairs)
        r = -rng.uniform(0.01, 400, reals)
        out = np.concatenate((c, c.conj(), r.astype(complex)))
        return out[rng.permutation(out.size)]
    return roots(n_zero_pairs, n_zero_real), roots(n_pairs, n_real), float(rng.uniform(0.1, 1e4))


def _dob_cases() -> list[tuple[list[complex], list[complex], float, float]]:
    """(z, p, k, prewarp) of every continuous filter design_dob discretises, over cut-offs,
    Q types and a second nominal model."""
    out = []
    nominals = (NominalModel(), NominalModel(mn_den=(0.0, 0.002, 1.0), pn_den=(0.0, 0.05, 1.0)))
    for q_type, fc, nom in itertools.product(("q20", "q31"), (0.02, 0.5, 3.0, 10.0, 40.0),
                                             nominals):
        q = design_q(q_type, cutoff_hz=fc)
        out.append((*f1_continuous_zpk(q, nom), fc))
        qz, qp, qk = q.zpk()
        out.append(([complex(z) for z in qz], [complex(p) for p in qp], qk, fc))
    return out


@pytest.mark.parametrize("case", _dob_cases())
def test_bilinear_and_sections_of_the_dob_filters_are_scipys(case: tuple) -> None:
    z, p, k, fc = case
    fs = prewarped_fs(1000.0, fc)
    zz, pz = np.asarray(z, complex), np.asarray(p, complex)
    ours = lti.bilinear_zpk(zz, pz, k, fs)
    ref = signal.bilinear_zpk(zz, pz, k, fs)
    for a, b in zip(ours, ref, strict=True):
        _same(a, b)
    _same(lti.zpk2sos(*ours), signal.zpk2sos(*ref, pairing="nearest"))


@pytest.mark.parametrize("shape", [(1, 0, 0, 0), (0, 1, 0, 0), (1, 1, 0, 1), (2, 1, 1, 0),
                                   (0, 3, 0, 2), (3, 0, 2, 1), (1, 2, 1, 2), (2, 3, 0, 0)])
def test_random_designs_are_scipys(shape: tuple[int, int, int, int]) -> None:
    rng = np.random.default_rng(sum(shape) * 7 + shape[0])
    for _ in range(20):
        z, p, k = _random_zpk(rng, *shape)
        if len(z) > len(p):
            z = z[: len(p)]
        fs = float(rng.uniform(100, 5000))
        ours, ref = lti.bilinear_zpk(z, p, k, fs), signal.bilinear_zpk(z, p, k, fs)
        for a, b in zip(ours, ref, strict=True):
            _same(a, b)
        _same(lti.zpk2sos(*ours), signal.zpk2sos(*ref, pairing="nearest"))
        if len(p):
            _same(lti.zpk2tf(z, p, k)[0], signal.zpk2tf(z, p, k)[0])
            _same(lti.zpk2tf(z, p, k)[1], signal.zpk2tf(z, p, k)[1])
            for a, b in zip(lti.zpk2ss(z, p, k), signal.zpk2ss(z, p, k), strict=True):
                _same(a, b)


def test_repeated_poles_near_one_pair_as_scipy() -> None:
    """A triple pole near z = 1 (Q31 at a low cut-off) and equal real parts: the tie-breaks."""
    p = np.array([0.9999, 0.9999, 0.9999, 0.5 + 0.2j, 0.5 - 0.2j, 0.5 + 0.1j, 0.5 - 0.1j])
    z = np.array([-1.0, -1.0, 0.3, 0.99 + 0.01j, 0.99 - 0.01j])
    _same(lti.zpk2sos(z, p, 2.5), signal.zpk2sos(z, p, 2.5, pairing="nearest"))
    _same(lti.zpk2sos([], [], 3.0), signal.zpk2sos([], [], 3.0, pairing="nearest"))
    with pytest.raises(ValueError, match="conjugate"):
        lti.zpk2sos([], [0.5 + 0.1j, 0.2], 1.0)


@pytest.mark.parametrize("args", [
    (2, (4.0, 150.0), "bandpass", 1000.0),  # the watchdog's and the nonlinear check's band
    (2, (1.0, 40.0), "bandpass", 500.0),
    (2, (0.5, 499.0), "bandpass", 1000.0),
    (2, 20.0, "highpass", 1000.0),  # autotune's command noise
    (2, 5.0, "highpass", 2000.0),
    (2, 20.0, "lowpass", 1000.0),
    (3, 33.0, "lowpass", 1000.0),
    (4, (10.0, 60.0), "bandpass", 1000.0),
])
def test_butter_sections_are_scipys(args: tuple) -> None:
    order, wn, btype, fs = args
    _same(lti.butter_sos(order, wn, btype, fs),
          signal.butter(order, wn, btype=btype, fs=fs, output="sos"))


def test_butter_refuses_bad_bands_naming_them() -> None:
    with pytest.raises(ValueError, match="cutoff_hz"):
        lti.butter_sos(2, (4.0, 600.0), "bandpass", 1000.0)
    with pytest.raises(ValueError, match="cutoff_hz"):
        lti.butter_sos(2, (40.0, 4.0), "bandpass", 1000.0)
    with pytest.raises(ValueError, match="btype"):
        lti.butter_sos(2, 4.0, "bandstop", 1000.0)


def test_sosfilt_is_scipys_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    x = rng.standard_normal(5000) * 50
    for sos in (signal.butter(2, (4.0, 150.0), btype="bandpass", fs=1000.0, output="sos"),
                signal.butter(2, 20.0, btype="highpass", fs=1000.0, output="sos"),
                signal.butter(5, 0.2, output="sos")):
        _same(lti.sosfilt(sos, x), signal.sosfilt(sos, x))
    with pytest.raises(ValueError, match="a0"):
        lti.sosfilt([[1.0, 0, 0, 2.0, 0, 0]], x)


@pytest.mark.parametrize("nominal", [
    NominalModel(),
    NominalModel(mn_den=(0.0, 0.002, 1.0), pn_den=(0.0, 0.05, 1.0)),
    NominalModel(mn_den=(0.0, 0.001, 1.0), pn_num=(0.0, 0.0, 2.0), pn_den=(0.0, 0.01, 1.0)),
])
def test_state_space_conversions_of_the_plant_are_scipys(nominal: NominalModel) -> None:
    z, p, k = mp_zpk(nominal)
    zz, pz = np.array(z), np.array(p)
    for a, b in zip(lti.zpk2ss(zz, pz, k), signal.zpk2ss(zz, pz, k), strict=True):
        _same(a, b)
    a, b, c, _ = signal.zpk2ss(zz, pz, k)
    a, b, c = (np.real(np.atleast_2d(m)) for m in (a, b, c))
    n = a.shape[0]
    ag = np.zeros((n + 1, n + 1))
    ag[:n, :n], ag[n, :n] = a * 0.9, c[0]
    bg = np.concatenate([b[:, 0], [0.1]])
    cg = np.zeros(n + 1)
    cg[n] = 1.0
    ours = lti.ss2tf(ag, bg[:, None], cg[None, :], np.zeros((1, 1)))
    ref = signal.ss2tf(ag, bg[:, None], cg[None, :], np.zeros((1, 1)))
    for x, y in zip(ours, ref, strict=True):
        _same(x, y)


@pytest.mark.parametrize("num, den", [
    ([1.0], [1.013e-05, 0.004501, 1.0]),
    ([2.0e-3, 0.9, 1.0], [0.0005169, 0.03215, 1.0]),
    ([0.0, 0.0, 2.0], [0.0, 0.05, 1.0]),  # leading zeros in both: stripped as scipy does
    ([1e-6, 1e-4, 3.0, 1.0], [4e-9, 1e-6, 0.03, 0.5, 1.0]),
    ([3.0], [2.0]),  # a constant gain: no states
])
def test_tf2ss_of_the_linear_rig_is_scipys(num: list[float], den: list[float]) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", signal.BadCoefficients)
        ref = signal.tf2ss(np.array(num), np.array(den))
    for a, b in zip(lti.tf2ss(np.array(num), np.array(den)), ref, strict=True):
        _same(a, b)


def test_the_start_path_does_not_import_scipy_signal() -> None:
    """`dobtune check`'s and the controller's imports (the gate, the loop, the watchdog, the
    nonlinear check) leave scipy.signal out: it is 0.5-0.7 s of every start."""
    code = ("import sys, controller.cli.check, controller.process.analysis_worker, "
            "controller.core.watchdog, controller.sim.nonlinear_check, controller.__main__; "
            "print('scipy.signal' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stderr


def _nominals() -> list[NominalModel]:
    """The article's model, two others with a pole at 0 or a first-order Pn, and random
    second-order Pn (1-300 Hz, damping 0.01-1.5) with random Mn and zeros."""
    out = [NominalModel(), NominalModel(mn_den=(0.0, 0.002, 1.0), pn_den=(0.0, 0.05, 1.0)),
           NominalModel(mn_den=(0.0, 0.001, 1.0), pn_num=(0.0, 0.0, 2.0), pn_den=(0.0, 0.01, 1.0))]
    rng = np.random.default_rng(11)
    for _ in range(30):
        wn, zeta = 2 * np.pi * rng.uniform(1.0, 300.0), rng.uniform(0.01, 1.5)
        out.append(NominalModel(
            mn_den=(0.0, float(rng.uniform(1e-4, 0.05)), 1.0),
            pn_num=(0.0, float(rng.uniform(0.0, 1e-3)), float(rng.uniform(0.3, 3.0))),
            pn_den=(float(1 / wn**2), float(2 * zeta / wn), 1.0)))
    return out


def test_expm_is_scipys_to_rounding() -> None:
    """`lti.expm` (scipy's algorithm in numpy: the same Padé degree and scaling, the same sums)
    against scipy.linalg.expm on random matrices of norm 1e-4 to ~300 (every degree 3-13, with
    and without scaling), triangular and diagonal ones: within 1e-12 ||A||_1 of the largest
    entry (measured: 1.5e-13; the difference is rounding: BLAS and LAPACK builds differ)."""
    rng = np.random.default_rng(5)
    cases = [rng.standard_normal((n, n)) * scale
             for scale in (1e-4, 1e-2, 0.3, 1.0, 3.0, 10.0, 30.0) for n in (2, 3, 4, 6, 8)
             for _ in range(8)]
    cases += [np.triu(rng.standard_normal((5, 5))) * s for s in (0.1, 10.0, 100.0)]
    cases += [np.diag([-3.0, 0.5, 2.0]), np.array([[0.7]]), np.zeros((3, 3))]
    for a in cases:
        ref = linalg.expm(a)
        tol = 1e-12 * max(1.0, float(np.max(np.sum(np.abs(a), axis=0)))) * np.max(np.abs(ref))
        assert np.max(np.abs(lti.expm(a) - ref)) <= tol, a
    with pytest.raises(ValueError, match="square"):
        lti.expm(np.ones((2, 3)))


@pytest.mark.parametrize("rate_hz", [500.0, 1000.0, 4000.0])
def test_the_gate_s_zoh_plant_is_scipys_to_rounding(rate_hz: float) -> None:
    """The gate's sampled plant (`loop_model.discrete_plant`: ZOH of Mn Pn with the angle as an
    extra state, through `lti.expm`) against scipy.signal.cont2discrete(method='zoh') of the
    same augmented system: Phi and Gamma each within 1e-12 of their largest entry (measured:
    3.4e-14; scipy's own expm of the gate's matrix: 5.9e-15). Entry by entry the smallest, the
    angle's step response over one period (~1e-10), differs from cont2discrete's by up to
    4e-10 relative: there scipy is the less accurate (an extended-precision Taylor series
    agrees with `lti.expm` to 5e-16, with scipy's expm to 4e-10)."""
    for nominal in _nominals():
        z, p, k = mp_zpk(nominal)
        a, b, c, d = (np.real(np.atleast_2d(m)) for m in signal.zpk2ss(np.array(z), np.array(p), k))
        n = a.shape[0]
        aug_a = np.zeros((n + 1, n + 1))
        aug_a[:n, :n], aug_a[n, :n] = a, c[0]
        aug_b = np.concatenate([b[:, 0], [d[0, 0]]])[:, None]
        phi, gam, *_ = signal.cont2discrete((aug_a, aug_b, np.eye(n + 1), np.zeros((n + 1, 1))),
                                            1.0 / rate_hz, method="zoh")
        pl = discrete_plant(nominal, rate_hz)
        ours_phi = np.vstack([pl.a[:n, :n], pl.a[n + 1, :n]])  # x and the angle rows
        ours_gam = np.concatenate([pl.b[:n], [pl.b[n + 1]]])
        for ours, ref in ((ours_phi, phi[:, :n]), (ours_gam, gam[:, 0])):
            assert np.max(np.abs(ours - ref)) <= 1e-12 * np.max(np.abs(ref)), (nominal, rate_hz)
