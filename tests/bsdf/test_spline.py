"""The not-a-knot cubic spline of the colour report (flakedb.bsdf.spline.cubic_spline_not_a_knot).

Guards against a wrong end condition or slope system: a not-a-knot spline reproduces every cubic exactly
(de Boor ch. IV), and it is the same spline as scipy's CubicSpline (which the report used before).
"""

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from flakedb.bsdf.spline import cubic_spline_not_a_knot
from flakedb.rt.basis.quadrature import radau_hemisphere


@pytest.mark.parametrize("n", [4, 5, 8, 64])
def test_reproduces_cubics(n):
    x = radau_hemisphere(n).x
    c = np.array([[0.3, -1.0, 2.0, 0.7], [1.0, 0.0, -3.0, 5.0]])        # two cubics, coefficients of 1, x, x², x³
    y = np.stack([np.polynomial.polynomial.polyval(x, ck) for ck in c], axis=1)
    q = np.linspace(x[0], x[-1], 41)
    want = np.stack([np.polynomial.polynomial.polyval(q, ck) for ck in c], axis=1)
    # rounding of an O(n) solve with a well-conditioned (diagonally dominant inside) system: a few hundred ulps
    np.testing.assert_allclose(cubic_spline_not_a_knot(x, y, q), want, rtol=0, atol=1e3 * n * np.finfo(float).eps * 8)


def test_equals_scipy_not_a_knot():
    x = radau_hemisphere(24).x
    rng = np.random.default_rng(3)
    y = rng.random((x.size, 3))
    q = np.linspace(x[0], x[-1], 57)
    np.testing.assert_allclose(cubic_spline_not_a_knot(x, y, q), CubicSpline(x, y, axis=0)(q),
                               rtol=0, atol=1e3 * x.size * np.finfo(float).eps)


def test_refuses_too_few_or_unsorted():
    with pytest.raises(ValueError, match="≥ 4 strictly ascending"):
        cubic_spline_not_a_knot([0, 1, 2], [0, 1, 2], [0.5])
    with pytest.raises(ValueError, match="≥ 4 strictly ascending"):
        cubic_spline_not_a_knot([0, 2, 1, 3], [0, 1, 2, 3], [0.5])
