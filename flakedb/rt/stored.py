"""Media whose reflectance function comes from the precomputed store (issue #6, docs/model.md §5).

The store (:mod:`flakedb.store.versions`) holds a species' R(μ_i, μ_o, φ_d) on the grid of
:func:`flakedb.store.compress.grid_nodes`: μ the solver's full node set inside the binder, φ_d the m points
π k/(m − 1) of [0, π], as cosine-series coefficients in φ_d (orders 0 … m − 1): the DCT-I of the raw
samples, or the compressed factors' product U_pairs · Fourier(V_pairs) (paper §4 end: "R's Fourier
coefficients are then one matrix product").  :class:`StoredReflectance` evaluates that series

    R(μ_i, μ_o, φ) = Σ_{l<m} R_l(μ_i, μ_o) cos(l φ)

at grid nodes only (the solver's nodes are the grid's nodes; anything else is refused, not
interpolated) and at any φ the projector asks for (the trigonometric interpolant through the m
stored samples: exact at the stored φ_k, band-limited to order m − 1 between them).

Media (the interface of :mod:`flakedb.rt.media`: ``sigma_t``, ``sigma_s``, ``kernel``, ``phi_bandwidth``):

* :class:`StoredFlakeMedium`: kernel = (aρ/2) R(μ_i, μ_o, φ_d) D(h), the formula of
  :func:`flakedb.rt.microflake.kernel_Ergun` ((aρ/4) R(c) (D(h) + D(−h)), D even) with R(c(μ_i, μ_o,
  φ_d)) read from the store and D(h) (the Beckmann density at the half vector, which depends on the
  recipe's α, not stored) evaluated directly.  σ_t(μ) and σ_s(μ) are *not* in the store: they need
  the flake's T(c) (σ_t) and a 1-D integral over flake normals; they stay the accurate 1-D
  integrals :func:`flakedb.rt.microflake.extinction_Ergun` / :func:`~flakedb.rt.microflake.scattering_Ergun`
  of the species' FlakeOptics, passed in as callables (they are cheap: a few ms per band).
* :class:`StoredPigmentMedium`: the store's pigment R is 4π ϖ p(cos Θ) (:mod:`flakedb.store.compress`;
  ϖ = C_sca/C_ext), so the kernel ρ C_sca p = ρ C_ext · R/(4π) = σ_t R/(4π), with σ_t = ρ C_ext and
  σ_s = ρ C_sca, direction-independent.

Channels: the coefficients may be any linear combination of the stored wavelengths (a band
selection, or the RGB mode's spectra → linear sRGB map), applied before the solve
(:meth:`flakedb.store.versions.StoreVersion.stored_reflectance`); a pigment's per-band weight ρ C_ext goes in before that map
(``weights``), since the RGB mode converts C_sca p, not p.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flakedb.rt.microflake import flake_ndf_at_halfvector

#: Solver nodes and store grid nodes must agree to this (absolute, in μ).
NODE_TOL = 1e-12


class StoredGridMismatch(ValueError):
    """The solver asked for the reflectance at a μ that is not a node of the store's grid."""


@dataclass(frozen=True, eq=False)
class StoredReflectance:
    """R's cosine series on the store grid: ``mu`` (n_mu,) ascending grid cosines, ``coeffs``
    (C, n_mu, n_mu, L) [channel, incident node, outgoing node, order]; ``source`` a description
    (store, version, species, raw / compressed) for error messages and records."""

    mu: np.ndarray
    coeffs: np.ndarray
    source: str = "store"

    def __post_init__(self):
        mu = np.asarray(self.mu, dtype=float)
        c = np.asarray(self.coeffs, dtype=float)
        if c.ndim == 3:
            c = c[None]
        if mu.ndim != 1 or np.any(np.diff(mu) <= 0):
            raise ValueError(f"StoredReflectance.mu must be strictly ascending (the store grid), got shape {mu.shape}")
        if c.ndim != 4 or c.shape[1] != mu.size or c.shape[2] != mu.size:
            raise ValueError(f"StoredReflectance.coeffs must be (C, {mu.size}, {mu.size}, L), got {c.shape}")
        object.__setattr__(self, "mu", mu)
        object.__setattr__(self, "coeffs", np.ascontiguousarray(c))

    @property
    def channels(self) -> int:
        return self.coeffs.shape[0]

    @property
    def n_orders(self) -> int:
        return self.coeffs.shape[-1]

    def node_index(self, mu):
        """Indices of the grid nodes equal (within :data:`NODE_TOL`) to ``mu`` (any shape); refuses others."""
        mu = np.asarray(mu, dtype=float)
        j = np.clip(np.searchsorted(self.mu, mu), 1, self.mu.size - 1)
        left, right = self.mu[j - 1], self.mu[j]
        j = np.where(np.abs(mu - left) <= np.abs(right - mu), j - 1, j)
        err = np.abs(self.mu[j] - mu)
        if err.size and err.max() > NODE_TOL:
            k = int(np.argmax(err))
            raise StoredGridMismatch(
                f"μ = {mu.ravel()[k]:.15g} is not a node of the stored grid (nearest {self.mu[j.ravel()[k]]:.15g}, "
                f"off by {err.max():.3g} > {NODE_TOL:g}) of {self.source}: the store was built for another "
                f"node count n or top interface index η than the solve ({self.mu.size} grid nodes); rebuild it "
                f"with `flakedb build --n N --eta-top ETA` for the recipe's n and binder index")
        return j

    def evaluate(self, mu_i, mu_o, phi_d):
        """R (C, *broadcast shape) at grid nodes ``mu_i``, ``mu_o`` and any azimuths ``phi_d``."""
        mu_i, mu_o, phi = (np.asarray(a, dtype=float) for a in (mu_i, mu_o, phi_d))
        ndim = max(mu_i.ndim, mu_o.ndim, phi.ndim)
        mu_i, mu_o, phi = (a.reshape((1,) * (ndim - a.ndim) + a.shape) for a in (mu_i, mu_o, phi))
        bm = np.broadcast_shapes(mu_i.shape, mu_o.shape)
        ii, oo = np.broadcast_arrays(self.node_index(mu_i), self.node_index(mu_o))
        L = self.n_orders
        if ndim >= 1 and bm[-1] == 1 and all(s == 1 for s in phi.shape[:-1]):
            # the projector's layout: nodes on the leading axes, φ on the last: one matrix product
            g = self.coeffs[:, ii[..., 0], oo[..., 0], :]  # (C, *bm[:-1], L)
            cos = np.cos(np.arange(L)[:, None] * phi.reshape(-1)[None, :])  # (L, P)
            return g @ cos
        full = np.broadcast_shapes(bm, phi.shape)
        ii, oo = np.broadcast_to(ii, full), np.broadcast_to(oo, full)
        ph = np.broadcast_to(phi, full)
        cos = np.cos(np.arange(L) * ph[..., None])  # (*full, L)
        return np.einsum("c...l,...l->c...", self.coeffs[:, ii, oo, :], cos)


