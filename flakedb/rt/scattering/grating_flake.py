"""Grating-embossed (diffractive, holographic) micro-flakes as a scattering medium (issue 35; docs/model.md §3,
"Grating flakes"): the kernel σ_s f_p(ω_i → ω_o) of flakes that reflect like the specular flakes of
:mod:`flakedb.rt.scattering.microflake` but diffract the reflected light into the orders of a linear grating of
period Λ whose direction in the flake plane is uniform in azimuth.

Conventions as :mod:`flakedb.rt.scattering.microflake` (propagation directions, ``mu > 0`` travels down, φ_d = 0
forward / mirror); the flake normal density D is even over the sphere (both faces reflect) and ∫ D = 1.

Grating equation (reflection, order k, in the binder of index n_b; a flake of normal n, grating direction t̂)
--------------------------------------------------------------------------------------------------------
The flake-plane part of the direction changes by k g t̂, g = λ / (n_b Λ):

    P_n(ω_o) = P_n(ω_i) + k g t̂,    ω_o · n of the sign opposite to ω_i · n (reflection),

an order with |P_n(ω_o)| ≥ 1 is evanescent.  k = 0 is the mirror.

Order efficiencies (scalar theory of a sinusoidal reflection grating, the energy closed on the mirror order)
--------------------------------------------------------------------------------------------------------
Of the power R(c_in) a flake reflects (c_in = |ω_i·n|, R the flake's reflectance, e.g. the metal's), order
k ≠ 0 carries e_k = J_|k|²(Φ_k), Φ_k = 2π n_b a (c_in + c_out,k) / λ (Kirchhoff / Raman–Nath: the phase of a
surface a sin(2π x/Λ); :func:`sinusoidal_order_efficiency`), where it propagates; the mirror order carries the
rest, η_0 = 1 − Σ_{k≠0, propagating} e_k (η_0 → J_0² when every order propagates at one Φ, Σ J_k² = 1).  So a
flake reflects exactly R(c_in) (the grating only redistributes it; the power scalar theory puts in evanescent
orders returns to the mirror order, where a rigorous (RCWA) solution would share it among the propagating
orders: an assumption), and since e_k is symmetric in (c_in, c_out) and J_|k| = J_|−k|, the kernel is
reciprocal where R is constant in c.  η_0 ≥ 0 needs Σ e_k ≤ 1: guaranteed for 4π n_b a / λ ≤ j'_{1,1} =
1.8412 (every J_k, k ≥ 1, increases up to it); beyond, a scan of Φ_max 1.8-6, g 0.3-1.2, all c_in and
azimuths gives Σ e_k ≤ 0.89 (docs/model.md §3); η_0 is clipped at 0 should it ever fall below.

Kernel (the cone formula; the derivation of flakedb.match.grating moved into the medium's frame)
-------------------------------------------------------------------------------------------------
With s = ω_o − ω_i, H = |s| = 2 sin(Θ/2), h = s / H (the specular flakes' half vector), a uniform grating
azimuth turns the 2-D delta δ²(P_n(s) − k g t̂) into δ(|P_n(s)| − r)/(2π r), r = |k| g, and |P_n(s)| = H sin β
(β the angle between n and ±h): the orders ±k select the normals on the cone β₀ = asin(r / H) around ±h (two
antipodal cones, one flake population: the factor 2), and

    σ_s f_|k| = aρ · 2 sin β₀ / (H cos β₀ r) · ⟨D(n) |ω_i·n| |ω_o·n| V(n) R(|ω_i·n|) 2 J_|k|²(Φ_k)⟩_φ  (r < H),

⟨·⟩_φ the mean over the cone's azimuth φ (periodic trapezoidal rule on ``n_cone`` nodes, :func:`cone_nodes`), V = 1 where
(ω_i·n)(ω_o·n) < 0 (the order leaves on the lit side).  The mirror order is the specular flakes' kernel
(aρ/2) R(c) D(h) (:func:`flakedb.rt.scattering.microflake.kernel_Ergun`) times η_0 averaged over the grating
azimuth ψ at n = h: for each order k the propagating arc |P_h(ω_i) + k g t̂(ψ)| < 1 is an interval of ψ in closed
form, and e_k is integrated on it by Gauss–Legendre in u = √(ψ − ψ_c) (c_out,k ∝ √(ψ − ψ_c) at the arc's end).
As r → 0 the cone closes on h and the order-k term tends to 2 J_k² times the mirror term (tested).

σ_t and σ_s are the specular flakes' (:func:`flakedb.rt.scattering.microflake.extinction_Ergun`,
``scattering_Ergun``): the grating changes where the reflected light goes, not how much.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.special import jv

from flakedb.rt.common.params import check_range
from flakedb.rt.common.reuse import array_key
from flakedb.rt.scattering.media import KernelBasis
from flakedb.rt.scattering.microflake import (
    FlakeOptics,
    extinction_Ergun,
    flake_distribution,
    interp_rows,
    scattering_Ergun,
)

__all__ = ["GratingFlakeMedium", "grating_flake_kernel", "sinusoidal_order_efficiency", "highest_order",
           "mirror_order_efficiency", "SCALAR_PHASE_GUARANTEE", "GRATING_CONE_NODES_PER_INV_ALPHA", "cone_nodes", "GRATING_ARC_NODES"]

#: j'_{1,1}, the first maximum of J_1: below a peak phase 4π n_b a / λ of this, Σ_{k≠0} e_k ≤ 1 − J_0² holds
#: for any cosines (module docstring).
SCALAR_PHASE_GUARANTEE = 1.8411837813406593
#: Nodes on the cone of flake normals (periodic trapezoidal rule in φ) per unit 1/α, clipped to
#: [:data:`GRATING_CONE_MIN`, :data:`GRATING_CONE_MAX`] (:func:`cone_nodes`): the lobe of D on the cone is ~α
#: wide.  Measured against 1024 nodes (Λ 700 nm, a 50 nm, 500 nm, 400 random pairs): α 0.08 with 48 nodes
#: 1.9e-6 of the kernel's maximum (32: 1.3e-4), α 0.3 with 32 nodes 9e-5 (mean 8e-6).
GRATING_CONE_NODES_PER_INV_ALPHA = 4.0
GRATING_CONE_MIN, GRATING_CONE_MAX = 32, 256
#: Gauss–Legendre nodes on each order's propagating arc of grating azimuths (the mirror order's η_0).
GRATING_ARC_NODES = 12


@functools.lru_cache(maxsize=4)
def _gauss_legendre(n):
    return np.polynomial.legendre.leggauss(int(n))


def sinusoidal_order_efficiency(order, cos_in, cos_out, wavelength_nm, amplitude_nm, n_binder=1.5):
    """e_|k| = J_|k|²(Φ), Φ = 2π n_b a (c_in + c_out) / λ: the fraction of the reflected power in *one* order
    k of a sinusoidal reflection grating of amplitude a = ``amplitude_nm`` (surface a sin(2π x/Λ), peak to
    valley 2a), scalar (Kirchhoff / Raman–Nath) theory, cosines to the flake normal, λ in vacuum (the phase is
    taken in the binder, n_b).  At one Φ, Σ over all integers k is 1 (Σ J_k² = 1).  Scalar theory is the limit
    Λ ≫ λ with shallow grooves; it ignores polarisation, the metal's phase and the resonances that rigorous
    (RCWA) theory gives at Λ/λ ~ 1-2 (E. G. Loewen and E. Popov, Diffraction Gratings and Applications, 1997).

    >>> e = [sinusoidal_order_efficiency(k, 0.9, 0.9, 550.0, 80.0) for k in range(-30, 31)]
    >>> bool(abs(sum(e) - 1.0) < 1e-12)
    True
    """
    phi = (2.0 * np.pi * np.asarray(n_binder, float) * amplitude_nm
           * (np.asarray(cos_in, float) + np.asarray(cos_out, float)) / np.asarray(wavelength_nm, float))
    return _bessel_j(abs(int(order)), phi) ** 2


#: Terms of the power series of J_k used by :func:`_bessel_j` for arguments ≤ :data:`_SERIES_MAX_ARG`: the
#: dropped tail at x = 8 is below 1e-16 of the largest term (which is ≤ 1e3: ~13 digits kept).
_SERIES_TERMS = 36
_SERIES_MAX_ARG = 8.0


def _bessel_j(k, x):
    """J_k(x) for an integer k ≥ 0: the power series J_k(x) = (x/2)^k Σ_m (−x²/4)^m / (m! (m+k)!) (Abramowitz &
    Stegun 9.1.10) by Horner's rule where every argument is ≤ 8 (the grating phases here; 4-10× faster than
    scipy's general ``jv``), else ``scipy.special.jv``.  Agrees with ``jv`` to 1e-13 (tested)."""
    x = np.asarray(x, float)
    if x.size == 0 or np.max(np.abs(x)) > _SERIES_MAX_ARG:
        return jv(k, x)
    y = -0.25 * x * x
    acc = np.ones_like(x)
    for m in range(min(_SERIES_TERMS, 10 + int(3.0 * np.max(np.abs(x)))), 0, -1):   # Horner: ratio y / (m (m+k))
        acc = 1.0 + acc * y / (m * (m + k))
    return acc * (0.5 * x) ** k / float(np.prod(np.arange(1, k + 1)))


