"""A whole paint stack solved by adding-doubling: top interface, slabs, bottom (docs/model.md §1, §4).

    air | top interface (none, smooth or rough dielectric) | slab … slab | bottom (Lambertian,
    rough conductor or none)

:func:`solve_stack` builds every component's scattering matrices on a common quadrature and number
of Fourier orders, doubles the slabs and adds everything.  The result, :class:`StackBSDF`, holds the
BSDF of the stack seen from above (and the transmission blocks when the stack is not opaque), the
analytic delta term of a smooth top, and evaluates them.
"""

import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from flakedb.conventions import fourier_weight
from flakedb.rt import interface as itf
from flakedb.rt.layer import (
    Layer,
    add,
    add_reflection_only,
    direct_only_orders,
    extend_orders,
    homogeneous_slab,
    identity_layer,
    pad_orders,
)
from flakedb.rt.legendre import LegendreKernel
from flakedb.rt.media import channel_key, channel_subset, kernel_basis
from flakedb.rt.microfacet import jackson_factors
from flakedb.rt.orders import order_tail, reflection_over, reflection_under_smooth
from flakedb.rt.params import check_alpha, check_complex_index, check_range
from flakedb.rt.projection import ProjectedKernel, project_kernel_basis
from flakedb.rt.quadrature import binder_chain_quadratures, default_tir_nodes, radau_hemisphere


@dataclass
class Smooth:
    """Smooth dielectric top interface of relative index eta (binder / air), handled exactly."""

    eta: float

    def __post_init__(self):
        check_range("Smooth", "eta", self.eta, 0.0, None, lo_open=True)


@dataclass
class Rough:
    """Rough dielectric top interface: Beckmann roughness alpha, relative index eta.
    ``energy_compensation`` (default): lossless, with the multiple-scattering lobe of
    docs/rough-interfaces.md; False: the single-scattering Walter et al. 2007 model."""

    eta: float
    alpha: float
    energy_compensation: bool = True

    def __post_init__(self):
        check_range("Rough", "eta", self.eta, 0.0, None, lo_open=True)
        check_alpha("Rough", self.alpha)


@dataclass
class Slab:
    """A homogeneous slab of ``thickness_um`` holding ``medium`` (see :mod:`flakedb.rt.media`)."""

    thickness_um: float
    medium: object

    def __post_init__(self):
        check_range("Slab", "thickness_um", self.thickness_um, 0.0, None)


@dataclass
class InnerSmooth:
    """A smooth interface between two slabs (docs/model.md §4 "Inner interface"): relative index
    ``eta`` = n_below / n_above (the binder below over the binder above; a rise > 1 or a fall < 1).
    Placed in the ``slabs`` list of :func:`solve_stack` between the slabs it separates; every binder
    lives on its rule of :func:`flakedb.rt.quadrature.binder_chain_quadratures` (one node set on the
    Snell invariant: the interface maps shared nodes one to one, lossless and reciprocal)."""

    eta: float

    def __post_init__(self):
        check_range("InnerSmooth", "eta", self.eta, 0.0, None, lo_open=True)


@dataclass
class InnerRough:
    """A rough interface between two slabs: Beckmann roughness ``alpha`` > 0, relative index ``eta`` =
    n_below / n_above (a rise or a fall), by flux-cell integration between the two binders' rules
    (:func:`flakedb.rt.interface.rough_dielectric`, docs/rough-interfaces.md, docs/model.md §4 "Inner
    interface").  ``energy_compensation`` (default): lossless, with the multiple-scattering lobe; False:
    the single-scattering Walter et al. 2007 model.  Placed in ``slabs`` as :class:`InnerSmooth` is."""

    eta: float
    alpha: float
    energy_compensation: bool = True

    def __post_init__(self):
        check_range("InnerRough", "eta", self.eta, 0.0, None, lo_open=True)
        check_alpha("InnerRough", self.alpha)


@dataclass
class Lambertian:
    """Diffuse primer of albedo (scalar or per channel) at the bottom of the stack."""

    albedo: object

    def __post_init__(self):
        check_range("Lambertian", "albedo", self.albedo, 0.0, 1.0)


#: Default budget of the order choice: the dropped Fourier tail of the final BSDF is at most this
#: fraction of its order-0 maximum (docs/orders.md).
ORDER_TOL = 1e-4


@dataclass
class RoughConductor:
    """Beckmann microfacet metal at the bottom of the stack (Walter et al. 2007 reflection with a
    conductor's Fresnel factor): complex index ``N`` = n + ik of the metal (scalar or per channel),
    relative to vacuum; the solver divides by the binder's index above it.  ``alpha`` > 0.
    ``energy_compensation``: add Kulla & Conty's multiple-scattering lobe (default)."""

    N: object
    alpha: float
    energy_compensation: bool = True

    def __post_init__(self):
        check_complex_index("RoughConductor", "N", self.N)
        check_alpha("RoughConductor", self.alpha)


