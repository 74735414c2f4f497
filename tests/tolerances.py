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
import scipy.linalg

#: Unit roundoff of IEEE double precision.
U = np.finfo(np.float64).eps / 2


def gamma(n):
    """γ_n = n u / (1 − n u) (Higham eq. 3.5): the relative bound of a sum of n rounded products
    (elementwise for an array of counts)."""
    nu = np.asarray(n, dtype=float) * U
    if np.any(nu >= 1):
        raise ValueError(f"gamma({n}): n u >= 1, no bound")
    return nu / (1 - nu) if nu.ndim else float(nu / (1 - nu))


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


def sum_tol(n_terms: int, abs_terms, evaluations: int = 2, extra_ops: int = 0) -> np.ndarray:
    """:func:`assert_within_sum_bound`'s bound as an absolute tolerance (use with ``rtol=0``):
    ``evaluations · γ_{n_terms + extra_ops} · Σ|terms|`` elementwise (Higham eq. 3.5)."""
    return evaluations * gamma(n_terms + extra_ops) * np.abs(np.asarray(abs_terms, float))


def product_tol(*factors, evaluations: int = 2, extra_ops: int = 0) -> np.ndarray:
    """Elementwise bound of a chain product ``A1 @ A2 @ … @ Ak`` (numpy broadcasting and batching):

        |fl(A1 ⋯ Ak) − A1 ⋯ Ak| ≤ γ_{n1 + … + n_{k−1}} |A1| ⋯ |Ak|

    where n_j is the inner dimension of the j-th product (Higham §3.5, eq. 3.13, with
    (1 + γ_a)(1 + γ_b) ≤ 1 + γ_{a+b}, Lemma 3.3).  Any blocking, summation order or thread split a BLAS
    picks is covered.  ``extra_ops``: further rounded operations per element (an addition, a scaling)."""
    P = np.abs(np.asarray(factors[0], float))
    n = 0
    for A in factors[1:]:
        A = np.abs(np.asarray(A, float))
        n += A.shape[-2] if A.ndim > 1 else A.shape[-1]
        P = P @ A
    return evaluations * gamma(n + extra_ops) * P


def solve_tol(A, X, evaluations: int = 2, extra_ops: int = 0) -> np.ndarray:
    """Elementwise bound of X = A⁻¹ B solved by LU with partial pivoting (LAPACK gesv), to first order
    in u: the computed X̂ solves (A + ΔA) X̂ = B with |ΔA| ≤ γ_{3n} P|L̂||Û| (Higham Thm 9.4), hence

        |X̂ − X| ≤ γ_{3n} |A⁻¹| P|L̂||Û| |X̂|          (Higham §7.2, eq. 7.11, componentwise form).

    Batched over leading axes.  A second method with the same backward error (another pivoted LU, an
    unpivoted block inverse of a near-identity A: no growth) is ``evaluations = 2``; ``extra_ops``: the
    further rounded operations per element (e.g. n for inv(A) @ B)."""
    A = np.asarray(A, float)
    n = A.shape[-1]
    P, L, U = scipy.linalg.lu(A)
    LU = P @ (np.abs(L) @ np.abs(U))
    return evaluations * gamma(3 * n + extra_ops) * (np.abs(np.linalg.inv(A)) @ (LU @ np.abs(np.asarray(X, float))))


def adding_tol(top, R2, evaluations: int = 2) -> np.ndarray:
    """Elementwise bound of the adding equation's top reflection R = Rt + Tbt R2 (I − Rb R2)⁻¹ Ttb
    of ``top`` (a Layer: .Rt, .Ttb, .Rb, .Tbt) over a reflection R2 (paper eq. 4, flakedb.rt.basis.layer.add,
    add_reflection_only, flakedb.rt.adding.orders), to first order in u: forming
    A = I − Rb R2 errs by γ_{h+1}(I + |Rb||R2|) (eq. 3.13 and one subtraction), the solve X = A⁻¹ Ttb by
    :func:`solve_tol`'s γ_{3h} |A⁻¹| P|L||U| |X| plus |A⁻¹| δA |X|, and R = Rt + Tbt (R2 X) by
    γ_{2h+1}(|Rt| + |Tbt||R2||X|) + |Tbt||R2| δX."""
    Rt, Tbt, Rb, Ttb, R2 = (np.asarray(a, float) for a in (top.Rt, top.Tbt, top.Rb, top.Ttb, R2))
    h = Rb.shape[-1]
    A = np.eye(h) - Rb @ R2
    X = np.linalg.solve(A, np.broadcast_to(Ttb, A.shape[:-2] + Ttb.shape[-2:]))
    dA = gamma(h + 1) * (np.eye(h) + np.abs(Rb) @ np.abs(R2))
    dX = solve_tol(A, X, evaluations=1) + np.abs(np.linalg.inv(A)) @ (dA @ np.abs(X))
    aTR = np.abs(Tbt) @ np.abs(R2)
    return evaluations * (gamma(2 * h + 1) * (np.abs(Rt) + aTR @ np.abs(X)) + aTR @ dX)


