"""Sampling and compression of the flake reflectance function R(μ_i, μ_o, φ_d) (docs/model.md §5, paper §4
end and §6, Figure 4).  Pure numpy: arrays in, arrays out; the paper's Figure 4 plot is drawn by figures/figure4.py.

What is sampled
---------------
Conventions: :mod:`flakedb.conventions` (μ > 0 travels down, φ_d = φ_o − φ_i, φ_d = 0 forward).  The
micro-flake kernel (paper eq. 2, :func:`flakedb.rt.scattering.microflake.kernel_Ergun`) is
(aρ/2) R(c) D(h) with the flake cosine c = |ω_i·h| = |ω_o − ω_i|/2, so

    c²(μ_i, μ_o, φ_d) = (1 − ω_i·ω_o)/2,   ω_i·ω_o = cos Θ = μ_i μ_o + s_i s_o cos φ_d,  s = √(1 − μ²).

The stored reflectance function of a species is therefore R(μ_i, μ_o, φ_d) = R(c(μ_i, μ_o, φ_d)):

* flakes (interference, mirror): the flake's unpolarised reflectance R(c) per wavelength
  (:func:`flakedb.paint.species.flake_reflectance_transmittance`); dimensionless, in [0, 1];
* pigments (paper eq. 8, :func:`flakedb.rt.scattering.microflake.pigment_kernel_Ergun`): with the uniform
  normal density and the representation of :func:`flakedb.rt.scattering.microflake.pigment_extinction_Ergun`
  (opaque flakes of area a = 2 C_ext), a R = 8π C_sca p(cos Θ), i.e. the dimensionless
  R = 4π ϖ p(cos Θ), ϖ = C_sca/C_ext, p the ensemble Mie phase function in 1/sr (normalised to 1 over
  the sphere, cos Θ = ω_i·ω_o).  It exceeds 1 near forward scattering (it is a reflectance times a
  phase-function ratio, not an energy fraction).

The 1-D functions R(c) and p(cos Θ) are tabulated on ``n_table`` nodes uniform in angle
(c = cos θ, θ ∈ [0, π/2]; cos Θ, Θ ∈ [0, π]) and linearly interpolated onto the grid — the same
piecewise-linear-in-c representation as the solver's :class:`flakedb.rt.scattering.microflake.FlakeOptics`.

The grid
--------
μ: the solver's full node set *inside the binder* for n nodes in air (n even), sign order
``[-x_h … -x_1, x_1 … x_h]`` — the nodes on which :func:`flakedb.rt.adding.stack.solve_stack` projects a
medium's kernel.  Without a top interface, or a rough one (``eta_top`` None or 1), that is the
Gauss–Radau set (:func:`flakedb.rt.basis.quadrature.radau_hemisphere`, h = n/2 per hemisphere, n nodes in
all).  Below a smooth coat of index η > 1 (``eta_top`` = η) it is the Snell image of the n/2 outside
Radau nodes plus :func:`flakedb.rt.basis.quadrature.default_tir_nodes` Gauss–Legendre nodes in the totally
internally reflected range (:func:`flakedb.rt.basis.quadrature.snell_mapped_quadrature`), so
n_mu = 2 (n/2 + h_tir) > n nodes.  φ_d: the m points
φ_k = π k/(m − 1), k = 0 … m − 1 of [0, π] (both ends; :func:`flakedb.rt.basis.fourier.phi_samples` with
N = m − 1), whose DCT-I (:func:`flakedb.rt.basis.fourier.cosine_coefficients`) gives the cosine orders
0 … m − 1.  Array layout: ``R[i, o, k] = R(mu[i], mu[o], phi[k])``; flattened to (n_mu², m) with row
``i·n_mu + o``.

Compression (docs/model.md §5)
-------------------------
√R ≈ Σ_{i<r} s_i u_i v_iᵀ (truncated SVD), and the square expands into k = r(r+1)/2 column pairs

    R̂ = (Σ_i a_i v_iᵀ)∘(Σ_j a_j v_jᵀ) = Σ_{i≤j} w_ij (a_i∘a_j)(v_i∘v_j)ᵀ,  a_i = s_i u_i,  w_ii = 1, w_ij = 2,

stored as ``U_pairs`` (n², k) (the w_ij a_i∘a_j columns) and ``V_pairs`` (k, m) (the v_i∘v_j rows),
pairs ordered (0,0), (0,1), …, (0,r−1), (1,1), … .  R̂ ≥ 0 by construction.  The Fourier factors are
the DCT-I of the rows of ``V_pairs``; R's cosine coefficients are ``U_pairs @ F``.  Storage
k(n² + m) numbers per channel instead of n² m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flakedb.paint import species as sp
from flakedb.paint.components import adaptive_flake_optics
from flakedb.rt.basis.fourier import cosine_coefficients, phi_samples
from flakedb.rt.basis.legendre import legendre_moments_gauss
from flakedb.rt.basis.quadrature import (
    default_tir_nodes,
    radau_hemisphere,
    snell_mapped_quadrature,
)
from flakedb.rt.scattering.stored import flake_factors

__all__ = [
    "grid_nodes",
    "scattering_cosine_grid",
    "sample_reflectance",
    "SqrtSVDFactors",
    "pair_indices",
    "sqrt_svd_compress",
    "svd_compress",
    "fourier_factors",
    "reconstruct",
    "reconstruct_fourier",
    "nmf_compress",
    "mean_relative_error",
    "storage_bytes",
]

#: default number of table nodes for R(c) / p(cos Θ) before interpolation onto the grid.
DEFAULT_N_TABLE = 2049
#: entries with R ≤ MRE_THRESHOLD · max R are left out of :func:`mean_relative_error`.
MRE_THRESHOLD = 1e-6


# --------------------------------------------------------------------------------------------
# The (μ_i, μ_o, φ_d) grid and R on it
# --------------------------------------------------------------------------------------------



def _inside_quadrature(n, eta_top, top="smooth"):
    """The solver's hemisphere rule inside the binder for n nodes in air (n even, checked by the
    caller) below a smooth top of index ``eta_top`` (None or 1: plain Gauss–Radau); ``top`` "rough":
    below a rough top, where the solver keeps the air-side Gauss–Radau rule inside too."""
    q = radau_hemisphere(n // 2)
    if top not in ("smooth", "rough"):
        raise ValueError(f"top = {top!r}: 'smooth' or 'rough'")
    if eta_top is not None and top == "smooth":
        eta = float(eta_top)
        if not np.isfinite(eta) or eta < 1.0:
            raise ValueError(f"eta_top = {eta_top}: the top interface's index (binder / air) must be ≥ 1 "
                             f"(1 or None: no smooth interface, plain Gauss–Radau nodes)")
        if eta > 1.0:
            q = snell_mapped_quadrature(q, eta, default_tir_nodes(q.h, eta))
    return q


def grid_nodes(n, m, eta_top=None, top="smooth"):
    """The sampling grid: ``mu`` (n_mu,) the solver's full inside node set, ``phi`` (m,) radians on [0, π].

    ``n`` (even, ≥ 2) is the solver's node count in air (n/2 per hemisphere).  ``eta_top``: None or
    1 → plain Gauss–Radau (n_mu = n; no top interface, or a rough one); η > 1 → the quadrature below
    a smooth interface of relative index η (Snell-mapped Radau nodes plus the default TIR nodes,
    module docstring).  ``m`` ≥ 2.
    """
    n, m = int(n), int(m)
    if n < 2 or n % 2:
        raise ValueError(f"n = {n}: the μ grid needs an even node count ≥ 2 (n/2 per hemisphere); use n = {max(2, n + n % 2)}")
    if m < 2:
        raise ValueError(f"m = {m}: the φ_d grid needs at least 2 samples on [0, π] (both ends)")
    q = _inside_quadrature(n, eta_top, top)
    mu, _ = q.full()
    return mu, phi_samples(m - 1)


def scattering_cosine_grid(mu, phi):
    """cos Θ = ω_i·ω_o = μ_i μ_o + s_i s_o cos φ_d on the grid, shape (n, n, m), clipped to [−1, 1]."""
    mu = np.asarray(mu, dtype=float)
    s = np.sqrt(np.clip(1.0 - mu * mu, 0.0, None))
    cos_t = mu[:, None, None] * mu[None, :, None] + (s[:, None] * s[None, :])[:, :, None] * np.cos(phi)[None, None, :]
    return np.clip(cos_t, -1.0, 1.0)


def _interp_channels(x_table, y_table, x):
    """Linear interpolation of each row of ``y_table`` (C, T) at ``x`` (any shape) → (C, *x.shape)."""
    out = np.empty((y_table.shape[0],) + x.shape)
    flat = x.ravel()
    for ch in range(y_table.shape[0]):
        out[ch] = np.interp(flat, x_table, y_table[ch]).reshape(x.shape)
    return out


def sample_reflectance(entry, wavelength_nm, n_binder, n, m, n_table=DEFAULT_N_TABLE, eta_top=None):
    """R(μ_i, μ_o, φ_d) of one catalogue species on the (n_mu, n_mu, m) grid of
    :func:`grid_nodes` ``(n, m, eta_top)``, per wavelength → (W, n_mu, n_mu, m) (n_mu = n for
    ``eta_top`` None or 1).

    ``entry``: a species of the catalogue (:func:`flakedb.paint.catalog.get_species`); ``wavelength_nm``
    (W,) vacuum wavelengths in nm; ``n_binder`` scalar or (W,) real binder index.  Dimensionless; see
    the module docstring for what R is for flakes and pigments and how it is interpolated.
    """
    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    nb = np.broadcast_to(np.asarray(n_binder, dtype=float), wl.shape)
    mu, phi = grid_nodes(n, m, eta_top)
    cos_t = scattering_cosine_grid(mu, phi)
    if entry["kind"] in ("interference_flake", "mirror_flake"):
        c_grid = np.sqrt(np.clip(0.5 * (1.0 - cos_t), 0.0, 1.0))
        c_tab = np.cos(np.linspace(0.5 * np.pi, 0.0, n_table))  # ascending, uniform in angle
        c_tab[0] = 0.0
        R_tab, _ = sp.flake_reflectance_transmittance(entry, wl, c_tab, nb)
        return _interp_channels(c_tab, np.asarray(R_tab, dtype=float), c_grid)
    if entry["kind"] == "pigment":
        ct_tab = np.cos(np.linspace(np.pi, 0.0, n_table))  # ascending cos Θ
        ct_tab[0], ct_tab[-1] = -1.0, 1.0
        po = sp.pigment_optics(entry, wl, nb, mu=ct_tab)
        albedo = np.asarray(po.c_sca_um2, float) / np.asarray(po.c_ext_um2, float)
        R_tab = 4.0 * np.pi * albedo[:, None] * np.asarray(po.phase_function, dtype=float)
        return _interp_channels(ct_tab, R_tab, cos_t)
    raise ValueError(f"sample_reflectance: unknown species kind {entry['kind']!r}")


# --------------------------------------------------------------------------------------------
# Square-root SVD compression
# --------------------------------------------------------------------------------------------


def _as_matrix(R):
    R = np.asarray(R, dtype=float)
    if R.ndim == 3:
        return R.reshape(R.shape[0] * R.shape[1], R.shape[2])
    if R.ndim == 2:
        return R
    raise ValueError(f"expected R of shape (n, n, m) or (n², m), got {R.shape}")


def pair_indices(rank):
    """The k = r(r+1)/2 pairs (i, j), i ≤ j, in storage order: two (k,) int arrays."""
    i, j = np.triu_indices(int(rank))
    return i, j


@dataclass(frozen=True)
class SqrtSVDFactors:
    """Result of :func:`sqrt_svd_compress`: ``U_pairs`` (n², k), ``V_pairs`` (k, m), ``singular_values``
    (r,) of √R, ``rank`` r.  ``U_pairs @ V_pairs`` is the compressed R̂ (n², m)."""

    U_pairs: np.ndarray
    V_pairs: np.ndarray
    singular_values: np.ndarray
    rank: int


def _svd_fixed_sign(A, rank):
    """Truncated SVD with a deterministic sign: each v_i's largest-magnitude entry is positive."""
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    r = int(rank)
    if r < 1:
        raise ValueError(f"rank must be ≥ 1, got {rank}")
    if r > len(s):
        raise ValueError(f"rank {r} exceeds min(n², m) = {len(s)} for a matrix of shape {A.shape}")
    U, s, Vt = U[:, :r], s[:r], Vt[:r]
    idx = np.argmax(np.abs(Vt), axis=1)
    sign = np.sign(Vt[np.arange(r), idx])
    sign[sign == 0] = 1.0
    return U * sign, s, Vt * sign[:, None]