def _per_channel(x, ndim):
    x = np.atleast_1d(np.asarray(x, dtype=float))
    return x.reshape((-1,) + (1,) * ndim)


@dataclass(eq=False)
class StoredFlakeMedium:
    """Micro-flakes with R from the store (module docstring).  ``alpha``: Beckmann spread;
    ``a_rho_per_um``: loading aρ (1/µm); ``R_source``: :class:`StoredReflectance`;
    ``sigma_t_fn``, ``sigma_s_fn``: callables μ → (C, *μ.shape) in 1/µm (the 1-D integrals)."""

    alpha: float
    a_rho_per_um: float
    R_source: StoredReflectance
    sigma_t_fn: object
    sigma_s_fn: object

    def sigma_t(self, mu):
        return self.sigma_t_fn(np.abs(np.asarray(mu, dtype=float)))

    def sigma_s(self, mu):
        return self.sigma_s_fn(np.abs(np.asarray(mu, dtype=float)))

    def kernel(self, mu_i, mu_o, phi_d):
        """(aρ/2) R(μ_i, μ_o, φ_d) D(h), h = normalize(ω_o − ω_i) (as kernel_Ergun), 1/(µm·sr)."""
        d = flake_ndf_at_halfvector(mu_i, mu_o, phi_d, self.alpha)
        R = self.R_source.evaluate(mu_i, mu_o, phi_d)
        return (0.5 * self.a_rho_per_um) * R * d[None]

    @property
    def phi_bandwidth(self):
        # as FlakeMedium: a few samples per lobe width √2 α, refined adaptively by the projection
        return int(2 ** np.ceil(np.log2(max(8.0, 8.0 * np.pi / (np.sqrt(2.0) * self.alpha)))))


@dataclass(eq=False)
class StoredPigmentMedium:
    """Pigments with R = 4π ϖ p from the store (module docstring).  ``R_source`` must already carry
    the per-channel weight ρ C_ext (``StoreVersion.stored_reflectance(weights=ρ C_ext)``), so that the
    kernel is R_source/(4π) = ρ C_sca p; ``sigma_t_per_um`` = ρ C_ext and ``sigma_s_per_um`` =
    ρ C_sca per channel (C,).  ``nonnegative``: the kernel is clipped at 0 (the RGB mode's phase ≥ 0;
    the solver's renormalisation to σ_s then plays the part of the direct path's re-normalisation of
    the clipped phase table)."""

    R_source: StoredReflectance
    sigma_t_per_um: object
    sigma_s_per_um: object
    #: clip the kernel at 0 (RGB mode: the linear sRGB map of the stored spectral series has negative
    #: lobes where the direct path clips its RGB phase function to ≥ 0; see flakedb.paint.mapping)
    nonnegative: bool = False

    def sigma_t(self, mu):
        mu = np.asarray(mu, dtype=float)
        return _per_channel(self.sigma_t_per_um, mu.ndim) * np.ones_like(mu)

    def sigma_s(self, mu):
        mu = np.asarray(mu, dtype=float)
        return _per_channel(self.sigma_s_per_um, mu.ndim) * np.ones_like(mu)

    def kernel(self, mu_i, mu_o, phi_d):
        """ρ C_ext R/(4π) = ρ C_sca p(cos Θ), 1/(µm·sr) (≥ 0 with ``nonnegative``)."""
        k = self.R_source.evaluate(mu_i, mu_o, phi_d) / (4.0 * np.pi)
        return np.maximum(k, 0.0) if self.nonnegative else k

    @property
    def phi_bandwidth(self):
        # the stored series has m orders; sampling it at 2 (m − 1) intervals resolves it exactly
        return int(2 ** np.ceil(np.log2(max(8, self.R_source.n_orders - 1))))
