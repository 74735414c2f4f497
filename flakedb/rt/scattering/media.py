"""Scattering media for the slab solver: phase-function media (isotropic, Henyey–Greenstein,
von Mises–Fisher, tabulated) and mixtures of components (docs/model.md §3: "species mix in one layer by adding their
σ_t, σ_s and kernels").

A medium component provides

* ``sigma_t(mu)`` → (C, …) extinction in 1/µm at cosines ``mu`` (may depend on direction),
* ``kernel(mu_i, mu_o, phi_d)`` → (C, …) the scattering kernel σ_s f_p(ω_i → ω_o) in
  1/(µm·sr) (conventions: propagation directions, φ_d = 0 forward),
* ``phi_bandwidth`` — a first guess of the number of φ intervals the kernel needs (the projection
  refines it adaptively),

and is symmetric under z → −z (the solver relies on it, see :func:`flakedb.rt.basis.layer.thin_slab_diamond`).
"""

from dataclasses import dataclass, field

import numpy as np

from flakedb.rt.basis.legendre import LEGENDRE_K_MAX, LEGENDRE_TOL, legendre_moments, truncate_legendre
from flakedb.rt.scattering.microflake import (
    FlakeOptics,
    extinction_Ergun,
    flake_distribution,
    interp_rows,
    kernel_Ergun,
    kernel_Ergun_basis,
    phase_HG,  # noqa: F401  (re-exported: the one HG definition)
    scattering_Ergun,
    table_basis,
)
from flakedb.rt.common.params import check_range
from flakedb.rt.common.reuse import array_key


def cos_scattering_angle(mu_i, mu_o, phi_d):
    """cos Θ = ω_i · ω_o for propagation directions with cosines μ_i, μ_o and azimuth difference φ_d.

    With ω = (sin θ cos φ, sin θ sin φ, −μ) (conventions): cos Θ = μ_i μ_o + sin θ_i sin θ_o cos φ_d.
    """
    si = np.sqrt(np.maximum(1.0 - mu_i**2, 0.0))
    so = np.sqrt(np.maximum(1.0 - mu_o**2, 0.0))
    return np.clip(mu_i * mu_o + si * so * np.cos(phi_d), -1.0, 1.0)


def _channels(a):
    return np.atleast_1d(np.asarray(a, dtype=float))


# ---------------------------------------------------------------------------------------------
# von Mises–Fisher phase function (docs/model.md §3 "von Mises–Fisher phase function")
# ---------------------------------------------------------------------------------------------