def sqrt_svd_compress(R, rank):
    """Paper §4/§6 compression: truncated SVD of √R at rank r, squared into k = r(r+1)/2 pairs.

    ``R``: (n, n, m) or (n², m), non-negative (tiny negatives from round-off are clipped to 0).
    Returns :class:`SqrtSVDFactors`; see the module docstring for the pair expansion.

    A sharp lobe (a Gaussian band) at rank 3: the square-root factorisation stays non-negative, a plain
    truncated SVD rings below zero; the storage is the paper's 1:5.53 at n = m = 200, r = 8:

    >>> t = np.linspace(0.0, 1.0, 40)
    >>> R = np.exp(-(((t[:, None] - t[None, :]) / 0.1) ** 2))
    >>> f = sqrt_svd_compress(R, 3)
    >>> f.U_pairs.shape, bool(reconstruct(f.U_pairs, f.V_pairs).min() >= 0.0)
    ((40, 6), True)
    >>> A, B = svd_compress(R, 3)
    >>> bool((A @ B).min() < -0.1)
    True
    >>> s = storage_bytes(200, 200, 8)
    >>> round(s["raw_MiB"], 2), round(s["compressed_MiB"], 2), round(s["ratio"], 2)
    (61.04, 11.04, 5.53)
    """
    A = np.sqrt(np.clip(_as_matrix(R), 0.0, None))
    U, s, Vt = _svd_fixed_sign(A, rank)
    a = U * s  # (n², r)
    i, j = pair_indices(rank)
    w = np.where(i == j, 1.0, 2.0)
    U_pairs = a[:, i] * a[:, j] * w
    V_pairs = Vt[i] * Vt[j]
    return SqrtSVDFactors(np.ascontiguousarray(U_pairs), np.ascontiguousarray(V_pairs), s, int(rank))


