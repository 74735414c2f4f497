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
from numpy.polynomial.legendre import leggauss

from flakedb.rt.basis.special import gauss_jacobi


def gauss_radau_unit(h):
    """Gauss–Radau rule on (0, 1] with a fixed node at 1: ``(x, w)`` ascending, ``sum(w) = 1``.

    Exact for polynomials of degree ≤ 2h − 2.  The h − 1 free nodes are the zeros of the Jacobi
    polynomial P_{h−1}^{(1,0)} on [−1, 1] (Abramowitz & Stegun 25.4.31, mirrored), the fixed node
    carries weight 2/h² on [−1, 1].

    Examples
    --------
    With h = 4 nodes the rule integrates x⁶ on (0, 1] exactly (1/7), but not x⁷ (degree 2h − 1):

    >>> x, w = gauss_radau_unit(4)
    >>> float(x[-1]), round(float(w.sum()), 14)
    (1.0, 1.0)
    >>> round(float(np.sum(w * x**6)), 14) == round(1 / 7, 14), round(float(np.sum(w * x**7)), 6)
    (True, 0.125102)
    """
    h = int(h)
    if h < 1:
        raise ValueError(f"need at least one node per hemisphere, got h={h}")
    if h == 1:
        return np.array([1.0]), np.array([1.0])
    t, wj = gauss_jacobi(h - 1, 1.0, 0.0)  # weight (1 - t)
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
    t, w = leggauss(int(h))
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


@dataclass(frozen=True)
class BinderChain:
    """The rules of a chain of binders joined by inner interfaces (:func:`binder_chain_quadratures`):
    ``rules[k]`` the hemisphere rule in binder k (top to bottom) and ``pairs[k] = (ia, ib)`` the node
    pairs that cross the interface between binders k and k + 1 (node ``ia[j]`` of the rule above ↔
    node ``ib[j]`` of the rule below)."""

    rules: tuple
    pairs: tuple
    indices: tuple


def binder_chain_quadratures(anchor, n_anchor, indices, first_segment_nodes=None):
    """Rules in every binder of a chain joined by smooth (or rough) inner interfaces, built on the
    **Snell invariant** p = n sin θ (docs/model.md §4 "Inner interface"), in which a node is the same
    direction in every binder it can propagate in; index rises *and* falls are lossless by construction.

    A direction of invariant p propagates in every binder of index n_k > p.  With u = p², the flux
    measure of a hemisphere, n_k² μ_k dμ_k = −½ du, is the same in every binder: a node is (u_j, m_j)
    with the invariant flux weight m_j = n_k² w_k μ_k, and binder k's rule is every node with
    u_j < n_k², at μ_k = sqrt(1 − u_j/n_k²), w_k = m_j / (n_k² μ_k).  The u axis is cut at the squared
    indices {n_k²} of the chain:

    * (0, n_anchor²]: the ``anchor`` rule (the air's Gauss–Radau rule under a smooth top, n_anchor = 1;
      otherwise the Gauss–Radau rule of the least dense binder);
    * each further segment (u_lo, u_hi] is the grazing range of the binder with n_K² = u_hi (totally
      internally reflected in every less dense binder it touches): Gauss–Legendre in μ_K on
      (0, sqrt(1 − u_lo/u_hi)), so every binder's rule is smooth images of Gauss rules plus a Gauss rule
      of its own, exact for μ (Σ 2 w μ = 1) and a rule for anything smooth.  Node count: the heuristic of
      :func:`default_tir_nodes`, half the density of the nodes already placed, max(4, ⌈½ N(u < u_lo) ℓ⌉)
      over the segment's length ℓ in μ_K (``first_segment_nodes`` overrides it for the first segment);
      for a smooth top and rising indices it gives the rules of :func:`snell_mapped_quadrature` applied
      binder after binder.

    Across an interface between binders a and b the nodes with u < min(n_a², n_b²) are shared: Snell's
    law maps them node to node with η² w_b μ_b = w_a μ_a (basic radiance), the others are totally
    internally reflected.  For a *fall* of the index (n_b < n_a) the rule above thus holds the Snell image
    of the whole rule below plus Gauss nodes in its own totally reflected range (0, μ_c), μ_c =
    sqrt(1 − (n_b/n_a)²): the mirror of a rise.

    ``indices``: the binders' indices, top to bottom, relative to the medium the anchor's index is
    relative to (all ≥ ``n_anchor``).  Returns a :class:`BinderChain`.
    """
    n2 = [float(n) ** 2 for n in indices]
    n0 = float(n_anchor) ** 2
    if min(n2) < n0 * (1.0 - 1e-12):
        raise ValueError(f"binder indices {[float(n) for n in indices]} fall below the anchor's {float(n_anchor):g}: "
                         f"its rule cannot be split")
    # the segments: (u_hi, μ and w in the binder whose grazing range the segment is), the anchor first
    own = [(n0, anchor.x, anchor.w)]
    placed = anchor.h
    # one break per distinct index: the chain's indices are products of the interfaces' ratios, so a binder that
    # returns to an index above it (1.37 → 1.48 → 1.37) lands a few ulps off it (1.37 · (1.48/1.37) · (1.37/1.48)
    # = 1.3699999999999999); taken as its own segment, that gap of ~1e-16 got 4 Gauss nodes of weight ~1e-17,
    # whose flux cells the rough interfaces' cell rule divided by zero (a NaN BSDF) and whose near-duplicate
    # nodes made the smooth steps' tables ring below zero
    breaks = []
    for v in sorted(n2):
        if v > n0 * (1.0 + 1e-12) and (not breaks or v > breaks[-1] * (1.0 + 1e-12)):
            breaks.append(v)
    lo = n0
    for k, hi in enumerate(breaks):
        ell = np.sqrt(1.0 - lo / hi)
        if k == 0 and first_segment_nodes is not None:
            cnt = int(first_segment_nodes)
        else:
            cnt = int(max(4, np.ceil(0.5 * placed * ell)))
        if cnt > 0:
            xg, wg = gauss_legendre_interval(cnt, 0.0, ell)
            own.append((hi, xg, wg))
            placed += cnt
        lo = hi
    rules = []
    for nk2 in n2:
        parts_x, parts_w = [], []
        for hi, xo, wo in own:
            if hi > nk2 * (1.0 + 1e-12):
                continue
            if abs(hi - nk2) <= 1e-12 * nk2:  # the segment's own binder (or one of equal index): as built
                parts_x.append(xo)
                parts_w.append(wo)
            else:
                xk = np.sqrt(1.0 - hi * (1.0 - xo**2) / nk2)  # u = n_K² (1 − μ_K²) seen in binder k
                parts_x.append(xk)
                parts_w.append(hi * wo * xo / (nk2 * xk))  # m = n_K² w_K μ_K = n_k² w_k μ_k
        x = np.concatenate(parts_x)
        w = np.concatenate(parts_w)
        order = np.argsort(x, kind="stable")
        rules.append((x[order], w[order]))
    pairs, quads = [], []
    for k, (x, w) in enumerate(rules):
        if k == 0:
            n_mapped = anchor.h if n0 < n2[0] * (1.0 - 1e-12) else len(x)
        else:
            n_mapped = min(len(x), len(rules[k - 1][0]))
        quads.append(HemisphereQuadrature(x, w, n_mapped))
    for k in range(len(rules) - 1):
        ha, hb = len(rules[k][0]), len(rules[k + 1][0])
        N = min(ha, hb)
        pairs.append((np.arange(ha - N, ha), np.arange(hb - N, hb)))
    return BinderChain(tuple(quads), tuple(pairs), tuple(float(n) for n in indices))
