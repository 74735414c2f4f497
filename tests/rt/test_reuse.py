"""The fit's reuse cache (flakedb.rt.common.reuse) and the projection's use of it (flakedb.rt.scattering.projection).

Guards against: a cache that grows without bound or keeps values after its fit; a cached projection that
differs from the uncached one (in memory and over the memory budget, in chunks); and a change of a
non-loading quantity (the flakes' orientation α) served from the cache instead of computed afresh.
"""

import numpy as np
import pytest

from flakedb.rt.scattering.media import FlakeMedium, Mixture, PhaseMedium, kernel_basis
from flakedb.rt.scattering.microflake import FlakeOptics
from flakedb.rt.scattering.projection import project_kernel_basis
from flakedb.rt.basis.quadrature import gauss_radau_unit
from flakedb.rt.common.reuse import ReuseCache, active_cache, array_key, reusing
from tests.tolerances import ulps


def test_cache_is_bounded_and_least_recently_used_goes_first():
    c = ReuseCache(budget_bytes=3 * 800)  # three arrays of 100 float64
    for k in range(3):
        c.put(k, np.full(100, float(k)))
    assert c.get(0) is not None                       # 0 is now the most recently used
    c.put(3, np.zeros(100))                           # over the budget: the least recently used (1) goes
    assert c.get(1) is None and c.get(0) is not None and c.get(2) is not None and c.get(3) is not None
    assert c.nbytes == 3 * 800 <= c.budget_bytes and len(c) == 3
    c.put("big", np.zeros(1000))                      # larger than the whole budget: not kept
    assert c.get("big") is None and c.nbytes <= c.budget_bytes
    with pytest.raises(ValueError):                   # a served value is shared: read-only
        c.get(0)[0] = 1.0


def test_scope_releases_the_cache():
    assert active_cache() is None
    with reusing() as c:
        assert active_cache() is c
        c.put("x", np.ones(3))
    assert active_cache() is None
    assert array_key(np.ones(3)) != array_key(np.ones(4)) and array_key(np.ones(3)) == array_key([1.0, 1.0, 1.0])


X, W_NODES = gauss_radau_unit(10)
C_GRID = np.linspace(0.0, 1.0, 30)
R_TAB = np.stack([0.3 + 0.2 * C_GRID, 0.5 - 0.1 * C_GRID**2, 0.1 + 0.0 * C_GRID])


def _mixture(a_rho, sigma, alpha=0.2):
    """Flakes (loading aρ, spread α) and an HG pigment (loading ∝ ``sigma``) in one layer, three channels."""
    return Mixture([FlakeMedium(alpha, FlakeOptics(C_GRID, R_TAB, 0.2 * np.ones_like(R_TAB)), a_rho),
                    PhaseMedium(np.array([1.0, 2.0, 0.5]) * sigma, 0.8, ("hg", np.array([0.5, 0.6, 0.5])))])


def _project(medium, budget, reuse):
    kb = kernel_basis(medium)
    mu_o = np.concatenate([-X, X])
    W = W_NODES[:, None] * np.concatenate([W_NODES, W_NODES])[None, :]
    c, info = project_kernel_basis(kb.fn, kb.M, X, mu_o, tol=1e-5, n_start=8, weights=W, budget_bytes=budget,
                                   max_orders=20, resident_orders=8, parts=kb.parts if reuse else None)
    return kb.M, np.asarray(c), info


def _same_choice(gi, ri):
    """The same sampling, order count and convergence; the reported tail to rounding (the groups' envelopes
    are summed group by group)."""
    assert {k: v for k, v in gi.items() if k != "tail"} == {k: v for k, v in ri.items() if k != "tail"}
    assert gi["tail"] == pytest.approx(ri["tail"], rel=1e-12)


@pytest.mark.parametrize("budget", [None, 2e5], ids=["in memory", "chunked"])
def test_cached_projection_is_the_uncached_one(budget):
    """Loadings change between evaluations: the basis groups come from the cache (hits) and every
    channel's coefficients M·a are those of the uncached projection; a changed α is a new key (misses) and
    gives the uncached projection at that α, not the cached one at the old α."""
    with reusing() as cache:
        _project(_mixture(1.0, 1.0), budget, True)             # fills the cache
        misses = cache.misses
        for args in [(3.0, 1.0), (1.0, 0.01), (0.5, 4.0)]:     # loadings only
            M, got, gi = _project(_mixture(*args), budget, True)
            M0, ref, ri = _project(_mixture(*args), budget, False)
            _same_choice(gi, ri)
            a, b = np.einsum("cb,lb...->lc...", M, got), np.einsum("cb,lb...->lc...", M0, ref)
            np.testing.assert_allclose(a, b, rtol=0, atol=ulps(64, np.abs(b).max()))
        assert cache.misses == misses and cache.hits > 0      # nothing recomputed
        hits = cache.hits
        M, got, gi = _project(_mixture(1.0, 1.0, alpha=0.1), budget, True)   # a non-loading change
        assert cache.misses > misses                          # the flakes' group computed afresh …
        M0, ref, ri = _project(_mixture(1.0, 1.0, alpha=0.1), budget, False)
        _, old, _ = _project(_mixture(1.0, 1.0), budget, False)
        _same_choice(gi, ri)
        assert cache.hits > hits                 # … the pigment's reused
        a, b = np.einsum("cb,lb...->lc...", M, got), np.einsum("cb,lb...->lc...", M0, ref)
        np.testing.assert_allclose(a, b, rtol=0, atol=ulps(64, np.abs(b).max()))
        assert got.shape != old.shape or np.abs(got - old).max() > 1e-3 * np.abs(old).max()
