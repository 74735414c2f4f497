"""Quadrature rules in μ for the adding-doubling solver (docs/model.md §4).

One rule per hemisphere (the integrands jump at μ = 0: reflection and transmission differ), no
node at μ = 0.  Nodes are the positive cosines ``x_1 < … < x_h``; a full node set in the solver's
sign convention (see :mod:`flakedb.conventions`) is ``[-x_h … -x_1, x_1 … x_h]``.

The default rule is **Gauss–Radau on (0, 1] with the node fixed at μ = 1**: exact for polynomials
of degree 2h − 2 on each hemisphere, includes normal incidence exactly and excludes μ = 0.

A smooth dielectric interface (docs/model.md §4) needs the quadrature inside the binder to be the image
of the outside one through Snell's law, plus extra nodes in the totally internally reflected range
(0, μ_c); :func:`snell_mapped_quadrature` builds it.
"""

from dataclasses import dataclass

import numpy as np
from scipy.special import roots_jacobi, roots_legendre


def gauss_radau_unit(h):
    """Gauss–Radau rule on (0, 1] with a fixed node at 1: ``(x, w)`` ascending, ``sum(w) = 1``.

    Exact for polynomials of degree ≤ 2h − 2.  The h − 1 free nodes are the zeros of the Jacobi
    polynomial P_{h−1}^{(1,0)} on [−1, 1] (Abramowitz & Stegun 25.4.31, mirrored), the fixed node
    carries weight 2/h² on [−1, 1].
    """
    h = int(h)
    if h < 1:
        raise ValueError(f"need at least one node per hemisphere, got h={h}")
    if h == 1:
        return np.array([1.0]), np.array([1.0])
    t, wj = roots_jacobi(h - 1, 1.0, 0.0)  # weight (1 - t)
    w = wj / (1.0 - t)
    t = np.append(t, 1.0)
    w = np.append(w, 2.0 / h**2)
    # map [-1, 1] -> [0, 1]
    x = 0.5 * (t + 1.0)
    w = 0.5 * w
    order = np.argsort(x)
    return x[order], w[order]


def gauss_legendre_interval(h, a, b):
    """Gauss–Legendre rule with h nodes on (a, b): ``(x, w)`` ascending."""
    t, w = roots_legendre(int(h))
    return 0.5 * (b - a) * t + 0.5 * (b + a), 0.5 * (b - a) * w


@dataclass(frozen=True)
class HemisphereQuadrature:
    """Positive nodes ``x`` (ascending, in (0, 1]) and weights ``w`` of one hemisphere.

    ``n_mapped`` is the number of nodes (the largest ones) that are images of the outside nodes
    through a smooth interface; the remaining small ones lie in the totally internally reflected
    range.  For a plain rule ``n_mapped = len(x)``.
    """

    x: np.ndarray
    w: np.ndarray
    n_mapped: int

    @property
    def h(self):
        return len(self.x)

    def full(self):
        """Nodes and weights in the conventions' sign order ``[-x_h … -x_1, x_1 … x_h]``."""
        return np.concatenate([-self.x[::-1], self.x]), np.concatenate([self.w[::-1], self.w])


def radau_hemisphere(h):
    """Plain Gauss–Radau hemisphere rule (see :func:`gauss_radau_unit`)."""
    x, w = gauss_radau_unit(h)
    return HemisphereQuadrature(x, w, len(x))


def snell_cos(mu_out, eta):
    """Cosine inside a medium of relative index ``eta`` (> 1) of light refracted from outside.

    Snell's law: sin θ_in = sin θ_out / η, so μ_in = sqrt(1 − (1 − μ_out²)/η²).
    """
    mu_out = np.asarray(mu_out, dtype=float)
    return np.sqrt(1.0 - (1.0 - mu_out**2) / eta**2)