def svd_compress(R, rank):
    """Plain truncated SVD of R itself (no square root): (A (n², r), B (r, m)), R̂ = A @ B (may be < 0)."""
    U, s, Vt = _svd_fixed_sign(_as_matrix(R), rank)
    return U * s, Vt


def fourier_factors(V_pairs):
    """Cosine-series (DCT-I) coefficients of each row of the φ factor: (k, m) → (k, m), orders 0 … m−1.

    R's cosine coefficients are then ``U_pairs @ fourier_factors(V_pairs)`` (:func:`reconstruct_fourier`).
    """
    return cosine_coefficients(np.asarray(V_pairs, dtype=float))


def reconstruct(U_pairs, V_pairs, n=None):
    """R̂ = U_pairs @ V_pairs, (n², m); reshaped to (n, n, m) when ``n`` is given."""
    R = np.asarray(U_pairs) @ np.asarray(V_pairs)
    return R.reshape(n, n, -1) if n is not None else R


def reconstruct_fourier(U_pairs, F, n=None):
    """R's cosine coefficients from the Fourier factors: U_pairs @ F, (n², L) or (n, n, L)."""
    return reconstruct(U_pairs, F, n)


# --------------------------------------------------------------------------------------------
# NMF (Lee & Seung 1999), the paper's alternative
# --------------------------------------------------------------------------------------------


