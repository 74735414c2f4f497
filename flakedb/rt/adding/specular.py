"""The specular part of a stack's reflection, and the pole (docs/model.md §4 "Inner interface",
"Specular paths and the pole").

A smooth inner interface reflects a mirror image: a delta in direction, which in the cosine series of
φ_d is the same matrix in every Fourier order.  Seen from the air through a smooth top (or without a
top interface) it stays a delta, and a delta's truncated series rings below zero (a 1.5 coat over a 1.6
basecoat at n = 32 reached −0.42 against a maximum of 2.17).  The paths that never scatter (the direct
beam through slabs, the mirrors and refractions of smooth interfaces) add up to a matrix R_s that is
the same in every order; it is computed once by adding the parts' specular blocks alone
(:func:`specular_reflection`), taken out of every order of the solved R^t before the order choice
(the remainder is the scattered light, whose series decays), and put back with the Jackson kernel's
factors at the chosen order count L (:func:`smoothed_specular`): R^t_l = R^t_l,scattered + g_l R_s.
g_0 = 1 keeps its energy exactly, g_l ≥ 0 of a positive kernel keeps it positive (a mirror becomes a
lobe ≈ π/L wide in φ_d at its own node pair), and R_s is symmetric (reciprocity kept).

At the pole μ = 1 a direction has no azimuth, so only order 0 may be non-zero in the row and the column
of the node μ = 1 (:func:`flakedb.rt.basis.pole.zero_pole_orders`); a discrete cell rule leaves azimuth-dependent terms there
(coated aluminium: +84 % at n = 48 in the normal-incidence column, falling as 1/n).
"""

import numpy as np

from flakedb.rt.boundaries.microfacet import jackson_factors
from flakedb.rt.adding.orders import reflection_over, reflection_under_smooth
from flakedb.rt.basis.pole import pole_index, zero_pole_orders  # noqa: F401  (re-exported)


def specular_reflection(parts, through_top):
    """R_s (C, h, h) of the stack seen from above: the parts' specular blocks (:meth:`specular` of
    :mod:`flakedb.rt.adding.parts`) added bottom-up over a black bottom (a primer or a rough metal reflects
    nothing unscattered), then ``through_top(R)`` (the smooth top's transmission and internal
    reflections, or the identity).  None when nothing is reflected unscattered."""
    R = None
    for part in reversed(parts):
        R = reflection_over(part.specular(), R)
    if R is None or not np.any(R):
        return None
    Rs = through_top(np.asarray(R))
    return None if not np.any(Rs) else np.array(Rs[0])


def smooth_top_transfer(smooth1, h_out):
    """``(t, F_in, h_tir)`` of a smooth top's layer (:func:`flakedb.rt.boundaries.interface.smooth_dielectric`):
    the transmissions 1 − F at the mapped nodes and the internal reflection (the arguments of
    :func:`flakedb.rt.adding.orders.reflection_under_smooth`)."""
    h_tir = smooth1.Ttb.shape[-2] - h_out
    t = smooth1.Ttb[0, 0][h_tir + np.arange(h_out), np.arange(h_out)]
    return t, np.diagonal(smooth1.Rb[0, 0]), h_tir


def under_smooth(smooth1, h_out):
    """``R ↦`` R^t of the smooth top over a body of reflection R (:func:`smooth_top_transfer`)."""
    t, F_in, h_tir = smooth_top_transfer(smooth1, h_out)
    return lambda R: reflection_under_smooth(t, F_in, h_tir, R)


def smoothed_specular(Rs, L):
    """The specular matrix as L Fourier orders: g_l R_s (L, C, h, h), g the Jackson factors
    (:func:`flakedb.rt.boundaries.microfacet.jackson_factors`), order 0 exactly R_s.

    >>> Rs = 0.04 * np.eye(3)[None]                    # a mirror: (C, h, h)
    >>> S = smoothed_specular(Rs, 8)
    >>> S.shape, bool(np.array_equal(S[0], Rs)), bool(np.all(S >= 0.0)), bool(np.all(np.diff(S[:, 0, 0, 0]) <= 0))
    ((8, 1, 3, 3), True, True, True)
    """
    return jackson_factors(L)[:, None, None, None] * Rs[None]
