"""The body of a stack as solver parts: each slab and inner interface on the rules of its binders
(docs/model.md §4 "Inner interface"), able to give any range of Fourier orders of its scattering
matrices and its specular (never-scattered) part.

* :class:`SlabPart` — a slab's projected kernel, σ_t and thickness: the eigen-solution (or doubling)
  where the kernel has orders, the exact direct beam beyond them;
* :class:`SmoothInnerPart` — a smooth interface between two binders: the same blocks in every order
  (a delta in φ_d), all of it specular;
* :class:`RoughInnerPart` — a rough interface between two binders, zero beyond its own orders.

:func:`binder_chain` gives every binder's rule; :func:`build_parts` projects the slabs' kernels once
and builds the inner interfaces.
"""

import numpy as np

from flakedb.rt.boundaries import interface as itf
from flakedb.rt.adding.channels import GroupView
from flakedb.rt.adding.components import InnerRough, InnerSmooth, Smooth
from flakedb.rt.basis.layer import Layer, direct_only_orders, extend_orders, homogeneous_slab
from flakedb.rt.scattering.medium_projection import project_medium
from flakedb.rt.boundaries.microfacet import flux_cell_edges
from flakedb.rt.basis.quadrature import binder_chain_quadratures, radau_hemisphere


def order_range(b, l0, l1):
    """Orders l0 … l1 − 1 of a block that is zero beyond its own orders: a view where it has them, a
    broadcast zero (no memory) where it has none, padded with zeros in between.


    >>> b = np.ones((2, 1, 3, 3))                       # a block with orders 0 and 1
    >>> order_range(b, 1, 4)[:, 0, 0, 0].tolist(), order_range(b, 5, 7).shape, float(order_range(b, 5, 7).max())
    ([1.0, 0.0, 0.0], (2, 1, 3, 3), 0.0)
    """
    if l0 >= b.shape[0]:
        return np.broadcast_to(np.zeros((1,) + b.shape[1:]), (l1 - l0,) + b.shape[1:])
    if l1 <= b.shape[0]:
        return b[l0:l1]
    return np.concatenate([b[l0:l1], np.zeros((l1 - b.shape[0],) + b.shape[1:])], axis=0)


def layer_orders(layer, l0, l1):
    """Orders l0 … l1 − 1 of a layer whose blocks are zero beyond their own order counts (a rough
    interface, whose inner blocks may stop earlier than R^t): :func:`order_range` of each block."""
    return Layer(*(order_range(b, l0, l1) for b in (layer.Rt, layer.Ttb, layer.Rb, layer.Tbt)))


class SlabPart:
    """A homogeneous slab on the rule ``q`` of its binder: projected kernel ``pk``, σ_t ``sig`` (C, h)
    (1/µm), thickness ``d`` (µm)."""

    def __init__(self, pk, sig, d, q, settings):
        self.pk, self.sig, self.d, self.q, self.s = pk, sig, d, q, settings

    @property
    def n_orders(self):
        return self.pk.n_orders

    def dark_from(self, l0):
        """Whether the slab reflects nothing in orders ≥ ``l0`` over a black bottom (only its direct
        beam is left there)."""
        return self.pk.n_orders <= l0

    def block(self, l0, l1, threads=1):
        """Layer of orders l0 … l1 − 1: the slab solved where the kernel has orders, the exact direct beam
        beyond (:func:`flakedb.rt.basis.layer.extend_orders`)."""
        q, sig, d, pk = self.q, self.sig, self.d, self.pk
        k1 = min(l1, pk.n_orders)
        if k1 <= l0:
            return direct_only_orders(q.x, sig, d, l1 - l0, max(pk.channels, sig.shape[0]))
        K_T, K_R = pk.blocks(l0, k1)
        layer = homogeneous_slab(q.x, q.w, sig, K_T, K_R, d, self.s.slice_tau, l0=l0, threads=threads,
                                 method=self.s.slab_method)
        return extend_orders(layer, l1 - l0, q.x, sig, d)

    def specular(self):
        """The never-scattered part (one order, the same in every order): the direct beam
        e^{−σ_t d/μ} both ways, no reflection."""
        return direct_only_orders(self.q.x, self.sig, self.d, 1, self.sig.shape[0])


