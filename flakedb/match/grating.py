"""Diffractive (grating-embossed, holographic) flakes in single scattering: can they make the RGL colour-shift
paint? (issue 35, docs/validation.md §4a, the feasibility step).

A SpectraFlair-type flake is a reflective (aluminium) platelet embossed with a linear grating of period Λ; in
the coat its normal m follows an orientation law D (the catalogue's, :mod:`flakedb.rt.scattering.microflake`)
and the grating's direction t̂ in the flake plane is uniform in azimuth ψ.  Directions here are unit vectors
inside the binder (real index n_b), ω_i towards the light and ω_o towards the viewer.

Grating equation (reflection, order m, in the binder)
-----------------------------------------------------
The tangential (flake-plane) component of the wave vector changes by m 2π/Λ; in unit direction vectors, with
P_m the projection onto the flake plane,

    P_m(ω_o) = −P_m(ω_i) + m (λ / (n_b Λ)) t̂,   i.e.   P_m(ω_i + ω_o) = m g t̂,   g = λ / (n_b Λ),

and ω_o's normal component follows from |ω_o| = 1 (an order with |P_m(ω_o)| > 1 is evanescent).  m = 0 is the
mirror: ω_i + ω_o ∥ m.

Flake BRDF and the population's BRDF
------------------------------------
A flake sends the fraction η_m of the power it intercepts into order m: its BRDF is η_m δ²(P_m(ω_o) − P_m(ω_r)
− m g t̂), a delta in the flake-plane coordinates (d²P_m(ω_o) = (ω_o·m) dω_o).  Over a population whose normals
have the projected-area density D_p (∫ D_p(m) (m·z) dm = 1, flakes covering the coat once: D_p = 2 D / ⟨m·z⟩
with D the flake-convention density, even and unit over the sphere) the single-scattering BRDF is

    f(ω_i, ω_o) = 1/(μ_i μ_o) ∫ D_p(m) ⟨ω_i·m⟩ ⟨ω_o·m⟩ Σ_m η_m ∫ dψ/2π δ²(P_m(ω_i + ω_o) − m g t̂(ψ)) dm,

(μ = cos to the coat normal, ⟨x⟩ = max(x, 0)).  The ψ average of the 2-D delta is δ(|s| − |m| g)/(2π |m| g) for
s = P_m(ω_i + ω_o), whose length is H sin β with H = |ω_i + ω_o| = 2 cos θ_d and β the angle between m and the
half vector h.  So the orders ±m together (η_|m| = η_{+m} + η_{−m}: a uniform ψ makes them alike) select the
normals on the cone β₀ = asin(r/H), r = |m| g, around h:

    f_|m| = η_|m| sin β₀ / (2π r H cos β₀ μ_i μ_o) ∫_0^{2π} D_p(m(β₀, φ)) ⟨ω_i·m⟩ ⟨ω_o·m⟩ dφ     (r < H; else 0)

(from dm = sin β dβ dφ and δ(H sin β − r) = δ(β − β₀)/(H cos β₀)).  As r → 0 the cone closes on h and
f → η₀ D_p(h)/(4 μ_i μ_o), the specular flake (microfacet) BRDF: the m = 0 term is evaluated in that form.
The φ integral is the trapezoidal rule on ``n_phi`` nodes (periodic; the clipped cosines make it converge as
1/n_phi², tested).  :func:`grating_brdf_montecarlo` is an independent estimate (random normals and azimuths,
the grating equation solved per flake, outgoing directions binned).

Feasibility model for a measured paint (:func:`grating_paint_reflectance`)
-------------------------------------------------------------------------
Single scattering under a smooth clear coat: R(λ) = π [T(θ_i) T(θ_v) / n_b² · Σ_|m| a_|m| f_|m|(ω_i', ω_o'; λ) ]
+ k_d, with ω' refracted by Snell, T = 1 − F the unpolarised Fresnel transmittance (radiance n_b² in, 1/n_b² out),
a_|m| = c η_|m| the order weights (c the flakes' projected coverage, ≤ 1; η spectrally flat) and k_d a grey
Lambertian floor (the multiply scattered and primer light).  No extinction along the path, no inter-reflection:
an upper bound on how much of the light single scattering delivers, not a replacement for the solver.
"""