def snell_mapped_quadrature(outside, eta, h_tir):
    """Quadrature inside the binder below a smooth interface of relative index ``eta``.

    The ``outside.h`` outside nodes map to inside nodes μ_b = snell_cos(x, η) with weights
    w_b = w_x · x / (η² μ_b) (the Jacobian dμ_b/dx, from η² μ_b dμ_b = x dx), so the mapped
    rule integrates over (μ_c, 1] with μ_c = sqrt(1 − 1/η²).  The range (0, μ_c), reached only by
    light scattered inside and totally internally reflected at the interface, gets ``h_tir``
    Gauss–Legendre nodes.  For η ≤ 1 (not a binder below air) this is refused.
    """
    if eta <= 1.0:
        raise ValueError(f"snell_mapped_quadrature needs eta > 1 (binder below air), got {eta}")
    mu_c = np.sqrt(1.0 - 1.0 / eta**2)
    xb = snell_cos(outside.x, eta)
    wb = outside.w * outside.x / (eta**2 * xb)
    if h_tir > 0:
        xt, wt = gauss_legendre_interval(h_tir, 0.0, mu_c)
        x = np.concatenate([xt, xb])
        w = np.concatenate([wt, wb])
    else:
        x, w = xb, wb
    return HemisphereQuadrature(x, w, outside.h)


def default_tir_nodes(h_out, eta):
    """A stated heuristic for the node count in the TIR range (0, μ_c): half the outside density.

    Light in that range never leaves through a smooth interface directly; it only feeds further
    scattering, so it needs far fewer nodes than the range's length suggests.  Measured (a flake +
    HG basecoat under η = 1.5, h = 24 outside nodes, against 60 TIR nodes): 6, 9, 12, 18 TIR nodes
    give albedo errors 3.5e-6, 1.7e-6, 1.0e-6, 5.1e-7 and BSDF errors 2.7e-5 … 4e-6 of the peak,
    while the solve cost grows as (h + h_tir)³.  Half the outside density, h_out · μ_c / 2 (at
    least 4), is the default; convergence in this count is tested (tests/test_rt_solver.py).
    """
    mu_c = np.sqrt(1.0 - 1.0 / eta**2)
    return int(max(4, np.ceil(0.5 * h_out * mu_c)))


def inner_interface_quadrature(above, eta_rel, h_tir):
    """Quadrature in the binder below a smooth *inner* interface (docs/model.md §4 "Inner interface")
    of relative index ``eta_rel`` = n_below / n_above, and the node pairs it maps.

    Every direction that crosses the interface maps node to node (Snell, as
    :func:`snell_mapped_quadrature`), with the Jacobian weights w_b = w_a μ_a / (η² μ_b):

    * η > 1: all ``above.h`` nodes map into (μ_c, 1], μ_c = sqrt(1 − 1/η²); the range (0, μ_c) below,
      reached only by light scattered there and totally internally reflected, gets ``h_tir``
      Gauss–Legendre nodes (below-side TIR);
    * η < 1: the above nodes with μ_a > μ_c = sqrt(1 − η²) map onto the whole hemisphere below; those
      at or under μ_c are totally internally reflected (above-side TIR) and have no partner;
    * η = 1: the same rule (every node maps to itself).

    Returns ``(below, ia, ib)``: the rule below and the index arrays of mapped pairs (above node
    ``ia[k]`` ↔ below node ``ib[k]``).
    """
    if eta_rel >= 1.0:
        below = snell_mapped_quadrature(above, eta_rel, h_tir) if eta_rel > 1.0 else \
            HemisphereQuadrature(above.x.copy(), above.w.copy(), above.h)
        ia = np.arange(above.h)
        return below, ia, below.h - above.h + ia
    mu_c = np.sqrt(1.0 - eta_rel**2)
    ia = np.nonzero(above.x > mu_c)[0]
    xa, wa = above.x[ia], above.w[ia]
    xb = np.sqrt(np.maximum(1.0 - (1.0 - xa**2) / eta_rel**2, 0.0))
    wb = wa * xa / (eta_rel**2 * xb)
    return HemisphereQuadrature(xb, wb, len(ia)), ia, np.arange(len(ia))