@dataclass
class SolverSettings:
    """Discretisation: ``n`` nodes in air (n/2 per hemisphere), tolerance of the φ projections,
    optical thickness of the first slice before doubling, nodes in the TIR range (None: heuristic),
    the largest number of Fourier orders (None: 2n), and the memory one group of spectral channels may
    use (None: :data:`MEMORY_BUDGET_BYTES`).

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
    memory_budget_bytes: float | None = None
    #: Orders from the physics (docs/orders.md): an opaque stack keeps the fewest orders whose
    #: dropped tail Σ_{l≥L} max|g_l| is ≤ order_tol × max|g_0| of its cosine-weighted BSDF
    #: g = f μ_i μ_o (reflection from above, without the smooth coat's delta); None keeps every order the components carry (up to the cap),
    #: the previous behaviour, which stays the default of this class so that an explicit
    #: ``max_orders`` keeps meaning a fixed order count.  :data:`ORDER_TOL` (1e-4) is the product
    #: default (:meth:`SolverSettings.product`).
    order_tol: float | None = None
    #: Project kernels through their spectral basis (docs/projection.md); False samples every channel.
    kernel_basis: bool = True
    #: How homogeneous slabs are solved (:func:`flakedb.rt.layer.homogeneous_slab`): "eigen", the exact
    #: eigen-solution of the discrete-ordinate equations (default), or "doubling" from a thin slice
    #: of optical thickness ``slice_tau`` (the fallback for non-reciprocal kernels).
    slab_method: str = "eigen"
    #: Jackson-filter a medium kernel cut by the order cap (:func:`_damp_if_capped`): its truncated
    #: series rings negative otherwise.  False: plain truncation (order-convergence studies).
    filter_capped_kernels: bool = True
    #: Threads over the (orders, channels) batch of the slab solvers (:func:`flakedb.rt.layer.double_symmetric`,
    #: the eigen-solution); > 1 also builds a rough top in a background thread while the slabs are
    #: projected.  Compose sets the machine's core count.  BLAS itself runs one thread per call during a solve.
    threads: int = 1
    #: Progress callback ``progress(stage, detail)`` (stage "projection" or "solve", detail a dict),
    #: called after each slab's kernel projection and each layer of each order block; None: silent.
    progress: object = None

    def report(self, stage, **detail):
        if self.progress is not None:
            self.progress(stage, detail)

    @classmethod
    def product(cls, n, **kw):
        """Settings with the orders chosen from the physics at :data:`ORDER_TOL` (compose's default)."""
        kw.setdefault("order_tol", ORDER_TOL)
        return cls(n=int(n), **kw)

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
        if S.shape[1] > 1 and S.strides[1] == 0:  # channels solved once (grey): stays a broadcast view
            return np.broadcast_to(S[:, :1] / (cl * (w_i * x_i)[None, None, None, :]), S.shape)
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

    def eval_nodes(self, phi_d):
        """f (1/sr) of reflection at all node pairs and azimuths: (C, h_o, h_i, len(phi_d))."""
        f = self.f_coefficients("Rt")
        phi_d = np.atleast_1d(phi_d)
        cos = np.cos(np.arange(f.shape[0])[:, None] * phi_d[None, :])  # (L, P)
        return np.einsum("lcoi,lp->coip", f, cos)


def legendre_moments(medium, tol):
    """The medium's Legendre moments when its kernel is σ_s times an HG, vMF or tabulated phase
    function (:meth:`flakedb.rt.media.PhaseMedium.legendre_moments`), else None."""
    fn = getattr(medium, "legendre_moments", None)
    return None if fn is None else fn(tol)


def _component_orders_hint(medium):
    return int(getattr(medium, "phi_bandwidth", 16))


def medium_kernel_blocks(medium, x, w, tol, max_orders, renormalize=True, basis=True):
    """Project a medium's kernel on the cosine series for the down→down and down→up blocks.

    Returns K_T, K_R of shape (L, C, h, h) (1/(µm·sr)) and the projection info; the projection
    itself is :func:`project_medium` (renormalisation, spectral basis), of which this returns all
    orders up to ``max_orders``.
    """
    pk, info = project_medium(medium, x, w, tol, max_orders, renormalize, basis)
    K_T, K_R = pk.blocks(0, min(pk.n_orders, max_orders))
    return K_T, K_R, info


def project_medium(medium, x, w, tol, max_orders, renormalize=True, basis=True, filter_capped=True):
    """A medium's kernel projected on the cosine series: a :class:`flakedb.rt.projection.ProjectedKernel`
    (K_T, K_R blocks of any orders on demand) and the projection info.

    With ``basis`` (default) the kernel is projected through its spectral basis
    (:func:`flakedb.rt.media.kernel_basis`, docs/projection.md): B basis kernels are sampled and
    transformed once and the C channels combined from them, with the adaptive criteria applied to
    the channels exactly as before; ``basis=False`` samples every channel's kernel (the previous path;
    the same coefficients to rounding, tested).

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
    if hasattr(medium, "projected_kernel"):  # precomputed factors (flakedb.rt.stored): no projection here
        pk, info = medium.projected_kernel(
            x, max_orders, lambda m: project_medium(m, x, w, tol, max_orders, renormalize=False, basis=basis,
                                                    filter_capped=False))
    elif basis and (lm := legendre_moments(medium, tol)) is not None:
        # an HG, vMF or tabulated phase function: its Legendre moments and the addition theorem, no φ sampling
        chi, linfo = lm
        pk = LegendreKernel(x, chi, np.atleast_2d(medium.sigma_s(x))[:, 0], max_orders=max_orders)
        info = {"kernel": "Legendre moments and the addition theorem", "legendre_degree": linfo["degree"],
                "tail": linfo["tail"], "converged": True}
    else:
        kb = kernel_basis(medium) if basis else None
        fn, M = (medium.kernel, None) if kb is None else (kb.fn, kb.M)
        coeffs, info = project_kernel_basis(fn, M, x, mu_o, tol=tol, n_start=n_start, n_max=n_max, weights=W)
        pk = ProjectedKernel(coeffs[:max_orders], M)
        if M is not None:
            info["basis_functions"] = int(M.shape[1])
    h = len(x)
    if renormalize and hasattr(medium, "sigma_s"):
        target = np.atleast_2d(medium.sigma_s(x))  # (C, h)
        K_T0, K_R0 = pk.blocks(0, 1)
        M0 = 2.0 * np.pi * (K_T0[0] + K_R0[0])  # (C, o, i)
        scale = np.ones(np.broadcast_shapes(target.shape, M0.shape[:1] + (h,)))
        # symmetric scaling K → diag(s) K diag(s) keeps the kernel reciprocal; fixed point of
        # s_i Σ_o M[o, i] w_o s_o = σ_s(μ_i) by a damped multiplicative iteration
        for _ in range(50):
            col = np.einsum("coi,o,co->ci", M0, w, scale)
            with np.errstate(divide="ignore", invalid="ignore"):
                upd = np.where(col > 0, np.sqrt(target / (scale * col)), 1.0)
            scale = scale * upd
            if np.abs(upd - 1.0).max() < 1e-15:
                break
        info["renorm_max_dev"] = float(np.abs(scale**2 - 1.0).max())
        pk.scale = scale
    return _damp_if_capped(pk, info, max_orders) if filter_capped else (pk, info)


#: A kernel whose last kept order still exceeds CAPPED_TAIL × its order 0 was cut by the order cap.
CAPPED_TAIL = 1e-4


class DampedKernel:
    """A projected kernel whose orders are multiplied by damping factors g_l (:func:`_damp_if_capped`)."""

    def __init__(self, inner, g):
        self.inner = inner
        self.g = np.asarray(g, float)

    @property
    def n_orders(self):
        return self.inner.n_orders

    @property
    def channels(self):
        return self.inner.channels

    def blocks(self, l0=0, l1=None):
        K_T, K_R = self.inner.blocks(l0, l1)
        k1 = min(l0 + K_T.shape[0], self.g.size)
        g = np.zeros(K_T.shape[0])
        g[: max(0, k1 - l0)] = self.g[l0:k1]
        return K_T * g[:, None, None, None], K_R * g[:, None, None, None]


def _damp_if_capped(pk, info, max_orders):
    """A kernel cut by the order cap (its last order above :data:`CAPPED_TAIL` × order 0) rings: its
    truncated cosine series goes negative (perfect mirror flakes α 0.15 in air at n = 32: the BSDF
    reaches −3.5 % of its maximum).  Like the rough interfaces (docs/rough-interfaces.md,
    "Positivity"), it is then smoothed in φ by the Jackson kernel's factors
    (:func:`flakedb.rt.microfacet.jackson_factors`): a positive convolution ≈ π/L wide that keeps
    order 0 (energy, the renormalisation) and reciprocity.  Decided from the blocks alone, so the
    store's factors and the direct projection are treated alike."""
    L = pk.n_orders
    if L < int(max_orders) or L < 2:
        return pk, info
    K_T0, K_R0 = pk.blocks(0, 1)
    K_TL, K_RL = pk.blocks(L - 1, L)
    ref = max(float(np.abs(K_T0).max()), float(np.abs(K_R0).max()))
    last = max(float(np.abs(K_TL).max()), float(np.abs(K_RL).max()))
    if ref <= 0.0 or last <= CAPPED_TAIL * ref:
        return pk, info
    return DampedKernel(pk, jackson_factors(L)), {**info, "jackson_damped": True, "capped_last_order": last / ref}


#: Memory the solver may use for one group of spectral channels (bytes); channels are independent,
#: so a large problem is solved in groups of channels that fit (``SolverSettings.memory_budget_bytes``
#: overrides; compose takes it from ``$FLAKEDB_MEMORY_BUDGET``).
MEMORY_BUDGET_BYTES = 4 * 2**30


def _n_channels(slabs, bottom):
    """Largest channel count among the media (σ_t at one node) and the primer's albedo."""
    C = 1
    for slab in slabs:
        if isinstance(slab, (InnerSmooth, InnerRough)):
            continue
        C = max(C, np.atleast_2d(slab.medium.sigma_t(np.array([0.5]))).shape[0])
    if bottom is not None:
        C = max(C, np.atleast_1d(bottom.N if isinstance(bottom, RoughConductor) else bottom.albedo).size)
    return C


def _bytes_per_channel(n, h_in, cap):
    """A stated estimate of the solver's peak memory per spectral channel: the kernel projection's
    coefficient arrays (a few copies of h_in × 2h_in × 2·cap orders) and the per-order blocks (about
    ten h_in × h_in × cap arrays: kernels, four layer blocks, solve temporaries)."""
    return 8 * (4 * h_in * 2 * h_in * (2 * cap + 1) + 10 * cap * h_in * h_in)




def solve_stack(top, slabs, bottom, settings=None, channels=None):
    """Solve the stack; returns a :class:`StackBSDF`.

    ``top``: None (index-matched, no interface), :class:`Smooth` or :class:`Rough`.
    ``slabs``: list of :class:`Slab`.  ``bottom``: :class:`Lambertian`, :class:`RoughConductor` or
    None (transmission into a half-space of the binder's index).  ``channels``: number of spectral channels (inferred from
    the components when None).

    Channels are independent: when the estimated memory (:func:`_bytes_per_channel`) of all of them
    together exceeds the budget (``settings.memory_budget_bytes``, default ``MEMORY_BUDGET_BYTES``), the
    channels are solved in groups and the results joined (orders padded to the largest count).
    """
    s = settings or SolverSettings()
    # small batched matrices: one BLAS thread per call (measured: the batched doubling of 100 × 100
    # blocks ran 4.4× slower with OpenBLAS at 2 threads than at 1 on a 2-core machine); parallelism,
    # if any, is over the batch (``settings.threads``)
    with threadpool_limits(limits=1, user_api="blas"):
        return _solve_stack_grouped(top, slabs, bottom, s, channels)


def _solve_stack_grouped(top, slabs, bottom, s, channels):
    if s.n % 2 == 0 and s.n >= 2:
        C = int(channels) if channels else _n_channels(slabs, bottom)
        distinct = _distinct_channels(slabs, bottom, C)
        if distinct is not None:  # channels that scatter identically are solved once
            first, inverse = distinct
            sub_slabs = [sl if isinstance(sl, (InnerSmooth, InnerRough)) else
                         Slab(sl.thickness_um, channel_subset(sl.medium, first)) for sl in slabs]
            res = _solve_stack_grouped(top, sub_slabs, _bottom_subset(bottom, first), s, len(first))
            return _expand_channels(res, inverse)
        h_out = s.n // 2
        h_in = h_out + (0 if not isinstance(top, Smooth) or top.eta == 1.0 else
                        (s.h_tir if s.h_tir is not None else default_tir_nodes(h_out, top.eta)))
        budget = float(s.memory_budget_bytes or MEMORY_BUDGET_BYTES)
        group = max(1, int(budget // _bytes_per_channel(s.n, h_in, s.order_cap)))
        if C > group:
            return _solve_in_channel_groups(top, slabs, bottom, s, C, group)
    return _solve_stack(top, slabs, bottom, s)


class _SharedProjection:
    """A medium whose kernel is projected once for all channels and handed to each channel group as a
    subset (:class:`_GroupView`): the projection is the channel-independent geometry (through the
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


class _GroupView:
    """Channels ``idx`` of a :class:`_SharedProjection` (what :func:`_solve_stack` projects or reuses)."""

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
        sub = _kernel_channel_subset(pk, self.idx)
        if sub is None:
            return project_medium(self.sub, x, w, s.tol, s.order_cap, basis=s.kernel_basis,
                                  filter_capped=s.filter_capped_kernels)
        return sub, info


def _kernel_channel_subset(pk, idx):
    """Channels ``idx`` of a projected kernel (ProjectedKernel, DampedKernel, or one with a
    ``channel_subset`` method), or None for other kinds."""
    if isinstance(pk, DampedKernel):
        inner = _kernel_channel_subset(pk.inner, idx)
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


def _bottom_subset(bottom, idx):
    """The bottom restricted to the channels ``idx`` (a per-channel value sliced; None stays None)."""
    if bottom is None:
        return None
    if isinstance(bottom, RoughConductor):
        N = np.atleast_1d(bottom.N)
        return RoughConductor(N if N.size == 1 else N[idx], bottom.alpha, bottom.energy_compensation)
    a = np.atleast_1d(np.asarray(bottom.albedo, dtype=float))
    return Lambertian(a if a.size == 1 else a[idx])


def _distinct_channels(slabs, bottom, C):
    """``(first, inverse)`` when some of the stack's C channels scatter identically: ``first`` (U,) the
    first channel of each distinct kind, ``inverse`` (C,) the kind of every channel (channels in the
    order of first appearance).  None when every channel differs, or when a medium does not state its
    per-channel parameters (:func:`flakedb.rt.media.channel_key`).  Channels are compared through every
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


def _expand_channels(res, inverse):
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
    return StackBSDF(x=res.x, w=res.w, Rt=spread(res.Rt), eta=res.eta, delta_F=res.delta_F, Ttb=spread(res.Ttb),
                     Rb=spread(res.Rb), Tbt=spread(res.Tbt), x_in=res.x_in, w_in=res.w_in, info=info)


def _solve_in_channel_groups(top, slabs, bottom, s, C, group):
    """The channels solved ``group`` at a time (the memory budget), each group's blocks written into the
    result as soon as it is solved (orders beyond a group's own count are zero).  The groups share the
    slabs' projections and a rough top: the interface does not depend on the channels, so it is built
    once (it took 0.3 s per group at n = 200, 9 groups for 41 bands)."""
    shared = [None if isinstance(sl, (InnerSmooth, InnerRough)) else _SharedProjection(sl.medium) for sl in slabs]
    top_cache = {}
    out, infos, meta, L = {}, [], None, 0
    for c0 in range(0, C, group):
        idx = np.arange(c0, min(C, c0 + group))
        sub_slabs = [sl if isinstance(sl, (InnerSmooth, InnerRough)) else
                     Slab(sl.thickness_um, _GroupView(shared[j], idx)) for j, sl in enumerate(slabs)]
        sub_bottom = _bottom_subset(bottom, idx)
        s.report("channels", channels=(int(c0), int(idx[-1]) + 1), of=int(C))
        p = _solve_stack(top, sub_slabs, sub_bottom, s, top_cache=top_cache)
        infos.append(p.info)
        if meta is None:
            meta = dict(x=p.x, w=p.w, eta=p.eta, delta_F=p.delta_F, x_in=p.x_in, w_in=p.w_in)
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
        del p
    info = {"orders": L, "channel_groups": [[int(c0), int(min(C, c0 + group))] for c0 in range(0, C, group)],
            "groups": infos}
    return StackBSDF(Rt=out["Rt"], Ttb=out.get("Ttb"), Rb=out.get("Rb"), Tbt=out.get("Tbt"), info=info, **meta)


def _binder_chain(top, eta, slabs, q_out, s):
    """The rules of every binder of the stack (:func:`flakedb.rt.quadrature.binder_chain_quadratures`,
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
    n_min = min(indices)
    return binder_chain_quadratures(radau_hemisphere(s.n // 2), n_min, indices)


#: The background thread of :func:`_submit` (created on first use, under the lock).
_BACKGROUND: list = []
_BACKGROUND_LOCK = threading.Lock()


def _submit(n_threads, fn, /, *args, **kw):
    """``fn(*args, **kw)`` in the background thread when ``n_threads`` > 1, else now; a future either way."""
    if int(n_threads) <= 1:
        done = Future()
        done.set_result(fn(*args, **kw))
        return done
    with _BACKGROUND_LOCK:
        if not _BACKGROUND:
            _BACKGROUND.append(ThreadPoolExecutor(1, thread_name_prefix="flakedb-solve"))
    return _BACKGROUND[0].submit(fn, *args, **kw)


def _solve_stack(top, slabs, bottom, s, top_cache=None):
    if s.n % 2 or s.n < 2:
        raise ValueError(f"the node count n must be even and ≥ 2 (n/2 per hemisphere), got {s.n}")
    q_out = radau_hemisphere(s.n // 2)
    info = {}
    if isinstance(top, Smooth):
        if top.eta == 1.0:
            top = None
    if isinstance(top, (Smooth, Rough)):
        eta = top.eta
    elif top is None:
        eta = 1.0
    else:
        raise TypeError(f"unknown top interface {top!r}")
    chain = _binder_chain(top, eta, slabs, q_out, s)
    q_in = chain.rules[0]

    # kernels of the slabs projected once (each with its own order count), each on the rule of its
    # binder: inner interfaces (InnerSmooth) separate binders (docs/model.md §4 "Inner interface")
    projected = []
    eta_binder = eta
    b = 0  # the binder the next item lies in
    k = 0
    for item in slabs:
        if isinstance(item, (InnerSmooth, InnerRough)):
            q_a, q_b = chain.rules[b], chain.rules[b + 1]
            ia, ib = chain.pairs[b]
            rec = {"eta": float(item.eta), "nodes_above": int(q_a.h), "nodes_below": int(q_b.h)}
            if isinstance(item, InnerRough):
                layer, rinfo = itf.rough_dielectric(q_a, q_b, item.eta, item.alpha, tol=s.tol, max_orders=s.order_cap,
                                                    energy_compensation=item.energy_compensation)
                projected.append(("rough", layer))
                rec.update(alpha=float(item.alpha), orders=int(layer.n_orders))
            else:
                projected.append(("interface", q_a, q_b, ia, ib, item.eta))
            b += 1
            eta_binder = eta_binder * item.eta
            info.setdefault("inner_interfaces", []).append(rec)
            continue
        slab = item
        q = chain.rules[b]
        sig = np.atleast_2d(slab.medium.sigma_t(q.x))
        if isinstance(slab.medium, _GroupView):  # a channel group: the projection of all channels, reused
            pk, pinfo = slab.medium.projected(q.x, q.w, s)
        else:
            pk, pinfo = project_medium(slab.medium, q.x, q.w, s.tol, s.order_cap, basis=s.kernel_basis,
                                       filter_capped=s.filter_capped_kernels)
        projected.append((pk, sig, slab.thickness_um, q))
        info[f"slab{k}"] = {"orders": pk.n_orders, **pinfo}
        k += 1
        s.report("projection", layer=k, layers=len(slabs), orders=pk.n_orders)
    q_bottom = chain.rules[-1]

    top_layer = None
    delta_F = None
    L_bottom = 0
    Rc = None
    if isinstance(bottom, RoughConductor):
        Rc, cinfo = itf.rough_conductor(q_bottom, np.asarray(bottom.N, dtype=complex) / eta_binder, bottom.alpha,
                                        tol=s.tol, max_orders=s.order_cap,
                                        energy_compensation=bottom.energy_compensation)
        L_bottom = Rc.shape[0]
        info["bottom"] = {k: v for k, v in cinfo.items() if k != "albedo"}
    L_rest = ([L_bottom, 1] + [p[0].n_orders for p in projected if not isinstance(p[0], str)]
              + [p[1].n_orders for p in projected if p[0] == "rough"])

    # a rough top: with threads > 1 built in the background while the body's first orders are solved
    # (both mostly numpy calls that release the GIL).  Over an opaque body without a smooth inner
    # interface, the body reflects nothing beyond its components' orders (a slab's direct beam over a
    # black bottom reflects nothing), so the top's inner blocks are needed only below max(L_rest)
    # ``top_cache`` (channel groups): one top for every group, read only (never written in place)
    top_job = None
    if isinstance(top, Rough):
        smooth_inside = any(isinstance(p[0], str) and p[0] == "interface" for p in projected)
        inner = max(L_rest) if bottom is not None and not smooth_inside else None
        key = None if top_cache is None else (q_out.x.tobytes(), q_out.w.tobytes(), q_in.x.tobytes(), q_in.w.tobytes(),
                                              float(top.eta), float(top.alpha), s.tol, s.order_cap,
                                              bool(top.energy_compensation), inner)
        top_job = None if key is None else top_cache.get(key)
        if top_job is None:
            top_job = _submit(s.threads, itf.rough_dielectric, q_out, q_in, top.eta, top.alpha, tol=s.tol,
                              max_orders=s.order_cap, energy_compensation=top.energy_compensation, inner_orders=inner)
            if key is not None:
                top_cache[key] = top_job

    def total_orders():
        """The stack's order count; waits for the rough top (its own order count is part of it)."""
        nonlocal top_layer
        L_top = 0
        if top_job is not None:
            if top_layer is None:
                top_layer, _ = top_job.result()
                info["top"] = {"orders": top_layer.n_orders}
            L_top = top_layer.n_orders
        return min(max([L_top] + L_rest), s.order_cap)

    if isinstance(top, Smooth):
        smooth1, delta_F = itf.smooth_dielectric(q_out, q_in, top.eta, 1)

    def slab_block(pk, sig, d, q, l0, l1):
        """Layer of orders l0 … l1 − 1 of a slab: doubling where the kernel has orders, the exact
        direct beam beyond (extend_orders); an inner interface: the same blocks in every order."""
        k1 = min(l1, pk.n_orders)
        if k1 <= l0:
            return direct_only_orders(q.x, sig, d, l1 - l0, max(pk.channels, sig.shape[0]))
        K_T, K_R = pk.blocks(l0, k1)
        # while the rough top is built in the background, one thread fewer here (no oversubscription)
        busy = top_job is not None and not top_job.done()
        layer = homogeneous_slab(q.x, q.w, sig, K_T, K_R, d, s.slice_tau, l0=l0,
                                 threads=max(1, s.threads - 1) if busy else s.threads,
                                 method=s.slab_method)
        return extend_orders(layer, l1 - l0, q.x, sig, d)

    def item_block(item, l0, l1):
        """Layer of orders l0 … l1 − 1 of a slab or an inner interface."""
        if isinstance(item[0], str) and item[0] == "rough":  # its own orders, zero beyond them
            return _layer_orders(item[1], l0, l1)
        if isinstance(item[0], str):
            _, q_a, q_b, ia, ib, eta_rel = item
            return itf.smooth_inner(q_a, q_b, ia, ib, eta_rel, l1 - l0)
        pk, sig, d, q = item
        return slab_block(pk, sig, d, q, l0, l1)

    def top_block(l0, l1):
        if isinstance(top, Rough):
            return _layer_orders(top_layer, l0, l1)
        return Layer(*(np.broadcast_to(b, (l1 - l0,) + b.shape[1:]) for b in (smooth1.Rt, smooth1.Ttb, smooth1.Rb, smooth1.Tbt)))

    opaque = bottom is not None
    if opaque and s.order_tol is not None:
        Rt, oinfo = _solve_opaque_in_order_blocks(top, q_out, q_in, q_bottom, projected, bottom, total_orders, s, item_block,
                                                  top_block, smooth1 if isinstance(top, Smooth) else None, Rc,
                                                  top_rt=(lambda: top_layer.Rt) if isinstance(top, Rough) else None,
                                                  top_rt_writable=top_cache is None,
                                                  body_orders=inner if isinstance(top, Rough) else None)
        info.update(oinfo)
        return StackBSDF(x=q_out.x, w=q_out.w, Rt=Rt, eta=eta, delta_F=delta_F, x_in=q_in.x, w_in=q_in.w,
                         info=info)

    # all orders at once (transmissive stacks, or order_tol None)
    L = total_orders()
    body = None
    for k, item in enumerate(projected):
        layer = item_block(item, 0, L)
        body = layer if body is None else add(body, layer)
        s.report("solve", layer=k + 1, layers=len(projected), orders=(0, L), of=L)
    if body is None:
        body = identity_layer(L, q_in.h)
    top_layer_L = None if top is None else top_block(0, L)

    if isinstance(bottom, RoughConductor):
        body = Layer(*_reflection_over(body, pad_orders(Rc, L)))
    elif bottom is not None:
        prim = itf.lambertian(q_bottom, bottom.albedo, L)
        body = Layer(*_reflection_over(body, prim.Rt))
    whole = body if top_layer_L is None else add(top_layer_L, body)
    info["orders"] = L
    return StackBSDF(
        x=q_out.x, w=q_out.w, Rt=whole.Rt, eta=eta, delta_F=delta_F,
        Ttb=None if opaque else whole.Ttb, Rb=None if opaque else whole.Rb,
        Tbt=None if opaque else whole.Tbt, x_in=q_bottom.x, w_in=q_bottom.w, info=info,
    )


#: First block of orders solved by the order choice; later blocks double the count solved so far.
FIRST_ORDER_BLOCK = 16


def _solve_opaque_in_order_blocks(top, q_out, q_in, q_bottom, projected, bottom, L_max, s, item_block, top_block, smooth1,
                                  Rc=None, top_rt=None, body_orders=None, top_rt_writable=True):
    """R^t of an opaque stack, orders solved in blocks (16, then doubling) bottom-up with
    reflection-only adding, until :func:`flakedb.rt.orders.order_tail` says the BSDF's dropped tail is
    within ``s.order_tol`` (docs/orders.md).  ``Rc``: the rough conductor bottom's R^t (all its
    orders), None for a Lambertian primer.  ``L_max``: the stack's order count, or a function that
    returns it (waiting for a top built in the background: the body's first block is solved before
    it is called).  ``top_rt``: for a rough top, a function returning its R^t (L_top, 1, h, h) once
    built: where the body reflects nothing, the stack's R^t is that block, and the result is written
    into it when the shapes allow and ``top_rt_writable`` (the solver's own array, not one shared by
    channel groups: no second copy of a many-order top).
    ``body_orders``: the order beyond which the body below the top reflects nothing (None: unknown); with a
    top built in the background, the body's orders up to it (at most 64) are solved before waiting for
    the top, instead of only the first block.  Returns (Rt (L', C, h, h), info)."""
    if smooth1 is not None:
        h_tir = q_in.h - q_out.h
        t = smooth1.Ttb[0, 0][h_tir + np.arange(q_out.h), np.arange(q_out.h)]
        F_in = np.diagonal(smooth1.Rb[0, 0])

    def reflection(l0, l1):
        R = None
        if Rc is not None:  # a rough conductor bottom carries orders of its own
            Rb = pad_orders(Rc, max(l1, Rc.shape[0]))[l0:l1]
            for k, item in enumerate(reversed(projected)):
                Rb = reflection_over(item_block(item, l0, l1), Rb)
                s.report("solve", layer=len(projected) - k, layers=len(projected), orders=(l0, l1), of=L_report)
            return Rb
        if l0 == 0:  # the Lambertian primer has order 0 only: its adding runs for that order alone
            prim = itf.lambertian(q_bottom, bottom.albedo, 1).Rt
            R0 = prim
            for item in reversed(projected):
                R0 = reflection_over(item_block(item, 0, 1), R0)
            R = R0
            l0 = 1
        if l1 > l0:
            Rr = None
            for k, item in enumerate(reversed(projected)):
                # a slab without kernel orders here (only its direct beam) over a black bottom reflects
                # nothing: the bottom stays black, no blocks are built
                if not (Rr is None and not isinstance(item[0], str) and item[0].n_orders <= l0):
                    Rr = reflection_over(item_block(item, l0, l1), Rr)
                s.report("solve", layer=len(projected) - k, layers=len(projected), orders=(l0, l1), of=L_report)
            if Rr is None:  # the body reflects nothing in these orders
                if R is None:
                    return None
                Rr = np.zeros((l1 - l0, 1, q_in.h, q_in.h))
            if R is None:
                R = Rr
            else:
                shape = np.broadcast_shapes(R.shape[1:], Rr.shape[1:])
                R = np.concatenate([np.broadcast_to(R, R.shape[:1] + shape), np.broadcast_to(Rr, Rr.shape[:1] + shape)])
        return R

    def through_top(R, l0, l1):
        if top is None:
            return R
        if isinstance(top, Smooth):
            return reflection_under_smooth(t, F_in, h_tir, R)
        return reflection_over(top_block(l0, l1), R)

    first = None
    if callable(L_max):  # the body's first block does not need the top: solve it while the top is built
        L_report = L_first = min(s.order_cap, max(FIRST_ORDER_BLOCK, min(body_orders or 0, 4 * FIRST_ORDER_BLOCK)))
        first = reflection(0, L_first)
        L_max = L_max()
    L_report = L_max
    out, a = None, []  # out: R^t of the orders solved so far, (L_max, C, h, h) filled block by block
    # the cosine-weighted BSDF f μ_i μ_o = S_l μ_o / (c_l w_i) (conventions; reciprocal: the flux a
    # coefficient carries between the two directions per unit projected solid angle) measures the
    # decay: grazing pairs, where f itself grows as 1/(μ_i μ_o) for a rough coat, do not dictate the
    # order count (docs/orders.md)
    flux = q_out.x[:, None] / q_out.w[None, :]
    l0, f0max, done = 0, None, False
    L_keep, tail = 1, 0.0
    while l0 < L_max:
        l1 = min(L_max, max(FIRST_ORDER_BLOCK, 2 * l0))
        if first is not None and l0 < first.shape[0]:  # orders are independent: blocks inside the solved ones
            l1 = min(l1, first.shape[0])
            R = first[l0:l1]
        else:
            R = reflection(l0, l1)
        own = None  # the rough top's R^t array, when it holds these orders of the result as they are
        if R is None:  # a black body: the top's own reflection (no blocks built, no solve)
            if top_rt is not None:
                own = top_rt()
                Rt = _order_range(own, l0, l1)
            else:
                Rt = np.broadcast_to(np.zeros((1, 1, q_out.h, q_out.h)), (l1 - l0, 1, q_out.h, q_out.h))
        else:
            Rt = through_top(R, l0, l1)
        if out is None or np.broadcast_shapes(out.shape[1:], Rt.shape[1:]) != out.shape[1:]:
            shape = Rt.shape[1:] if out is None else np.broadcast_shapes(out.shape[1:], Rt.shape[1:])
            trt = top_rt() if top_rt is not None else None
            if trt is not None and top_rt_writable and trt.shape[0] >= L_max and trt.shape[1:] == shape and l0 == 0:
                grown = trt  # written in place: block l is read (through_top) before order l is written
            else:
                grown = np.empty((L_max,) + shape)
                if out is not None:
                    grown[:l0] = out[:l0]
            out = grown
        if own is None or out is not own:
            out[l0:l1] = Rt
        amax = np.empty(l1 - l0)
        for c0 in range(0, l1 - l0, FIRST_ORDER_BLOCK):  # |Rt| flux-weighted, a few orders at a time
            g = np.abs(Rt[c0:c0 + FIRST_ORDER_BLOCK])
            g *= flux
            amax[c0:c0 + FIRST_ORDER_BLOCK] = g.reshape(g.shape[0], -1).max(axis=1)
        amax /= fourier_weight(np.arange(l0, l1))
        if f0max is None:
            f0max = float(amax[0])
        a.extend((amax / (f0max if f0max > 0 else 1.0)).tolist())
        l0 = l1
        L_keep, tail, done = order_tail(a, L_max, s.order_tol)
        if done:
            break
    info = {"orders": int(L_keep), "orders_solved": int(l0), "orders_available": int(L_max),
            "order_tol": float(s.order_tol), "order_tail": float(tail), "order_converged": bool(done),
            "order_decay": [float(v) for v in a]}
    return out[:L_keep], info


def _order_range(b, l0, l1):
    """Orders l0 … l1 − 1 of a block that is zero beyond its own orders: a view where it has them, a
    broadcast zero (no memory) where it has none, padded with zeros in between."""
    if l0 >= b.shape[0]:
        return np.broadcast_to(np.zeros((1,) + b.shape[1:]), (l1 - l0,) + b.shape[1:])
    return b[l0:l1] if l1 <= b.shape[0] else pad_orders(b[l0:l1], l1 - l0)


def _layer_orders(layer, l0, l1):
    """Orders l0 … l1 − 1 of a layer whose blocks are zero beyond their own order counts (a rough
    interface, whose inner blocks may stop earlier than R^t): :func:`_order_range` of each block."""
    return Layer(*(_order_range(b, l0, l1) for b in (layer.Rt, layer.Ttb, layer.Rb, layer.Tbt)))


def _reflection_over(layer, bottom_Rt):
    """(Rt, Ttb, Rb, Tbt) of ``layer`` over an opaque bottom: only Rt survives; the others are zero."""
    Rt = add_reflection_only(layer, bottom_Rt)
    return (Rt,) + tuple(np.zeros((1, 1) + blk.shape[-2:]) for blk in (layer.Ttb, layer.Rb, layer.Tbt))
