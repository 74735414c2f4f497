"""Float tolerances from the arithmetic, not from one machine's run (issue #21).

A result computed two ways agrees to within the rounding of the operations between them.  For a sum
of ``n`` products (a dot product, a matrix product, an einsum contraction, a quadrature) the classical
bound (Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed., §3.1, eq. 3.5) is

    |fl(Σ a_i b_i) − Σ a_i b_i| ≤ γ_n Σ |a_i b_i|,    γ_n = n u / (1 − n u),  u = 2⁻⁵³,

whatever the summation order, blocking or thread count a BLAS picks: the bound is relative to the sum
of the absolute terms, not to the result, which may cancel.  Two evaluations of the same quantity
(e.g. a BLAS product against an einsum) each carry that error, so their difference is bounded by
twice it.  Elementwise numpy functions (exp, log, sqrt…) are correctly rounded or within a few ulps;
:func:`ulps` states those bounds.
"""

from __future__ import annotations

import numpy as np

#: Unit roundoff of IEEE double precision.
U = np.finfo(np.float64).eps / 2


def gamma(n: int) -> float:
    """γ_n = n u / (1 − n u) (Higham eq. 3.5): the relative bound of a sum of n rounded products."""
    nu = n * U
    if nu >= 1:
        raise ValueError(f"gamma({n}): n u >= 1, no bound")
    return nu / (1 - nu)


def ulps(k: float, scale) -> np.ndarray:
    """k units in the last place of ``scale`` (an absolute tolerance)."""
    return k * np.finfo(np.float64).eps * np.abs(np.asarray(scale, dtype=float))


def assert_within_sum_bound(actual, desired, n_terms: int, abs_terms, evaluations: int = 2, extra_ops: int = 0):
    """Assert ``|actual − desired| ≤ evaluations · γ_{n_terms + extra_ops} · abs_terms`` elementwise.

    ``abs_terms``: Σ|a_i b_i| of each element (broadcastable), i.e. the same computation on absolute
    values; ``evaluations``: how many of the two sides carry a rounding of that size (2 for two ways
    of computing one quantity, 1 against an exact value); ``extra_ops``: further rounded operations
    per element (a division, a final scaling).
    """
    actual, desired = np.asarray(actual, float), np.asarray(desired, float)
    bound = evaluations * gamma(n_terms + extra_ops) * np.asarray(abs_terms, float)
    err = np.abs(actual - desired)
    bad = err > bound
    if np.any(bad):
        i = np.unravel_index(np.argmax(np.where(bad, err / np.maximum(bound, 1e-300), 0)), err.shape)
        raise AssertionError(f"{int(bad.sum())} of {err.size} elements outside the rounding bound; worst at {i}: "
                             f"|Δ| = {err[i]:.3e} > {bound[i]:.3e} (γ_{n_terms + extra_ops} × {evaluations} × Σ|terms|)")
