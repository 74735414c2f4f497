"""The rounding bounds of tests/tolerances.py hold, and are not vacuous (issue #21).

Each bound is checked against a reference computed in extended precision (numpy's longdouble: 64-bit
significand on x86-64, u = 2⁻⁶⁴, so the reference's own error is ~2000 × below the bound), on random
data whose results cancel; and each bound stays in the rounding regime (≤ 1e-12 of the data's scale; a
lower limit on the error seen would itself depend on the machine).

Guards against: a bound that is wrong by a factor (a γ_n with the wrong n, a missing |·|), or one so loose
it hides a real error.
"""

import numpy as np
import pytest

from tests import tolerances as tol

LD = np.longdouble
pytestmark = pytest.mark.skipif(np.finfo(LD).eps > 1e-18, reason="needs an extended-precision longdouble")


def _matmul_ld(A, B):
    return np.einsum("...ij,...jk->...ik", A.astype(LD), B.astype(LD))


@pytest.mark.parametrize("shape", [(7, 300, 5), (4, 33, 33), (64, 64, 64)])
def test_product_bound_holds_for_a_blas_product(shape):
    rng = np.random.default_rng(1)
    m, k, n = shape
    A, B, C = rng.normal(size=(m, k)), rng.normal(size=(k, n)), rng.normal(size=(n, 3))
    got = (A @ B) @ C
    ref = _matmul_ld(_matmul_ld(A, B), C)
    bound = tol.product_tol(A, B, C, evaluations=1)
    err = np.abs(got - ref).astype(float)
    assert np.all(err <= bound)
    assert bound.max() <= 1e-12 * (np.abs(A) @ np.abs(B) @ np.abs(C)).max()  # in the rounding regime


@pytest.mark.parametrize("n,near_identity", [(5, False), (40, False), (120, False), (69, True)])
def test_solve_bound_holds_for_lapack(n, near_identity):
    """Dense random matrices (the componentwise bound is then pessimistic) and the doubling's I − R R."""
    rng = np.random.default_rng(2)
    if near_identity:
        R = 0.3 * rng.random((3, n, n)) / n
        A = np.eye(n) - R @ R
    else:
        A = rng.normal(size=(3, n, n)) + 0.5 * np.eye(n) * np.sqrt(n)
    B = rng.normal(size=(3, n, 4))
    X = np.linalg.solve(A, B)
    # reference: two steps of iterative refinement with the residual in extended precision
    ref = X.astype(LD)
    for _ in range(2):
        r = B.astype(LD) - np.einsum("...ij,...jk->...ik", A.astype(LD), ref)
        ref = ref + np.linalg.solve(A, r.astype(float)).astype(LD)
    bound = tol.solve_tol(A, X, evaluations=1)
    err = np.abs(X - ref).astype(float)
    assert np.all(err <= bound)
    assert not near_identity or bound.max() <= 1e-12 * np.abs(X).max()  # no growth: in the rounding regime


@pytest.mark.parametrize("N", [64, 256])
def test_fft_bound_holds_for_the_cosine_coefficients(N):
    from flakedb.rt.basis.fourier import cosine_coefficients

    rng = np.random.default_rng(3)
    g = rng.normal(size=N + 1)
    a = cosine_coefficients(g)
    k = np.arange(N + 1)
    cos = np.cos(np.pi * np.outer(k, k).astype(LD) / LD(N))  # longdouble cosines
    c = np.full(N + 1, LD(2))
    c[0] = c[-1] = LD(1)
    ref = (cos @ (c * g.astype(LD))) / LD(N)
    ref[0] *= LD(0.5)
    ref[-1] *= LD(0.5)
    err = np.abs(a - ref).astype(float)
    bound = tol.fft_tol(2 * N, np.sqrt(2) * np.linalg.norm(g) / N, evaluations=1) + tol.ulps(1, a)
    assert np.all(err <= bound)
    assert np.max(bound) <= 1e-12 * np.abs(g).max()


def test_sum_bound_and_adding_bound_hold():
    rng = np.random.default_rng(4)
    x, y = rng.normal(size=(5, 1000)), rng.normal(size=(1000, 3))
    got = x @ y
    ref = _matmul_ld(x, y)
    b = tol.sum_tol(1000, np.abs(x) @ np.abs(y), evaluations=1)
    assert np.all(np.abs(got - ref).astype(float) <= b)

    from flakedb.rt.basis.layer import Layer, add_reflection_only

    h = 12
    top = Layer(*(0.4 * rng.random((2, 3, h, h)) / h for _ in range(4)))
    R2 = 0.9 * rng.random((2, 3, h, h)) / h
    got = add_reflection_only(top, R2)
    A = np.eye(h) - top.Rb @ R2
    Xr = np.linalg.solve(A, top.Ttb).astype(LD)  # refined once in extended precision
    Ald = np.eye(h, dtype=LD) - _matmul_ld(top.Rb, R2)
    res = top.Ttb.astype(LD) - np.einsum("...ij,...jk->...ik", Ald, Xr)
    Xr = Xr + np.linalg.solve(A, res.astype(float)).astype(LD)
    ref = top.Rt.astype(LD) + np.einsum("...ij,...jk->...ik", top.Tbt.astype(LD), np.einsum("...ij,...jk->...ik", R2.astype(LD), Xr))
    err = np.abs(got - ref).astype(float)
    bound = tol.adding_tol(top, R2, evaluations=1)
    assert np.all(err <= bound)
    assert bound.max() <= 1e-12 * np.abs(got).max()


def test_ulps_and_assert_within_report_the_worst_element():
    tol.assert_ulps(np.exp(np.array([1.0, 2.0])), np.exp(np.array([1.0, 2.0])), 0)
    with pytest.raises(AssertionError, match="beyond 1 ulps"):
        tol.assert_ulps(np.array([1.0 + 4e-16]), np.array([1.0]), 1)
    with pytest.raises(AssertionError, match="1 of 2 elements outside"):
        tol.assert_within(np.array([0.0, 1.0]), np.array([0.0, 0.0]), 0.5)