class SmoothInnerPart:
    """A smooth interface between the binders of rules ``q_a`` (above) and ``q_b`` (below), mapped
    node pairs ``ia`` ↔ ``ib``, relative index ``eta`` = n_below / n_above
    (:func:`flakedb.rt.boundaries.interface.smooth_inner`)."""

    n_orders = 0  # the same blocks in every order: it does not bound the stack's order count

    def __init__(self, q_a, q_b, ia, ib, eta):
        self.q_a, self.q_b, self.ia, self.ib, self.eta = q_a, q_b, ia, ib, eta

    def dark_from(self, l0):
        return False

    def block(self, l0, l1, threads=1):
        return itf.smooth_inner(self.q_a, self.q_b, self.ia, self.ib, self.eta, l1 - l0)

    def specular(self):
        """All of it (a mirror and a refraction): its blocks of one order."""
        return self.block(0, 1)


class RoughInnerPart:
    """A rough interface between two binders: its layer (zero beyond its own orders)."""

    def __init__(self, layer):
        self.layer = layer

    @property
    def n_orders(self):
        return self.layer.n_orders

    def dark_from(self, l0):
        return False

    def block(self, l0, l1, threads=1):
        return layer_orders(self.layer, l0, l1)

    def specular(self):
        """Nothing crosses or leaves a rough interface unscattered: zero blocks of one order."""
        return Layer(*(np.zeros((1, 1) + b.shape[-2:]) for b in (self.layer.Rt, self.layer.Ttb, self.layer.Rb,
                                                                   self.layer.Tbt)))


