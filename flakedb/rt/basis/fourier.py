"""Projection of azimuth-dependent functions onto the cosine series in φ_d (docs/model.md §4).

A function g(μ_i, μ_o, φ_d) that is even and 2π-periodic in φ_d is expanded as
g = Σ_l a_l(μ_i, μ_o) cos(l φ_d).  Sampling φ_d on the N + 1 points φ_k = π k / N of [0, π] and
taking the type-I discrete cosine transform gives the a_l exactly for band-limited g (l ≤ N) and
with an aliasing error equal to the folded-back tail otherwise.  The number of samples and the
number of orders are chosen adaptively: N doubles until the coefficients stop changing to the
requested tolerance, and the series is truncated where the remaining tail is below it — never a
fixed constant (docs/model.md §3).
"""

import numpy as np


def cosine_coefficients(samples):
    """Cosine-series coefficients a_0 … a_N from samples at φ_k = π k / N, k = 0 … N (last axis).

    DCT-I: y_l = g_0 + (−1)^l g_N + 2 Σ_{k=1}^{N−1} g_k cos(π k l / N); a_l = y_l / N for
    0 < l < N and a_0 = y_0 / (2N), a_N = y_N / (2N).

    Examples
    --------
    Samples of 1 + 0.5 cos 2φ give back exactly those two coefficients:

    >>> phi = phi_samples(8)
    >>> a = cosine_coefficients(1.0 + 0.5 * np.cos(2 * phi))
    >>> a.shape, bool(np.allclose(a, [1.0, 0.0, 0.5, 0, 0, 0, 0, 0, 0], rtol=0, atol=1e-15))
    ((9,), True)
    """
    from scipy.fft import dct  # lazy: scipy.fft adds 25 ms to every import of the solver; only sampled projections need it

    samples = np.asarray(samples, dtype=float)
    n = samples.shape[-1] - 1
    if n < 1:
        raise ValueError("need at least two samples on [0, π]")
    a = dct(samples, type=1, axis=-1) / n
    a[..., 0] *= 0.5
    a[..., -1] *= 0.5
    return a


def phi_samples(n):
    """The N + 1 sample azimuths φ_k = π k / N (radians) used by :func:`cosine_coefficients`."""
    return np.pi * np.arange(n + 1) / n


def project_azimuthal(fn, mu_i, mu_o, tol=1e-5, n_start=16, n_max=16384, chunk_elems=4_000_000,
                      weights=None):
    """Cosine-series coefficients of ``fn(mu_i, mu_o, phi_d)`` on a node grid, chosen adaptively.

    Parameters
    ----------
    fn : callable ``fn(mu_i[:, None, None], mu_o[None, :, None], phi[None, None, :])`` returning an
        array of shape (C, Hi, Ho, P) or (Hi, Ho, P) (broadcastable).  Any units.
    mu_i, mu_o : (Hi,), (Ho,) cosines in the conventions' sign convention.
    tol : relative tolerance: the coefficients change by less than ``tol · s`` when the φ sampling
        is doubled, and the dropped tail Σ_{k≥L} |a_k| is below ``tol · s`` for every (μ_i, μ_o),
        where s = max over the grid of Σ_k |a_k| (a bound of |fn|).
    weights : optional (Hi, Ho) importance of each node pair (e.g. the energy a unit of ``fn``
        carries between the two nodes in the solver); errors and tails are measured on
        ``weights · a``.  Without it every pair counts alike, which lets grazing pairs (tiny
        quadrature weights, very narrow lobes in φ) dictate the order count.
    n_start : first number of φ intervals; a good first guess (e.g. from the lobe width) saves work.

    Returns
    -------
    coeffs : (L, C, Ho, Hi) array — order, channel, outgoing node, incident node (the solver's
        layout).  ``L`` is the adaptively chosen number of orders (≥ 1).
    info : dict with ``n_phi`` (largest sampling used) and ``tail`` (the relative dropped tail).
    """
    mu_i = np.asarray(mu_i, dtype=float)
    mu_o = np.asarray(mu_o, dtype=float)
    hi, ho = len(mu_i), len(mu_o)

    def evaluate(idx, n):
        phi = phi_samples(n)
        v = fn(mu_i[idx, None, None], mu_o[None, :, None], phi[None, None, :])
        v = np.asarray(v, dtype=float)
        if v.ndim == 3:
            v = v[None]
        return np.broadcast_to(v, v.shape[:1] + (len(idx), ho, n + 1))

    # Adaptive sampling is decided on the whole grid (chunked over incident nodes for memory).
    # Each round compares the coefficients from n and 2n intervals; the 2n result of one round is
    # the n result of the next, so every sampling is evaluated once.
    def coefficients(n):
        per_node = max(1, chunk_elems // max(1, ho * (n + 1)))
        return np.concatenate([cosine_coefficients(evaluate(np.arange(s, min(hi, s + per_node)), n))
                               for s in range(0, hi, per_node)], axis=1)  # (C, Hi, Ho, n+1)

    W = None if weights is None else np.asarray(weights, dtype=float)[None, :, :, None]
    n = max(2, int(n_start))
    a = coefficients(n)
    while True:
        a_prev, a = a, coefficients(2 * n)
        a_prev_w, a_w = (a_prev, a) if W is None else (a_prev * W, a * W)
        scale = np.abs(a_w).sum(axis=-1).max()
        if scale == 0.0:
            return np.zeros((1, a.shape[0], ho, hi)), {"n_phi": 2 * n, "tail": 0.0, "converged": True}
        change = np.abs(a_w[..., :n] - a_prev_w[..., :n]).max() / scale
        upper = np.abs(a_w[..., n:]).sum(axis=-1).max() / scale
        if max(change, upper) <= tol or 2 * n >= n_max:
            break
        n *= 2
    # truncation: smallest L with tail Σ_{k≥L} |a_k| ≤ tol · scale everywhere
    tails = np.flip(np.cumsum(np.flip(np.abs(a_w), axis=-1), axis=-1), axis=-1)  # tails[..., k] = Σ_{j≥k}
    worst = tails.reshape(-1, tails.shape[-1]).max(axis=0) / scale
    below = np.nonzero(worst <= tol)[0]
    L = int(below[0]) if len(below) else a.shape[-1]
    L = max(L, 1)
    coeffs = np.moveaxis(a[..., :L], -1, 0)  # (L, C, Hi, Ho)
    coeffs = np.swapaxes(coeffs, -1, -2)  # (L, C, Ho, Hi)
    info = {"n_phi": 2 * n, "tail": float(worst[L]) if L < len(worst) else 0.0,
            "converged": bool(max(change, upper) <= tol)}
    return np.ascontiguousarray(coeffs), info
