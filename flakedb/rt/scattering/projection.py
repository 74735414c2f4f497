"""Projection of a medium's kernel through its spectral basis, once for all channels (docs/projection.md).

A medium's kernel is linear in what varies with wavelength (paper eq. 2: a flake's R(c); a
pigment's σ_s p(cos Θ)), so k_c = Σ_b M[c, b] k_b with a few basis kernels k_b
(:class:`flakedb.rt.scattering.media.KernelBasis`).  The cosine-series projection (docs/model.md §4,
:mod:`flakedb.rt.basis.fourier`) is linear too: the basis kernels are sampled and transformed once and every
channel's coefficients are M times theirs.  :func:`project_kernel_basis` applies exactly the adaptive
criteria of :func:`flakedb.rt.basis.fourier.project_azimuthal` to the C channel combinations (computed in
chunks, never stored whole), and :class:`ProjectedKernel` hands out the channel coefficients of any
range of orders on demand, so a solver that chooses its order count from the physics only builds the
orders it uses.
"""

import numpy as np

from flakedb.rt.basis.fourier import cosine_coefficients, phi_samples
from flakedb.rt.common.reuse import active_cache, array_key


def _combine(M, a):
    """(C, B) @ (B, …) → (C, …); ``M`` None means the identity (the basis *is* the channels)."""
    if M is None:
        return a
    return (M @ a.reshape(a.shape[0], -1)).reshape((M.shape[0],) + a.shape[1:])


def _chunks(hi, per):
    return [slice(s, min(hi, s + per)) for s in range(0, hi, per)]


#: Memory [bytes] a projection's φ samples and coefficients may take before it handles its incident
#: nodes in chunks (:func:`project_kernel_basis`).  Measured: direct tri-coat pearl white held 1.3 GB
#: at n = 64 but 9.8 GB at n = 128 (B × h × 2h × (n_φ + 1) float64, 4–5 of them); 3 GiB sent the
#: 3-species basecoat at n = 200 (3.5 GB in memory) into chunks, 23 s → 38 s.  Issue 26 (every catalogue
#: recipe at n = 128 within 3 GB, a 4 GB machine): 1 GiB.  Particle pearlescent at n = 128 (B = 41):
#: 4.27 → 2.67 GB peak, CPU 18 → 24.5 s, colours identical (ΔE00 0).  A caller may pass ``budget_bytes``.
PROJECTION_BUDGET_BYTES = 1 * 2**30

#: Orders of a projection over its memory budget kept in memory (:class:`ChunkedCoefficients`); higher
#: orders are evaluated again when a solver asks for them.  The order choice of an opaque stack solves
#: blocks of 8, then as far as its decay predicts (:data:`flakedb.rt.adding.order_blocks.FIRST_ORDER_BLOCK`) and stops where
#: its BSDF's tail is within the order tolerance: 11–31 orders for every catalogue recipe at n = 128
#: (docs/cost-model.md), while the projection of a kernel that never converges at grazing pairs carries
#: up to the cap 2n = 256.  Particle pearlescent at n = 128 (B = 41 basis kernels): the 256 orders held
#: 1.3 GB, the 64 kept 0.33 GB.
RESIDENT_ORDERS = 64