from __future__ import annotations

import functools

import numpy as np

from flakedb.optics.fresnel import fresnel_dielectric_real
from flakedb.rt.scattering.grating_flake import sinusoidal_order_efficiency
from flakedb.rt.scattering.microflake import flake_ndf, sample_flake_normal

__all__ = ["binder_directions", "grating_brdf", "grating_brdf_montecarlo", "grating_paint_reflectance",
           "mean_flake_cosine", "projected_density",
           "sinusoidal_efficiency"]


@functools.lru_cache(maxsize=8)
def _gauss_legendre(n):
    return np.polynomial.legendre.leggauss(int(n))


def mean_flake_cosine(alpha, distribution="beckmann", n_quad=400) -> float:
    """⟨m·z⟩ = ∫_{upper} 2 D(m) (m·z) dm of the flake-convention density D (:func:`flake_ndf`): the projected area
    per unit flake area.  Gauss–Legendre in u = cos θ_m on [0, 1] with the 2π of the azimuth; 1 for α → 0."""
    x, w = _gauss_legendre(n_quad)
    u = 0.5 * (x + 1.0)
    return float(np.sum(0.5 * w * 2.0 * flake_ndf(u, alpha, distribution) * u) * 2.0 * np.pi)


def projected_density(cos_theta_m, alpha, distribution="beckmann"):
    """D_p(m) = 2 D(m) / ⟨m·z⟩ [1/sr] on the upper hemisphere: ∫ D_p (m·z) dm = 1 (module docstring)."""
    return 2.0 * flake_ndf(cos_theta_m, alpha, distribution) / mean_flake_cosine(alpha, distribution)