def highest_order(wavelength_nm, period_nm, n_binder) -> int:
    """The largest |k| that can propagate for any flake and direction pair: k g < 2, g = λ/(n_b Λ)."""
    g = np.min(np.asarray(wavelength_nm, float) / (np.asarray(n_binder, float) * float(period_nm)))
    return int(np.ceil(2.0 / g)) - 1 if g < 2.0 else 0


def mirror_order_efficiency(p_abs, c_in, g, amplitude_nm, wavelength_nm, n_binder, K, n_arc=GRATING_ARC_NODES):
    """η_0 averaged over a uniform grating azimuth ψ, (...): 1 − Σ_{k=1..K} 2 ⟨1[order k propagates] e_k⟩_ψ
    for a flake lit at incidence cosine ``c_in`` with |P_n(ω_i)| = ``p_abs`` (= √(1 − c_in²)), all arrays
    broadcasting with ``g`` = λ/(n_b Λ), ``wavelength_nm`` and ``n_binder``.  Order ±k leaves with
    |P|² = p² + k²g² + 2 k g p cos ψ' (ψ' from P_n(ω_i)), propagating for cos ψ' < c* = (1 − p² − k²g²)/(2kgp):
    the arc ψ' ∈ (ψ_c, π] of length π − ψ_c out of π (by symmetry), integrated by Gauss–Legendre in
    u = √(ψ' − ψ_c).  Clipped at 0 (module docstring)."""
    x, w = _gauss_legendre(n_arc)
    p, ci, g, lam, nb = np.broadcast_arrays(*(np.asarray(v, float) for v in (p_abs, c_in, g, wavelength_nm,
                                                                            n_binder)))
    total = np.zeros(p.shape)
    for k in range(1, K + 1):                        # K ≤ a handful (highest_order): not a hot loop
        kg = k * g
        with np.errstate(divide="ignore", invalid="ignore"):
            cstar = np.where(p > 0.0, (1.0 - p * p - kg * kg) / (2.0 * kg * np.maximum(p, 1e-300)),
                             np.where(kg < 1.0, 2.0, -2.0))
        psi_c = np.arccos(np.clip(cstar, -1.0, 1.0))
        umax = np.sqrt(np.maximum(np.pi - psi_c, 0.0))
        u = 0.5 * umax[..., None] * (x + 1.0)                                  # (..., n_arc)
        psi = psi_c[..., None] + u * u
        q2 = (p * p + kg * kg)[..., None] + (2.0 * kg * p)[..., None] * np.cos(psi)
        c_out = np.sqrt(np.clip(1.0 - q2, 0.0, 1.0))
        e = sinusoidal_order_efficiency(k, ci[..., None], c_out, lam[..., None], amplitude_nm, nb[..., None])
        integral = np.sum(0.5 * umax[..., None] * w * 2.0 * u * e, axis=-1)  # ∫ e dψ' over the arc
        total = total + 2.0 * integral / np.pi                                # ±k, mean over ψ' in [0, π]
    return np.maximum(1.0 - total, 0.0)