def binder_chain(top, eta, slabs, q_out, s):
    """The rules of every binder of the stack (:func:`flakedb.rt.basis.quadrature.binder_chain_quadratures`,
    docs/model.md §4 "Inner interface"), top to bottom.  Under a smooth top the chain is anchored on the
    air's rule (the top binder's rule holds its Snell image); under a rough top on the Gauss–Radau rule
    of the least dense binder (the rough interface joins any two rules); without a top interface the
    top binder's rule is the air's, so no binder below may be less dense than it."""
    indices = [eta]
    for item in slabs:
        if isinstance(item, (InnerSmooth, InnerRough)):
            if not (np.isfinite(item.eta) and item.eta > 0):
                raise ValueError(f"{item!r}: the relative index n_below / n_above must be a positive real number")
            if isinstance(item, InnerRough) and not (np.isfinite(item.alpha) and item.alpha > 0):
                raise ValueError(f"{item!r}: the Beckmann roughness alpha must be > 0 (a smooth inner interface "
                                 f"is InnerSmooth)")
            indices.append(indices[-1] * float(item.eta))
    if isinstance(top, Smooth):
        if min(indices) < 1.0:
            raise ValueError(
                f"binder indices {[round(v, 6) for v in indices]} relative to the air: a binder below a smooth "
                f"top must not be less dense than the air (allowed: every index ≥ 1)")
        # ``h_tir`` counts the nodes of the top's totally reflected range, the first segment unless a binder
        # below is less dense than the top one (that range is then split at its index)
        h_first = s.h_tir if s.h_tir is not None and min(indices) >= indices[0] else None
        return binder_chain_quadratures(q_out, 1.0, indices, first_segment_nodes=h_first)
    if top is None and min(indices) < 1.0:
        raise ValueError(
            f"binder indices {[round(v, 6) for v in indices]} relative to the index-matched top: without a "
            f"top interface the output rule is the top binder's, so no binder below may be less dense "
            f"(allowed: every index ≥ 1; or give the stack a top interface)")
    return binder_chain_quadratures(radau_hemisphere(s.n // 2), min(indices), indices)


#: A rough inner interface is solved as a smooth one when its index step reflects at most this fraction at normal
#: incidence, ((η − 1)/(η + 1))², ...
NEAR_MATCH_FRESNEL = 1e-4
#: ... and its transmitted lobe, ≈ α |1 − 1/η| wide, is narrower than this fraction of the median flux cell (in θ)
#: of the two binders' rules (the solve cannot tell it from a delta).
NEAR_MATCH_LOBE_CELLS = 0.1


def near_matched(eta, alpha, q_a, q_b) -> dict | None:
    """Why a rough inner interface of relative index ``eta`` and Beckmann ``alpha`` between rules ``q_a``, ``q_b``
    is solved as a smooth one (a dict for ``info``), or None.  A nearly index-matched rough interface barely
    refracts: its transmitted lobe, α |1 − 1/η| wide, is far narrower than any node cell, and the flux-cell
    integration that resolves it (sub-cells ∝ α |1 − 1/η|, :func:`flakedb.rt.boundaries.microfacet.rough_dielectric_cells`)
    grew without bound: 1.5 → 1.501 at α 0.03 asked for 110 GiB at n = 32, 1.406 → 1.404 at α 0.134 for 16 GB.
    Solved smooth, the transmission is the delta it is at this resolution (docs/model.md §4, "Inner interface"),
    and the reflection, ≤ :data:`NEAR_MATCH_FRESNEL` of the light, keeps its energy but becomes a mirror.

    >>> from flakedb.rt.basis.quadrature import radau_hemisphere
    >>> q = radau_hemisphere(16)
    >>> bool(near_matched(1.501 / 1.5, 0.03, q, q)), near_matched(1.6 / 1.5, 0.1, q, q)
    (True, None)
    """
    fresnel = ((eta - 1.0) / (eta + 1.0)) ** 2
    lobe = alpha * abs(1.0 - 1.0 / eta)
    # the rules' typical cell (the median: Snell images beside the critical angle make a few cells 1000x narrower)
    cell = min(float(np.median(np.diff(np.arccos(np.clip(flux_cell_edges(q.x, q.w), 0.0, 1.0))[::-1])))
               for q in (q_a, q_b))
    if fresnel > NEAR_MATCH_FRESNEL or lobe > NEAR_MATCH_LOBE_CELLS * cell:
        return None
    return {"solved_as": "smooth (nearly index-matched)", "normal_fresnel": float(fresnel),
            "transmitted_lobe_rad": float(lobe), "median_cell_rad": cell}


def build_parts(slabs, chain, s, info):
    """The parts of the body, top to bottom: kernels of the slabs projected once (each with its own order
    count) on the rule of its binder, the inner interfaces between the rules they separate.  Fills
    ``info`` (``slab<k>``, ``inner_interfaces``) and reports each projection."""
    parts = []
    b = k = 0  # b: the binder the next item lies in; k: slabs so far
    for item in slabs:
        if isinstance(item, (InnerSmooth, InnerRough)):
            q_a, q_b = chain.rules[b], chain.rules[b + 1]
            rec = {"eta": float(item.eta), "nodes_above": int(q_a.h), "nodes_below": int(q_b.h)}
            near = near_matched(float(item.eta), float(item.alpha), q_a, q_b) if isinstance(item, InnerRough) else None
            if near is not None:
                parts.append(SmoothInnerPart(q_a, q_b, *chain.pairs[b], item.eta))
                rec.update(alpha=float(item.alpha), **near)
            elif isinstance(item, InnerRough):
                layer, _ = itf.rough_dielectric(q_a, q_b, item.eta, item.alpha, tol=s.tol, max_orders=s.order_cap,
                                                energy_compensation=item.energy_compensation, threads=s.threads)
                parts.append(RoughInnerPart(layer))
                rec.update(alpha=float(item.alpha), orders=int(layer.n_orders))
            else:
                parts.append(SmoothInnerPart(q_a, q_b, *chain.pairs[b], item.eta))
            b += 1
            info.setdefault("inner_interfaces", []).append(rec)
            continue
        q = chain.rules[b]
        sig = np.atleast_2d(item.medium.sigma_t(q.x))
        if isinstance(item.medium, GroupView):  # a channel group: the projection of all channels, reused
            pk, pinfo = item.medium.projected(q.x, q.w, s)
        else:
            pk, pinfo = project_medium(item.medium, q.x, q.w, s.tol, s.order_cap, basis=s.kernel_basis,
                                       filter_capped=s.filter_capped_kernels)
        parts.append(SlabPart(pk, sig, item.thickness_um, q, s))
        info[f"slab{k}"] = {"orders": pk.n_orders, **pinfo}
        k += 1
        s.report("projection", layer=k, layers=len(slabs), orders=pk.n_orders)
    return parts
