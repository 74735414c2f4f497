"""Media assembled from precomputed, projected kernel factors (issue #11, docs/store.md).

The kernel of every species is linear in what varies with wavelength (paper eq. 2: a flake's R(c);
a pigment's σ_s p(cos Θ)) and in its loading.  The store (:mod:`flakedb.store.versions`) therefore
holds, per species and per (n, η, α), the *projected* kernel blocks per unit loading compressed
across wavelength,

    K_λ[l, o, i] = Σ_r U[λ, r] V_r[l, o, i]        (flakes; V float32, orders chunked)

and for pigments the Legendre moments χ_k(λ) of the phase function with C_ext, C_sca (the addition
theorem gives the blocks without azimuthal quadrature, :mod:`flakedb.rt.basis.legendre`).  Compose then
only contracts: a recipe's channels are a linear map of the store's wavelengths (selection,
interpolation, or the RGB mode's spectra → linear sRGB), so a channel's kernel is
(loading · map @ U) @ V — :class:`FactorKernel` — and a layer's kernel is the sum over its species
(:class:`SumKernel`).  Nothing is sampled in φ or transformed.

Both kernels follow :class:`flakedb.rt.scattering.projection.ProjectedKernel`'s interface (``n_orders``,
``channels``, ``blocks(l0, l1)``, ``scale``), so :func:`flakedb.rt.adding.stack.project_medium` renormalises
them as any projected kernel and the solver asks only for the orders it uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flakedb.rt.basis.legendre import LegendreKernel
from flakedb.rt.scattering.media import FlakeMedium, channel_subset
from flakedb.rt.scattering.microflake import (
    FlakeOptics,
    extinction_Ergun,
    kernel_Ergun_basis,
    projected_area,
    scattering_Ergun,
)
from flakedb.rt.scattering.projection import project_kernel_basis

#: Solver nodes and the store's nodes must agree to this (absolute, in μ).
NODE_TOL = 1e-12


class StoredGridMismatch(ValueError):
    """The solver's nodes are not the nodes the stored kernel was projected on."""


def check_nodes(x_store, x, source="the store"):
    """Refuse a solve whose inside nodes ``x`` differ from the stored ones."""
    x_store, x = np.asarray(x_store, float), np.asarray(x, float)
    if x_store.shape != x.shape or np.abs(x_store - x).max() > NODE_TOL:
        raise StoredGridMismatch(
            f"the solve's {x.size} inside nodes are not the {x_store.size} nodes {source} was projected on: "
            f"it was built for another node count n or top interface index η; rebuild it with "
            f"`flakedb build --n N --eta-top ETA` for the recipe's n and binder index")


class FactorKernel:
    """Projected kernel Σ_r weights[c, r] V_r of C channels from factors V (r, L, 2, h, h)
    [rank, order, block (0: K_T down→down, 1: K_R down→up), outgoing, incident] per unit loading.

    ``read(l0, l1)`` → V[:, l0:l1] (float32 or float64; a lazy reader of the store's chunks, or an
    array's slice); ``weights`` (C, r) = loading × channel map @ U; ``n_orders`` the stored count."""

    def __init__(self, read, weights, n_orders, h):
        self.read = read
        self.weights = np.atleast_2d(np.asarray(weights, dtype=float))
        self._L = int(n_orders)
        self.h = int(h)
        self.scale = None

    @property
    def n_orders(self):
        return self._L

    @property
    def channels(self):
        return self.weights.shape[0]

    def blocks(self, l0=0, l1=None):
        l1 = self._L if l1 is None else int(l1)
        out = _contract_factors([self], l0, l1)
        return _scaled(out[0], out[1], self.scale, in_place=True)

    def channel_subset(self, idx):
        """The kernel of channels ``idx`` (the same factors, those channels' weights and scale)."""
        k = FactorKernel(self.read, _rows(self.weights, idx), self._L, self.h)
        k.scale = None if self.scale is None else _rows(self.scale, idx)
        return k


