"""Interfaces and boundaries as scattering matrices (docs/model.md §4).

* :func:`smooth_dielectric` — the smooth interface handled exactly: the inside quadrature is the
  Snell image of the outside one (:func:`flakedb.rt.basis.quadrature.snell_mapped_quadrature`), so
  refraction maps node j outside to node j inside with weight 1 − F, internal reflection is
  diagonal (F, and 1 in the totally internally reflected range), all in every Fourier order (a
  delta in φ_d has every order).  The first-surface mirror reflection F(θ_i) is *not* put in the
  matrix: it is returned as an analytic delta term (docs/bsdf-format.md, "Carrying a smooth clear coat's
  mirror reflection").
* :func:`rough_dielectric` — a Beckmann microfacet dielectric (Walter et al. 2007, with the exact
  Smith shadowing), reflection and transmission both ways including total internal reflection,
  integrated over the nodes' flux cells so that it carries exactly the continuous BSDF's energy
  and reciprocity at any n (:mod:`flakedb.rt.boundaries.microfacet`, docs/rough-interfaces.md).
  :func:`rough_dielectric_point_sampled` is the former node-sampled projection, kept as the
  "before" of the comparison (it creates energy once the lobe is narrower than the node spacing).
* :func:`rough_conductor` — a Beckmann microfacet conductor at the bottom of the stack.
* :func:`lambertian` — a diffuse primer at the bottom of the stack, order 0 only.

All matrices act on basic radiance (conventions, "Radiance across interfaces").
"""

import numpy as np

from flakedb.conventions import fourier_weight
from flakedb.optics.fresnel import fresnel_dielectric, fresnel_dielectric_real
from flakedb.rt.basis.fourier import project_azimuthal
from flakedb.rt.basis.layer import Layer, pad_orders
from flakedb.rt.boundaries.microfacet import rough_conductor_cells, rough_dielectric_cells, smith_G1


def smooth_dielectric(q_out, q_in, eta, L):
    """Smooth interface of relative index ``eta`` between the outside rule ``q_out`` and the Snell-
    mapped inside rule ``q_in`` (its last ``q_in.n_mapped == q_out.h`` nodes are the images).

    Returns ``(layer, delta_F)`` with ``delta_F`` (h_out,) the first-surface Fresnel reflectance at
    the outside nodes (the analytic delta term), and the layer's Rt = 0.
    """
    ho, hi = q_out.h, q_in.h
    if q_in.n_mapped != ho:
        raise ValueError("inside quadrature is not the Snell image of the outside one")
    F_out = fresnel_dielectric(q_out.x, eta).R  # from above, at the outside nodes
    h_tir = hi - ho
    j = np.arange(ho)
    T = np.zeros((hi, ho))
    T[h_tir + j, j] = 1.0 - F_out
    # Internal reflection from below at the inside nodes: F is the same at corresponding angles
    # (Stokes); in the TIR range it is 1.
    F_in = fresnel_dielectric(-q_in.x, eta).R
    Rb = np.diag(F_in)
    shape = (L, 1)
    layer = Layer(
        Rt=np.zeros(shape + (ho, ho)),
        Ttb=np.broadcast_to(T, shape + T.shape).copy(),
        Rb=np.broadcast_to(Rb, shape + Rb.shape).copy(),
        Tbt=np.broadcast_to(T.T, shape + T.T.shape).copy(),
    )
    return layer, F_out




def microfacet_Beckmann_ndf(cos_h, alpha):
    """Beckmann normal distribution (per projected area, Walter et al. 2007 eq. 25), cos_h > 0.

    The projected microfacet area is that of the surface: ∫ D(h) cos θ_h dω_h = 1 (Walter et al. eq. 4).

    >>> c, w = np.polynomial.legendre.leggauss(64)
    >>> c, w = 0.5 * (c + 1), 0.5 * w                      # Gauss–Legendre on (0, 1)
    >>> round(float(2 * np.pi * np.sum(w * microfacet_Beckmann_ndf(c, 0.3) * c)), 9)
    1.0
    """
    c2 = np.clip(cos_h, 1e-300, 1.0) ** 2
    tan2 = (1.0 - c2) / c2
    return np.where(cos_h > 0, np.exp(-tan2 / alpha**2) / (np.pi * alpha**2 * c2 * c2), 0.0)