def nmf_compress(R, rank, n_iter=500, seed=0, eps=1e-12):
    """Non-negative matrix factorisation R ≈ W H by Lee & Seung's multiplicative updates for the
    Frobenius norm (Nature 401, 788 (1999); Lee & Seung, NIPS 13 (2001), Theorem 1):

        H ← H ∘ (Wᵀ R) / (Wᵀ W H + eps),   W ← W ∘ (R Hᵀ) / (W H Hᵀ + eps).

    ``R`` (n, n, m) or (n², m), non-negative; ``rank`` r; ``n_iter`` update sweeps; a deterministic
    start from ``numpy.random.default_rng(seed)`` scaled to R's mean.  Returns (W (n², r), H (r, m)).
    """
    V = np.clip(_as_matrix(R), 0.0, None)
    r = int(rank)
    if r < 1:
        raise ValueError(f"rank must be ≥ 1, got {rank}")
    rng = np.random.default_rng(seed)
    scale = np.sqrt(max(V.mean(), eps) / r)
    W = scale * rng.random((V.shape[0], r)) + eps
    H = scale * rng.random((r, V.shape[1])) + eps
    for _ in range(int(n_iter)):
        H *= (W.T @ V) / (W.T @ W @ H + eps)
        W *= (V @ H.T) / (W @ (H @ H.T) + eps)
    return W, H


