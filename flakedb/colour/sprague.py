"""Sprague (1880) interpolation of uniformly sampled data, as CIE 167:2005 §4 specifies it, as a matrix.

For samples p_0 … p_{n−1} at x_j = x_0 + j h (n ≥ 6), CIE 167:2005 (after Sprague 1880) interpolates
on each interval [x_i, x_{i+1}] by the fifth-order polynomial through the six samples p_{i−2} … p_{i+3},

    p(X) = a_0 + a_1 X + a_2 X² + a_3 X³ + a_4 X⁴ + a_5 X⁵,   X = (x − x_i) / h ∈ [0, 1],

    a_0 = p_i
    a_1 = (  2 p_{i−2} − 16 p_{i−1}           + 16 p_{i+1} −  2 p_{i+2}             ) / 24
    a_2 = (−   p_{i−2} + 16 p_{i−1} −  30 p_i + 16 p_{i+1} −    p_{i+2}             ) / 24
    a_3 = (− 9 p_{i−2} + 39 p_{i−1} −  70 p_i + 66 p_{i+1} − 33 p_{i+2} +  7 p_{i+3}) / 24
    a_4 = ( 13 p_{i−2} − 64 p_{i−1} + 126 p_i − 124 p_{i+1} + 61 p_{i+2} − 12 p_{i+3}) / 24
    a_5 = (− 5 p_{i−2} + 25 p_{i−1} −  50 p_i + 50 p_{i+1} − 25 p_{i+2} +  5 p_{i+3}) / 24,

with two samples added beyond each end by the boundary extrapolation of CIE 167:2005 (its Table 1):

    p_{−2}  = ( 884 p_0 − 1960 p_1 + 3033 p_2 − 2648 p_3 + 1080 p_4 − 180 p_5) / 209
    p_{−1}  = ( 508 p_0 −  540 p_1 +  488 p_2 −  367 p_3 +  144 p_4 −  24 p_5) / 209

and mirrored at the upper end (p_n, p_{n+1} from p_{n−1} … p_{n−6} with the same coefficients).
p(0) = p_i and p(1) = p_{i+1}: the interpolant passes through every sample.  The scheme is linear in
the samples, so evaluating it at nodes x' is a matrix: p(x') = S p with S = :func:`sprague_matrix`.
docs/colorimetry.md says where flakedb uses it (the grid → 1 nm map of the tristimulus weights).
"""

from __future__ import annotations

import numpy as np

#: Rows a_0 … a_5 of the interval polynomial, columns p_{i−2} … p_{i+3} (CIE 167:2005), times 24.
SPRAGUE_POLYNOMIAL_24 = np.array([
    [0, 0, 24, 0, 0, 0],
    [2, -16, 0, 16, -2, 0],
    [-1, 16, -30, 16, -1, 0],
    [-9, 39, -70, 66, -33, 7],
    [13, -64, 126, -124, 61, -12],
    [-5, 25, -50, 50, -25, 5],
], dtype=float)
#: Boundary extrapolation (CIE 167:2005 Table 1), times 209: p_{−2}, p_{−1} from p_0 … p_5.
SPRAGUE_BOUNDARY_209 = np.array([
    [884, -1960, 3033, -2648, 1080, -180],
    [508, -540, 488, -367, 144, -24],
], dtype=float)


def sprague_extension(n: int) -> np.ndarray:
    """E (n + 4, n): the samples with two extrapolated ones at each end, p_ext = E p (module docstring)."""
    if n < 6:
        raise ValueError(f"Sprague interpolation needs at least 6 samples, got {n}")
    E = np.zeros((n + 4, n))
    E[2:n + 2] = np.eye(n)
    B = SPRAGUE_BOUNDARY_209 / 209.0
    E[0, :6] = B[0]
    E[1, :6] = B[1]
    E[n + 2, n - 6:] = B[1, ::-1]          # p_n from p_{n-1} ... p_{n-6}
    E[n + 3, n - 6:] = B[0, ::-1]          # p_{n+1}
    return E


def sprague_matrix(x, x_new) -> np.ndarray:
    """S (len(x_new), len(x)) with p(x_new) = S p for samples p at the uniform nodes ``x`` (n ≥ 6).

    ``x_new`` must lie in [x_0, x_{n−1}] (nothing is extrapolated).  A node x_new = x_j gives the unit
    row of p_j up to rounding.  Vectorised: one (len(x_new), 6) weight table and one gather.

    Away from the ends the interpolant reproduces a quartic exactly, and it passes through the samples
    (near the ends CIE 167's extrapolation is exact for straight lines only):

    >>> x = np.arange(10.0)
    >>> x_new = np.array([2.5, 4.25, 7.0])
    >>> S = sprague_matrix(x, x_new)
    >>> p = lambda t: 1 + t - 0.3 * t**2 + 0.02 * t**3 + 0.004 * t**4
    >>> bool(np.allclose(S @ p(x), p(x_new), rtol=1e-12, atol=0)), bool(np.allclose(S.sum(axis=1), 1.0))
    (True, True)
    """
    x = np.asarray(x, dtype=float)
    xn = np.asarray(x_new, dtype=float)
    n = x.size
    if x.ndim != 1 or xn.ndim != 1:
        raise ValueError("x and x_new must be 1-D")
    E = sprague_extension(n)
    h = (x[-1] - x[0]) / (n - 1)
    if np.any(np.abs(np.diff(x) - h) > 1e-9 * abs(h)) or h <= 0:
        raise ValueError("Sprague interpolation needs strictly increasing, uniformly spaced x")
    if np.any(xn < x[0] - 1e-9 * h) or np.any(xn > x[-1] + 1e-9 * h):
        raise ValueError(f"x_new must lie in [{x[0]:g}, {x[-1]:g}]; nothing is extrapolated")
    i = np.clip(np.searchsorted(x, xn, side="left") - 1, 0, n - 2)   # interval [x_i, x_{i+1}]
    X = (xn - x[i]) / h
    powers = X[:, None] ** np.arange(6)[None, :]                      # (F, 6)
    w = powers @ (SPRAGUE_POLYNOMIAL_24 / 24.0)                       # (F, 6): weights of p_{i-2..i+3}
    rows = E[i[:, None] + np.arange(6)[None, :]]                      # (F, 6, n); ext index of p_{i-2} is i
    return np.einsum("fk,fkn->fn", w, rows)
