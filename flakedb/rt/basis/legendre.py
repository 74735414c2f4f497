"""Phase-function kernels on the cosine series without azimuthal quadrature (docs/store.md).

A phase function of the scattering angle, p(cos Θ), cos Θ = μ_i μ_o + s_i s_o cos φ_d
(conventions: propagation directions), has the Legendre expansion

    p(cos Θ) = Σ_k (2k + 1)/(4π) χ_k P_k(cos Θ),   χ_k = 2π ∫_{-1}^{1} p(t) P_k(t) dt   (χ_0 = 1),

and the addition theorem of spherical harmonics (e.g. Chandrasekhar 1960, §48; Arfken 12.8)

    P_k(cos Θ) = 4π/(2k + 1) [S_k^0(μ_i) S_k^0(μ_o) + 2 Σ_{m≥1} S_k^m(μ_i) S_k^m(μ_o) cos(m φ_d)],

S_k^m(μ) = √((2k+1)/(4π) (k−m)!/(k+m)!) P_k^m(μ) the orthonormal associated Legendre functions
(:func:`flakedb.rt.basis.special.sph_legendre_all`, θ = arccos μ).  So the cosine-series coefficients of the
kernel σ_s p(cos Θ) on the quadrature nodes are, for order m,

    a_m(μ_i, μ_o) = c_m σ_s Σ_{k≥m} χ_k S_k^m(μ_i) S_k^m(μ_o),   c_0 = 1, c_m = 2,

a sum of products of functions of μ_i and of μ_o: no φ sampling, no DCT.  S_k^m(−μ) = (−1)^{k+m} S_k^m(μ)
gives the reflection block.

The moments of a tabulated p (linear interpolation in cos Θ, as :class:`flakedb.rt.scattering.media.PhaseMedium`
evaluates it) are exact: χ = 2π p @ Hᵀ with H[k, j] = ∫ hat_j(t) P_k(t) dt computed once per grid by
per-segment Gauss–Legendre quadrature of degree ≥ k + 1 (:func:`hat_legendre_matrix`).  The series is
truncated at the first K whose dropped tail Σ_{k>K} (2k+1)/(4π) |χ_k| is ≤ ``tol`` × Σ_k (2k+1)/(4π) |χ_k|
(a bound of max p) for every channel.  Measured on the catalogue's pigments (380–780 nm, 0.5° table):
K = 38–53 at 1e-6, the tail from the table's kinks ~1e-8 beyond.
"""

from functools import lru_cache

import numpy as np
from numpy.polynomial.legendre import leggauss

from flakedb.rt.basis.special import sph_legendre_all

#: Truncation of the Legendre series (relative dropped tail, see the module docstring).
LEGENDRE_TOL = 1e-6
#: Largest Legendre degree considered.
LEGENDRE_K_MAX = 512


def hat_legendre_matrix(cos_grid, K):
    """H (K + 1, T): H[k, j] = ∫_{-1}^{1} hat_j(t) P_k(t) dt for the hat functions of the ascending
    grid ``cos_grid`` (T,) (the piecewise-linear interpolant of values v is Σ_j v_j hat_j).  Exact to
    rounding: on each segment the integrand is a polynomial of degree k + 1, integrated by
    Gauss–Legendre with K/2 + 2 nodes."""
    return _hat_legendre_matrix(tuple(np.asarray(cos_grid, dtype=float).tolist()), int(K)).copy()


