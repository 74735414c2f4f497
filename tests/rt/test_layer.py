"""Doubling of symmetric layers (flakedb/rt/basis/layer.py, docs/model.md §4).

Guards against: a chunked / in-place doubling that differs from add(S, S) (a chunk boundary that
skips or repeats matrices, an update that uses the new R or T where the old one is meant, a
broadcast T that is not expanded), and a thread split that changes the result.
"""

import numpy as np
import pytest

import flakedb.rt.basis.layer as ly
from flakedb.rt.basis.layer import Layer, add, double_symmetric
from tests import tolerances as tol


def _whole_batch(R, T, times):
    """The whole-batch doubling written out (add(S, S) for a symmetric S, docs/model.md §4), with the
    doubling's own solve (:func:`flakedb.rt.basis.layer._solve_near_identity`, per matrix)."""
    eye = np.eye(R.shape[-1])
    for _ in range(times):
        X = ly._solve_near_identity(eye - R @ R, T)
        R, T = R + T @ (R @ X), T @ X
    return R, T


def _layers(L=3, C=5, h=11, seed=0):
    rng = np.random.default_rng(seed)
    R = 0.3 * rng.random((L, C, h, h)) / h
    T = 0.5 * rng.random((L, C, h, h)) / h + 0.5 * np.eye(h)
    return R, T


@pytest.mark.parametrize("h", [11, 40])
@pytest.mark.parametrize("chunk", [1, 4, None])
def test_chunked_doubling_is_the_whole_batch_doubling(monkeypatch, chunk, h):
    """Chunks of 1, 4 (15 = 3·4 + 3: a ragged last chunk) and all matrices give the whole-batch result
    bit for bit, and equal the adding equations applied to S over S (h = 40: the block inverse recurses)."""
    monkeypatch.setattr(ly, "DOUBLING_CHUNK_BYTES", ly.DOUBLING_CHUNK_BYTES if chunk is None else 8 * h * h * chunk)
    R, T = _layers(h=h)
    R0, T0 = R.copy(), T.copy()
    Rd, Td = double_symmetric(R, T, 4)
    Rw, Tw = _whole_batch(R, T, 4)
    np.testing.assert_array_equal(Rd, Rw)  # exact by construction: the same BLAS/LAPACK call on each matrix, chunked or not
    np.testing.assert_array_equal(Td, Tw)
    np.testing.assert_array_equal(R, R0)  # inputs untouched
    np.testing.assert_array_equal(T, T0)
    S = Layer(R, T, R, T)
    for _ in range(4):
        S = add(S, S)
    np.testing.assert_allclose(Rd, S.Rt, rtol=0, atol=1e-12 * np.abs(S.Rt).max())
    np.testing.assert_allclose(Td, S.Ttb, rtol=0, atol=1e-12 * np.abs(S.Ttb).max())


def test_doubling_broadcasts_T_and_threads_agree():
    """A T shared by all channels (C = 1) is doubled as if repeated; two threads give the serial result."""
    R, T = _layers(C=4)
    T1 = T[:, :1]
    Rd, Td = double_symmetric(R, T1, 3)
    Rw, Tw = _whole_batch(R, np.broadcast_to(T1, R.shape), 3)
    np.testing.assert_array_equal(Rd, Rw)  # exact by construction: a broadcast T is the same values; threads split the batch
    np.testing.assert_array_equal(Td, Tw)
    R2, T2 = double_symmetric(R, T1, 3, threads=2)
    np.testing.assert_array_equal(R2, Rd)
    np.testing.assert_array_equal(T2, Td)
    R0, T0 = double_symmetric(R, T, 0)
    assert R0 is R and T0 is T


@pytest.mark.parametrize("factor,doubled", [(0.5, False), (2.0, True)])
def test_symmetry_tolerance_decides_the_slab_method(factor, doubled):
    """A kernel asymmetric by ``factor`` × EIGEN_SYMMETRY_TOL × max |K| (here a negative entry) is solved
    by the eigen-solution below the tolerance and doubled above it; a zero kernel is the exact
    attenuation."""
    from flakedb.rt.scattering.media import PhaseMedium
    from flakedb.rt.basis.quadrature import radau_hemisphere
    from flakedb.rt.adding.stack import medium_kernel_blocks

    q = radau_hemisphere(6)
    med = PhaseMedium(np.ones(2), np.array([0.6, 0.9]), ("hg", 0.5))
    K_T, K_R, _ = medium_kernel_blocks(med, q.x, q.w, 1e-6, 8)
    sig = med.sigma_t(q.x)
    K_T, K_R = K_T.copy(), K_R.copy()
    K_T[0, :, 3, 3] = -10.0 * np.abs(K_T).max()  # the largest |K| is negative (still a solvable slab)
    K_R[0, 1, 0, 2] += factor * ly.EIGEN_SYMMETRY_TOL * max(np.abs(K_T).max(), np.abs(K_R).max())
    got = ly.homogeneous_slab(q.x, q.w, sig, K_T, K_R, 2.0)
    dbl = ly.homogeneous_slab(q.x, q.w, sig, K_T, K_R, 2.0, method="doubling")
    assert np.array_equal(got.Rt, dbl.Rt) == doubled
    zero = ly.homogeneous_slab(q.x, q.w, sig, 0 * K_T, 0 * K_R, 2.0)
    np.testing.assert_array_equal(zero.Rt, 0.0)
    tol.assert_ulps(np.diagonal(zero.Ttb, axis1=-2, axis2=-1), np.broadcast_to(np.exp(-2.0 * sig / q.x), zero.Ttb.shape[:-1]),
                    2.0 * sig / q.x + 4)  # τσ/μ rounded twice (×|arg|), exp ≤ 1 ulp each side


def test_block_inverse_solve_matches_pivoted_lapack_and_falls_back():
    """The doubling's solve (block inverse, no pivoting) against LAPACK's pivoted solve on passive
    layers' I − R R (h = 69: three levels of recursion), and a matrix that needs pivoting (a zero
    leading block) is caught by the probe and solved by LAPACK."""
    rng = np.random.default_rng(3)
    h = 69
    R = 0.3 * rng.random((6, h, h)) / h
    T = 0.5 * rng.random((6, h, h)) / h + 0.5 * np.eye(h)
    A = np.eye(h) - R @ R
    X = ly._solve_near_identity(A, T)
    ref = np.linalg.solve(A, T)
    tol.assert_within(X, ref, tol.solve_tol(A, ref, extra_ops=h))  # LU backward error both ways (no growth: A ≈ I), + inv(A) @ T
    P = np.eye(h)[::-1] + 0.01 * rng.random((h, h))  # anti-diagonal: A11 singular-ish, pivoting needed
    A2 = np.concatenate([A, P[None]])
    T2 = np.concatenate([T, T[:1]])
    X2 = ly._solve_near_identity(A2, T2)
    np.testing.assert_allclose(A2[-1] @ X2[-1], T2[-1], rtol=0, atol=1e-10)
    np.testing.assert_array_equal(X2[-1], np.linalg.solve(A2[-1:], T2[-1:])[0])  # exact by construction: the fallback is this call
