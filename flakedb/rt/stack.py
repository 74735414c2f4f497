"""A whole paint stack solved by adding-doubling: top interface, slabs, bottom (model.md §1, §4).

    air | top interface (none, smooth or rough dielectric) | slab … slab | bottom (Lambertian,
    rough conductor or none)

:func:`solve_stack` builds every component's scattering matrices on a common quadrature and number
of Fourier orders, doubles the slabs and adds everything.  The result, :class:`StackBSDF`, holds the
BSDF of the stack seen from above (and the transmission blocks when the stack is not opaque), the
analytic delta term of a smooth top, and evaluates them.
"""

from dataclasses import dataclass, field

import numpy as np

from flakedb.conventions import fourier_weight
from flakedb.rt import interface as itf
from flakedb.rt.fourier import project_azimuthal
from flakedb.rt.layer import Layer, add, extend_orders, homogeneous_slab, identity_layer, pad_orders
from flakedb.rt.quadrature import default_tir_nodes, radau_hemisphere, snell_mapped_quadrature


@dataclass
class Smooth:
    """Smooth dielectric top interface of relative index eta (binder / air), handled exactly."""

    eta: float


@dataclass
class Rough:
    """Rough dielectric top interface: Beckmann roughness alpha, relative index eta."""

    eta: float
    alpha: float


@dataclass
class Slab:
    """A homogeneous slab of ``thickness_um`` holding ``medium`` (see :mod:`flakedb.rt.media`)."""

    thickness_um: float
    medium: object


@dataclass
class Lambertian:
    """Diffuse primer of albedo (scalar or per channel) at the bottom of the stack."""

    albedo: object


@dataclass
class RoughConductor:
    """Beckmann microfacet metal at the bottom of the stack (Walter et al. 2007 reflection with a
    conductor's Fresnel factor): complex index ``N`` = n + ik of the metal (scalar or per channel),
    relative to vacuum; the solver divides by the binder's index above it.  ``alpha`` > 0."""

    N: object
    alpha: float


@dataclass
class SolverSettings:
    """Discretisation: ``n`` nodes in air (n/2 per hemisphere), tolerance of the φ projections,
    optical thickness of the first slice before doubling, nodes in the TIR range (None: heuristic),
    and the largest number of Fourier orders (None: 2n).

    The order cap is a stated heuristic: a μ quadrature of n/2 nodes per hemisphere cannot resolve
    lobes narrower than its node spacing, and azimuthal detail finer than that is wasted (layerlab
    chose 267 orders at n = 200 for a Beckmann α = 0.1 coat).  Narrow micro-flake kernels at grazing
    angles would otherwise ask for thousands of orders that carry almost no energy.  Whether the cap
    was reached is reported in ``info``; convergence in it is tested.
    """

    n: int = 64
    tol: float = 1e-5
    slice_tau: float = 2.0**-7
    h_tir: int | None = None
    max_orders: int | None = None

    @property
    def order_cap(self):
        return int(self.max_orders) if self.max_orders else 2 * self.n