def _frame(h):
    """Two unit vectors (..., 3) orthogonal to the unit vectors h (..., 3) and to each other."""
    a = np.where(np.abs(h[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    e1 = np.cross(h, a)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return e1, np.cross(h, e1)


def sinusoidal_efficiency(order, cos_in, cos_out, wavelength_nm, depth_nm, n_binder=1.5):
    """η_|m| of the orders ±m together (m ≠ 0: 2 J_m²(Φ); m = 0: J_0²(Φ)) of a sinusoidal reflection grating of
    amplitude a = ``depth_nm`` (surface height a sin(2π x/Λ), peak-to-valley 2a) per unit reflectance, scalar
    (Kirchhoff / Raman–Nath) theory: the reflected phase k n_b (cos θ_in + cos θ_out) z(x) has the Jacobi–Anger
    expansion Σ_m J_m(Φ) e^{i m 2π x/Λ}, Φ = 2π n_b a (cos θ_in + cos θ_out)/λ, cosines to the flake normal.
    Σ over all m of the returned values is 1 (Σ J_m² = 1): the grating only redistributes the reflected power.
    Scalar theory is the limit Λ ≫ λ with shallow grooves; it ignores polarisation, the metal's phase and the
    resonances (Wood anomalies) that rigorous electromagnetic theory (RCWA) gives at Λ/λ ~ 1-2 (E. G. Loewen and
    E. Popov, Diffraction Gratings and Applications, 1997, on the domains of scalar theory).

    >>> total = sum(sinusoidal_efficiency(m, 0.9, 0.8, 550.0, 120.0) for m in range(40))
    >>> bool(abs(total - 1.0) < 1e-12)
    True
    """
    return (1.0 if order == 0 else 2.0) * sinusoidal_order_efficiency(order, cos_in, cos_out, wavelength_nm, depth_nm,
                                                                      n_binder)


def grating_brdf(wi, wo, wavelength_nm, period_nm, alpha, distribution="beckmann", orders=(0, 1, 2),
                 n_binder=1.5, n_phi=512, depth_nm=None):
    """f_|m| [1/sr] (M, N, W) of a grating-flake population with unit efficiency per order |m| in ``orders``
    (M,), at direction pairs ``wi``, ``wo`` (N, 3) in the binder (unit, z the coat normal, both μ > 0) and
    wavelengths (W,) [nm] in vacuum, period Λ = ``period_nm``, binder index ``n_binder``: the cone formula of the
    module docstring (m = 0: D_p(h)/(4 μ_i μ_o)).  With ``depth_nm`` the efficiency of each order is that of a
    sinusoidal grating of that amplitude (:func:`sinusoidal_efficiency`), evaluated at each flake's own cosines
    on the cone, instead of 1.  Vectorised over directions, wavelengths and φ."""
    wi = np.atleast_2d(np.asarray(wi, float))
    wo = np.atleast_2d(np.asarray(wo, float))
    lam = np.asarray(wavelength_nm, float)
    mu_i, mu_o = wi[:, 2], wo[:, 2]
    s = wi + wo
    H = np.linalg.norm(s, axis=-1)                                        # 2 cos θ_d
    h = s / H[:, None]
    norm = 2.0 / mean_flake_cosine(alpha, distribution)
    dp = lambda c: norm * flake_ndf(c, alpha, distribution)              # D_p (projected_density)
    out = np.zeros((len(orders), len(wi), lam.size))
    e1, e2 = _frame(h)
    phi = np.arange(n_phi) * (2.0 * np.pi / n_phi)
    cph, sph = np.cos(phi), np.sin(phi)
    for k, m in enumerate(orders):                                        # ≤ 3 orders: not a hot loop
        if m == 0:
            out[k] = (dp(h[:, 2]) / (4.0 * mu_i * mu_o))[:, None]
            if depth_nm is not None:
                cd = np.sum(wi * h, axis=-1)[:, None]
                out[k] *= sinusoidal_efficiency(0, cd, cd, lam[None, :], depth_nm, n_binder)
            continue
        r = abs(m) * lam[None, :] / (n_binder * period_nm)                # (1, W)
        sb = r / H[:, None]                                               # sin β₀ (N, W)
        ok = sb < 1.0
        sb = np.where(ok, sb, 0.0)
        cb = np.sqrt(1.0 - sb * sb)
        # normals on the cone: (N, W, P, 3)
        ring = cph[:, None] * e1[:, None, :] + sph[:, None] * e2[:, None, :]       # (N, P, 3)
        n = cb[..., None, None] * h[:, None, None, :] + sb[..., None, None] * ring[:, None, :, :]
        ci = np.maximum(np.einsum("nwpk,nk->nwp", n, wi), 0.0)
        co = np.maximum(np.einsum("nwpk,nk->nwp", n, wo), 0.0)
        up = n[..., 2] > 0.0
        integ = np.where(up, dp(np.where(up, n[..., 2], 1.0)), 0.0) * ci * co
        if depth_nm is not None:
            integ = integ * sinusoidal_efficiency(m, ci, co, lam[None, :, None], depth_nm, n_binder)
        ring_mean = integ.mean(axis=-1)                                   # (1/2π) ∫ dφ
        val = sb * ring_mean / (r * H[:, None] * cb * (mu_i * mu_o)[:, None])
        out[k] = np.where(ok, val, 0.0)
    return out


def grating_brdf_montecarlo(wi, wo, wavelength_nm, period_nm, alpha, order, distribution="beckmann",
                            n_binder=1.5, n_samples=2_000_000, cone_deg=2.0, seed=0, depth_nm=None):
    """Brute-force estimate of f_|m| [1/sr] at one pair (ω_i, ω_o) in the binder and one wavelength, with unit
    efficiency shared equally by +|m| and −|m|: flake normals drawn from the upper-hemisphere density 2 D(m)
    (:func:`sample_flake_normal`), grating azimuths uniform, the sign of m at random; each flake intercepts
    ⟨ω_i·m⟩ / (⟨m·z⟩ μ_i) of the coat's irradiance (⟨m·z⟩ the sample mean of m·z) and sends it along the
    direction the grating equation gives (dropped if evanescent or behind the flake); the BRDF is the power
    landing in a cone of half-angle ``cone_deg`` around ω_o over (N · solid angle · μ_o).  Independent of
    :func:`grating_brdf` (no cone formula, no projection).  With ``depth_nm`` each flake's power is weighted by
    :func:`sinusoidal_efficiency` at its own incidence and exit cosines.  Returns (estimate, its standard error)."""
    rng = np.random.default_rng(seed)
    wi = np.asarray(wi, float)
    wo = np.asarray(wo, float)
    n = sample_flake_normal(rng.random(n_samples), rng.random(n_samples), alpha, distribution)
    mean_cos = n[:, 2].mean()
    psi = rng.uniform(0.0, 2.0 * np.pi, n_samples)
    # grating direction: a uniform azimuth in the flake plane, from a fixed in-plane pair
    ref = np.where(np.abs(n[:, :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    u = np.cross(n, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(n, u)
    t = np.cos(psi)[:, None] * u + np.sin(psi)[:, None] * v
    sign = np.where(rng.random(n_samples) < 0.5, -1.0, 1.0)
    g = order * wavelength_nm / (n_binder * period_nm)
    cin = n @ wi
    wi_t = wi[None, :] - cin[:, None] * n
    out_t = -wi_t + (sign * g)[:, None] * t                                # flake-plane part of ω_o
    t2 = np.sum(out_t ** 2, axis=1)
    prop = t2 < 1.0
    w_out = out_t + np.sqrt(np.maximum(1.0 - t2, 0.0))[:, None] * n
    hit = prop & (cin > 0) & (np.arccos(np.clip(w_out @ wo, -1.0, 1.0)) < np.radians(cone_deg))
    weight = np.where(hit, np.maximum(cin, 0.0) / (mean_cos * wi[2]), 0.0)
    if depth_nm is not None:
        cout = np.maximum(np.sum(w_out * n, axis=1), 0.0)
        weight = weight * sinusoidal_efficiency(order, np.maximum(cin, 0.0), cout, wavelength_nm, depth_nm, n_binder)
    omega = 2.0 * np.pi * (1.0 - np.cos(np.radians(cone_deg)))
    scale = 1.0 / (omega * wo[2])
    return float(weight.mean() * scale), float(weight.std() / np.sqrt(n_samples) * scale)


def binder_directions(geometries_deg, n_binder=1.5):
    """(ω_i', ω_o', μ_i, μ_v) of in-plane geometries (G, 2) (θ_i, aspecular γ; viewer at θ_v = θ_i − γ, as
    :func:`flakedb.match.halfangle.binder_half_angles_deg`): the refracted unit vectors (G, 3) and the cosines
    in air (G,).  The light on the −x side, the viewer on +x at positive θ_v."""
    g = np.atleast_2d(np.asarray(geometries_deg, float))
    ti, tv = np.radians(g[:, 0]), np.radians(g[:, 0] - g[:, 1])
    si, sv = np.sin(ti) / n_binder, np.sin(tv) / n_binder
    wi = np.stack([-si, np.zeros_like(si), np.sqrt(1 - si * si)], axis=1)
    wo = np.stack([sv, np.zeros_like(sv), np.sqrt(1 - sv * sv)], axis=1)
    return wi, wo, np.cos(ti), np.cos(tv)


def grating_paint_reflectance(geometries_deg, wavelength_nm, period_nm, alpha, weights, k_d=0.0,
                              distribution="beckmann", orders=(0, 1, 2), n_binder=1.5, n_phi=256, depth_nm=None):
    """Reflectance factors R (G, W) of the single-scattering grating-flake paint (module docstring) at in-plane
    geometries (G, 2) [deg]: ``weights`` (M,) the order weights a_|m| = c η_|m| for ``orders`` (scalars, or (M, W)
    spectra), ``k_d`` the grey Lambertian floor.  With ``depth_nm`` the orders carry the sinusoidal grating's
    efficiencies (:func:`grating_brdf`) and ``weights`` is c R_flake (the coverage times the flake metal's
    reflectance)."""
    wi, wo, mu_i, mu_v = binder_directions(geometries_deg, n_binder)
    f = grating_brdf(wi, wo, wavelength_nm, period_nm, alpha, distribution, orders, n_binder, n_phi, depth_nm)
    T = (1.0 - fresnel_dielectric_real(mu_i, n_binder)) * (1.0 - fresnel_dielectric_real(mu_v, n_binder))
    w = np.asarray(weights, float)
    w = w[:, None, None] if w.ndim == 1 else w[:, None, :]
    fsum = np.sum(w * f, axis=0)                                          # (G, W)
    return np.pi * (T / n_binder ** 2)[:, None] * fsum + k_d
