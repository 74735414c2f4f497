"""Spectral channels of a stack (docs/model.md §4, "Channels"): channels that scatter identically are
solved once, and a problem larger than the memory budget is solved in groups of channels that share
the slabs' kernel projections and a rough top.  Channels are independent: the results are joined."""

import numpy as np

from flakedb.rt.adding.components import InnerRough, InnerSmooth, Lambertian, RoughConductor, Slab
from flakedb.rt.scattering.media import channel_key, channel_subset
from flakedb.rt.scattering.medium_projection import DampedKernel, project_medium
from flakedb.rt.scattering.projection import ProjectedKernel
from flakedb.rt.adding.stack_bsdf import StackBSDF

def n_channels(slabs, bottom):
    """Largest channel count among the media (σ_t at one node) and the primer's albedo.

    >>> from flakedb.rt.adding.components import Lambertian
    >>> n_channels([], Lambertian([0.2, 0.5, 1.0])), n_channels([], Lambertian(0.5)), n_channels([], None)
    (3, 1, 1)
    """
    C = 1
    for slab in slabs:
        if isinstance(slab, (InnerSmooth, InnerRough)):
            continue
        C = max(C, np.atleast_2d(slab.medium.sigma_t(np.array([0.5]))).shape[0])
    if bottom is not None:
        C = max(C, np.atleast_1d(bottom.N if isinstance(bottom, RoughConductor) else bottom.albedo).size)
    return C


def bytes_per_channel(n, h_in, cap):
    """A stated estimate of the solver's peak memory per spectral channel: the kernel projection's
    coefficient arrays (a few copies of h_in × 2h_in × 2·cap orders) and the per-order blocks (about
    ten h_in × h_in × cap arrays: kernels, four layer blocks, solve temporaries)."""
    return 8 * (4 * h_in * 2 * h_in * (2 * cap + 1) + 10 * cap * h_in * h_in)



class SharedProjection:
    """A medium whose kernel is projected once for all channels and handed to each channel group as a
    subset (:class:`GroupView`): the projection is the channel-independent geometry (through the
    spectral basis), so projecting it again per group only repeated it (8× at n = 200, 16 channels)."""

    def __init__(self, medium):
        self.medium = medium
        self.cache = {}

    def projected(self, x, w, s):
        key = (x.tobytes(), w.tobytes(), s.tol, s.order_cap, s.kernel_basis, s.filter_capped_kernels)
        if key not in self.cache:
            self.cache = {key: project_medium(self.medium, x, w, s.tol, s.order_cap, basis=s.kernel_basis,
                                              filter_capped=s.filter_capped_kernels)}
        return self.cache[key]


class GroupView:
    """Channels ``idx`` of a :class:`SharedProjection` (what :func:`_solve_stack` projects or reuses)."""

    def __init__(self, shared, idx):
        self.shared = shared
        self.idx = idx
        self.sub = channel_subset(shared.medium, idx)

    def sigma_t(self, mu):
        return self.sub.sigma_t(mu)

    def sigma_s(self, mu):
        return self.sub.sigma_s(mu)

    def projected(self, x, w, s):
        """(kernel, info) of these channels: the shared projection's subset, or (a kernel type without
        a channel subset) this group's own projection."""
        pk, info = self.shared.projected(x, w, s)
        sub = kernel_channel_subset(pk, self.idx)
        if sub is None:
            return project_medium(self.sub, x, w, s.tol, s.order_cap, basis=s.kernel_basis,
                                  filter_capped=s.filter_capped_kernels)
        return sub, info


def kernel_channel_subset(pk, idx):
    """Channels ``idx`` of a projected kernel (ProjectedKernel, DampedKernel, or one with a
    ``channel_subset`` method), or None for other kinds."""
    if isinstance(pk, DampedKernel):
        inner = kernel_channel_subset(pk.inner, idx)
        return None if inner is None else DampedKernel(inner, pk.g)
    if hasattr(pk, "channel_subset"):  # stored factors, sums, Legendre kernels
        return pk if pk.channels == 1 else pk.channel_subset(idx)
    if not isinstance(pk, ProjectedKernel) or pk.channels == 1:
        return pk if isinstance(pk, ProjectedKernel) else None
    scale = pk.scale
    if scale is not None and scale.shape[0] > 1:
        scale = scale[idx]
    if pk.M is not None:
        return ProjectedKernel(pk.coeffs, pk.M[idx], scale)
    return ProjectedKernel(pk.coeffs[:, idx], None, scale)


def bottom_subset(bottom, idx):
    """The bottom restricted to the channels ``idx`` (a per-channel value sliced; None stays None)."""
    if bottom is None:
        return None
    if isinstance(bottom, RoughConductor):
        N = np.atleast_1d(bottom.N)
        return RoughConductor(N if N.size == 1 else N[idx], bottom.alpha, bottom.energy_compensation)
    a = np.atleast_1d(np.asarray(bottom.albedo, dtype=float))
    return Lambertian(a if a.size == 1 else a[idx])