@dataclass
class StackBSDF:
    """The solved stack.  Blocks are in the solver's normalisation (conventions), air-side nodes.

    ``Rt`` (L, C, h, h): reflection from above; ``Ttb``/``Rb``/``Tbt`` are present only for stacks
    without a primer (transmission to a medium below with the binder's index).  ``delta_F`` (h,) is
    the first-surface Fresnel reflectance of a smooth top at the air-side nodes (None otherwise).
    """

    x: np.ndarray
    w: np.ndarray
    Rt: np.ndarray
    eta: float
    delta_F: np.ndarray | None
    Ttb: np.ndarray | None = None
    Rb: np.ndarray | None = None
    Tbt: np.ndarray | None = None
    x_in: np.ndarray | None = None
    w_in: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    @property
    def n_orders(self):
        return self.Rt.shape[0]

    def f_coefficients(self, block="Rt"):
        """Cosine coefficients f_l(μ_i → μ_o) (1/sr) of a block, (L, C, h_out, h_in).

        f_l = S_l[o, i] / (c_l w_i μ_i) (conventions).  For transmission blocks this is the
        basic-radiance BSDF; multiply by (η_o/η_i)² for radiance.
        """
        S = getattr(self, block)
        x_i, w_i = (self.x, self.w) if block in ("Rt", "Ttb") else (self.x_in, self.w_in)
        cl = fourier_weight(np.arange(S.shape[0]))[:, None, None, None]
        return S / (cl * (w_i * x_i)[None, None, None, :])

    def albedo(self, include_delta=True):
        """Directional albedo of reflection at the air-side nodes, (C, h): ∫ f |μ_o| dω_o (+ F)."""
        S0 = self.Rt[0]  # (C, h_o, h_i)
        a = np.einsum("coi,o->ci", S0, self.w * self.x) / (self.w * self.x)[None, :]
        if include_delta and self.delta_F is not None:
            a = a + self.delta_F[None, :]
        return a

    def transmittance(self):
        """Directional transmittance (C, h) into the medium below (flux fraction), if transmissive."""
        if self.Ttb is None:
            return None
        S0 = self.Ttb[0]
        return np.einsum("coi,o->ci", S0, self.w_in * self.x_in) / (self.w * self.x)[None, :]

    def to_table(self, metadata=None, channels=None):
        """The result as a :class:`flakedb.bsdf.BSDFTable` (coefficients of f·|μ_o| on the full
        node set ``[-x_h … -x_1, x_1 … x_h]``, bsdf-format.md conventions).

        Reflection from above fills (incident μ_i > 0, outgoing μ_o < 0).  Transmissive stacks
        also fill the transmission and bottom-reflection blocks when the binder side uses the same
        nodes as the air side (index-matched or rough top), in radiance units (η² rule,
        conventions); below a smooth coat the inside nodes differ and only reflection is stored.
        """
        from flakedb.bsdf import BSDFTable

        h = len(self.x)
        L = self.n_orders
        C = self.Rt.shape[1]
        mu = np.concatenate([-self.x[::-1], self.x])
        coeffs = np.zeros((C, 2 * h, 2 * h, L))
        pos = np.arange(h, 2 * h)  # full-set index of +x_k
        neg = np.arange(h - 1, -1, -1)  # full-set index of −x_k

        def put(block, i_idx, o_idx, x_out, scale=1.0):
            f = self.f_coefficients(block) * scale  # (L, C, o, i)
            val = np.transpose(f, (1, 3, 2, 0)) * x_out[None, None, :, None]  # (C, i, o, L)
            coeffs[:, i_idx[:, None], o_idx[None, :], :] = val

        put("Rt", pos, neg, self.x)
        same_nodes = self.x_in is not None and len(self.x_in) == h and np.allclose(self.x_in, self.x)
        if self.Ttb is not None and same_nodes:
            put("Ttb", pos, pos, self.x, self.eta**2)  # radiance: (η_o/η_i)² f_basic
            put("Tbt", neg, neg, self.x, 1.0 / self.eta**2)
            put("Rb", neg, pos, self.x)
        delta = {"kind": "fresnel", "eta": float(self.eta)} if self.delta_F is not None else None
        return BSDFTable(mu=mu, coeffs=coeffs, eta=float(self.eta), alpha=(0.0, 0.0), delta=delta,
                         metadata=dict(metadata or {}), channels=channels)

    def eval_nodes(self, phi_d):
        """f (1/sr) of reflection at all node pairs and azimuths: (C, h_o, h_i, len(phi_d))."""
        f = self.f_coefficients("Rt")
        phi_d = np.atleast_1d(phi_d)
        cos = np.cos(np.arange(f.shape[0])[:, None] * phi_d[None, :])  # (L, P)
        return np.einsum("lcoi,lp->coip", f, cos)


def _component_orders_hint(medium):
    return int(getattr(medium, "phi_bandwidth", 16))