def _rows(a, idx):
    """Rows ``idx`` of a per-channel array; a one-row (channel-independent) array unchanged."""
    return a if a.shape[0] == 1 else a[idx]


def _contract_factors(kernels, l0, l1):
    """Σ over ``kernels`` (:class:`FactorKernel`, same h) of their unscaled blocks for orders l0 … l1 − 1
    as one (2, l1 − l0, C, h, h) array (K_T, K_R each contiguous): the parts' weights side by side,
    (C, Σr), times their factors stacked, (Σr, h·h), one batched GEMM per (block, order) written straight
    into the result; orders beyond a kernel's count are zero rows of its factors, orders beyond every
    kernel's count zero."""
    h = kernels[0].h
    C = max(k.channels for k in kernels)
    L = max(0, l1 - l0)
    live = [(k, min(l1, k.n_orders)) for k in kernels if min(l1, k.n_orders) > l0]
    kmax = max([k1 for _, k1 in live], default=l0)
    out = np.empty((2, L, C, h * h))
    out[:, kmax - l0:] = 0.0
    if live:
        W = np.concatenate([np.broadcast_to(k.weights, (C, k.weights.shape[1])) for k, _ in live], axis=1)
        V = np.empty((W.shape[1], kmax - l0, 2, h * h))
        r0 = 0
        for k, k1 in live:
            r = k.weights.shape[1]
            V[r0:r0 + r, : k1 - l0] = np.reshape(k.read(l0, k1), (r, k1 - l0, 2, h * h))
            V[r0:r0 + r, k1 - l0:] = 0.0
            r0 += r
        np.matmul(W, V.transpose(2, 1, 0, 3), out=out[:, : kmax - l0])  # (C, Σr) @ (2, l, Σr, h·h)
    return out.reshape(2, L, C, h, h)


def _scaled(K_T, K_R, scale, in_place=False):
    """s_o K[o, i] s_i for both blocks (``scale`` (C, h), None: unchanged); ``in_place`` for arrays the
    caller owns."""
    if scale is not None:
        f = scale[None, :, :, None] * scale[None, :, None, :]
        if in_place:
            K_T *= f
            K_R *= f
        else:
            K_T = K_T * f
            K_R = K_R * f
    return K_T, K_R


class SumKernel:
    """The kernel of a mixture: the sum of its parts' kernels (each with the ProjectedKernel
    interface and the same channels or one channel), renormalised as a whole by ``scale``."""

    def __init__(self, parts):
        self.parts = list(parts)
        self.scale = None

    @property
    def n_orders(self):
        return max(p.n_orders for p in self.parts)

    @property
    def channels(self):
        return max(p.channels for p in self.parts)

    def blocks(self, l0=0, l1=None):
        l1 = self.n_orders if l1 is None else int(l1)
        factors = [p for p in self.parts if isinstance(p, FactorKernel) and p.scale is None]
        K_T = K_R = None
        if factors:  # the stored flake species: one contraction of all their factors
            K_T, K_R = _contract_factors(factors, l0, l1)
        for p in self.parts:  # the others summed into the same buffers
            if any(p is f for f in factors):
                continue
            a, b = p.blocks(l0, l1)
            if K_T is None:
                K_T, K_R = np.array(a, dtype=float), np.array(b, dtype=float)
            elif a.shape[1] > K_T.shape[1]:  # a one-channel sum so far and a C-channel part
                K_T, K_R = K_T + a, K_R + b
            else:
                K_T += a
                K_R += b
        return _scaled(K_T, K_R, self.scale, in_place=True)

    def channel_subset(self, idx):
        """The kernel of channels ``idx``, or None when a part has no channel subset."""
        parts = [p if p.channels == 1 else getattr(p, "channel_subset", lambda i: None)(idx) for p in self.parts]
        if any(p is None for p in parts):
            return None
        k = SumKernel(parts)
        k.scale = None if self.scale is None else _rows(self.scale, idx)
        return k