def distinct_channels(slabs, bottom, C):
    """``(first, inverse)`` when some of the stack's C channels scatter identically: ``first`` (U,) the
    first channel of each distinct kind, ``inverse`` (C,) the kind of every channel (channels in the
    order of first appearance).  None when every channel differs, or when a medium does not state its
    per-channel parameters (:func:`flakedb.rt.scattering.media.channel_key`).  Channels are compared through every
    per-channel input (media, primer albedo, conductor index): equal inputs give equal outputs, so a
    grey stack in RGB is solved once (docs/model.md §4, "Channels")."""
    if C <= 1:
        return None
    keys = []
    for item in slabs:
        if isinstance(item, (InnerSmooth, InnerRough)):
            continue
        k = channel_key(item.medium, C)
        if k is None:
            return None
        keys.append(k)
    if isinstance(bottom, RoughConductor):
        N = np.atleast_1d(np.asarray(bottom.N, dtype=complex))
        keys.append(np.stack([N.real, N.imag], axis=1))
    elif bottom is not None:
        keys.append(np.atleast_1d(np.asarray(bottom.albedo, dtype=float))[:, None])
    if not keys:
        return np.zeros(1, dtype=int), np.zeros(C, dtype=int)
    rows = np.concatenate([np.broadcast_to(k, (C, k.shape[1])) for k in keys], axis=1)
    _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    if len(first) == C:
        return None
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[np.ravel(inverse)]


def expand_channels(res, inverse):
    """The solved distinct channels spread back to every channel: a broadcast view (no copy) when they
    are all one kind, else a gather along the channel axis."""
    C = len(inverse)

    def spread(b):
        if b is None:
            return None
        if b.shape[1] == 1:
            return np.broadcast_to(b, b.shape[:1] + (C,) + b.shape[2:])
        return np.take(b, inverse, axis=1)

    info = dict(res.info, distinct_channels=int(inverse.max()) + 1, channels=C)
    spec = {} if res.specular is None else {
        "specular": np.take(np.broadcast_to(res.specular, (int(inverse.max()) + 1,) + res.specular.shape[1:]),
                            inverse, axis=0),
        "specular_orders": np.take(np.broadcast_to(res.specular_orders, (int(inverse.max()) + 1,)), inverse)}
    return StackBSDF(x=res.x, w=res.w, Rt=spread(res.Rt), eta=res.eta, delta_F=res.delta_F, Ttb=spread(res.Ttb),
                     Rb=spread(res.Rb), Tbt=spread(res.Tbt), x_in=res.x_in, w_in=res.w_in, info=info,
                     eta_bottom=res.eta_bottom, top_alpha=res.top_alpha, **spec)


def solve_in_channel_groups(solve, top, slabs, bottom, s, C, group):
    """The channels solved ``group`` at a time (the memory budget), each group's blocks written into the
    result as soon as it is solved (orders beyond a group's own count are zero).  The groups share the
    slabs' projections and a rough top: the interface does not depend on the channels, so it is built
    once (it took 0.3 s per group at n = 200, 9 groups for 41 bands).  ``solve(top, slabs, bottom, s,
    top_cache=)`` solves one group (:func:`flakedb.rt.adding.stack.solve_stack`'s single-group solver)."""
    shared = [None if isinstance(sl, (InnerSmooth, InnerRough)) else SharedProjection(sl.medium) for sl in slabs]
    top_cache = {}
    out, infos, meta, L = {}, [], None, 0
    for c0 in range(0, C, group):
        idx = np.arange(c0, min(C, c0 + group))
        sub_slabs = [sl if isinstance(sl, (InnerSmooth, InnerRough)) else
                     Slab(sl.thickness_um, GroupView(shared[j], idx)) for j, sl in enumerate(slabs)]
        sub_bottom = bottom_subset(bottom, idx)
        s.report("channels", channels=(int(c0), int(idx[-1]) + 1), of=int(C))
        p = solve(top, sub_slabs, sub_bottom, s, top_cache=top_cache)
        infos.append(p.info)
        if meta is None:
            meta = dict(x=p.x, w=p.w, eta=p.eta, delta_F=p.delta_F, x_in=p.x_in, w_in=p.w_in, eta_bottom=p.eta_bottom,
                        top_alpha=p.top_alpha)
        L = max(L, p.n_orders)
        for name in ("Rt", "Ttb", "Rb", "Tbt"):
            b = getattr(p, name)
            if b is None:
                continue
            have = out.get(name)
            if have is None or have.shape[0] < b.shape[0]:
                grown = np.zeros((b.shape[0], C) + b.shape[2:])
                if have is not None:
                    grown[:have.shape[0]] = have
                out[name] = have = grown
            have[:b.shape[0], c0:c0 + len(idx)] = b
        if p.specular is not None:  # each group's inner mirrors, smoothed over that group's orders
            spec = out.setdefault("specular", np.zeros((C,) + p.specular.shape[1:]))
            orders = out.setdefault("specular_orders", np.ones(C, dtype=int))
            spec[c0:c0 + len(idx)] = p.specular
            orders[c0:c0 + len(idx)] = p.specular_orders
        del p
    info = {"orders": L, "channel_groups": [[int(c0), int(min(C, c0 + group))] for c0 in range(0, C, group)],
            "groups": infos}
    return StackBSDF(Rt=out["Rt"], Ttb=out.get("Ttb"), Rb=out.get("Rb"), Tbt=out.get("Tbt"), info=info,
                     specular=out.get("specular"), specular_orders=out.get("specular_orders"), **meta)