def medium_kernel_blocks(medium, x, w, tol, max_orders, renormalize=True):
    """Project a medium's kernel on the cosine series for the down→down and down→up blocks.

    Returns K_T, K_R of shape (L, C, h, h) (1/(µm·sr)) and the projection info.

    With ``renormalize`` (default), the kernel is scaled symmetrically, K[o, i] → s_o K[o, i] s_i
    (which keeps it reciprocal), so that the discrete scattering integral
    Σ_o 2π w_o (K_T + K_R)_0[o, i] equals the medium's accurately integrated σ_s(μ_i)
    (``medium.sigma_s``).  A point-sampled kernel narrower than the node spacing
    otherwise creates or destroys energy; the scale factors' spread is reported in ``info``
    (``renorm_max_dev``) and tested.
    """
    mu_o = np.concatenate([-x, x])  # up-going (reflection-like) then down-going
    W = w[:, None] * np.concatenate([w, w])[None, :]  # flux carried i → o per unit kernel
    # φ sampling up to 2× the order cap: where the cap binds, aliasing from orders ≥ 2L into the
    # kept orders is far below the truncation itself
    n_max = max(2 * max_orders, 128)
    n_start = min(max(4, _component_orders_hint(medium)), n_max)
    coeffs, info = project_azimuthal(medium.kernel, x, mu_o, tol=tol, n_start=n_start,
                                     n_max=n_max, weights=W)
    coeffs = coeffs[:max_orders]
    h = len(x)
    K_T, K_R = coeffs[:, :, h:, :], coeffs[:, :, :h, :]
    if renormalize and hasattr(medium, "sigma_s"):
        target = np.atleast_2d(medium.sigma_s(x))  # (C, h)
        M = 2.0 * np.pi * (K_T[0] + K_R[0])  # (C, o, i)
        scale = np.ones(np.broadcast_shapes(target.shape, M.shape[:1] + (h,)))
        # symmetric scaling K → diag(s) K diag(s) keeps the kernel reciprocal; fixed point of
        # s_i Σ_o M[o, i] w_o s_o = σ_s(μ_i) by a damped multiplicative iteration
        for _ in range(50):
            col = np.einsum("coi,o,co->ci", M, w, scale)
            with np.errstate(divide="ignore", invalid="ignore"):
                upd = np.where(col > 0, np.sqrt(target / (scale * col)), 1.0)
            scale = scale * upd
            if np.abs(upd - 1.0).max() < 1e-15:
                break
        info["renorm_max_dev"] = float(np.abs(scale**2 - 1.0).max())
        ss = scale[None, :, :, None] * scale[None, :, None, :]
        K_T = K_T * ss
        K_R = K_R * ss
    return K_T, K_R, info


#: Memory the solver may use for one group of spectral channels (bytes); channels are independent,
#: so a large problem is solved in groups of channels that fit (``FLAKEDB_MEMORY_BUDGET`` overrides).
MEMORY_BUDGET_BYTES = 4 * 2**30


def _n_channels(slabs, bottom):
    """Largest channel count among the media (σ_t at one node) and the primer's albedo."""
    C = 1
    for slab in slabs:
        C = max(C, np.atleast_2d(slab.medium.sigma_t(np.array([0.5]))).shape[0])
    if bottom is not None:
        C = max(C, np.atleast_1d(bottom.N if isinstance(bottom, RoughConductor) else bottom.albedo).size)
    return C


def _bytes_per_channel(n, h_in, cap):
    """A stated estimate of the solver's peak memory per spectral channel: the kernel projection's
    coefficient arrays (a few copies of h_in × 2h_in × 2·cap orders) and the per-order blocks (about
    ten h_in × h_in × cap arrays: kernels, four layer blocks, solve temporaries)."""
    return 8 * (4 * h_in * 2 * h_in * (2 * cap + 1) + 10 * cap * h_in * h_in)