def microfacet_dielectric_Walter2007(mu_i, mu_o, phi_d, eta_rel, alpha, transmit):
    """Basic-radiance BSDF (1/sr) of a rough dielectric for light arriving on one side of it.

    ``mu_i`` > 0 and ``mu_o`` > 0 are the cosines of the incident and outgoing propagation
    directions against the normal on their own side (geometry of arrival from above); ``phi_d``
    as in the conventions; ``eta_rel`` = index of the far side / index of the arrival side.
    ``transmit`` False gives reflection f_r = F D G / (4 μ_i μ_o) (Walter et al. 2007 eq. 20),
    True gives transmission in basic radiance
    f_t = |i·h||o·h| (1 − F) D G / (μ_i μ_o (i·h + η o·h)²)  (Walter eq. 21 divided by η²).
    G is the separable Smith term with the exact Beckmann G1.
    """
    si = np.sqrt(np.maximum(1.0 - mu_i**2, 0.0))
    so = np.sqrt(np.maximum(1.0 - mu_o**2, 0.0))
    # graphics vectors: wi points back to where the light came from; wo's azimuth is φ_d + π
    wi = (si, 0.0 * si, mu_i)
    cphi, sphi = np.cos(phi_d + np.pi), np.sin(phi_d + np.pi)
    oz = -mu_o if transmit else mu_o
    wo = (so * cphi, so * sphi, oz)
    if not transmit:
        hx, hy, hz = wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]
    else:
        hx, hy, hz = -(wi[0] + eta_rel * wo[0]), -(wi[1] + eta_rel * wo[1]), -(wi[2] + eta_rel * wo[2])
    norm = np.sqrt(hx * hx + hy * hy + hz * hz)
    norm = np.where(norm > 0, norm, 1.0)
    flip = np.where(hz < 0, -1.0, 1.0)
    hx, hy, hz = hx * flip / norm, hy * flip / norm, hz * flip / norm
    i_h = wi[0] * hx + wi[1] * hy + wi[2] * hz
    o_h = wo[0] * hx + wo[1] * hy + wo[2] * hz
    D = microfacet_Beckmann_ndf(hz, alpha)
    G = smith_G1(mu_i, alpha) * smith_G1(mu_o, alpha)
    # the facet must face both directions consistently (χ⁺ terms)
    F = fresnel_dielectric_real(i_h, eta_rel)
    if not transmit:
        valid = (i_h > 0) & (o_h > 0)
        f = F * D * G / (4.0 * mu_i * mu_o)
    else:
        valid = (i_h > 0) & (o_h < 0)
        denom = (i_h + eta_rel * o_h) ** 2
        denom = np.where(denom > 0, denom, np.inf)
        f = np.abs(i_h * o_h) * (1.0 - F) * D * G / (mu_i * mu_o * denom)
    return np.where(valid & (hz > 0), f, 0.0)


def _bsdf_block(fn, x_in, w_in, x_out, w_out, tol, n_start, max_orders):
    """Scattering-matrix block S_l[o, i] = c_l w_i μ_i f_l from a BSDF ``fn(mu_i, mu_o, phi)``.

    The projected quantity is f·μ_o (the stored quantity of docs/bsdf-format.md), so the adaptive
    tolerance is relative to what a file holds.
    """
    W = (w_in * x_in)[:, None] * (w_out * 1.0)[None, :]  # energy carried i → o per unit f·μ_o
    coeffs, info = project_azimuthal(lambda mi, mo, ph: fn(mi, mo, ph) * mo, x_in, x_out, tol=tol,
                                     n_start=min(n_start, max(2 * max_orders, 128)), n_max=max(2 * max_orders, 128),
                                     weights=W)
    coeffs = coeffs[:max_orders]
    L = coeffs.shape[0]
    cl = fourier_weight(np.arange(L))[:, None, None, None]
    S = cl * coeffs / x_out[:, None] * (w_in * x_in)[None, :]
    return S, info


def rough_dielectric(q_out, q_in, eta, alpha, tol=1e-5, max_orders=512, energy_compensation=True, inner_orders=None,
                     threads=1, jobs=None):
    """Rough dielectric interface (Beckmann α, relative index η) as a :class:`Layer`, by flux-cell
    integration (:func:`flakedb.rt.boundaries.microfacet.rough_dielectric_cells`): every column of order 0
    carries the continuous BSDF's directional albedo, the blocks are reciprocal, and as α → 0 it
    tends to the smooth interface.  ``q_out`` is the rule above (air, or the binder above an inner
    interface), ``q_in`` the rule below; they may differ (the cells integrate between any two rules).
    ``eta`` = n_below / n_above, > 1 or < 1.
    ``energy_compensation``: add the reciprocal multiple-scattering lobe (lossless interface,
    :func:`flakedb.rt.boundaries.microfacet.dielectric_compensation`).  ``inner_orders``: T^tb, R^b and T^bt
    only below that order (:func:`flakedb.rt.boundaries.microfacet.rough_dielectric_cells`).  ``threads``, ``jobs``: the
    threads its independent parts run on, a :class:`flakedb.rt.common.jobs.SharedJobs` other threads may help
    (bit-identical either way).  Returns ``(layer, info)``.
    """
    same = q_in.h == q_out.h and np.array_equal(q_in.x, q_out.x) and np.array_equal(q_in.w, q_out.w)
    blocks, info = rough_dielectric_cells(q_out.x, q_out.w, eta, alpha, tol=tol, max_orders=max_orders,
                                          energy_compensation=energy_compensation,
                                          x_below=None if same else q_in.x, w_below=None if same else q_in.w,
                                          inner_orders=inner_orders, threads=threads, jobs=jobs)
    return Layer(*blocks), info


