"""flakedb.rt.basis.special against scipy.special (an independent implementation: Cephes / specfun / xsf) and
against closed forms (exactness of the Gauss rules, the sectoral functions)."""

import math

import numpy as np
import pytest
import scipy.special as sp

from flakedb.rt.basis import special
from flakedb.rt.basis.quadrature import gauss_radau_unit


def test_erf_matches_scipy_to_rounding():
    x = np.concatenate([np.linspace(-30.0, 30.0, 60001), [0.0, 1e-300, 1e-10, 0.999999, 1.0, 1.0000001, 7.99, 8.0,
                                                        8.01, 26.5, 27.0, np.inf, -np.inf]])
    ref = sp.erf(x)
    got = special.erf(x)
    assert np.all(np.abs(got - ref) <= 4e-16 * np.maximum(np.abs(ref), 1e-300))
    assert np.isnan(special.erf(np.nan))


def test_smith_denominator_without_cancellation():
    a = np.concatenate([np.logspace(-8, 2, 20001), [0.999999, 1.0, 1.000001, 8.0, 30.0]])
    ref = 1.0 + sp.erf(a) + np.exp(-a * a) / (a * math.sqrt(math.pi))
    assert np.max(np.abs(special.smith_masking_denominator(a) / ref - 1.0)) < 5e-16


@pytest.mark.parametrize("n,alpha,beta", [(1, 1, 0), (2, 1, 0), (7, 1, 0), (99, 1, 0), (399, 1, 0), (50, 0, 0),
                                          (30, 0.5, -0.5), (20, 2.5, 1.5)])
def test_gauss_jacobi_matches_scipy_and_is_exact(n, alpha, beta):
    t, w = special.gauss_jacobi(n, alpha, beta)
    tr, wr = sp.roots_jacobi(n, alpha, beta)
    assert np.max(np.abs(t - tr)) < 5e-15
    assert np.max(np.abs(w - wr) / wr) < 1e-9  # scipy's smallest weights (1e-9 at n = 399) carry 1e-10
    # exact for every Jacobi polynomial of degree 1 … 2n − 1 (orthogonal to 1 under the weight)
    for k in sorted(k for k in {1, 2, n, 2 * n - 1} if k <= 2 * n - 1):
        assert abs(w @ sp.eval_jacobi(k, alpha, beta, t)) < 1e-13 * w.sum()
    mu0 = 2 ** (alpha + beta + 1) * math.gamma(alpha + 1) * math.gamma(beta + 1) / math.gamma(alpha + beta + 2)
    assert abs(w.sum() - mu0) < 1e-14 * mu0


def test_gauss_radau_integrates_degree_2h_minus_2():
    for h in (1, 2, 5, 50, 200):
        x, w = gauss_radau_unit(h)
        assert x[-1] == 1.0
        for k in range(0, 2 * h - 1, max(1, (2 * h - 2) // 7)):
            assert abs(w @ x**k - 1.0 / (k + 1)) < 1e-14


@pytest.mark.skipif(not hasattr(sp, "sph_legendre_p_all"), reason="scipy.special.sph_legendre_p_all needs scipy >= 1.15")
@pytest.mark.parametrize("K,M", [(0, 0), (1, 1), (5, 3), (40, 39), (200, 150)])
def test_sph_legendre_all_matches_scipy(K, M):
    th = np.linspace(0.0, np.pi, 37)
    got = special.sph_legendre_all(K, M, th)
    ref = np.transpose(sp.sph_legendre_p_all(K, M, th)[0][:, : M + 1], (1, 0, 2))
    assert got.shape == (M + 1, K + 1, th.size)
    assert np.max(np.abs(got - ref)) < 1e-12
    # the sectoral closed form S_m^m = (−1)^m √((2m+1)!!/(4π (2m)!!)) sin^m θ
    m = min(M, 3)
    dfac = np.prod(np.arange(2 * m + 1, 0, -2, dtype=float)) / max(1.0, np.prod(np.arange(2 * m, 0, -2, dtype=float)))
    assert np.allclose(got[m, m], (-1) ** m * np.sqrt(dfac / (4 * np.pi)) * np.sin(th) ** m, rtol=1e-13, atol=1e-15)


def test_horner_in_place_is_the_written_out_rule_bit_for_bit():
    """Guards special._poly's in-place Horner rule (erf and Smith's G1 in every rough interface): the values
    of y = y·x + c written out."""
    x = np.random.default_rng(3).uniform(-7.0, 7.0, 1000)
    for coef in (special._T, special._U, special._P, special._Q):
        want = np.full_like(x, coef[0])
        for c in coef[1:]:
            want = want * x + c
        np.testing.assert_array_equal(special._poly(x, coef), want)