def _interp_channels(R, c_grid, x, rows):
    """R[rows[j]](x[j]): the rows of ``R`` (C, nc) named by ``rows`` (any shape, like ``x``), linear on
    ``c_grid`` and held constant outside it (as :func:`flakedb.rt.scattering.microflake.interp_rows`)."""
    if c_grid.size == 1:
        return R[rows, 0]
    xc = np.clip(x, c_grid[0], c_grid[-1])
    j = np.clip(np.searchsorted(c_grid, xc, side="right") - 1, 0, c_grid.size - 2)
    t = (xc - c_grid[j]) / (c_grid[j + 1] - c_grid[j])
    lo = R[rows, j]
    return lo + (R[rows, j + 1] - lo) * t


def cone_nodes(alpha) -> int:
    """The cone's node count for an orientation spread α (:data:`GRATING_CONE_NODES_PER_INV_ALPHA`)."""
    return int(np.clip(np.ceil(GRATING_CONE_NODES_PER_INV_ALPHA / float(alpha)), GRATING_CONE_MIN,
                       GRATING_CONE_MAX))


def _directions(mu_i, mu_o, phi_d):
    """Propagation unit vectors (N, 3) of (μ_i, μ_o, φ_d) (conventions: (s cos φ, s sin φ, −μ), φ_i = 0)."""
    s_i = np.sqrt(np.maximum(0.0, (1.0 - mu_i) * (1.0 + mu_i)))
    s_o = np.sqrt(np.maximum(0.0, (1.0 - mu_o) * (1.0 + mu_o)))
    wi = np.stack([s_i, np.zeros_like(s_i), -mu_i], axis=-1)
    wo = np.stack([s_o * np.cos(phi_d), s_o * np.sin(phi_d), -mu_o], axis=-1)
    return wi, wo