def rough_conductor(q, eta_complex, alpha, tol=1e-5, max_orders=512, energy_compensation=True):
    """Rough conductor (Beckmann α, complex index relative to the binder above, scalar or (C,)) at
    the bottom of the stack: reflection only, by flux-cell integration
    (:func:`flakedb.rt.boundaries.microfacet.rough_conductor_cells`).  Returns ``(Rt, info)``, Rt (L, C, h, h)."""
    return rough_conductor_cells(q.x, q.w, eta_complex, alpha, tol=tol, max_orders=max_orders,
                                 energy_compensation=energy_compensation)


def rough_dielectric_point_sampled(q_out, q_in, eta, alpha, tol=1e-5, max_orders=512):
    """The former discretisation: the BSDF sampled at the node pairs and projected on the cosine
    series (:func:`flakedb.rt.basis.fourier.project_azimuthal`).  Wrong once the lobe is narrower than
    the node spacing (energy created or lost); kept for comparison.  Returns ``(layer, info)``.
    """
    n_start = int(max(16, 2 ** np.ceil(np.log2(4.0 / alpha))))
    blocks = {}
    infos = {}
    for name, x_in, w_in, x_out, w_out, eta_rel, transmit in (
        ("Rt", q_out.x, q_out.w, q_out.x, q_out.w, eta, False),
        ("Ttb", q_out.x, q_out.w, q_in.x, q_in.w, eta, True),
        ("Rb", q_in.x, q_in.w, q_in.x, q_in.w, 1.0 / eta, False),
        ("Tbt", q_in.x, q_in.w, q_out.x, q_out.w, 1.0 / eta, True),
    ):
        fn = lambda mi, mo, ph, e=eta_rel, t=transmit: microfacet_dielectric_Walter2007(mi, mo, ph, e, alpha, t)
        blocks[name], infos[name] = _bsdf_block(fn, x_in, w_in, x_out, w_out, tol, n_start, max_orders)
    L = max(b.shape[0] for b in blocks.values())
    for k, b in blocks.items():
        if b.shape[0] < L:
            blocks[k] = pad_orders(b, L)
    return Layer(**blocks), infos


def lambertian(q, albedo, L):
    """Lambertian primer of spectral ``albedo`` (C,) at the bottom of a layer with rule ``q``.

    f = albedo/π, order 0 only: S_0[o, i] = 2π w_i μ_i · albedo/π = 2 albedo w_i μ_i.  Nothing is
    transmitted; the bottom-side blocks are zero.
    """
    albedo = np.atleast_1d(np.asarray(albedo, dtype=float))
    h = q.h
    Rt = np.zeros((L, len(albedo), h, h))
    Rt[0] = 2.0 * albedo[:, None, None] * (q.w * q.x)[None, None, :]
    zero = np.zeros((L, 1, h, h))
    return Layer(Rt, zero, zero.copy(), zero.copy())


def smooth_inner(q_above, q_below, ia, ib, eta_rel, L):
    """Smooth interface *between two slabs* (docs/model.md §4 "Inner interface"), relative index
    ``eta_rel`` = n_below / n_above (a rise > 1 or a fall < 1), on the rules of
    :func:`flakedb.rt.basis.quadrature.binder_chain_quadratures` (mapped pairs ``ia`` ↔ ``ib``: the nodes of equal
    Snell invariant; the others are totally reflected on their side).  Unlike the top, its mirror reflection is inside the stack, so it is
    in the matrix: R^t = diag(F_a), R^b = diag(F_b) (1 where no partner: total internal reflection),
    T^tb[ib, ia] = 1 − F_a[ia], T^bt = (T^tb)ᵀ, in every Fourier order (a delta in φ_d).

    Energy is conserved by construction: for each above node, R^t + T^tb carry F + (1 − F) = 1 of
    its flux (the mapped weights satisfy η² w_b μ_b = w_a μ_a, basic radiance), and the same from
    below; reciprocity: T^bt = (T^tb)ᵀ and diagonal reflections.  Returns a :class:`Layer` of L orders.
    """
    ha, hb = q_above.h, q_below.h
    F_a = fresnel_dielectric(q_above.x, eta_rel).R
    F_b = fresnel_dielectric(-q_below.x, eta_rel).R
    F_a = np.where(np.isin(np.arange(ha), ia), F_a, 1.0)
    F_b = np.where(np.isin(np.arange(hb), ib), F_b, 1.0)
    T = np.zeros((hb, ha))
    T[ib, ia] = 1.0 - F_a[ia]
    shape = (L, 1)
    return Layer(
        Rt=np.broadcast_to(np.diag(F_a), shape + (ha, ha)).copy(),
        Ttb=np.broadcast_to(T, shape + T.shape).copy(),
        Rb=np.broadcast_to(np.diag(F_b), shape + (hb, hb)).copy(),
        Tbt=np.broadcast_to(T.T, shape + T.T.shape).copy(),
    )