class _ChannelSubset:
    """A medium restricted to some of its channels (evaluates all, keeps ``idx``; used only when a
    medium has no cheaper ``subset``)."""

    def __init__(self, medium, idx):
        self.medium, self.idx = medium, np.asarray(idx)

    def _take(self, a):
        a = np.asarray(a)
        return a if a.shape[0] == 1 else a[self.idx]

    def sigma_t(self, mu):
        return self._take(np.atleast_1d(self.medium.sigma_t(mu)))

    def sigma_s(self, mu):
        return self._take(np.atleast_1d(self.medium.sigma_s(mu)))

    def kernel(self, mu_i, mu_o, phi_d):
        return self._take(self.medium.kernel(mu_i, mu_o, phi_d))

    @property
    def phi_bandwidth(self):
        return getattr(self.medium, "phi_bandwidth", 16)


def _subset(medium, idx):
    return medium.subset(idx) if hasattr(medium, "subset") else _ChannelSubset(medium, idx)


def solve_stack(top, slabs, bottom, settings=None, channels=None):
    """Solve the stack; returns a :class:`StackBSDF`.

    ``top``: None (index-matched, no interface), :class:`Smooth` or :class:`Rough`.
    ``slabs``: list of :class:`Slab`.  ``bottom``: :class:`Lambertian`, :class:`RoughConductor` or
    None (transmission into a half-space of the binder's index).  ``channels``: number of spectral channels (inferred from
    the components when None).

    Channels are independent: when the estimated memory (:func:`_bytes_per_channel`) of all of them
    together exceeds the budget (``MEMORY_BUDGET_BYTES`` or ``$FLAKEDB_MEMORY_BUDGET`` bytes), the
    channels are solved in groups and the results joined (orders padded to the largest count).
    """
    import os

    s = settings or SolverSettings()
    if s.n % 2 == 0 and s.n >= 2:
        C = int(channels) if channels else _n_channels(slabs, bottom)
        h_out = s.n // 2
        h_in = h_out + (0 if not isinstance(top, Smooth) or top.eta == 1.0 else
                        (s.h_tir if s.h_tir is not None else default_tir_nodes(h_out, top.eta)))
        budget = float(os.environ.get("FLAKEDB_MEMORY_BUDGET", MEMORY_BUDGET_BYTES))
        group = max(1, int(budget // _bytes_per_channel(s.n, h_in, s.order_cap)))
        if C > group:
            return _solve_in_channel_groups(top, slabs, bottom, s, C, group)
    return _solve_stack(top, slabs, bottom, s)


def _solve_in_channel_groups(top, slabs, bottom, s, C, group):
    parts, sizes = [], []
    for c0 in range(0, C, group):
        idx = np.arange(c0, min(C, c0 + group))
        sub_slabs = [Slab(sl.thickness_um, _subset(sl.medium, idx)) for sl in slabs]
        sub_bottom = None
        if bottom is not None:
            if isinstance(bottom, RoughConductor):
                N = np.atleast_1d(bottom.N)
                sub_bottom = RoughConductor(N if N.size == 1 else N[idx], bottom.alpha)
            else:
                a = np.atleast_1d(np.asarray(bottom.albedo, dtype=float))
                sub_bottom = Lambertian(a if a.size == 1 else a[idx])
        parts.append(_solve_stack(top, sub_slabs, sub_bottom, s))
        sizes.append(len(idx))
    L = max(p.n_orders for p in parts)

    def join(name):
        blocks = [getattr(p, name) for p in parts]
        if blocks[0] is None:
            return None
        out = []
        for k, b in zip(sizes, blocks):
            b = np.broadcast_to(b, (b.shape[0], k) + b.shape[2:])
            b = pad_orders(b, L)
            out.append(b)
        return np.concatenate(out, axis=1)

    first = parts[0]
    info = {"orders": L, "channel_groups": [[int(c0), int(min(C, c0 + group))] for c0 in range(0, C, group)],
            "groups": [p.info for p in parts]}
    return StackBSDF(x=first.x, w=first.w, Rt=join("Rt"), eta=first.eta, delta_F=first.delta_F,
                     Ttb=join("Ttb"), Rb=join("Rb"), Tbt=join("Tbt"), x_in=first.x_in, w_in=first.w_in, info=info)


def _solve_stack(top, slabs, bottom, s):
    if s.n % 2 or s.n < 2:
        raise ValueError(f"the node count n must be even and ≥ 2 (n/2 per hemisphere), got {s.n}")
    q_out = radau_hemisphere(s.n // 2)
    info = {}
    if isinstance(top, Smooth):
        if top.eta == 1.0:
            top = None
    if isinstance(top, Smooth):
        h_tir = s.h_tir if s.h_tir is not None else default_tir_nodes(q_out.h, top.eta)
        q_in = snell_mapped_quadrature(q_out, top.eta, h_tir)
        eta = top.eta
    elif isinstance(top, Rough):
        q_in = q_out
        eta = top.eta
    elif top is None:
        q_in = q_out
        eta = 1.0
    else:
        raise TypeError(f"unknown top interface {top!r}")

    # scattering matrices of the slabs (each with its own order count)
    slab_layers = []
    for k, slab in enumerate(slabs):
        sig = np.atleast_2d(slab.medium.sigma_t(q_in.x))
        K_T, K_R, pinfo = medium_kernel_blocks(slab.medium, q_in.x, q_in.w, s.tol, s.order_cap)
        layer = homogeneous_slab(q_in.x, q_in.w, sig, K_T, K_R, slab.thickness_um, s.slice_tau)
        slab_layers.append((layer, sig, slab.thickness_um))
        info[f"slab{k}"] = {"orders": K_T.shape[0], **pinfo}

    top_layer = None
    delta_F = None
    L_top = 0
    if isinstance(top, Rough):
        top_layer, rinfo = itf.rough_dielectric(q_out, q_in, top.eta, top.alpha, tol=s.tol,
                                                max_orders=s.order_cap)
        L_top = top_layer.n_orders
        info["top"] = {"orders": L_top}
    L_bottom = 0
    if isinstance(bottom, RoughConductor):
        Rc, cinfo = itf.rough_conductor(q_in, np.asarray(bottom.N, dtype=complex) / eta, bottom.alpha,
                                        tol=s.tol, max_orders=s.order_cap)
        L_bottom = Rc.shape[0]
        info["bottom"] = {k: v for k, v in cinfo.items() if k != "albedo"}
    L = min(max([L_top, L_bottom, 1] + [lay.n_orders for lay, _, _ in slab_layers]), s.order_cap)
    if isinstance(top, Smooth):
        top_layer, delta_F = itf.smooth_dielectric(q_out, q_in, top.eta, L)
    elif isinstance(top, Rough) and L_top < L:
        top_layer = Layer(*(pad_orders(b, L) for b in (top_layer.Rt, top_layer.Ttb, top_layer.Rb, top_layer.Tbt)))

    # stack the slabs from the top down
    body = None
    for layer, sig, d in slab_layers:
        layer = extend_orders(layer, L, q_in.x, sig, d)
        body = layer if body is None else add(body, layer)
    if body is None:
        body = identity_layer(L, q_in.h)

    if isinstance(bottom, RoughConductor):
        body = Layer(*_reflection_over(body, pad_orders(Rc, L)))
    elif bottom is not None:
        prim = itf.lambertian(q_in, bottom.albedo, L)
        body = Layer(*_reflection_over(body, prim.Rt))
    whole = body if top_layer is None else add(top_layer, body)
    opaque = bottom is not None
    info["orders"] = L
    return StackBSDF(
        x=q_out.x, w=q_out.w, Rt=whole.Rt, eta=eta, delta_F=delta_F,
        Ttb=None if opaque else whole.Ttb, Rb=None if opaque else whole.Rb,
        Tbt=None if opaque else whole.Tbt, x_in=q_in.x, w_in=q_in.w, info=info,
    )


def _reflection_over(layer, bottom_Rt):
    """(Rt, Ttb, Rb, Tbt) of ``layer`` over an opaque bottom: only Rt survives; the others are zero."""
    from flakedb.rt.layer import add_reflection_only

    Rt = add_reflection_only(layer, bottom_Rt)
    z = np.zeros((1, 1) + layer.Rb.shape[-2:])
    return Rt, z, z, z
