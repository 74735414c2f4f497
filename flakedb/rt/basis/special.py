"""The few special functions the solver's every run needs, on numpy alone (docs/model.md §4, "Imports").

``scipy.special`` takes 0.15 s to import (measured, scipy 1.17 on the 2-core machine: its array-API
layer imports ``numpy.testing``, ``numpy.f2py``, ``numpy.random`` and ``numpy.ma``), a fifth of the
whole-process budget of a rough-coat solve (issue #11).  Every solve needs a Gauss–Radau rule, a rough
interface needs erf (Smith masking), a phase function needs the normalised associated Legendre
functions; they are here, each tested against ``scipy.special`` to rounding (tests/rt/test_special.py).
Gauss–Legendre rules are numpy's own (``numpy.polynomial.legendre.leggauss``).  Rarer functions (``ive`` for a von Mises–Fisher phase function or flake) stay
with scipy, imported where they are used.

* :func:`erf`, :func:`smith_masking_denominator`: the rational approximations of the Cephes Math
  Library (S. L. Moshier, ``ndtr.c``, Cephes 2.8, 2000; public domain, the same ones scipy compiles),
  relative error ≤ 2e-16 on [0, ∞) by Cephes' own statement and ≤ 4e-16 against scipy in the tests.
* :func:`gauss_jacobi`: Golub & Welsch (Math. Comp. 23, 221 (1969)): nodes as the eigenvalues of the
  Jacobi matrix of the recurrence, weights from the orthonormal polynomials at the nodes (Christoffel
  numbers, accurate where eigenvector components lose relative precision).
* :func:`sph_legendre_all`: the standard recurrence for orthonormal associated Legendre functions
  (e.g. Holmes & Featherstone, J. Geodesy 76, 279 (2002), eq. 11–13), Condon–Shortley phase as scipy.
"""

import math

import numpy as np

# Cephes ndtr.c: erf(x) = x T(x²)/U(x²) for |x| < 1 and erfc(x) = e^{−x²} P(x)/Q(x) for 1 ≤ x < 8
# (coefficients highest degree first, U and Q with their leading 1).  Beyond x = 6 erf is 1 in double
# precision, so Cephes' third range (x ≥ 8) is not needed.
_T = (9.60497373987051638749E0, 9.00260197203842689217E1, 2.23200534594684319226E3,
      7.00332514112805075473E3, 5.55923013010394962768E4)
_U = (1.0, 3.35617141647503099647E1, 5.21357949780152679795E2, 4.59432382970980127987E3,
      2.26290000613890934246E4, 4.92673942608635921086E4)
_P = (2.46196981473530512524E-10, 5.64189564831068821977E-1, 7.46321056442269912687E0,
      4.86371970985681366614E1, 1.96520832956077098242E2, 5.26445194995477358631E2,
      9.34528527171957607540E2, 1.02755188689515710272E3, 5.57535335369399327526E2)
_Q = (1.0, 1.32281951154744992508E1, 8.67072140885989742329E1, 3.54937778887819891062E2,
      9.75708501743205489753E2, 1.82390916687909736289E3, 2.24633760818710981792E3,
      1.65666309194161350182E3, 5.57535340817727675546E2)


def _poly(x, coef):
    """Horner's rule, coefficients highest degree first (in place: one array)."""
    y = np.full_like(x, coef[0])
    for c in coef[1:]:
        y *= x
        y += c
    return y


def erf(x):
    """The error function, elementwise (float64); odd, ±1 beyond |x| ≈ 6."""
    x = np.asarray(x, dtype=float)
    a = np.abs(x)
    out = np.ones_like(a)  # erfc(6) e^{36} < 1e-16 e^{36}·e^{−36}: erf is 1 to double precision beyond 6
    small = a < 1.0
    if small.any():
        z = a[small] ** 2
        out[small] = a[small] * _poly(z, _T) / _poly(z, _U)
    mid = (a >= 1.0) & (a < 6.0)
    if mid.any():
        am = a[mid]
        out[mid] = 1.0 - np.exp(-am * am) * _poly(am, _P) / _poly(am, _Q)
    np.copysign(out, x, out=out)
    out[np.isnan(x)] = np.nan
    return out


def smith_masking_denominator(a):
    """1 + erf(a) + e^{−a²}/(a √π) for a > 0 (the denominator of the Beckmann Smith G1, Walter et al.
    2007 eq. 27), without cancellation: 2 + e^{−a²} (1/(a √π) − erfc(a) e^{a²}) for a ≥ 1, which is 2 to
    double precision beyond a = 6 (the bracket is ≈ 1/(2a³√π) there)."""
    a = np.asarray(a, dtype=float)
    out = np.full(a.shape, 2.0)
    small = a < 1.0
    if small.any():
        s = a[small]
        with np.errstate(divide="ignore", invalid="ignore"):
            out[small] = 1.0 + erf(s) + np.exp(-s * s) / (s * math.sqrt(math.pi))
    mid = (a >= 1.0) & (a < 6.0)
    if mid.any():
        m = a[mid]
        out[mid] = 2.0 + np.exp(-m * m) * (1.0 / (m * math.sqrt(math.pi)) - _poly(m, _P) / _poly(m, _Q))
    return out