def fft_tol(n_points: int, abs_norm2, evaluations: int = 2) -> float:
    """Bound on every coefficient of a radix-2-type FFT of N points (pocketfft, numpy/scipy): the computed
    ŷ = fl(F x) satisfies ‖ŷ − y‖₂ ≤ (log₂N η / (1 − log₂N η)) ‖y‖₂, η = μ + γ₄(√2 + μ), with μ ≈ u the
    accuracy of the twiddle factors (Higham Thm 24.2); ‖y‖₂ = √N ‖x‖₂.  ``abs_norm2``: ‖x‖₂ of the input
    times the scaling applied to the output (e.g. 2/N for cosine coefficients); the max norm of the error
    is at most its 2-norm."""
    k = int(np.ceil(np.log2(n_points)))
    eta = U + gamma(4) * (np.sqrt(2) + U)
    return evaluations * (k * eta / (1 - k * eta)) * np.sqrt(n_points) * float(abs_norm2)


def assert_ulps(actual, desired, k: float, scale=None):
    """|actual − desired| ≤ k ulps of ``scale`` (default: of ``desired``), elementwise, for an elementwise
    formula against its closed form (numpy's exp, log, sin… are within a few ulps; k counts the rounded
    operations between the two sides)."""
    actual, desired = np.asarray(actual), np.asarray(desired)
    tol = ulps(k, desired if scale is None else scale)
    err = np.abs(actual - desired)
    bad = ~(err <= tol)
    if np.any(bad):
        i = np.unravel_index(np.argmax(np.where(bad, err / np.maximum(np.broadcast_to(tol, err.shape), 1e-300), 0)), err.shape)
        raise AssertionError(f"{int(bad.sum())} of {err.size} elements beyond {k} ulps; worst at {i}: "
                             f"|Δ| = {err[i]:.3e} > {np.broadcast_to(tol, err.shape)[i]:.3e}")


def assert_within(actual, desired, bound, what: str = "the bound"):
    """Assert |actual − desired| ≤ bound elementwise (``bound`` broadcastable: an array from
    :func:`sum_tol`, :func:`product_tol`, :func:`solve_tol`… where ``assert_allclose`` takes scalars only)."""
    actual, desired = np.asarray(actual), np.asarray(desired)
    err = np.abs(actual - desired)
    bound = np.broadcast_to(np.asarray(bound, float), err.shape)
    bad = ~(err <= bound)
    if np.any(bad):
        i = np.unravel_index(np.argmax(np.where(bad, err / np.maximum(bound, 1e-300), 0)), err.shape)
        raise AssertionError(f"{int(bad.sum())} of {err.size} elements outside {what}; worst at {i}: "
                             f"|Δ| = {err[i]:.3e} > {bound[i]:.3e}")


#: Σ_k Σ_j |w_kj| / 24 of colour-science's Sprague polynomial coefficients (colour.algebra.SpragueInterpolator:
#: a = w_s r_s / 24, rows (2, −16, 0, 16, −2, 0) … (−5, 25, −50, 50, −25, 5)): 884 / 24.
SPRAGUE_ABS_WEIGHTS = 884 / 24
#: Σ_j |c_j| / 209 of its boundary rows (884, −1960, 3033, −2648, 1080, −180) … that pad two points at each end.
SPRAGUE_ABS_PAD = 9785 / 209


def sprague_node_tol(values, evaluations: int = 2) -> np.ndarray:
    """Bound on colour-science's Sprague interpolation of ``values`` (tabulated along axis 0) at its own
    nodes: a node is the right end of its interval (X = 1), returned as r_i + Σ_{k=1}^{5} a_k with
    a = w_s r_s / 24 (6 products, ÷ 24, 5 powers and 6 additions: γ_18), so it differs from the
    tabulated value by ≤ γ_18 (|r_i| + 884/24 · max|r| over the 6-point stencil), the two padded end
    points counting 9785/209 × the largest of the first (last) six.  The result depends on the BLAS
    kernel that evaluates w_s r_s."""
    y = np.abs(np.asarray(values, float))
    pad_lo = SPRAGUE_ABS_PAD * y[:6].max(axis=0, keepdims=True)
    pad_hi = SPRAGUE_ABS_PAD * y[-6:].max(axis=0, keepdims=True)
    r = np.concatenate([pad_lo, pad_lo, y, pad_hi, pad_hi])   # padded as colour-science pads, in magnitude
    win = np.lib.stride_tricks.sliding_window_view(r, 6, axis=0).max(axis=-1)  # win[s] = max r[s … s+5]
    # node m (padded index m + 2) is found in interval i = m + 1, stencil r[m − 1 … m + 4]; for m = 0 the
    # index −1 wraps to the last padded point
    stencil = np.concatenate([np.maximum(win[:1], pad_hi), win])
    return evaluations * gamma(18) * (y + SPRAGUE_ABS_WEIGHTS * stencil)