@dataclass(eq=False)
class FlakeFactors:
    """One flake species' stored factors at one (n, η, α), per unit loading aρ = 1/µm:
    ``x`` (h,) the inside nodes; ``U`` (W, r); ``read(l0, l1)`` → V (r, l1 − l0, 2, h, h);
    ``n_orders``; ``sigma_t`` (W, h) and ``sigma_s`` (W, h) (1-D integrals of paper eq. 2 with the
    flake's T and R); ``projected_area`` (h,) = ∫ |ω·m| D dm (σ_t of an opaque flake per unit aρ)."""

    x: np.ndarray
    U: np.ndarray
    read: object
    n_orders: int
    sigma_t: np.ndarray
    sigma_s: np.ndarray
    projected_area: np.ndarray
    source: str = "store"
    #: the flake-normal density the factors were projected for (flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS)
    distribution: str = "beckmann"


@dataclass(eq=False)
class StoredFlakeMedium:
    """Micro-flakes from stored factors: loading ``a_rho_per_um``, the recipe's channels as
    ``channel_map`` (C, W) @ (store wavelengths), ``opaque`` (T = 0: σ_t is the projected area)."""

    factors: FlakeFactors
    a_rho_per_um: float
    channel_map: np.ndarray
    opaque: bool = False

    def _nodes(self, mu):
        mu = np.abs(np.asarray(mu, dtype=float))
        idx = np.clip(np.searchsorted(self.factors.x, mu), 0, self.factors.x.size - 1)
        lo = np.clip(idx - 1, 0, self.factors.x.size - 1)
        idx = np.where(np.abs(self.factors.x[lo] - mu) < np.abs(self.factors.x[idx] - mu), lo, idx)
        if np.abs(self.factors.x[idx] - mu).max(initial=0.0) > NODE_TOL:
            check_nodes(self.factors.x, mu, self.factors.source)
        return idx

    def sigma_t(self, mu):
        idx = self._nodes(mu)
        if self.opaque:
            s = self.a_rho_per_um * self.factors.projected_area[idx]
            return np.broadcast_to(s, (self.channel_map.shape[0],) + np.shape(mu)).copy()
        return self.a_rho_per_um * (self.channel_map @ self.factors.sigma_t)[:, idx]

    def sigma_s(self, mu):
        return self.a_rho_per_um * (self.channel_map @ self.factors.sigma_s)[:, self._nodes(mu)]

    def subset(self, idx):
        return StoredFlakeMedium(self.factors, self.a_rho_per_um, self.channel_map[idx], self.opaque)

    def projected_kernel(self, x, max_orders, direct=None):
        check_nodes(self.factors.x, x, self.factors.source)
        w = self.a_rho_per_um * (self.channel_map @ self.factors.U)
        return FactorKernel(self.factors.read, w, min(self.factors.n_orders, int(max_orders)), x.size), {
            "kernel": f"stored factors, rank {self.factors.U.shape[1]} ({self.factors.source})"}


@dataclass(eq=False)
class StoredPigmentMedium:
    """Pigments from stored Mie optics: σ_t = ρ C_ext, σ_s = ρ C_sca per channel (C,) in 1/µm, and
    the phase function's Legendre moments ``chi`` (C, K + 1) (:class:`flakedb.rt.basis.legendre.LegendreKernel`)."""

    sigma_t_per_um: np.ndarray
    sigma_s_per_um: np.ndarray
    chi: np.ndarray
    source: str = "store"

    def sigma_t(self, mu):
        mu = np.asarray(mu, dtype=float)
        return np.asarray(self.sigma_t_per_um, float).reshape((-1,) + (1,) * mu.ndim) * np.ones_like(mu)

    def sigma_s(self, mu):
        mu = np.asarray(mu, dtype=float)
        return np.asarray(self.sigma_s_per_um, float).reshape((-1,) + (1,) * mu.ndim) * np.ones_like(mu)

    def subset(self, idx):
        take = lambda a: np.asarray(a, float)[idx] if np.ndim(a) and np.shape(a)[0] > 1 else a
        return StoredPigmentMedium(take(self.sigma_t_per_um), take(self.sigma_s_per_um), take(self.chi), self.source)

    def projected_kernel(self, x, max_orders, direct=None):
        k = LegendreKernel(x, self.chi, self.sigma_s_per_um, max_orders=max_orders)
        return k, {"kernel": f"Legendre moments (degree {k.K}) and the addition theorem ({self.source})"}