def _frame(h):
    """Unit vectors e1, e2 (..., 3) completing h (..., 3): e1 in the plane of h and the coat normal z (towards
    z), e2 = h × e1; x where h ∥ z.  Defined by the geometry alone, so the cone's nodes move with a rotation
    about z, a reversal of the path and the mirror z -> −z (reciprocity and the solver's symmetry hold node
    by node)."""
    z = np.array([0.0, 0.0, 1.0])
    e1 = z - h[..., 2:3] * h
    n1 = np.linalg.norm(e1, axis=-1, keepdims=True)
    e1 = np.where(n1 > 1e-9, e1 / np.where(n1 > 1e-9, n1, 1.0), np.array([1.0, 0.0, 0.0]))
    return e1, np.cross(h, e1)


#: Cones (and mirror-order terms) whose flake density stays below this fraction of its peak are skipped: they
#: add less than this relative to the kernel's scale (D is monotone in the polar angle for every registered law).
NDF_PRUNE = 1e-12

#: Points × channels × cone nodes handled at once by :func:`grating_flake_kernel` (memory: ~10 arrays of this).
_CHUNK_ELEMS = 1_000_000


def grating_flake_kernel(mu_i, mu_o, phi_d, alpha, c_grid, R, wavelength_nm, period_nm, amplitude_nm, n_binder,
                         a_rho_per_um, distribution="beckmann", n_cone=None, orders=None):
    """σ_s f_p(ω_i → ω_o) [1/(µm·sr)] of grating flakes, (C, *broadcast shape): the mirror order plus the
    cone terms of orders 1..K (module docstring).  ``R`` (C, nc): the flake reflectance at the flake cosines
    ``c_grid`` (nc,) per channel (linear in c between nodes); ``wavelength_nm`` (C,) each channel's vacuum
    wavelength; ``n_binder`` scalar or (C,); ``period_nm`` Λ; ``amplitude_nm`` the sinusoid's amplitude a
    (0: a specular flake); ``a_rho_per_um`` the loading (flake area per volume).  ``orders``: restrict to
    these |k| (tests; None: every order that can propagate, the mirror order included)."""
    check_range("grating_flake_kernel", "alpha", alpha, 0.0, None, lo_open=True)
    alpha = float(alpha)
    n_cone = cone_nodes(alpha) if n_cone is None else int(n_cone)
    ndf = flake_distribution(distribution).ndf
    mu_i, mu_o, phi_d = np.broadcast_arrays(np.asarray(mu_i, float), np.asarray(mu_o, float),
                                            np.asarray(phi_d, float))
    shape = mu_i.shape
    R = np.atleast_2d(np.asarray(R, float))
    C = R.shape[0]
    lam = np.broadcast_to(np.asarray(wavelength_nm, float).ravel(), (C,))
    nb = np.broadcast_to(np.asarray(n_binder, float).ravel(), (C,))
    g = lam / (nb * float(period_nm))                                         # (C,)
    K = highest_order(lam, period_nm, nb)
    ks = [k for k in range(0, K + 1) if orders is None or k in orders]
    c_grid = np.asarray(c_grid, float)
    wi, wo = _directions(mu_i.ravel(), mu_o.ravel(), phi_d.ravel())
    N = wi.shape[0]
    out = np.zeros((C, N))
    phi = np.arange(n_cone) * (2.0 * np.pi / n_cone)
    cph, sph = np.cos(phi), np.sin(phi)
    per = max(1, _CHUNK_ELEMS // max(1, C * n_cone))
    floor = NDF_PRUNE * float(ndf(np.array(1.0), alpha))                       # D is largest at the pole
    for lo in range(0, N, per):                                               # memory chunks
        sl = slice(lo, min(N, lo + per))
        a, b = wi[sl], wo[sl]
        s = b - a
        H = np.linalg.norm(s, axis=-1)
        ok = H > 1e-12
        Hs = np.where(ok, H, 1.0)
        h = np.where(ok[:, None], s / Hs[:, None], np.array([0.0, 0.0, 1.0]))
        if 0 in ks:
            c = 0.5 * H                                                       # |ω_i·h|
            dh = np.where(ok, ndf(h[:, 2], alpha), 0.0)
            base = 0.5 * dh[None, :] * interp_rows(R, c_grid, c)             # (C, n)
            if amplitude_nm > 0.0 and K > 0:
                lit = np.nonzero(dh > floor)[0]                               # η_0 only where the term counts
                p = np.sqrt(np.maximum(0.0, 1.0 - c[lit] * c[lit]))
                eta0 = np.zeros(base.shape)
                eta0[:, lit] = mirror_order_efficiency(p[None, :], c[lit][None, :], g[:, None], amplitude_nm,
                                                       lam[:, None], nb[:, None], K)
                base = base * eta0
            out[:, sl] += base
        e1, e2 = _frame(h)
        # n(φ) = cos β₀ h + sin β₀ (cos φ e1 + sin φ e2): its products with ω_i, ω_o and z are linear in the
        # per-point scalars below, so no (C, n, P, 3) array is formed
        ring_i = np.einsum("nk,nk->n", a, e1)[:, None] * cph + np.einsum("nk,nk->n", a, e2)[:, None] * sph
        ring_o = np.einsum("nk,nk->n", b, e1)[:, None] * cph + np.einsum("nk,nk->n", b, e2)[:, None] * sph
        ring_z = e1[:, 2:3] * cph + e2[:, 2:3] * sph                         # (n, P)
        h_i, h_o = np.einsum("nk,nk->n", a, h), np.einsum("nk,nk->n", b, h)
        theta_h = np.arccos(np.minimum(np.abs(h[:, 2]), 1.0))                 # ±h's angle to the pole
        for k in ks:                                                          # ≤ a handful of orders
            if k == 0 or amplitude_nm <= 0.0:
                continue
            r = k * g                                                         # (C,)
            sb_all = r[:, None] / Hs[None, :]                                 # sin β₀ (C, n)
            good = ok[None, :] & (sb_all < 1.0)
            # the cone's point nearest the pole is |θ_h − β₀| from it: skip cones where D stays below the floor
            near = np.abs(theta_h[None, :] - np.arcsin(np.where(good, sb_all, 0.0)))
            jc, jn = np.nonzero(good & (ndf(np.cos(near), alpha) > floor))
            if jc.size == 0:
                continue
            sb = sb_all[jc, jn][:, None]
            cb = np.sqrt(1.0 - sb * sb)
            ci = cb * h_i[jn][:, None] + sb * ring_i[jn]                      # (A, P)
            co = cb * h_o[jn][:, None] + sb * ring_o[jn]
            nz = cb * h[jn, 2][:, None] + sb * ring_z[jn]
            d = np.where((ci * co) < 0.0, ndf(nz, alpha), 0.0)               # V(n) D(n)
            live = np.nonzero(d > floor)                                      # the Bessel functions only there
            aci, aco = np.abs(ci[live]), np.abs(co[live])
            ch = jc[live[0]]
            eff = 2.0 * sinusoidal_order_efficiency(k, aci, aco, lam[ch], amplitude_nm, nb[ch])
            integ = np.zeros(d.shape)
            integ[live] = d[live] * aci * aco * _interp_channels(R, c_grid, aci, ch) * eff
            mean = integ.mean(axis=-1)                                        # (A,)
            fac = 2.0 * sb[:, 0] / (Hs[jn] * cb[:, 0] * r[jc])
            np.add.at(out, (jc, lo + jn), fac * mean)
    return (float(a_rho_per_um) * out).reshape((C,) + shape)


@dataclass
class GratingFlakeMedium:
    """Grating-embossed micro-flakes (module docstring): the specular flakes' σ_t, σ_s (orientation spread
    ``alpha`` of ``distribution``, :class:`FlakeOptics` ``optics``, loading ``a_rho_per_um``) with the
    reflected light diffracted by a sinusoidal grating of period ``period_nm`` and amplitude ``amplitude_nm``
    in a binder of index ``n_binder``; each channel is the vacuum wavelength ``wavelength_nm`` (C,) (spectral
    channels only: an RGB channel has no wavelength)."""

    alpha: float
    optics: object
    a_rho_per_um: float
    wavelength_nm: np.ndarray
    period_nm: float
    amplitude_nm: float
    n_binder: object = 1.5
    distribution: str = "beckmann"
    n_cone: int | None = None

    def __post_init__(self):
        check_range("GratingFlakeMedium", "alpha", self.alpha, 0.0, None, lo_open=True)
        check_range("GratingFlakeMedium", "a_rho_per_um", self.a_rho_per_um, 0.0, None)
        check_range("GratingFlakeMedium", "period_nm", self.period_nm, 0.0, None, lo_open=True)
        check_range("GratingFlakeMedium", "amplitude_nm", self.amplitude_nm, 0.0, None)
        self.distribution = flake_distribution(self.distribution).name
        self.wavelength_nm = np.broadcast_to(np.asarray(self.wavelength_nm, float).ravel(),
                                             (self.optics.R.shape[0],)).copy()
        self.n_binder = np.broadcast_to(np.asarray(self.n_binder, float).ravel(), self.wavelength_nm.shape).copy()

    def sigma_t(self, mu):
        return extinction_Ergun(np.abs(mu), self.alpha, self.optics, self.a_rho_per_um, distribution=self.distribution)

    def sigma_s(self, mu):
        return scattering_Ergun(np.abs(mu), self.alpha, self.optics, self.a_rho_per_um, distribution=self.distribution)

    def subset(self, idx):
        o = self.optics
        idx = np.atleast_1d(idx)
        return GratingFlakeMedium(self.alpha, FlakeOptics(o.c, o.R[idx], o.T[idx]), self.a_rho_per_um,
                                  self.wavelength_nm[idx], self.period_nm, self.amplitude_nm, self.n_binder[idx],
                                  self.distribution, self.n_cone)

    def channel_key(self, C):
        """(C, 2 nc + 2): R(c), T(c), the wavelength and the binder index of each channel (the geometry of the
        orders depends on λ / n_b)."""
        o = self.optics
        return np.concatenate([np.broadcast_to(o.R, (C, o.c.size)), np.broadcast_to(o.T, (C, o.c.size)),
                               self.wavelength_nm[:, None], self.n_binder[:, None]], axis=1)

    def _kernel_unit(self, mu_i, mu_o, phi_d):
        return grating_flake_kernel(mu_i, mu_o, phi_d, self.alpha, self.optics.c, self.optics.R, self.wavelength_nm,
                                    self.period_nm, self.amplitude_nm, self.n_binder, 1.0, self.distribution,
                                    self.n_cone)

    def kernel(self, mu_i, mu_o, phi_d):
        return float(self.a_rho_per_um) * self._kernel_unit(mu_i, mu_o, phi_d)

    def kernel_basis(self):
        """One basis kernel per channel (the orders' geometry depends on each channel's wavelength), per unit
        loading, with the loading in M = aρ I: the basis (and a fit's cached projection of it) is the same at
        every loading (:class:`flakedb.rt.scattering.media.KernelBasis`)."""
        o = self.optics
        key = ("grating flake", float(self.alpha), self.distribution, array_key(o.c), array_key(o.R),
               array_key(self.wavelength_nm), array_key(self.n_binder), float(self.period_nm),
               float(self.amplitude_nm), self.n_cone)
        C = o.R.shape[0]
        return KernelBasis(self._kernel_unit, float(self.a_rho_per_um) * np.eye(C), ((key, self._kernel_unit, C),))

    @property
    def phi_bandwidth(self):
        return flake_distribution(self.distribution).phi_samples(self.alpha)