def project_kernel_basis(fn, M, mu_i, mu_o, tol=1e-5, n_start=16, n_max=16384, weights=None,
                         chunk_elems=250_000, budget_bytes=None, max_orders=None, resident_orders=None, parts=None):
    """Cosine coefficients of the C functions Σ_b M[c, b] fn_b(μ_i, μ_o, φ_d), kept per basis function.

    ``fn(mu_i[:, None, None], mu_o[None, :, None], phi[None, None, :])`` → (B, Hi, Ho, P);
    ``M`` (C, B) or None (then B = C and the basis functions are the channels).  ``tol``,
    ``n_start``, ``n_max`` and ``weights`` (Hi, Ho) as in :func:`flakedb.rt.basis.fourier.project_azimuthal`,
    whose criteria are applied unchanged to the C combinations: the φ sampling doubles until the
    combined coefficients change by ≤ tol · s and the upper half carries ≤ tol · s, and the series is
    truncated at the first L whose dropped tail Σ_{k≥L} |a_k| ≤ tol · s for every channel and node
    pair (s = max over channels and pairs of Σ_k |a_k|, all on ``weights`` · a).

    Returns ``(coeffs, info)``: ``coeffs`` (L, B, Ho, Hi) — order, basis function, outgoing node,
    incident node — and ``info`` with ``n_phi``, ``tail``, ``converged`` like ``project_azimuthal``.

    Memory: a round keeps every pair's samples and coefficients (about 5 × B·Hi·Ho·(n_φ + 1) float64).
    When the next round would exceed ``budget_bytes`` (default :data:`PROJECTION_BUDGET_BYTES`), the
    rounds continue on chunks of incident nodes (:meth:`_BasisProjection.row_chunks`): the criteria are
    maxima over node pairs, so they are gathered chunk by chunk, each chunk's samples evaluated afresh
    each round (the coarser round's coefficients are those of its even samples), and the kept orders are
    kept from the last round's chunks.  Same azimuths, same values, same result (tested); about 2× the
    kernel evaluations, memory bounded by the budget.  ``max_orders`` caps the order count L (the tail in
    ``info`` is that of the uncapped count, as before).  With ``resident_orders`` (the solver passes
    :data:`RESIDENT_ORDERS`), a chunked projection keeps only its first orders and its last one in memory
    and returns a :class:`ChunkedCoefficients`, which evaluates the others again when asked.

    ``parts`` (:attr:`flakedb.rt.scattering.media.KernelBasis.parts`, the basis as keyed groups): inside a fit's
    :func:`flakedb.rt.common.reuse.reusing` scope each group's coefficients at a sampling (and its samples at
    φ_d = 0, π) are taken from the fit's cache when an earlier evaluation computed them, else computed and
    kept there; the criteria, M's combinations and the truncation are applied afresh, so the result is the
    uncached one (the transform acts on each basis kernel alone).  Not used over the memory budget.

    A kernel μ_i μ_o (1 + ½ cos φ) has two orders, a_0 = μ_i μ_o and a_1 = ½ μ_i μ_o:

    >>> mu = np.array([0.3, 1.0])
    >>> c, info = project_kernel_basis(lambda mi, mo, phi: (mi * mo * (1 + 0.5 * np.cos(phi)))[None], None, mu, mu)
    >>> c.shape, info["converged"]                              # (L, B, Ho, Hi)
    ((2, 1, 2, 2), True)
    >>> bool(np.allclose(c[:, 0], [np.outer(mu, mu), 0.5 * np.outer(mu, mu)], rtol=0, atol=1e-14))
    True
    """
    pr = _BasisProjection(fn, M, mu_i, mu_o, tol, n_max, weights, chunk_elems, budget_bytes, parts)
    n = max(2, int(n_start))
    B = pr.M.shape[1] if pr.M is not None else pr.evaluate(np.zeros(1), slice(0, 1)).shape[0]
    if 5 * 8 * B * pr.hi * pr.ho * (2 * n + 1) > pr.budget:  # the first round is already over the budget
        return pr.row_chunks(n, B, max_orders, resident_orders)
    a = pr.coefficients(n)
    while True:
        if 5 * 8 * a.shape[0] * pr.hi * pr.ho * (2 * n + 1) > pr.budget:
            pr.samples.clear()
            pr.part_samples.clear()
            return pr.row_chunks(n, a.shape[0], max_orders, resident_orders)
        a_prev, a = a, pr.coefficients(2 * n)
        scale, change, upper = pr.stats(a, a_prev, n)
        if scale == 0.0:
            return np.zeros((1, a.shape[0], pr.ho, pr.hi)), {"n_phi": 2 * n, "tail": 0.0, "converged": True}
        change /= scale
        upper /= scale
        if max(change, upper) <= tol or 2 * n >= n_max:
            break
        n *= 2
    pr.samples.clear()
    pr.part_samples.clear()
    coeffs, info = pr.truncate(a, scale, {"n_phi": 2 * n, "converged": bool(max(change, upper) <= tol)})
    return (coeffs if max_orders is None else coeffs[:max_orders]), info