@dataclass(eq=False)
class StoredMixture:
    """Several stored (or otherwise pre-projected) components in one layer: σ's and kernels add."""

    components: list

    def sigma_t(self, mu):
        return sum(np.asarray(c.sigma_t(mu), float) for c in self.components)

    def sigma_s(self, mu):
        return sum(np.asarray(c.sigma_s(mu), float) for c in self.components)

    def subset(self, idx):
        return StoredMixture([channel_subset(c, idx) for c in self.components])

    def projected_kernel(self, x, max_orders, direct=None):
        """``direct(medium)`` → (kernel, info) projects a component without stored factors (a custom
        species next to catalogue ones) the usual way."""
        parts, infos = [], []
        for c in self.components:
            if hasattr(c, "projected_kernel"):
                k, info = c.projected_kernel(x, max_orders)
            else:
                k, info = direct(c)
            parts.append(k)
            infos.append(info)
        return SumKernel(parts), {"components": infos}


#: Truncation of the spectral SVD of a flake's R(c) table: the smallest rank whose reconstruction
#: differs from the table by at most RANK_TOL × max R at every entry (measured, not bounded), hence no
#: kernel value by more than that fraction of the R = max R kernel (the kernel is linear in R with a
#: positive geometric factor, paper eq. 2; linear interpolation in c keeps the entry-wise bound).
RANK_TOL = 1e-5


def spectral_factors(table, rank_tol=RANK_TOL):
    """Truncated SVD of a (W, nc) table across wavelength: ``(U (W, r), basis (r, nc), info)`` with
    table ≈ U @ basis, r the smallest rank whose largest entry error max |table − U basis| is
    ≤ rank_tol · max |table| (rank_tol ≤ 0 or None: the numerical rank, 1e-13 of s_1).  ``info``:
    ``rank``, ``numerical_rank``, ``singular_values`` (relative to s_1), ``max_error`` (the largest
    entry error relative to max |table|), ``error_vs_rank`` (that error for r = 1 … the numerical rank).

    A table that is one spectrum times one angular profile has rank 1:

    >>> table = np.outer([1.0, 2.0, 3.0], [0.1, 0.2, 0.5, 0.3])            # (W, nc)
    >>> U, basis, info = spectral_factors(table)
    >>> info["rank"], U.shape, basis.shape, bool(np.allclose(U @ basis, table, rtol=0, atol=1e-13))
    (1, (3, 1), (1, 4), True)
    """
    table = np.atleast_2d(np.asarray(table, dtype=float))
    top = float(np.abs(table).max())
    if top == 0.0:
        return np.zeros((table.shape[0], 1)), np.zeros((1, table.shape[1])), {
            "rank": 1, "numerical_rank": 1, "singular_values": [0.0], "max_error": 0.0, "error_vs_rank": [0.0]}
    U, S, Vt = np.linalg.svd(table, full_matrices=False)
    num = max(1, int(np.sum(S > 1e-13 * S[0])))
    resid = table.copy()
    err = []
    for k in range(num):  # the residual after rank k + 1, entry-wise
        resid -= S[k] * np.outer(U[:, k], Vt[k])
        err.append(float(np.abs(resid).max()) / top)
    if rank_tol is None or rank_tol <= 0:
        r = num
    else:
        ok = [k for k, e in enumerate(err) if e <= rank_tol]
        r = ok[0] + 1 if ok else num
    # a deterministic sign: each basis row's largest entry positive
    sign = np.sign(Vt[np.arange(r), np.argmax(np.abs(Vt[:r]), axis=1)])
    sign[sign == 0] = 1.0
    info = {"rank": int(r), "numerical_rank": num, "singular_values": (S[:num] / S[0]).tolist(),
            "max_error": err[r - 1], "error_vs_rank": err}
    return U[:, :r] * sign, (S[:r, None] * Vt[:r]) * sign[:, None], info


