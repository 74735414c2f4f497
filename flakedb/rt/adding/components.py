"""The parts a paint stack is made of, and the solver's settings (docs/model.md §1, §4).

    air | top interface (None, :class:`Smooth` or :class:`Rough`) | slabs and inner interfaces
    (:class:`Slab`, :class:`InnerSmooth`, :class:`InnerRough`) | bottom (:class:`Lambertian`,
    :class:`RoughConductor` or None)

Plain parameter records, checked on construction; :func:`flakedb.rt.adding.stack.solve_stack` solves them.
"""

from dataclasses import dataclass

from flakedb.rt.common.params import check_alpha, check_complex_index, check_range

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
    """A homogeneous slab of ``thickness_um`` holding ``medium`` (see :mod:`flakedb.rt.scattering.media`)."""

    thickness_um: float
    medium: object

    def __post_init__(self):
        check_range("Slab", "thickness_um", self.thickness_um, 0.0, None)


@dataclass
class InnerSmooth:
    """A smooth interface between two slabs (docs/model.md §4 "Inner interface"): relative index
    ``eta`` = n_below / n_above (the binder below over the binder above; a rise > 1 or a fall < 1).
    Placed in the ``slabs`` list of :func:`solve_stack` between the slabs it separates; every binder
    lives on its rule of :func:`flakedb.rt.basis.quadrature.binder_chain_quadratures` (one node set on the
    Snell invariant: the interface maps shared nodes one to one, lossless and reciprocal)."""

    eta: float

    def __post_init__(self):
        check_range("InnerSmooth", "eta", self.eta, 0.0, None, lo_open=True)


@dataclass
class InnerRough:
    """A rough interface between two slabs: Beckmann roughness ``alpha`` > 0, relative index ``eta`` =
    n_below / n_above (a rise or a fall), by flux-cell integration between the two binders' rules
    (:func:`flakedb.rt.boundaries.interface.rough_dielectric`, docs/rough-interfaces.md, docs/model.md §4 "Inner
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
    """Diffuse primer of albedo (scalar or per channel) at the bottom of the stack.

    >>> Lambertian([0.2, 0.8]).albedo
    [0.2, 0.8]
    >>> Lambertian(1.2)
    Traceback (most recent call last):
    ...
    ValueError: Lambertian.albedo = 1.2 is outside the allowed range 0 ≤ albedo ≤ 1, finite
    """

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
    ``energy_compensation``: add the multiple-scattering lobe (default; docs/rough-interfaces.md)."""

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
    #: How homogeneous slabs are solved (:func:`flakedb.rt.basis.layer.homogeneous_slab`): "eigen", the exact
    #: eigen-solution of the discrete-ordinate equations (default), or "doubling" from a thin slice
    #: of optical thickness ``slice_tau`` (the fallback for non-reciprocal kernels).
    slab_method: str = "eigen"
    #: Jackson-filter a medium kernel cut by the order cap (:func:`flakedb.rt.scattering.medium_projection.damp_if_capped`): its truncated
    #: series rings negative otherwise.  False: plain truncation (order-convergence studies).
    filter_capped_kernels: bool = True
    #: Threads over the (orders, channels) batch of the slab solvers (:func:`flakedb.rt.basis.layer.double_symmetric`,
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