@lru_cache(maxsize=8)
def _hat_legendre_matrix(grid, K):
    t = np.asarray(grid)
    g, wg = leggauss(K // 2 + 2)
    a, b = t[:-1], t[1:]
    pts = 0.5 * (b - a)[:, None] * (g[None] + 1.0) + a[:, None]  # (S, G)
    ww = 0.5 * (b - a)[:, None] * wg[None]
    lam = (pts - a[:, None]) / (b - a)[:, None]  # hat of the right node on the segment
    wl, wr = ww * (1.0 - lam), ww * lam
    H = np.zeros((K + 1, t.size))
    p_prev, p = np.zeros_like(pts), np.ones_like(pts)
    for k in range(K + 1):
        if k >= 1:  # Bonnet: (k) P_k = (2k − 1) t P_{k−1} − (k − 1) P_{k−2}
            p_prev, p = p, ((2 * k - 1) * pts * p - (k - 1) * p_prev) / k
        H[k, :-1] += (wl * p).sum(axis=1)
        H[k, 1:] += (wr * p).sum(axis=1)
    return H


def legendre_moments(cos_grid, table, tol=LEGENDRE_TOL, k_max=LEGENDRE_K_MAX):
    """χ_k (C, K + 1) of the piecewise-linear phase functions ``table`` (C, T) on ``cos_grid`` (T,)
    (1/sr, cos Θ ascending, 1 forward), truncated at the tail criterion of the module docstring.

    Returns ``(chi, info)``; ``info``: ``degree`` K, ``tail`` (relative dropped tail), ``converged``
    (False when ``k_max`` was reached first)."""
    table = np.atleast_2d(np.asarray(table, dtype=float))
    K = 64
    while True:
        chi = 2.0 * np.pi * table @ hat_legendre_matrix(cos_grid, K).T  # (C, K + 1)
        term = np.abs(chi) * (2 * np.arange(K + 1) + 1) / (4.0 * np.pi)
        scale = term.sum(axis=1)
        scale = np.where(scale > 0, scale, 1.0)
        tails = np.flip(np.cumsum(np.flip(term, axis=1), axis=1), axis=1) / scale[:, None]
        worst = np.concatenate([tails.max(axis=0)[1:], [0.0]])  # worst[k] = tail beyond degree k
        ok = np.nonzero(worst <= tol)[0]
        if (len(ok) and ok[0] < K // 2) or K >= k_max:
            deg = int(ok[0]) if len(ok) else K
            return chi[:, : deg + 1], {"degree": deg, "tail": float(worst[deg]), "converged": bool(len(ok)) and deg < K}
        K = min(2 * K, int(k_max))


def normalized_legendre(x, K, M):
    """S_k^m(x_j) for k ≤ K, 0 ≤ m ≤ M: array (M + 1, K + 1, len(x)), zero for k < m (module docstring)."""
    theta = np.arccos(np.clip(np.asarray(x, dtype=float), -1.0, 1.0))
    M = min(int(M), int(K))
    return sph_legendre_all(int(K), M, theta)


class LegendreKernel:
    """The projected kernel of σ_s p(cos Θ) on the nodes ``x`` (h,) by the addition theorem: the
    :class:`flakedb.rt.scattering.projection.ProjectedKernel` interface (``n_orders``, ``channels``,
    ``blocks(l0, l1)``, ``scale``) with the blocks formed on demand.

    ``chi`` (C, K + 1) the Legendre moments, ``sigma_s`` (C,) in 1/µm (the kernel is σ_s p, in
    1/(µm·sr)); ``max_orders`` caps the order count (orders ≥ K + 1 are exactly zero).
    """

    def __init__(self, x, chi, sigma_s, max_orders=None, scale=None):
        self.x = np.asarray(x, dtype=float)
        self.chi = np.atleast_2d(np.asarray(chi, dtype=float))
        self.sigma_s = np.broadcast_to(np.atleast_1d(np.asarray(sigma_s, dtype=float)), (self.chi.shape[0],))
        self.K = self.chi.shape[1] - 1
        L = self.K + 1
        self._L = L if max_orders is None else min(L, int(max_orders))
        self.scale = scale
        self._S = None

    @property
    def n_orders(self):
        return self._L

    @property
    def channels(self):
        return self.chi.shape[0]

    def channel_subset(self, idx):
        """The kernel of channels ``idx`` (their moments, σ_s and scale; the Legendre functions shared)."""
        rows = lambda a: a if a.shape[0] == 1 else a[idx]
        k = LegendreKernel(self.x, rows(self.chi), rows(self.sigma_s), max_orders=self._L,
                           scale=None if self.scale is None else rows(self.scale))
        k._S = self._S
        return k

    def _legendre(self):
        if self._S is None:
            self._S = normalized_legendre(self.x, self.K, self._L - 1)  # (L, K + 1, h)
        return self._S

    def blocks(self, l0=0, l1=None):
        """(K_T, K_R), each (l1 − l0, C, h, h) [order, channel, outgoing, incident] in 1/(µm·sr).

        a_m[o, i] = c_m Σ_{k ≥ m} w_k S_k^m(μ_o) S_k^m(μ_i), w = σ_s χ (S_k^m = 0 for k < m), and for
        reflection S_k^m(−μ_o) = (−1)^{k+m} S_k^m(μ_o): with E and O the sums over k + m even and odd,
        K_T = c_m (E + O) and K_R = c_m (E − O).  Orders of one parity share the parity split of k, and a
        group of orders starts its sums at its smallest m: half the products of summing all k twice."""
        l1 = self._L if l1 is None else int(l1)
        h, C = self.x.size, self.channels
        K_T = np.zeros((max(0, l1 - l0), C, h, h))
        K_R = np.zeros_like(K_T)
        k1 = min(l1, self._L)
        if k1 > l0:
            S = self._legendre()  # (L, K + 1, h)
            w = self.sigma_s[:, None] * self.chi  # (C, K + 1)
            for parity in (0, 1):
                ms = np.arange(l0 + (parity - l0) % 2, k1, 2)  # the orders m ≡ parity (mod 2)
                # a group's temporaries (its orders × C × K/2 × h) bounded to ~32 MB
                g = max(1, min(16, (4 << 20) // max(1, C * (self.K + 1) * h // 2)))
                for c0 in range(0, ms.size, g):
                    mm = ms[c0:c0 + g]
                    k0 = int(mm[0])  # S_k^m = 0 for k < m ≤ every m of the group
                    Sg = S[mm]  # (g, K + 1, h)
                    sums = []
                    for ks in (slice(k0, None, 2), slice(k0 + 1, None, 2)):  # k + m even (E), odd (O)
                        Sk = Sg[:, ks]  # (g, n_k, h)
                        if Sk.shape[1] == 0:
                            sums.append(0.0)
                            continue
                        A = Sk[:, None] * w[None, :, ks, None]  # (g, C, n_k, h)
                        sums.append(np.swapaxes(Sk, 1, 2)[:, None] @ A)  # (g, C, h, h)
                    E, O = sums
                    cm = np.where(mm == 0, 1.0, 2.0)[:, None, None, None]
                    K_T[mm - l0] = cm * (E + O)
                    K_R[mm - l0] = cm * (E - O)
        if self.scale is not None:
            s = self.scale  # (C', h): s_o K[o, i] s_i
            f = s[None, :, :, None] * s[None, :, None, :]
            K_T *= f
            K_R *= f
        return K_T, K_R


def legendre_moments_gauss(nodes, weights, values, tol=LEGENDRE_TOL, k_max=LEGENDRE_K_MAX):
    """χ_k (C, K + 1) of phase functions given at Gauss–Legendre ``nodes`` (G,) with ``weights`` (G,)
    on [−1, 1] (``values`` (C, G) in 1/sr): χ_k = 2π Σ_g w_g p(t_g) P_k(t_g), exact for the smooth p
    up to the rule's degree (use G > k_max).  Truncated as :func:`legendre_moments`.

    The Henyey–Greenstein phase function has the moments χ_k = g^k, and its series gives it back:

    >>> from flakedb.rt.scattering.microflake import phase_HG
    >>> t, w = np.polynomial.legendre.leggauss(64)
    >>> chi, info = legendre_moments_gauss(t, w, phase_HG(t, 0.5))
    >>> bool(np.allclose(chi[0, :6], 0.5 ** np.arange(6), rtol=0, atol=1e-12)), info["converged"]
    (True, True)
    >>> t2 = np.array([0.3, -0.7])
    >>> bool(np.allclose(legendre_series(chi, t2)[0], phase_HG(t2, 0.5), rtol=1e-5, atol=0))
    True
    """
    values = np.atleast_2d(np.asarray(values, dtype=float))
    t = np.asarray(nodes, dtype=float)
    K = min(int(k_max), len(t) - 1)
    P = np.empty((K + 1, t.size))
    P[0] = 1.0
    if K >= 1:
        P[1] = t
    for k in range(2, K + 1):
        P[k] = ((2 * k - 1) * t * P[k - 1] - (k - 1) * P[k - 2]) / k
    chi = 2.0 * np.pi * (values * np.asarray(weights, dtype=float)[None]) @ P.T  # (C, K + 1)
    return truncate_legendre(chi, tol)


def truncate_legendre(chi, tol=LEGENDRE_TOL):
    """Moments ``chi`` (C, K + 1) truncated at the first degree whose dropped tail is ≤ ``tol`` (module
    docstring); returns ``(chi, info)`` as :func:`legendre_moments` (``converged`` False when the cut is
    at the last given degree K: the tail beyond K is not known)."""
    chi = np.atleast_2d(np.asarray(chi, dtype=float))
    K = chi.shape[1] - 1
    term = np.abs(chi) * (2 * np.arange(K + 1) + 1) / (4.0 * np.pi)
    scale = term.sum(axis=1)
    scale = np.where(scale > 0, scale, 1.0)
    tails = np.flip(np.cumsum(np.flip(term, axis=1), axis=1), axis=1) / scale[:, None]
    worst = np.concatenate([tails.max(axis=0)[1:], [0.0]])  # worst[k]: relative tail beyond degree k
    ok = np.nonzero(worst <= tol)[0]
    deg = int(ok[0]) if len(ok) else K
    return chi[:, : deg + 1], {"degree": deg, "tail": float(worst[deg]), "converged": bool(len(ok)) and deg < K}


def legendre_series(chi, t):
    """p(t) = Σ_k (2k + 1)/(4π) χ_k P_k(t) for moments ``chi`` (C, K + 1) at cosines ``t`` (T,) → (C, T)."""
    chi = np.atleast_2d(np.asarray(chi, dtype=float))
    t = np.asarray(t, dtype=float)
    K = chi.shape[1] - 1
    out = np.zeros((chi.shape[0], t.size))
    p_prev, p = np.zeros_like(t), np.ones_like(t)
    for k in range(K + 1):
        if k >= 1:
            p_prev, p = p, ((2 * k - 1) * t * p - (k - 1) * p_prev) / k
        out += ((2 * k + 1) / (4.0 * np.pi) * chi[:, k])[:, None] * p[None]
    return out