def flake_factors(c, R, T, alpha, x, w, tol=1e-5, max_orders=None, rank_tol=RANK_TOL, distribution="beckmann"):
    """The stored quantities of one flake species at one (nodes, α, ``distribution``), per unit loading
    aρ = 1/µm (``distribution``: the flake-normal density, :data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS`).

    ``c`` (nc,), ``R``, ``T`` (W, nc): the flake's tables (:class:`flakedb.rt.scattering.microflake.FlakeOptics`);
    ``x``, ``w`` (h,) the solver's inside hemisphere rule; ``tol``, ``max_orders`` as the solver's
    projection (:func:`flakedb.rt.adding.stack.project_medium`: same φ sampling, weights and criteria, here
    on the W wavelengths as channels).  The kernel (aρ/2) R(c) D(h) is linear in R, so with
    R ≈ U @ basis (:func:`spectral_factors`) the kernel of wavelength λ is Σ_r U[λ, r] k_r, and the
    basis kernels k_r are projected once (:func:`flakedb.rt.scattering.projection.project_kernel_basis`).

    Returns a dict: ``U`` (W, r), ``V`` (r, L, 2, h, h) [rank, order, (K_T, K_R), outgoing, incident]
    in 1/(µm·sr), ``sigma_t``, ``sigma_s`` (W, h) in 1/µm, ``projected_area`` (h,), ``info``.
    """
    x = np.asarray(x, dtype=float)
    w = np.asarray(w, dtype=float)
    h = x.size
    max_orders = int(max_orders) if max_orders else 4 * h
    U, basis, sinfo = spectral_factors(R, rank_tol)
    optics = FlakeOptics(c, R, T)
    sigma_t = extinction_Ergun(x, alpha, optics, 1.0, distribution=distribution)
    sigma_s = scattering_Ergun(x, alpha, optics, 1.0, distribution=distribution)
    area = projected_area(x, alpha, distribution=distribution)
    mu_o = np.concatenate([-x, x])
    Wt = w[:, None] * np.concatenate([w, w])[None, :]
    n_max = max(2 * max_orders, 128)
    n_start = min(max(4, FlakeMedium(alpha, optics, 1.0, distribution).phi_bandwidth), n_max)
    coeffs, pinfo = project_kernel_basis(lambda mi, mo, ph: kernel_Ergun_basis(mi, mo, ph, alpha, c, basis, 1.0,
                                                                               distribution),
                                         U, x, mu_o, tol=tol, n_start=n_start, n_max=n_max, weights=Wt)
    coeffs = coeffs[:max_orders]  # (L, r, 2h, h), outgoing [−x, +x]
    L = coeffs.shape[0]
    V = np.empty((U.shape[1], L, 2, h, h))
    V[:, :, 0] = np.moveaxis(coeffs[:, :, h:, :], 1, 0)  # K_T: down → down
    V[:, :, 1] = np.moveaxis(coeffs[:, :, :h, :], 1, 0)  # K_R: down → up
    return {"U": U, "V": V, "sigma_t": sigma_t, "sigma_s": sigma_s, "projected_area": area,
            "info": {**sinfo, "orders": int(L), "n_phi": pinfo["n_phi"], "projection_converged": pinfo["converged"]}}