def phase_vMF(cos_theta, kappa):
    """von Mises–Fisher phase function (Fisher 1953; Mardia & Jupp 2000, ch. 9, on the sphere S²)

        p(cos Θ) = κ / (4π sinh κ) · exp(κ cos Θ)   [1/sr],   ∫_sphere p dω = 1,

    evaluated as κ / (2π (1 − e^{−2κ})) · exp(κ (cos Θ − 1)), which neither overflows nor cancels
    (κ = 0: 1/(4π), isotropic).  ``cos_theta`` (cos Θ = ω_i·ω_o of propagation directions, 1 forward)
    and ``kappa`` (κ ≥ 0) broadcast.  docs/model.md §3."""
    k = np.asarray(kappa, dtype=float)
    if np.any(~(k >= 0.0)) or np.any(~np.isfinite(k)):
        raise ValueError(f"phase_vMF needs a finite concentration kappa >= 0, got {kappa!r}")
    ct = np.asarray(cos_theta, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = np.where(k > 0.0, k / (2.0 * np.pi * -np.expm1(-2.0 * k)), 1.0 / (4.0 * np.pi))
    return norm * np.exp(k * (ct - 1.0))


def vmf_mean_cosine(kappa):
    """Mean cosine g = <cos Θ> = coth κ − 1/κ of the vMF phase function (the Langevin function;
    Mardia & Jupp 2000, ch. 9: A_3(κ) = I_{3/2}(κ)/I_{1/2}(κ)); series κ/3 − κ³/45 + 2κ⁵/945 below κ = 1e-2 (where the
    closed form cancels).  docs/model.md §3."""
    k = np.asarray(kappa, dtype=float)
    small = k < 1e-2
    ks = np.where(small, 1.0, k)
    with np.errstate(over="ignore"):
        big = ks / np.tanh(ks) - 1.0  # κ coth κ − 1, then / κ
    return np.where(small, k / 3.0 - k**3 / 45.0 + 2.0 * k**5 / 945.0, big / ks)


def vmf_kappa_from_mean_cosine(g):
    """κ ≥ 0 with coth κ − 1/κ = g, for 0 ≤ g < 1 (the inverse of :func:`vmf_mean_cosine`, which is
    increasing): vectorised bisection on [0, 1/(1 − g)] (coth κ − 1/κ ≥ 1 − 1/κ brackets it) to
    relative 1e-14.  docs/model.md §3.

    The vMF phase function integrates to 1 over the sphere, and κ → g → κ is a round trip:

    >>> t, w = np.polynomial.legendre.leggauss(64)
    >>> round(float(2 * np.pi * np.sum(w * phase_vMF(t, 3.0))), 12)
    1.0
    >>> g = vmf_mean_cosine(3.0)
    >>> round(float(g), 6), round(float(vmf_kappa_from_mean_cosine(g)), 9)
    (0.671636, 3.0)
    """
    g = np.asarray(g, dtype=float)
    if np.any(~(g >= 0.0)) or np.any(~(g < 1.0)):
        raise ValueError(f"a vMF mean cosine must be 0 <= g < 1 (the vMF lobe points forward), got {g!r}")
    lo = np.zeros_like(g)
    hi = 1.0 / (1.0 - g) + 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        up = vmf_mean_cosine(mid) < g
        lo, hi = np.where(up, mid, lo), np.where(up, hi, mid)
        if np.all(hi - lo <= 1e-14 * np.maximum(hi, 1e-300)):
            break
    return 0.5 * (lo + hi)


def vmf_legendre_moments(kappa, K):
    """Legendre moments χ_k = 2π ∫ p(t) P_k(t) dt, k = 0 … K, of the vMF phase function, (C, K + 1)
    for ``kappa`` scalar or (C,):

        χ_k = i_k(κ) / i_0(κ) = I_{k+1/2}(κ) / I_{1/2}(κ)

    (i_k the modified spherical Bessel functions of the first kind: the Legendre expansion
    e^{κt} = Σ_k (2k + 1) i_k(κ) P_k(t), Abramowitz & Stegun §10.2; Mardia & Jupp 2000, ch. 9).
    Computed with the exponentially scaled Bessel function ``scipy.special.ive`` (the e^{−κ} factors
    cancel in the ratio), so it neither overflows for large κ (tested to κ = 2000) nor needs
    ``spherical_in`` (which overflows beyond κ ≈ 700); κ = 0 gives (1, 0, 0, …).  The moments
    decay like exp(−k(k + 1)/(2κ)) for large κ.  docs/model.md §3."""
    from scipy.special import ive  # lazy: scipy.special takes 0.15 s to import (flakedb.rt.basis.special); only von Mises–Fisher needs it
    k = np.atleast_1d(np.asarray(kappa, dtype=float))
    if np.any(~(k >= 0.0)) or np.any(~np.isfinite(k)):
        raise ValueError(f"vMF moments need a finite kappa >= 0, got {kappa!r}")
    deg = np.arange(int(K) + 1, dtype=float)
    kk = np.where(k > 0.0, k, 1.0)[:, None]
    with np.errstate(under="ignore"):
        chi = ive(deg[None, :] + 0.5, kk) / ive(0.5, kk)
    chi = np.where(k[:, None] > 0.0, chi, (deg[None, :] == 0).astype(float))
    return np.nan_to_num(chi, nan=0.0)


def vmf_legendre_degree(kappa, tol=LEGENDRE_TOL, k_max=LEGENDRE_K_MAX):
    """The Legendre degree K at which the vMF series' relative dropped tail is ≤ ``tol``
    (:func:`flakedb.rt.basis.legendre.truncate_legendre`) for every κ in ``kappa``; the kernel has no
    azimuthal order above it (addition theorem, :mod:`flakedb.rt.basis.legendre`)."""
    k = np.atleast_1d(np.asarray(kappa, dtype=float))
    K = 64
    while True:
        _, info = truncate_legendre(vmf_legendre_moments(k, K), tol)
        if info["converged"] and info["degree"] < K or K >= k_max:
            return int(info["degree"])
        K = min(2 * K, int(k_max))


@dataclass
class PhaseMedium:
    """Direction-independent extinction with a phase function of the scattering angle.

    ``sigma_t_per_um`` and ``albedo`` are per channel (C,) or scalars.  ``phase`` is ``"isotropic"``,
    ``("hg", g)`` with g per channel or scalar, ``("vmf", kappa)`` (von Mises–Fisher,
    :func:`phase_vMF`, κ ≥ 0 per channel or scalar), or ``("table", cos_theta, values)`` with values
    (C, n) or (n,) in 1/sr (normalised to 1 over the sphere; linear interpolation in cos Θ).
    """

    sigma_t_per_um: object
    albedo: object
    phase: object = "isotropic"

    def __post_init__(self):
        check_range("PhaseMedium", "sigma_t_per_um", self.sigma_t_per_um, 0.0, None)
        check_range("PhaseMedium", "albedo", self.albedo, 0.0, 1.0)
        ph = self.phase
        if isinstance(ph, str):
            if ph != "isotropic":
                raise ValueError(f"PhaseMedium.phase = {ph!r}: use 'isotropic', ('hg', g), ('vmf', kappa) or "
                                 f"('table', cos_theta, values)")
        elif ph[0] == "hg":
            check_range("PhaseMedium", "phase g", ph[1], -1.0, None, lo_open=True)
            if np.any(np.asarray(ph[1], dtype=float) >= 1.0):
                raise ValueError(f"PhaseMedium.phase g = {ph[1]!r} is outside the allowed range -1 < g < 1")
        elif ph[0] == "vmf":
            check_range("PhaseMedium", "phase kappa", ph[1], 0.0, None)
        elif ph[0] == "table":
            ct = np.asarray(ph[1], dtype=float)
            check_range("PhaseMedium", "phase cos_theta", ct, -1.0, 1.0)
            if ct.ndim != 1 or ct.size < 2 or np.any(np.diff(ct) <= 0):
                raise ValueError("PhaseMedium.phase cos_theta must be a strictly ascending list of ≥ 2 cosines")
            check_range("PhaseMedium", "phase values", ph[2], 0.0, None)

    def sigma_t(self, mu):
        s = _channels(self.sigma_t_per_um)
        return np.broadcast_to(s.reshape((-1,) + (1,) * np.ndim(mu)), (len(s),) + np.shape(mu))

    def _p(self, cos_t):
        ph = self.phase
        if ph == "isotropic":
            return np.full((1,) + np.shape(cos_t), 1.0 / (4.0 * np.pi))
        kind = ph[0]
        if kind == "hg":
            g = _channels(ph[1]).reshape((-1,) + (1,) * np.ndim(cos_t))
            return phase_HG(cos_t[None], g)
        if kind == "vmf":
            k = _channels(ph[1]).reshape((-1,) + (1,) * np.ndim(cos_t))
            return phase_vMF(cos_t[None], k)
        if kind == "table":
            ct = np.asarray(ph[1], dtype=float)
            vals = np.atleast_2d(np.asarray(ph[2], dtype=float))
            return np.stack([np.interp(cos_t, ct, v) for v in vals])
        raise ValueError(f"unknown phase function {ph!r}; use 'isotropic', ('hg', g), ('vmf', kappa) "
                         "or ('table', cos, p)")

    def sigma_s(self, mu):
        return self.sigma_t(mu) * _channels(self.albedo).reshape((-1,) + (1,) * np.ndim(mu))

    def subset(self, idx):
        """The same medium restricted to channels ``idx`` (per-channel values sliced)."""
        def take(a):
            a = np.asarray(a, dtype=float)
            return a if a.ndim == 0 or a.shape[0] == 1 else a[idx]

        ph = self.phase
        if ph != "isotropic":
            if ph[0] in ("hg", "vmf"):
                ph = (ph[0], take(ph[1]))
            elif ph[0] == "table":
                vals = np.asarray(ph[2], dtype=float)
                ph = ("table", ph[1], vals[idx] if vals.ndim == 2 and vals.shape[0] > 1 else vals)
        return PhaseMedium(take(self.sigma_t_per_um), take(self.albedo), ph)

    def channel_key(self, C):
        """(C, k): every per-channel parameter of the medium as one row per channel; two channels with
        equal rows scatter identically (the solver then solves one of them, docs/model.md §4)."""
        parts = [_channels(self.sigma_t_per_um)[:, None], _channels(self.albedo)[:, None]]
        ph = self.phase
        if ph != "isotropic":  # HG g or vMF κ per channel, or the table's rows of values
            parts.append(_channels(ph[1])[:, None] if ph[0] in ("hg", "vmf")
                         else np.atleast_2d(np.asarray(ph[2], dtype=float)))
        return _key_rows(parts, C)

    def kernel(self, mu_i, mu_o, phi_d):
        cos_t = cos_scattering_angle(mu_i, mu_o, phi_d)
        ss = (_channels(self.sigma_t_per_um) * _channels(self.albedo)).reshape((-1,) + (1,) * cos_t.ndim)
        return ss * self._p(cos_t)

    def legendre_moments(self, tol=LEGENDRE_TOL):
        """``(χ, info)``: the Legendre moments (C, K + 1) of the phase function, truncated at the
        relative tail ``tol`` (:func:`flakedb.rt.basis.legendre.truncate_legendre`): χ_k = g^k for HG (its
        generating function, Henyey & Greenstein 1941), :func:`vmf_legendre_moments` for vMF, the exact
        moments of the linear interpolant for a table (:func:`flakedb.rt.basis.legendre.legendre_moments`).
        None for the isotropic phase function, or when the series needs more than ``LEGENDRE_K_MAX``
        degrees (HG with |g| → 1, a very sharp forward peak).  The kernel then follows from the
        addition theorem with no azimuthal sampling (:class:`flakedb.rt.basis.legendre.LegendreKernel`;
        docs/model.md §3)."""
        if self.phase == "isotropic" or self.phase[0] not in ("hg", "vmf", "table"):
            return None
        C = max(_channels(self.sigma_t_per_um).size, _channels(self.albedo).size)
        if self.phase[0] == "table":
            chi, info = legendre_moments(self.phase[1], np.atleast_2d(np.asarray(self.phase[2], dtype=float)), tol)
        else:
            par = _channels(self.phase[1])
            if self.phase[0] == "hg":
                if np.max(np.abs(par)) >= 1.0:
                    return None
                chi = par[:, None] ** np.arange(LEGENDRE_K_MAX + 1)[None, :]
            else:
                # twice the degree the tail asks for: the cut then lies before the last computed
                # degree, where the dropped tail is measured (truncate_legendre's "converged")
                K = vmf_legendre_degree(np.max(par), tol)
                chi = vmf_legendre_moments(par, min(LEGENDRE_K_MAX, 2 * K + 2))
            chi, info = truncate_legendre(chi, tol)
        # cut before the last computed degree: the dropped tail is then the measured one
        if not (info["converged"] and info["degree"] < LEGENDRE_K_MAX):
            return None
        return np.broadcast_to(chi, (max(C, chi.shape[0]), chi.shape[1])), info

    def kernel_basis(self):
        """The kernel as Σ_b M[c, b] k_b (:class:`KernelBasis`): σ_s(c) times a phase function that
        is one of a few basis functions of cos Θ — one per distinct HG g, or the rows of a truncated
        SVD of a phase table (the table's linear interpolant is linear in its values)."""
        sig_s = _channels(self.sigma_t_per_um) * _channels(self.albedo)
        ph = self.phase
        if ph == "isotropic":
            return _single_part(("isotropic",), lambda mi, mo, p: np.full(
                (1,) + np.shape(cos_scattering_angle(mi, mo, p)), 1.0 / (4.0 * np.pi)), sig_s[:, None])
        if ph[0] in ("hg", "vmf"):
            g = _channels(ph[1])
            C = max(sig_s.size, g.size)
            g = np.broadcast_to(g, (C,))
            uniq, inv = np.unique(g, return_inverse=True)
            M = np.zeros((C, uniq.size))
            M[np.arange(C), inv.ravel()] = np.broadcast_to(sig_s, (C,))
            phase_fn = phase_HG if ph[0] == "hg" else phase_vMF

            def lobe(mi, mo, p):
                cos_t = cos_scattering_angle(mi, mo, p)
                return phase_fn(cos_t[None], uniq.reshape((-1,) + (1,) * cos_t.ndim))

            return _single_part((ph[0], array_key(uniq)), lobe, M)
        if ph[0] == "table":
            ct = np.asarray(ph[1], dtype=float)
            U, V = table_basis(np.atleast_2d(np.asarray(ph[2], dtype=float)))
            C = max(sig_s.size, U.shape[0])
            M = np.broadcast_to(sig_s[:, None], (C, 1)) * np.broadcast_to(U, (C, U.shape[1]))
            return _single_part(("table", array_key(ct), array_key(V)),
                                lambda mi, mo, p: interp_rows(V, ct, cos_scattering_angle(mi, mo, p)), M)
        raise ValueError(f"unknown phase function {ph!r}; use 'isotropic', ('hg', g), ('vmf', kappa) "
                         "or ('table', cos, p)")

    @property
    def phi_bandwidth(self):
        if self.phase == "isotropic":
            return 2
        if self.phase[0] == "hg":
            g = float(np.max(np.abs(_channels(self.phase[1]))))
            return int(2 ** np.ceil(np.log2(max(8.0, 8.0 / max(1e-3, 1.0 - g)))))
        if self.phase[0] == "vmf":
            # no azimuthal order above the Legendre degree of the series (addition theorem): start
            # the φ sampling at twice it
            K = vmf_legendre_degree(np.max(_channels(self.phase[1])))
            return int(2 ** np.ceil(np.log2(max(8.0, 2.0 * (K + 1)))))
        return 64


@dataclass
class Mixture:
    """Several components in one layer: extinctions and kernels add (docs/model.md §3)."""

    components: list = field(default_factory=list)

    def sigma_t(self, mu):
        return sum(_bc(c.sigma_t(mu)) for c in self.components)

    def sigma_s(self, mu):
        return sum(_bc(c.sigma_s(mu)) for c in self.components)

    def subset(self, idx):

        return Mixture([channel_subset(c, idx) for c in self.components])

    def channel_key(self, C):
        """(C, k): the components' keys side by side (None when one has none)."""
        keys = [channel_key(c, C) for c in self.components]
        return None if any(k is None for k in keys) else _key_rows(keys, C)

    def kernel(self, mu_i, mu_o, phi_d):
        return sum(c.kernel(mu_i, mu_o, phi_d) for c in self.components)

    def kernel_basis(self):
        """The components' bases side by side: kernels add, so the combination matrices are
        concatenated along the basis axis (channel counts of 1 broadcast)."""
        parts = [kernel_basis(c) for c in self.components]
        if any(p is None for p in parts):
            return None
        C = max(p.M.shape[0] for p in parts)
        M = np.concatenate([np.broadcast_to(p.M, (C, p.M.shape[1])) for p in parts], axis=1)

        def fn(mi, mo, ph):
            vals = [np.asarray(p.fn(mi, mo, ph), dtype=float) for p in parts]
            shape = np.broadcast_shapes(*(v.shape[1:] for v in vals))
            return np.concatenate([np.broadcast_to(v, v.shape[:1] + shape) for v in vals], axis=0)

        keyed = None if any(p.parts is None for p in parts) else tuple(g for p in parts for g in p.parts)
        return KernelBasis(fn, M, keyed)

    @property
    def phi_bandwidth(self):
        return max(c.phi_bandwidth for c in self.components)


def _bc(a):
    return np.asarray(a, dtype=float)


#: Relative truncation of the SVD of a flake's R(c) table for its kernel basis (:meth:`FlakeMedium.kernel_basis`):
#: the kernel is linear in R, so the dropped part changes every channel's kernel by at most this fraction of
#: the largest singular value — two decades below the projection's tolerance 1e-5.  It was 1e-13: metallic
#: silver's MgF2-coated aluminium kept 34 basis functions for 41 bands (14 at 1e-7), and every φ sample of the
#: projection is taken per basis function.
FLAKE_BASIS_RTOL = 1e-7


@dataclass
class FlakeMedium:
    """Translucent micro-flakes (paper eq. 2, docs/model.md §3): orientation spread ``alpha`` of the
    flake-normal density ``distribution`` (a key of :data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS`:
    "beckmann", paper eq. 5, or "ggx"), flake optics :class:`flakedb.rt.scattering.microflake.FlakeOptics`
    (R(c), T(c) per channel) and loading ``a_rho_per_um`` (flake area per volume, 1/µm).  σ_t(μ) is
    the accurate 1-D integral of :func:`flakedb.rt.scattering.microflake.extinction_Ergun`; the kernel is
    :func:`flakedb.rt.scattering.microflake.kernel_Ergun`.
    """

    alpha: float
    optics: object
    a_rho_per_um: float
    distribution: str = "beckmann"

    def __post_init__(self):
        check_range("FlakeMedium", "alpha", self.alpha, 0.0, None, lo_open=True)
        check_range("FlakeMedium", "a_rho_per_um", self.a_rho_per_um, 0.0, None)
        try:
            self.distribution = flake_distribution(self.distribution).name
        except ValueError as exc:
            raise ValueError(f"FlakeMedium.distribution: {exc}") from None

    def sigma_t(self, mu):
        return extinction_Ergun(np.abs(mu), self.alpha, self.optics, self.a_rho_per_um, distribution=self.distribution)

    def subset(self, idx):
        o = self.optics
        if o.R.shape[0] == 1:
            return self
        return FlakeMedium(self.alpha, FlakeOptics(o.c, o.R[idx], o.T[idx]), self.a_rho_per_um, self.distribution)

    def channel_key(self, C):
        """(C, 2 nc): the flake's R(c) and T(c) rows (α, c and the loading are shared by every channel)."""
        return _key_rows([np.atleast_2d(self.optics.R), np.atleast_2d(self.optics.T)], C)

    def sigma_s(self, mu):
        return scattering_Ergun(np.abs(mu), self.alpha, self.optics, self.a_rho_per_um, distribution=self.distribution)

    def kernel(self, mu_i, mu_o, phi_d):
        return kernel_Ergun(mu_i, mu_o, phi_d, self.alpha, self.optics, self.a_rho_per_um, self.distribution)

    def kernel_basis(self):
        """The kernel (aρ/2) R(c) D(h) is linear in R(c) and in the loading aρ (paper eq. 2): R's table (C, nc)
        factored as M @ V (truncated SVD, :func:`flakedb.rt.scattering.microflake.table_basis`), basis kernels
        (1/2) V_b(c) D(h) per unit aρ with the geometry c, D(h) computed once for all rows, and aρ in the
        combination aρ M (so the basis is the same at every loading: :attr:`KernelBasis.parts`)."""
        M, V = table_basis(self.optics.R, rtol=FLAKE_BASIS_RTOL)
        c, alpha, dist = self.optics.c, self.alpha, self.distribution
        key = ("flake", float(alpha), dist, array_key(c), array_key(V))
        return _single_part(key, lambda mi, mo, ph: kernel_Ergun_basis(mi, mo, ph, alpha, c, V, 1.0, dist),
                            float(self.a_rho_per_um) * M)

    @property
    def phi_bandwidth(self):
        # the distribution's first guess from the mirror lobe's width in φ (microflake: FlakeDistribution.
        # phi_samples); the projection refines adaptively
        return flake_distribution(self.distribution).phi_samples(self.alpha)


class ChannelSubset:
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


def _key_rows(parts, C):
    """Per-channel parameter blocks (C or 1, k_j) broadcast to C rows and joined, (C, Σ k_j)."""
    return np.concatenate([np.broadcast_to(np.asarray(p, dtype=float), (C, np.shape(p)[1])) for p in parts], axis=1)


def channel_key(medium, C):
    """(C, k) parameters that fix each channel's scattering (:meth:`PhaseMedium.channel_key`), or None
    for a medium that does not state them (its channels are then all solved)."""
    fn = getattr(medium, "channel_key", None)
    return None if fn is None else fn(C)


def channel_subset(medium, idx):
    """``medium`` restricted to the channels ``idx`` (its own ``subset`` when it has one)."""
    return medium.subset(idx) if hasattr(medium, "subset") else ChannelSubset(medium, idx)


@dataclass
class KernelBasis:
    """A medium's kernel written as k_c(μ_i, μ_o, φ_d) = Σ_b M[c, b] k_b(μ_i, μ_o, φ_d)
    (docs/projection.md): ``fn(mu_i, mu_o, phi_d)`` → (B, *shape) the basis kernels in 1/(µm·sr),
    ``M`` (C, B) dimensionless.  The projection on the cosine series is linear, so the basis kernels
    are projected once and the C channels' coefficients are M times theirs: the geometry (and the
    azimuthal sampling) is paid per basis function, not per channel.

    ``parts``: the basis as consecutive groups of basis kernels, ``((key, fn_part, width), …)``, each
    ``key`` a hashable identity of ``fn_part`` (everything its values depend on, never a loading: the
    loading sits in M), so that a fit's evaluations can reuse each group's projection
    (:mod:`flakedb.rt.common.reuse`); None where the basis states no identity."""

    fn: object
    M: np.ndarray
    parts: tuple | None = None


def _single_part(key, fn, M):
    """A basis of one keyed group (:attr:`KernelBasis.parts`)."""
    return KernelBasis(fn, M, ((key, fn, int(np.atleast_2d(M).shape[1])),))


def kernel_basis(medium):
    """The :class:`KernelBasis` of a medium, or None when it has none (then its C channel kernels are
    projected one by one, e.g. media read from the store, or mixtures holding one)."""
    kb = medium.kernel_basis() if hasattr(medium, "kernel_basis") else None
    if kb is None:
        return None
    return KernelBasis(kb.fn, np.atleast_2d(np.asarray(kb.M, dtype=float)), getattr(kb, "parts", None))
