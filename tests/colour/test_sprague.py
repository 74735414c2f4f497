"""Sprague (1880) interpolation as CIE 167:2005 specifies it (flakedb.colour.sprague).

Guards against: wrong polynomial or boundary coefficients (the matrix must equal colour-science's
independent SpragueInterpolator to 1e-12 on random data, and reproduce polynomials: degree ≤ 4 on
interior intervals, where the 6-point scheme is exact, degree ≤ 1 everywhere, which is what the
boundary extrapolation keeps); an interpolant that misses its samples; mis-indexed intervals at the
grid's ends; silent extrapolation or too few samples.
"""

import colour
import numpy as np
import pytest

from flakedb.colour.sprague import sprague_matrix


@pytest.mark.parametrize("lo, hi, step", [(380, 780, 10), (380, 780, 5), (360, 780, 20), (400, 694, 7), (0, 5, 1)])
def test_equals_colour_science_sprague(lo, hi, step):
    x = np.arange(lo, hi + 0.5, step, dtype=float)
    fine = np.linspace(lo, hi, (x.size - 1) * 4 * step + 1)        # 0.25 nm nodes, grid nodes included
    rng = np.random.default_rng(7)
    y = rng.normal(size=(3, x.size))
    ref = np.stack([colour.algebra.SpragueInterpolator(x, yk)(fine) for yk in y])
    got = y @ sprague_matrix(x, fine).T
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_passes_through_the_samples_and_reproduces_polynomials():
    x = np.arange(380.0, 781.0, 10.0)
    fine = np.linspace(380.0, 780.0, 401)
    S = sprague_matrix(x, fine)
    np.testing.assert_allclose(S[::10], np.eye(x.size), atol=1e-14)
    t, tf = (x - 580.0) / 200.0, (fine - 580.0) / 200.0
    inner = (fine >= x[2]) & (fine <= x[-3])                       # intervals with no extrapolated sample
    for d in range(5):
        err = np.abs(S @ t**d - tf**d)
        assert err[inner].max() < 1e-13, d
        if d <= 1:
            assert err.max() < 1e-13, d
    # degree 5 is not reproduced (a 6-point scheme of order 5 with 4-th order differences): the test bites
    assert np.abs(S @ t**5 - tf**5)[inner].max() > 1e-8


def test_refuses_extrapolation_short_and_non_uniform_grids():
    x = np.arange(380.0, 781.0, 10.0)
    with pytest.raises(ValueError, match="nothing is extrapolated"):
        sprague_matrix(x, [379.0])
    with pytest.raises(ValueError, match="at least 6"):
        sprague_matrix(x[:5], x[:5])
    with pytest.raises(ValueError, match="uniformly"):
        sprague_matrix(np.r_[x[:-1], 795.0], x)
