"""Tolerance bands per CIELAB coordinate (flakedb.colour.bands.coordinate_bands), the shaded bands of the QC report.

Guards against: a band drawn as ±limit for a formula whose tolerance body is not a sphere (ΔE00, CMC, DIN99,
ΔE94 scale each direction differently), a band that is not where ΔE reaches the limit, a sign swapped between
the two ends, and a zero limit that bisects to a non-zero band.
"""

import numpy as np
import pytest

from flakedb.colour.bands import coordinate_bands
from flakedb.colour.tolerance import FORMULAS, parse_formula

REFS = np.array([[50.0, 10.0, -5.0], [82.0, -30.0, 60.0], [28.0, 2.0, 1.0], [65.0, 0.0, 0.0], [40.0, 45.0, 20.0]])
LIMITS = np.array([1.0, 2.0, 0.5, 1.2, 3.0])
# the bisection ends with a bracket of adjacent floats: ΔE at the edge is the limit to the float resolution of the
# step times the slope (≤ ~3, ΔE per CIELAB unit) plus the formula's own rounding (tens of operations)
RTOL = 1e-12


@pytest.mark.parametrize("key", sorted(FORMULAS))
def test_each_edge_is_where_delta_e_reaches_the_limit(key):
    f = parse_formula(key)
    b = coordinate_bands(f, REFS, LIMITS)
    assert b.shape == (len(REFS), 3, 2) and np.all(b[..., 0] < 0) and np.all(b[..., 1] > 0)
    for c in range(3):
        for s in range(2):
            edge = REFS.copy()
            edge[:, c] += b[:, c, s]
            np.testing.assert_allclose(f.delta_E(REFS, edge), LIMITS, rtol=RTOL)
            inside = REFS.copy()
            inside[:, c] += 0.99 * b[:, c, s]
            assert np.all(f.delta_E(REFS, inside) < LIMITS)


def test_closed_forms():
    """ΔE*ab: a sphere, ±limit exactly.  CMC(l:c) along L*: ΔE = |ΔL|/(l S_L) with S_L a function of the
    reference's L* only (Clarke, McDonald & Rigg 1984: S_L = 0.040975 L/(1 + 0.01765 L) for L ≥ 16, else
    0.511), so t = ±l S_L limit.  ΔE94 (graphic arts) along L*: S_L = k_L = 1, t = ±limit."""
    np.testing.assert_allclose(coordinate_bands(parse_formula("deab"), REFS, LIMITS),
                               np.broadcast_to(LIMITS[:, None, None] * [-1.0, 1.0], (len(REFS), 3, 2)), rtol=RTOL)
    L = REFS[:, 0]
    s_l = np.where(L < 16, 0.511, 0.040975 * L / (1 + 0.01765 * L))
    for l_, c_ in ((2.0, 1.0), (1.0, 1.0)):
        b = coordinate_bands(parse_formula(f"cmc:{l_:g}:{c_:g}"), REFS, LIMITS)
        np.testing.assert_allclose(b[:, 0, 1], l_ * s_l * LIMITS, rtol=RTOL)
        np.testing.assert_allclose(b[:, 0, 0], -l_ * s_l * LIMITS, rtol=RTOL)
    np.testing.assert_allclose(coordinate_bands(parse_formula("de94"), REFS, LIMITS)[:, 0], LIMITS[:, None] * [-1, 1],
                               rtol=RTOL)


def test_zero_limit_and_scalar_limit():
    assert np.all(coordinate_bands(parse_formula("de00"), REFS, 0.0) == 0.0)
    np.testing.assert_array_equal(coordinate_bands(parse_formula("de00"), REFS, 1.0),
                                  coordinate_bands(parse_formula("de00"), REFS, np.ones(len(REFS))))