class _BasisProjection:
    """The state of one :func:`project_kernel_basis` call: the kernel, its basis and the samples kept
    between rounds.

    The criteria act on the C channel combinations.  M None: exact, on the channels themselves.  With a
    basis (B < C typically), the combinations are never formed on all samples: with
    μ_b = max_c |M[c, b]|, |Σ_b M[c, b] x_b| ≤ Σ_b μ_b |x_b| bounds every numerator (exact for
    B = 1), and the scale s is bounded from below by the combinations' values at φ_d = 0 and π and
    their order-0 coefficients (|g(φ)| ≤ Σ_k |a_k|; kernels peak at φ_d = 0: mirror reflection,
    forward scattering).  So the sampling and the order count are at least those the exact
    criteria would choose, at B/C of the cost (docs/projection.md)."""

    def __init__(self, fn, M, mu_i, mu_o, tol, n_max, weights, chunk_elems, budget_bytes, parts=None):
        self.fn, self.tol, self.n_max, self.chunk_elems = fn, tol, n_max, chunk_elems
        self.budget = float(PROJECTION_BUDGET_BYTES if budget_bytes is None else budget_bytes)
        self.mu_i = np.asarray(mu_i, dtype=float)
        self.mu_o = np.asarray(mu_o, dtype=float)
        self.hi, self.ho = len(self.mu_i), len(self.mu_o)
        self.M = None if M is None else np.atleast_2d(np.asarray(M, dtype=float))
        self.W = (np.ones((self.hi, self.ho)) if weights is None else
                  np.broadcast_to(np.asarray(weights, dtype=float), (self.hi, self.ho)))
        self.mu_b = None if self.M is None else np.abs(self.M).max(axis=0)
        self.samples = {}
        # the fit's cache (flakedb.rt.common.reuse) and the keyed groups of the basis, when both exist
        self.cache = active_cache() if parts else None
        self.parts = parts
        self.part_samples = {}
        if self.cache is not None:
            self.grid = (array_key(self.mu_i), array_key(self.mu_o))

    def evaluate(self, phi, rows=slice(None), fn=None):
        """Kernel samples (B, rows, Ho, len(phi)), in chunks of ``chunk_elems`` (of ``fn``, default the
        whole basis)."""
        fn = self.fn if fn is None else fn
        idx = np.arange(self.hi)[rows]
        ho = self.ho
        out = None
        for sl in _chunks(idx.size, max(1, 4 * self.chunk_elems // max(1, ho * len(phi)))):
            r = idx[sl]
            v = np.asarray(fn(self.mu_i[r, None, None], self.mu_o[None, :, None], phi[None, None, :]), dtype=float)
            if v.ndim == 3:
                v = v[None]
            if out is None:
                out = np.empty((v.shape[0], idx.size, ho, len(phi)))
            out[:, sl] = v
        return out

    def coefficients(self, n):
        """Basis coefficients (B, Hi, Ho, n + 1); the samples of n/2 intervals are the even ones of n,
        so each round evaluates only the new (odd) azimuths.  With the fit's cache: :meth:`cached_coefficients`."""
        if self.cache is not None:
            return self.cached_coefficients(n)
        v = self._samples(n, self.samples.pop(n // 2, None) if n % 2 == 0 else None)
        self.samples[n] = v
        return cosine_coefficients(v)

    def _samples(self, n, prev, fn=None):
        """The samples at n intervals, from those at n/2 (``prev``, or None) and the odd azimuths."""
        if prev is None:
            return self.evaluate(phi_samples(n), fn=fn)
        odd = self.evaluate(np.pi * (2 * np.arange(n // 2) + 1) / n, fn=fn)
        v = np.empty(prev.shape[:3] + (n + 1,))
        v[..., 0::2] = prev
        v[..., 1::2] = odd
        return v

    def cached_coefficients(self, n):
        """:meth:`coefficients` group by group (:attr:`flakedb.rt.scattering.media.KernelBasis.parts`): each group's
        coefficients (B_g, Hi, Ho, n + 1) and its samples at φ_d = 0 and π (what :meth:`scale_of` reads) from
        the fit's cache, or computed (from this call's samples at n/2 where it has them) and kept there."""
        coeffs, ends = [], []
        for g, (key, fn, _) in enumerate(self.parts):
            ck = ("basis coefficients", key, self.grid, int(n))
            hit = self.cache.get(ck)
            if hit is None:
                v = self._samples(n, self.part_samples.pop((g, n // 2), None) if n % 2 == 0 else None, fn)
                self.part_samples[(g, n)] = v
                hit = self.cache.put(ck, (cosine_coefficients(v), v[..., [0, -1]]))
            coeffs.append(hit[0])
            ends.append(hit[1])
        self.samples[n] = np.concatenate(ends, axis=0)  # (B, Hi, Ho, 2): φ_d = 0 and π
        return np.concatenate(coeffs, axis=0)

    def envelope(self, x):
        """(B, …) → (…): max over channels of |x_c| (exact) or its bound Σ_b μ_b |x_b|."""
        if self.M is None:
            return np.abs(x).max(axis=0)
        return np.tensordot(self.mu_b, np.abs(x), axes=(0, 0))

    def scale_of(self, v, a, W):
        """The scale's lower bound from the combinations at φ_d = 0, π and order 0 (None without a basis)."""
        if self.M is None:
            return None
        ends = np.stack([v[..., 0], v[..., -1], a[..., 0]], axis=-1)  # (B, Hi, Ho, 3)
        return float(np.abs(_combine(self.M, ends) * W[None, :, :, None]).max())

    def stats(self, a, a_prev, n):
        """Channel criteria (scale, change, upper) of the round comparing n and 2n intervals."""
        scale = self.scale_of(self.samples[2 * n], a, self.W)
        s_exact = change = upper = 0.0
        for sl in _chunks(self.hi, max(1, self.chunk_elems // max(1, a.shape[0] * self.ho * (2 * n + 1)))):
            Wc = self.W[sl, :, None]
            d = self.envelope(a[:, sl, :, :n] - a_prev[:, sl, :, :n]) * Wc
            change = max(change, float(d.max()))
            e = self.envelope(a[:, sl]) * Wc
            if self.M is None:
                s_exact = max(s_exact, float(e.sum(axis=-1).max()))
            upper = max(upper, float(e[..., n:].sum(axis=-1).max()))
        return (s_exact if self.M is None else scale), change, upper

    def truncate(self, a, scale, info):
        """The kept orders of the coefficients ``a`` (B, Hi, Ho, K): smallest L with tail Σ_{k≥L} |a_k|
        ≤ tol · scale for every channel and pair; returns ``(coeffs (L, B, Ho, Hi), info)``."""
        K = a.shape[-1]
        worst = np.zeros(K)
        for sl in _chunks(self.hi, max(1, self.chunk_elems // max(1, a.shape[0] * self.ho * K))):
            e = self.envelope(a[:, sl]) * self.W[sl, :, None]
            tails = np.flip(np.cumsum(np.flip(e, axis=-1), axis=-1), axis=-1)
            worst = np.maximum(worst, tails.reshape(-1, K).max(axis=0))
        worst /= scale
        below = np.nonzero(worst <= self.tol)[0]
        L = max(int(below[0]) if len(below) else K, 1)
        coeffs = np.ascontiguousarray(np.transpose(a[..., :L], (3, 0, 2, 1)))  # (L, B, Ho, Hi)
        return coeffs, {"n_phi": info["n_phi"], "tail": float(worst[L]) if L < K else 0.0,
                        "converged": info["converged"]}

    def _chunk_round(self, m, n, per, kept=None, last=None):
        """One round at m = 2n intervals over chunks of ``per`` incident nodes: (scale, change, upper,
        worst tails (m + 1,)).  ``kept`` (K, B, Ho, Hi): filled with the round's orders 0 … K − 1;
        ``last`` ``(l, (1, B, Ho, Hi))``: filled with order l."""
        scale = s_exact = change = upper = 0.0
        worst = np.zeros(m + 1)
        for sl in _chunks(self.hi, per):
            v = self.evaluate(phi_samples(m), sl)
            ac, ap = cosine_coefficients(v), cosine_coefficients(v[..., 0::2])
            if self.M is not None:
                scale = max(scale, self.scale_of(v, ac, self.W[sl]))
            del v
            if kept is not None:
                kept[..., sl] = np.transpose(ac[..., : kept.shape[0]], (3, 0, 2, 1))
            if last is not None:
                last[1][..., sl] = np.transpose(ac[..., last[0]: last[0] + 1], (3, 0, 2, 1))
            Wc = self.W[sl, :, None]
            change = max(change, float((self.envelope(ac[..., :n] - ap[..., :n]) * Wc).max()))
            del ap
            e = self.envelope(ac) * Wc
            del ac
            if self.M is None:
                s_exact = max(s_exact, float(e.sum(axis=-1).max()))
            upper = max(upper, float(e[..., n:].sum(axis=-1).max()))
            tails = np.flip(np.cumsum(np.flip(e, axis=-1), axis=-1), axis=-1)
            worst = np.maximum(worst, tails.reshape(-1, m + 1).max(axis=0))
        return (s_exact if self.M is None else scale), change, upper, worst

    def row_chunks(self, n, B, max_orders=None, resident=None):
        """The rounds from n on, incident nodes in chunks within the budget (see
        :func:`project_kernel_basis`); ``B`` basis functions.  Each round keeps its chunks' orders below
        ``resident`` (all without it) and the order ``max_orders`` − 1: the last round's are the result,
        so no pass of its own computes them; orders beyond those are evaluated on demand
        (:class:`ChunkedCoefficients`)."""
        ho, hi = self.ho, self.hi
        while True:
            m = 2 * n
            per = max(1, int(self.budget // (5 * 8 * B * ho * (m + 1))))
            K = m + 1 if resident is None else min(m + 1, int(resident))
            if max_orders is not None:
                K = min(K, int(max_orders))
            j = None if max_orders is None else int(max_orders) - 1
            if self.cache is not None:
                scale, change, upper, worst, kept, last = self.cached_chunk_round(m, n, K, j)
            else:
                kept = np.empty((K, B, ho, hi))
                last = (j, np.empty((1, B, ho, hi))) if j is not None and K <= j < m + 1 else None
                scale, change, upper, worst = self._chunk_round(m, n, per, kept, last)
            if scale == 0.0:
                return np.zeros((1, B, ho, hi)), {"n_phi": m, "tail": 0.0, "converged": True}
            converged = max(change, upper) / scale <= self.tol
            if converged or m >= self.n_max:
                break
            del kept, last
            n *= 2
        worst /= scale
        below = np.nonzero(worst <= self.tol)[0]
        L = max(int(below[0]) if len(below) else m + 1, 1)
        info = {"n_phi": m, "tail": float(worst[L]) if L < m + 1 else 0.0,
                "converged": bool(converged), "row_chunks": True}
        if max_orders is not None:
            L = min(L, int(max_orders))
        if L <= K:
            return (kept if L == K else np.ascontiguousarray(kept[:L])), info
        known = {L - 1: last[1]} if last is not None and last[0] == L - 1 else {}
        return ChunkedCoefficients(kept, L, _Recompute(self, m, per), known), info

    def group_round(self, fn, m, n, K, j, mu):
        """One chunked round (:meth:`_chunk_round`) of one keyed group of basis kernels ``fn`` with weights
        ``mu`` (B_g,) (max_c |M[c, b]| over its columns, scaled to a largest 1), as what the criteria need of
        it: Σ_b mu_b |a_b| (Hi, Ho, m + 1) and Σ_b mu_b |a_b − a'_b| over the first n orders (Hi, Ho, n)
        (a' the coefficients of the even samples), the samples at φ_d = 0, π and order 0 (B_g, Hi, Ho, 3),
        orders 0 … K − 1 (K, B_g, Ho, Hi) and order j (or None)."""
        ho, hi = self.ho, self.hi
        B = len(mu)
        per = max(1, int(self.budget // (5 * 8 * B * ho * (m + 1))))
        env = np.empty((hi, ho, m + 1))
        dif = np.empty((hi, ho, n))
        ends = np.empty((B, hi, ho, 3))
        kept = np.empty((K, B, ho, hi))
        last = np.empty((1, B, ho, hi)) if j is not None and K <= j < m + 1 else None
        for sl in _chunks(hi, per):
            v = self.evaluate(phi_samples(m), sl, fn=fn)
            ac, ap = cosine_coefficients(v), cosine_coefficients(v[..., 0::2])
            ends[:, sl] = np.stack([v[..., 0], v[..., -1], ac[..., 0]], axis=-1)
            del v
            kept[..., sl] = np.transpose(ac[..., :K], (3, 0, 2, 1))
            if last is not None:
                last[..., sl] = np.transpose(ac[..., j: j + 1], (3, 0, 2, 1))
            dif[sl] = np.tensordot(mu, np.abs(ac[..., :n] - ap[..., :n]), axes=(0, 0))
            del ap
            env[sl] = np.tensordot(mu, np.abs(ac), axes=(0, 0))
        return {"mu": mu, "env": env, "dif": dif, "ends": ends, "kept": kept, "last": last}

    def cached_chunk_round(self, m, n, K, j):
        """:meth:`_chunk_round` from each keyed group's round (:meth:`group_round`), taken from the fit's cache
        when an earlier evaluation computed it with weights proportional to this one's (a loading scales a
        group's columns of M: its envelope scales with it), else computed and kept.  The criteria are then
        formed from the groups' envelopes, Σ_g s_g Σ_{b∈g} mu_b |a_b| = :meth:`envelope`, so the choices and
        kept orders are those of the uncached round.  Returns (scale, change, upper, worst, kept, last)."""
        rounds, col = [], 0
        for key, fn, width in self.parts:
            mu = self.mu_b[col: col + width]
            col += width
            top = float(mu.max())
            unit = mu / top if top > 0 else np.ones_like(mu)
            ck = ("chunked round", key, self.grid, int(m), int(n), int(K), j)
            hit = self.cache.get(ck)
            if hit is None or not np.allclose(hit["mu"], unit, rtol=1e-12, atol=0.0):
                hit = self.cache.put(ck, self.group_round(fn, m, n, K, j, unit))
            rounds.append((top if top > 0 else 0.0, hit))
        W = self.W[:, :, None]
        env = sum(s * r["env"] for s, r in rounds) * W
        change = float((sum(s * r["dif"] for s, r in rounds) * W).max())
        upper = float(env[..., n:].sum(axis=-1).max())
        tails = np.flip(np.cumsum(np.flip(env, axis=-1), axis=-1), axis=-1)
        worst = tails.reshape(-1, m + 1).max(axis=0)
        ends = np.concatenate([r["ends"] for _, r in rounds], axis=0)
        scale = float(np.abs(_combine(self.M, ends) * self.W[None, :, :, None]).max())
        kept = np.concatenate([r["kept"] for _, r in rounds], axis=1)
        last = None if rounds[0][1]["last"] is None else (j, np.concatenate([r["last"] for _, r in rounds], axis=1))
        return scale, change, upper, worst, kept, last

    def orders_pass(self, m, per, l0, l1):
        """Orders l0 … l1 − 1 (l1 − l0, B, Ho, Hi) of the projection at m intervals, chunk by chunk as
        :meth:`row_chunks` computed them (the same samples, the same transform: the same values)."""
        out = None
        for sl in _chunks(self.hi, per):
            ac = cosine_coefficients(self.evaluate(phi_samples(m), sl))
            if out is None:
                out = np.empty((l1 - l0, ac.shape[0], self.ho, self.hi))
            out[..., sl] = np.transpose(ac[..., l0:l1], (3, 0, 2, 1))
        return out


class _Recompute:
    """Orders of a chunked projection evaluated again (:meth:`_BasisProjection.orders_pass`), the last
    range asked kept (the channel groups of a solve ask the same blocks in turn)."""

    def __init__(self, pr, m, per):
        self.pr, self.m, self.per = pr, m, per
        self.cache = (None, None)
        self.passes = 0

    def __call__(self, l0, l1):
        if self.cache[0] != (l0, l1):
            self.passes += 1
            self.cache = ((l0, l1), self.pr.orders_pass(self.m, self.per, l0, l1))
        return self.cache[1]


class ChunkedCoefficients:
    """Basis coefficients (L, B, Ho, Hi) of a projection over its memory budget
    (:func:`project_kernel_basis` with ``resident_orders``): orders 0 … K − 1 and the orders in
    ``known`` are held, the others evaluated again from the kernel on demand (the same values:
    :meth:`_BasisProjection.orders_pass`).  Sliced by orders (:meth:`orders`) or by basis functions
    (``c[:, idx]``); ``np.asarray`` gives every order.

    >>> c = ChunkedCoefficients(np.zeros((2, 1, 1, 1)), 4, lambda l0, l1: np.ones((l1 - l0, 1, 1, 1)))
    >>> c.shape, c.orders(1, 3)[:, 0, 0, 0].tolist(), np.asarray(c)[:, 0, 0, 0].tolist()
    ((4, 1, 1, 1), [0.0, 1.0], [0.0, 0.0, 1.0, 1.0])
    """

    def __init__(self, resident, L, recompute, known=None, idx=None):
        self.resident, self.L, self.recompute = resident, int(L), recompute
        self.known = dict(known or {})
        self.idx = idx

    @property
    def shape(self):
        return (self.L,) + self.resident.shape[1:]

    def _sub(self, a):
        return a if self.idx is None else a[:, self.idx]

    def orders(self, l0, l1):
        """Coefficients of orders l0 … l1 − 1 (l1 ≤ L)."""
        K = self.resident.shape[0]
        l1 = min(int(l1), self.L)
        if l1 <= K:
            return self.resident[l0:l1]
        if l1 - l0 == 1 and l0 in self.known:
            return self.known[l0]
        parts = [self.resident[l0:K]] if l0 < K else []
        parts.append(self._sub(self.recompute(max(l0, K), l1)))
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def __getitem__(self, key):
        """``c[:, idx]``: the basis functions ``idx`` (sharing the recomputation); ``c[l0:l1]``: orders."""
        if isinstance(key, tuple) and len(key) == 2 and key[0] == slice(None):
            full = np.arange(self.resident.shape[1]) if self.idx is None else np.asarray(self.idx)
            idx = full[key[1]]  # into the recomputed (all basis functions) arrays
            return ChunkedCoefficients(self.resident[:, key[1]], self.L, self.recompute,
                                       {k: v[:, key[1]] for k, v in self.known.items()}, idx)
        if isinstance(key, slice) and key.step is None:
            return self.orders(key.start or 0, self.L if key.stop is None else key.stop)
        raise IndexError(f"ChunkedCoefficients takes c[l0:l1] or c[:, idx], not {key!r}")

    def __array__(self, dtype=None, copy=None):
        a = self.orders(0, self.L)
        return a if dtype is None else a.astype(dtype)


class ProjectedKernel:
    """A medium's projected kernel on the nodes ``x`` (h,) of its hemisphere rule: the down→down
    (K_T) and down→up (K_R) blocks of every channel, built on demand for any range of orders.

    ``coeffs`` (L, B, 2h, h) are the basis coefficients from :func:`project_kernel_basis` with the
    outgoing nodes ordered [−x, +x]; ``M`` (C, B) (None: identity); ``scale`` (C, h) the symmetric
    renormalisation s_o K[o, i] s_i (or None).  Orders ≥ L are zero.
    """

    def __init__(self, coeffs, M, scale=None):
        self.coeffs = coeffs
        self.M = M
        self.scale = scale

    @property
    def n_orders(self):
        return self.coeffs.shape[0]

    @property
    def channels(self):
        return self.coeffs.shape[1] if self.M is None else self.M.shape[0]

    def blocks(self, l0=0, l1=None):
        """(K_T, K_R), each (l1 − l0, C, h, h) [order, channel, outgoing, incident] in 1/(µm·sr),
        for orders l0 … l1 − 1 (zero beyond the kernel's own order count)."""
        L = self.n_orders
        l1 = L if l1 is None else int(l1)
        h = self.coeffs.shape[-1]
        C = self.channels
        out = np.zeros((max(0, l1 - l0), C, 2 * h, h))
        k1 = min(l1, L)
        if k1 > l0:
            c = self.coeffs
            a = c[l0:k1] if isinstance(c, np.ndarray) else c.orders(l0, k1)  # (l, B, 2h, h)
            if self.M is None:
                out[: k1 - l0] = a
            else:
                out[: k1 - l0] = (self.M @ a.reshape(a.shape[0], a.shape[1], -1)).reshape(k1 - l0, C, 2 * h, h)
        if self.scale is not None:
            s = self.scale  # (C', h) broadcast over channels
            out *= np.concatenate([s, s], axis=1)[None, :, :, None] * s[None, :, None, :]
        return out[:, :, h:, :], out[:, :, :h, :]