# --------------------------------------------------------------------------------------------
# Error and storage
# --------------------------------------------------------------------------------------------


def mean_relative_error(R, R_hat, threshold=MRE_THRESHOLD):
    """Mean relative error of Figure 4: the mean of |R − R̂| / R over the entries with
    R > threshold · max(R) (entries where R vanishes have no relative error; the default threshold
    1e-6 drops only those).  ``R``, ``R_hat`` of the same size (any shape).  Returns a float."""
    R = np.asarray(R, dtype=float).ravel()
    R_hat = np.asarray(R_hat, dtype=float).ravel()
    if R.shape != R_hat.shape:
        raise ValueError(f"R has {R.size} entries, R_hat {R_hat.size}")
    mask = R > threshold * R.max()
    if not mask.any():
        raise ValueError("mean_relative_error: R has no entry above the threshold (all zero?)")
    return float(np.mean(np.abs(R[mask] - R_hat[mask]) / R[mask]))


def storage_bytes(n, m, rank, dtype="float64"):
    """Storage per channel: raw n² m numbers vs compressed k (n² + m), k = r(r+1)/2.

    Returns a dict with ``raw_bytes``, ``compressed_bytes``, ``raw_MiB``, ``compressed_MiB``,
    ``ratio`` (raw / compressed) and ``k``.  Paper §6: n = m = 200, r = 8, float64 → 61.04 MiB vs
    11.04 MiB, 1:5.53.
    """
    item = np.dtype(dtype).itemsize
    k = int(rank) * (int(rank) + 1) // 2
    raw = int(n) ** 2 * int(m) * item
    comp = k * (int(n) ** 2 + int(m)) * item
    mib = float(1 << 20)
    return {"k": k, "raw_bytes": raw, "compressed_bytes": comp, "raw_MiB": raw / mib,
            "compressed_MiB": comp / mib, "ratio": raw / comp}


# --------------------------------------------------------------------------------------------
# Figure 4
# --------------------------------------------------------------------------------------------

FIGURE4_SPECIES = ("metallic", "pearlescent", "cadmium-yellow")


def figure4_table(R_by_species, ranks=range(1, 13), nmf_iter=500, seed=0):
    """Mean relative error versus rank for each species' R (n, n, m): methods ``sqrt_svd`` (the
    paper's scheme, k pairs), ``svd`` (plain SVD of R) and ``nmf`` (Lee & Seung, ``nmf_iter`` sweeps).
    Returns ``{species: {method: [error per rank]}}`` plus ``ranks``."""
    ranks = [int(r) for r in ranks]
    out = {"ranks": ranks, "errors": {}}
    for name, R in R_by_species.items():
        rows = {"sqrt_svd": [], "svd": [], "nmf": []}
        for r in ranks:
            f = sqrt_svd_compress(R, r)
            rows["sqrt_svd"].append(mean_relative_error(R, reconstruct(f.U_pairs, f.V_pairs)))
            A, B = svd_compress(R, r)
            rows["svd"].append(mean_relative_error(R, A @ B))
            W, H = nmf_compress(R, r, n_iter=nmf_iter, seed=seed)
            rows["nmf"].append(mean_relative_error(R, W @ H))
        out["errors"][name] = rows
    return out




# --------------------------------------------------------------------------------------------
# The projected-kernel store (format 2, issue #11, docs/store.md)
# --------------------------------------------------------------------------------------------

#: Largest Legendre degree of the pigments' stored phase moments (the catalogue's need 38–53 at a
#: 1e-6 tail, flakedb.rt.basis.legendre) and the Gauss–Legendre nodes the Mie phase function is evaluated on.
LEGENDRE_STORE_DEGREE = 127
LEGENDRE_STORE_NODES = 192
#: Orders per chunk of a flake's V (compose reads only the chunks of the orders it solves).
ORDER_CHUNK = 16