def gauss_jacobi(n, alpha, beta):
    """Gauss–Jacobi nodes and weights for ∫_{−1}^{1} (1 − t)^α (1 + t)^β g(t) dt, α, β > −1, ascending;
    exact for polynomials g of degree ≤ 2n − 1 (Golub–Welsch, module docstring).

    Three nodes integrate (1 − t) t⁵ exactly (degree 2n − 1): ∫_{−1}^{1} (1 − t) t⁵ dt = −2/7.

    >>> t, w = gauss_jacobi(3, 1.0, 0.0)
    >>> round(float(np.sum(w * t**5)), 14) == round(-2 / 7, 14)
    True
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"gauss_jacobi needs n ≥ 1 nodes, got {n}")
    a, b = float(alpha), float(beta)
    k = np.arange(n, dtype=float)
    s = 2.0 * k + a + b
    with np.errstate(divide="ignore", invalid="ignore"):
        diag = np.where(s * (s + 2.0) != 0.0, (b * b - a * a) / (s * (s + 2.0)), (b - a) / (a + b + 2.0))
    diag[0] = (b - a) / (a + b + 2.0)
    kk = k[1:]
    s1 = s[1:]
    off = np.sqrt(4.0 * kk * (kk + a) * (kk + b) * (kk + a + b) / (s1 * s1 * (s1 + 1.0) * (s1 - 1.0)))
    J = np.diag(diag) + np.diag(off, 1) + np.diag(off, -1)
    t = np.linalg.eigvalsh(J)
    mu0 = 2.0 ** (a + b + 1.0) * math.gamma(a + 1.0) * math.gamma(b + 1.0) / math.gamma(a + b + 2.0)
    # Christoffel numbers: w_j = μ0 / Σ_k p_k(t_j)² with p_k the orthonormal polynomials of the recurrence
    # t p_k = off_{k+1} p_{k+1} + diag_k p_k + off_k p_{k−1}, p_0 = 1
    p_prev = np.zeros_like(t)
    p = np.ones_like(t)
    total = np.ones_like(t)
    for j in range(n - 1):
        p_next = ((t - diag[j]) * p - (off[j - 1] if j > 0 else 0.0) * p_prev) / off[j]
        p_prev, p = p, p_next
        total += p * p
    return t, mu0 / total


def sph_legendre_all(K, M, theta):
    """Orthonormal associated Legendre functions S_k^m(cos θ) = √((2k+1)/(4π) (k−m)!/(k+m)!) P_k^m(cos θ)
    for 0 ≤ m ≤ M, 0 ≤ k ≤ K (Condon–Shortley phase, as ``scipy.special.sph_legendre_p``; zero for
    k < m): array (M + 1, K + 1) + θ.shape.  Sectoral start S_m^m = −√((2m+1)/(2m)) sin θ S_{m−1}^{m−1},
    S_0^0 = 1/√(4π); then S_{m+1}^m = √(2m+3) cos θ S_m^m and, for k ≥ m + 2,
    S_k^m = a_k^m (cos θ S_{k−1}^m − S_{k−2}^m / a_{k−1}^m), a_k^m = √((4k² − 1)/(k² − m²))."""
    K, M = int(K), min(int(M), int(K))
    theta = np.asarray(theta, dtype=float)
    x, y = np.cos(theta), np.sin(theta)
    out = np.zeros((M + 1, K + 1) + theta.shape)
    m = np.arange(M + 1, dtype=float)
    # sectoral values S_m^m for every m (a cumulative product over m)
    fac = np.concatenate([[1.0 / math.sqrt(4.0 * math.pi)], -np.sqrt((2.0 * m[1:] + 1.0) / (2.0 * m[1:]))])
    sect = np.cumprod(fac)[(...,) + (None,) * theta.ndim] * y[None] ** m[(...,) + (None,) * theta.ndim]
    mi = np.arange(M + 1)
    out[mi, mi] = sect
    if K >= 1:
        mm = mi[mi + 1 <= K]
        out[mm, mm + 1] = np.sqrt(2.0 * m[mm, None] + 3.0).reshape((-1,) + (1,) * theta.ndim) * x[None] * sect[mm]
    for k in range(2, K + 1):  # three-term recurrence in k, all m ≤ k − 2 at once
        ms = m[: min(M, k - 2) + 1]
        if ms.size == 0:
            continue
        a_k = np.sqrt((4.0 * k * k - 1.0) / (k * k - ms * ms)).reshape((-1,) + (1,) * theta.ndim)
        a_k1 = np.sqrt((4.0 * (k - 1) ** 2 - 1.0) / ((k - 1) ** 2 - ms * ms)).reshape((-1,) + (1,) * theta.ndim)
        n = ms.size
        out[:n, k] = a_k * (x[None] * out[:n, k - 1] - out[:n, k - 2] / a_k1)
    return out
