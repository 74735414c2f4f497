"""A slab's medium kernel projected on the cosine series in φ_d (docs/projection.md, docs/model.md §3):
Legendre moments where the phase function has them, the adaptive φ projection through the spectral
basis otherwise, precomputed store factors where a medium carries them; the symmetric renormalisation
that makes the discrete kernel scatter what the medium scatters; the Jackson filter of a kernel cut by
the order cap."""

import numpy as np

from flakedb.rt.basis.legendre import LegendreKernel
from flakedb.rt.scattering.media import kernel_basis
from flakedb.rt.boundaries.microfacet import jackson_factors
from flakedb.rt.scattering.projection import RESIDENT_ORDERS, ProjectedKernel, project_kernel_basis

#: φ samples of a kernel projection at most, per order of the cap 2n (and at least 128).  It was 2 (4n samples:
#: where the cap binds, aliasing from orders ≥ 2L far below the truncation): metallic silver at n = 128 then
#: took 181 s and 8.4 GB, most of it the φ samples of kernels that never converge at grazing pairs, while the
#: stack keeps 11 orders.  Measured at 0.5 (n samples): metallic silver n = 96 ΔE00 ≤ 5e-5 against 2 at every
#: report geometry (23 → 4.4 s, 4.6 → 2.3 GB), particle pearlescent and tri-coat pearl white n = 64 ΔE00 0;
#: the kernel's renormalisation then reaches 1.6 % (metallic silver, n ≥ 96; compose warns above 1 %).
PHI_SAMPLES_PER_ORDER = 0.5


def legendre_moments(medium, tol):
    """The medium's Legendre moments when its kernel is σ_s times an HG, vMF or tabulated phase
    function (:meth:`flakedb.rt.scattering.media.PhaseMedium.legendre_moments`), else None."""
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
    """A medium's kernel projected on the cosine series: a :class:`flakedb.rt.scattering.projection.ProjectedKernel`
    (K_T, K_R blocks of any orders on demand) and the projection info.

    With ``basis`` (default) the kernel is projected through its spectral basis
    (:func:`flakedb.rt.scattering.media.kernel_basis`, docs/projection.md): B basis kernels are sampled and
    transformed once and the C channels combined from them, with the adaptive criteria applied to
    the channels exactly as before; ``basis=False`` samples every channel's kernel (the previous path;
    the same coefficients to rounding, tested).

    With ``renormalize`` (default), the kernel is scaled symmetrically, K[o, i] → s_o K[o, i] s_i
    (which keeps it reciprocal), so that the discrete scattering integral
    Σ_o 2π w_o (K_T + K_R)_0[o, i] equals the medium's accurately integrated σ_s(μ_i)
    (``medium.sigma_s``).  A point-sampled kernel narrower than the node spacing
    otherwise creates or destroys energy; the scale factors' spread is reported in ``info``
    (``renorm_max_dev``) and tested.

    >>> from flakedb.rt.scattering.media import PhaseMedium
    >>> from flakedb.rt.basis.quadrature import gauss_radau_unit
    >>> x, w = gauss_radau_unit(4)
    >>> pk, info = project_medium(PhaseMedium(2.0, 0.9, ("hg", 0.6)), x, w, 1e-6, 16)
    >>> K_T, K_R = pk.blocks(0, pk.n_orders)
    >>> scattered = 2 * np.pi * np.einsum("coi,o->ci", K_T[0] + K_R[0], w)     # = σ_s = 0.9 × 2.0 per µm
    >>> bool(np.allclose(scattered, 1.8, rtol=0, atol=1e-12)), bool(np.allclose(K_R, K_R.transpose(0, 1, 3, 2)))
    (True, True)
    """
    mu_o = np.concatenate([-x, x])  # up-going (reflection-like) then down-going
    W = w[:, None] * np.concatenate([w, w])[None, :]  # flux carried i → o per unit kernel
    # φ sampling up to 2× the order cap: where the cap binds, aliasing from orders ≥ 2L into the
    # kept orders is far below the truncation itself
    n_max = max(int(PHI_SAMPLES_PER_ORDER * max_orders), 128)
    n_start = min(max(4, _component_orders_hint(medium)), n_max)
    if hasattr(medium, "projected_kernel"):  # precomputed factors (flakedb.rt.scattering.stored): no projection here
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
        fn, M, parts = (medium.kernel, None, None) if kb is None else (kb.fn, kb.M, kb.parts)
        # over its memory budget the projection keeps its first RESIDENT_ORDERS orders (the order choice
        # rarely asks for more) and evaluates higher ones again on demand
        coeffs, info = project_kernel_basis(fn, M, x, mu_o, tol=tol, n_start=n_start, n_max=n_max, weights=W,
                                            max_orders=max_orders, resident_orders=RESIDENT_ORDERS, parts=parts)
        pk = ProjectedKernel(coeffs, M)
        if M is not None:
            info["basis_functions"] = int(M.shape[1])
    if renormalize and hasattr(medium, "sigma_s"):
        pk.scale, info["renorm_max_dev"] = renormalization(pk, np.atleast_2d(medium.sigma_s(x)), w)
    return damp_if_capped(pk, info, max_orders) if filter_capped else (pk, info)