def store_nodes(n, eta_top=None, top="smooth"):
    """The solver's positive inside nodes and weights ``(x, w)`` (h,) for n nodes in air below a smooth
    top of index ``eta_top`` (None or 1: plain Gauss–Radau, h = n/2), as :func:`flakedb.rt.adding.stack.solve_stack`
    builds them (:func:`grid_nodes` gives the full signed set)."""
    n = int(n)
    if n < 2 or n % 2:
        raise ValueError(f"n = {n}: the node count must be even and ≥ 2 (n/2 per hemisphere); use n = {max(2, n + n % 2)}")
    q = _inside_quadrature(n, eta_top, top)
    return q.x, q.w


def flake_task(entry, wavelength_nm, n_binder, n, alpha, eta_top, rank_tol, projection_tol, top="smooth",
               distribution="beckmann"):
    """A flake species' stored factors at (n, η, α, orientation ``distribution``) over ``wavelength_nm``
    (the whole spectrum): R(c),
    T(c) tabulated on the adaptive c grid of the direct path (:func:`flakedb.paint.components.adaptive_flake_optics`),
    then :func:`flakedb.rt.scattering.stored.flake_factors` (spectral SVD, projection of the basis kernels, σ's).
    Returns ``U`` float64, ``V`` float32 (r, L, 2, h, h), ``V_last_order`` = V[:, L − 1] (r, 2, h, h) (the order
    the Jackson filter's test reads, :func:`flakedb.rt.scattering.medium_projection.damp_if_capped`, without the 16-order
    chunk that holds it), ``sigma_t``, ``sigma_s``, ``projected_area`` and ``info``."""
    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    nb = np.broadcast_to(np.asarray(n_binder, dtype=float), wl.shape)
    c, R, T, c_err = adaptive_flake_optics(lambda cc: sp.flake_reflectance_transmittance(entry, wl, cc, nb))
    x, w = store_nodes(n, eta_top, top)
    f = flake_factors(c, R, T, float(alpha), x, w, tol=projection_tol, max_orders=2 * int(n),
                      rank_tol=rank_tol if rank_tol is not None else 0.0, distribution=distribution)
    V = f["V"].astype(np.float32)
    info = {**f["info"], "c_nodes": int(c.size), "c_grid_max_midpoint_error": c_err,
            "V_float32_max_error": float(np.abs(V - f["V"]).max() / max(np.abs(f["V"]).max(), 1e-300))}
    W, r = f["U"].shape
    L, h = V.shape[1], x.size
    info["storage_ratio"] = float(W * L * 2 * h * h / (r * L * 2 * h * h + W * r))  # per-wavelength blocks / factors
    return {"U": f["U"], "V": V, "V_last_order": np.ascontiguousarray(V[:, -1]), "sigma_t": f["sigma_t"],
            "sigma_s": f["sigma_s"], "projected_area": f["projected_area"], "info": info}


def pigment_task(entry, wavelength_nm, n_binder, degree=LEGENDRE_STORE_DEGREE, nodes=LEGENDRE_STORE_NODES,
                 n_quad=None):
    """A pigment's stored optics over ``wavelength_nm``: ⟨C_ext⟩, ⟨C_sca⟩ (µm²), ⟨V⟩ (µm³) and the
    Legendre moments χ_0 … χ_degree of its ensemble Mie phase function (normalised, χ_0 = 1),
    from the phase function at ``nodes`` Gauss–Legendre cosines (:func:`flakedb.rt.basis.legendre.legendre_moments_gauss`;
    no table, no interpolation).  ``n_quad``: the size quadrature (the store passes the one of its whole
    wavelength grid, :func:`flakedb.paint.species.pigment_n_quad`, so every block gets the same)."""
    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    t, wt = np.polynomial.legendre.leggauss(int(nodes))
    po = sp.pigment_optics(entry, wl, n_binder, mu=t, n_quad=n_quad)
    p = np.asarray(po.phase_function, dtype=float)
    chi, _ = legendre_moments_gauss(t, wt, p, tol=0.0, k_max=int(degree))
    chi = chi / chi[:, :1]
    return {"c_ext_um2": np.asarray(po.c_ext_um2, float), "c_sca_um2": np.asarray(po.c_sca_um2, float),
            "mean_volume_um3": np.full(wl.shape, float(po.mean_volume_um3)), "legendre_moments": chi}
