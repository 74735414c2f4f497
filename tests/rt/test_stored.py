"""Kernels assembled from stored factors (flakedb/rt/scattering/stored.py, docs/store.md): the contraction.

Guards against: a contraction that mixes up ranks, orders or the (K_T, K_R) blocks when several
species' factors are contracted in one GEMM; factors of a species with fewer orders leaking into
the orders beyond its count; a one-channel part, a Legendre part or the renormalisation lost in the
sum.
"""

import numpy as np

from flakedb.rt.basis.legendre import LegendreKernel
from flakedb.rt.basis.quadrature import radau_hemisphere
from flakedb.rt.scattering.stored import FactorKernel, SumKernel


def _factor_kernel(rng, r, L, C, h):
    V = rng.standard_normal((r, L, 2, h, h)).astype(np.float32)
    W = rng.standard_normal((C, r))
    return FactorKernel(lambda l0, l1: V[:, l0:l1], W, L, h), V.astype(float), W


def _explicit(V, W, L, l0, l1):
    """Σ_r W[c, r] V[r, l] written out per order, zero beyond the kernel's L orders."""
    C, h = W.shape[0], V.shape[-1]
    K = np.zeros((l1 - l0, C, 2, h, h))
    for j, l in enumerate(range(l0, l1)):
        if l < L:
            K[j] = np.einsum("cr,rbij->cbij", W, V[:, l])
    return K[:, :, 0], K[:, :, 1]


def test_sum_of_factor_kernels_is_the_sum_of_their_contractions():
    rng = np.random.default_rng(1)
    h, C = 5, 3
    x = radau_hemisphere(h).x
    (k1, V1, W1), (k2, V2, W2) = _factor_kernel(rng, 2, 7, C, h), _factor_kernel(rng, 3, 4, C, h)
    k3, V3, W3 = _factor_kernel(rng, 1, 6, 1, h)  # one channel, broadcast
    leg = LegendreKernel(x, 0.6 ** np.arange(6)[None].repeat(C, 0), np.linspace(1.0, 2.0, C))
    scale = 1.0 + 0.1 * rng.random((C, h))
    for l0, l1 in ((0, 1), (0, 9), (3, 8), (5, 7), (8, 10)):
        want_T = want_R = 0.0
        for V, W, L in ((V1, W1, 7), (V2, W2, 4), (V3, W3, 6)):
            a, b = _explicit(V, W, L, l0, l1)
            want_T, want_R = want_T + a, want_R + b
        lt, lr = leg.blocks(l0, l1)
        f = scale[None, :, :, None] * scale[None, :, None, :]
        want_T, want_R = (want_T + lt) * f, (want_R + lr) * f
        s = SumKernel([k1, leg, k2, k3])
        s.scale = scale
        got_T, got_R = s.blocks(l0, l1)
        assert got_T.shape == want_T.shape == (l1 - l0, C, h, h)
        np.testing.assert_allclose(got_T, want_T, rtol=0, atol=1e-13 * np.abs(want_T).max())
        np.testing.assert_allclose(got_R, want_R, rtol=0, atol=1e-13 * np.abs(want_R).max())
        # one species alone, renormalised by itself
        k1.scale = scale
        a, b = k1.blocks(l0, l1)
        w_T, w_R = _explicit(V1, W1, 7, l0, l1)
        np.testing.assert_allclose(a, w_T * f, rtol=0, atol=1e-13 * max(np.abs(w_T).max(), 1e-300))
        np.testing.assert_allclose(b, w_R * f, rtol=0, atol=1e-13 * max(np.abs(w_R).max(), 1e-300))
        k1.scale = None


def test_a_channel_subset_of_a_stored_kernel_is_those_channels_of_its_blocks():
    """A channel group solves with channel_subset(idx) of the whole projected kernel (not a second
    contraction): its blocks must be exactly those channels of the whole kernel's blocks, for factor,
    Legendre and summed kernels, with and without the renormalisation scale."""
    rng = np.random.default_rng(2)
    h, C = 5, 4
    x = radau_hemisphere(h).x
    (k1, _, _), (k2, _, _) = _factor_kernel(rng, 2, 7, C, h), _factor_kernel(rng, 3, 4, C, h)
    k3, _, _ = _factor_kernel(rng, 1, 6, 1, h)
    leg = LegendreKernel(x, np.linspace(0.3, 0.8, C)[:, None] ** np.arange(6)[None], np.linspace(1.0, 2.0, C))
    idx = np.array([1, 3])
    for kern in (k1, leg, SumKernel([k1, leg, k2, k3])):
        for scale in (None, 1.0 + 0.1 * rng.random((C, h))):
            kern.scale = scale
            whole = kern.blocks(0, 8)
            sub = kern.channel_subset(idx)
            assert sub.channels == idx.size
            for got, want in zip(sub.blocks(0, 8), whole):
                np.testing.assert_array_equal(got, want[:, idx])