def renormalization(pk, target, w):
    """Symmetric scale factors s (C, h) of a projected kernel, K[o, i] → s_o K[o, i] s_i (which keeps it
    reciprocal), so that Σ_o 2π w_o (K_T + K_R)_0[o, i] equals ``target`` (C, h) = σ_s(μ_i): the fixed
    point of s_i Σ_o M[o, i] w_o s_o = σ_s(μ_i) by a damped multiplicative iteration.  Returns
    ``(scale, max |s² − 1|)``.

    Where σ_s(μ_i) = 0 (a flake whose R(c) is 0 near c = 1, e.g. an interference minimum of a pearlescent
    flake in one RGB channel, seen along its narrow normal distribution) light from μ_i does not scatter:
    s_i = 0 zeroes column i (and, symmetrically, row i, which reciprocity also makes zero), and the
    iteration keeps it there (it used to divide 0 by 0: a NaN BSDF at every n).  Such columns, and those below
    :data:`RENORM_REPORT_FLOOR` of the channel's largest σ_s, are left out of the reported deviation.

    >>> M = np.array([[[1.0, 0.5], [0.5, 1.0]]]) / (2 * np.pi)       # (C, o, i), K_T0 + K_R0
    >>> class PK:
    ...     def blocks(self, l0, l1):
    ...         return M[None], 0.0 * M[None]
    >>> s, dev = renormalization(PK(), np.array([[1.5, 0.0]]), np.array([1.0, 1.0]))
    >>> np.round(s, 12).tolist(), round(dev, 12)                     # s_0² = 1.5, s_1 = 0
    ([[1.224744871392, 0.0]], 0.5)
    """
    h = len(w)
    K_T0, K_R0 = pk.blocks(0, 1)
    M0 = 2.0 * np.pi * (K_T0[0] + K_R0[0])  # (C, o, i)
    shape = np.broadcast_shapes(target.shape, M0.shape[:1] + (h,))
    target = np.broadcast_to(target, shape)
    live = target > 0.0
    scale = np.where(live, 1.0, 0.0)
    for _ in range(50):
        col = np.einsum("coi,o,co->ci", M0, w, scale)
        with np.errstate(divide="ignore", invalid="ignore"):
            upd = np.where(live & (col > 0), np.sqrt(target / (scale * col)), 1.0)
        scale = scale * upd
        if np.abs(upd - 1.0).max() < 1e-15:
            break
    # the reported deviation: columns that carry scattering (σ_s ≥ RENORM_REPORT_FLOOR of the channel's largest);
    # a column scattering 1e-6 of the peak may be rescaled by several times without moving any energy that shows
    # (a fuzzed recipe's warning read "renormalised by up to 351 %" there)
    shown = live & (target >= RENORM_REPORT_FLOOR * target.max(axis=-1, keepdims=True))
    return scale, float(np.abs(scale**2 - 1.0)[shown].max(initial=0.0))


#: Columns scattering less than this fraction of their channel's largest σ_s are left out of the reported
#: renormalisation deviation (:func:`renormalization`; they are still renormalised).
RENORM_REPORT_FLOOR = 1e-3


#: A kernel whose last kept order still exceeds CAPPED_TAIL × its order 0 was cut by the order cap.
CAPPED_TAIL = 1e-4


class DampedKernel:
    """A projected kernel whose orders are multiplied by damping factors g_l (:func:`damp_if_capped`)."""

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


def damp_if_capped(pk, info, max_orders):
    """A kernel cut by the order cap (its last order above :data:`CAPPED_TAIL` × order 0) rings: its
    truncated cosine series goes negative (perfect mirror flakes α 0.15 in air at n = 32: the BSDF
    reaches −3.5 % of its maximum).  Like the rough interfaces (docs/rough-interfaces.md,
    "Positivity"), it is then smoothed in φ by the Jackson kernel's factors
    (:func:`flakedb.rt.boundaries.microfacet.jackson_factors`): a positive convolution ≈ π/L wide that keeps
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
