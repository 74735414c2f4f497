"""Sparkle and graininess of a flake paint from its flake statistics: the analytic model of
docs/texture.md (§3 glints under a directional source, §4 graininess under a uniform sky).

Geometry (docs/texture.md §1).  Air above a smooth coat of the binder's real index η; every layer
below shares that binder (inner index changes are not modelled).  Depth z (µm) is measured in the
binder from the coat's surface down.  Light and view are given by polar angles in air, in the
plane of incidence on opposite sides of the normal; inside the binder their directions (pointing
*away* from the panel, toward the source and the observer) are l' and v' (Snell), and the mirror
condition of a flake is m = h' = normalize(l' + v').

The inputs are a :class:`TextureStack` (flake layers with their number density, log-normal
diameter distribution, thickness, orientation distribution and spread α and R(c), T(c) tables per channel; the extinction of
everything else per channel; per-channel luminance weights) and an observer
(:class:`flakedb.texture.instruments.Observer`).  Everything here is a pure function of those.

Optics reused from the solver's kernels: the flake-normal density D(m), its sampling and the flakes'
mean projected area, all through the registry :data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS` (a
layer's ``distribution``: Beckmann, paper eq. 5, GGX, or any family added there; no family is named
here), and the coat's Fresnel transmission (:func:`flakedb.optics.fresnel.fresnel_dielectric`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.polynomial.hermite_e import hermegauss as _hermegauss
from numpy.polynomial.legendre import leggauss as _leggauss

from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.rt.scattering.microflake import DEFAULT_DISTRIBUTION, FlakeOptics, extinction_Ergun, flake_distribution, projected_area
from flakedb.texture.instruments import DIFFRACTION_WAVELENGTH_NM


def j1(x):
    """Bessel J1 (scipy.special, imported on first use: a compose of a paint imports this module, and
    scipy.special's import costs ≈ 0.15 s of every run; docs/compose-overhead.md)."""
    from scipy.special import j1 as _j1  # lazy: scipy.special is slow to import; only the Airy terms need it

    return _j1(x)


def _poisson_ppf_scipy(q, lam):
    """scipy.stats.poisson.ppf's own steps, ceil(pdtrik(q, λ)) corrected by one step where pdtr already reaches q,
    on scipy.special (imported on first use as :func:`j1`): :func:`_poisson_ppf` where it cannot decide alone."""
    from scipy.special import pdtr, pdtrik  # lazy: scipy.special is slow to import; only the glint draws need it

    with np.errstate(invalid="ignore", divide="ignore"):
        vals = np.ceil(pdtrik(q, lam))
        vals1 = np.maximum(vals - 1.0, 0.0)
        return np.where(pdtr(vals1, lam) >= q, vals1, vals)


#: Relative width above P(K ≤ k − 1; λ) in which :func:`_poisson_ppf` defers to scipy's root finder: there scipy's
#: pdtrik, whose root may sit on either side of the integer, decides (it was seen off up to 1e-12 relative).
_PPF_SCIPY_BAND = 1e-9


def _poisson_ppf(q, lam):
    """Poisson quantile: the least k with P(K ≤ k; λ) ≥ q for q ∈ (0, 1), −1 at q = 0, ∞ at q = 1 (``q``, ``lam``
    broadcast; float): the integers of scipy.stats.poisson.ppf, without scipy.stats (≈ 0.3 s to import).

    The CDF pdtr(k, λ) (scipy.special, the function scipy's ppf checks its answer with) is tabulated per distinct
    λ for k = 0 … λ + 10√λ + 40 (when that table is not larger than a few entries per q) and searched by bisection for every q at once; scipy's own steps
    (:func:`_poisson_ppf_scipy`, a root finder per element) decide where the table cannot: q beyond the table,
    λ ≤ 0 or not finite, a table not non-decreasing, P(K ≤ k − 1) underflowed to 0, and q within
    :data:`_PPF_SCIPY_BAND` above P(K ≤ k − 1)."""
    from scipy.special import pdtr  # lazy: scipy.special is slow to import; only the glint draws need it

    q, lam = np.broadcast_arrays(np.asarray(q, float), np.asarray(lam, float))
    shape = q.shape
    q, lam = q.ravel(), lam.ravel()
    out = np.full(q.size, np.nan)
    inner = (q > 0.0) & (q < 1.0) & (lam > 0.0) & np.isfinite(lam)
    lu, row = np.unique(lam[inner], return_inverse=True)
    n_k = int(np.ceil(lu.max() + 10.0 * np.sqrt(lu.max()) + 40.0)) if lu.size else 0
    if lu.size and lu.size * n_k <= 4 * q.size + 4096:  # else the table costs more than the root finder per q
        cdf = pdtr(np.arange(n_k, dtype=float)[None, :], lu[:, None])  # (distinct λ, n_k)
        qi = q[inner]
        lo, hi = np.zeros(qi.size, np.int64), np.full(qi.size, n_k - 1, np.int64)
        for _ in range(int(np.ceil(np.log2(n_k))) + 1):  # the least index with cdf ≥ q (bisection, every q at once)
            mid = (lo + hi) // 2
            below = cdf[row, mid] < qi
            lo, hi = np.where(below, mid + 1, lo), np.where(below, hi, mid)
        k = lo
        prev = np.where(k > 0, cdf[row, np.maximum(k - 1, 0)], 0.0)
        monotone = np.all(np.diff(cdf, axis=1) >= 0.0, axis=1)[row]
        decided = ((cdf[row, k] >= qi) & (prev < qi) & (qi - prev > _PPF_SCIPY_BAND * qi) & monotone
                   & ((k == 0) | (prev > 0.0)))  # P(K ≤ k − 1) underflowed: q is subnormal
        out[np.flatnonzero(inner)[decided]] = k[decided]
    rest = np.isnan(out)  # everything the table did not decide
    if np.any(rest):
        out[rest] = _poisson_ppf_scipy(q[rest], lam[rest])
    out = np.where(q <= 0.0, -1.0, np.where(q >= 1.0, np.inf, out))
    return out.reshape(shape)


@lru_cache(maxsize=64)
def _gauss_rule(kind, n):
    x, w = (_leggauss if kind == "legendre" else _hermegauss)(int(n))
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w


def leggauss(n):
    """Gauss–Legendre nodes and weights of ``n`` points, computed once per ``n`` (read-only arrays): the
    indices ask for the same few rules hundreds of times per recipe."""
    return _gauss_rule("legendre", n)


def hermegauss(n):
    """Gauss–Hermite (probabilists') nodes and weights, cached as :func:`leggauss`."""
    return _gauss_rule("hermite", n)


#: A glint is a flake at least this fraction as bright as the brightest flake of its kind could be
#: (aligned, unattenuated, at the surface): a full-width-at-half-maximum count (docs/texture.md §3.3).
GLINT_FRACTION = 0.5
#: The fixed-luminance glint count's threshold: :data:`GLINT_FRACTION` of the peak of an aligned, unattenuated,
#: perfectly reflecting (R = 1) surface flake of this diameter (µm) at 555 nm, for the observer and geometry:
#: one luminance for every paint and flake size, as an instrument's or a person's threshold is.
GLINT_REFERENCE_DIAMETER_UM = 16.0
#: Sparkle exists only where a perfectly aligned surface flake is brighter than a perfect white
#: diffuser under the same light (luminance factor 1; docs/texture.md §3.5).
SPARKLE_MIN_PEAK = 1.0
#: Quadrature sizes: diameters (Gauss–Hermite in ln D), depths (Gauss–Legendre per layer).
N_DIAMETER, N_DEPTH = 12, 16
#: Flake normals under the sky: Gauss–Laguerre in tan²θ/α² × uniform azimuths.
N_TILT, N_AZIMUTH = 12, 12
#: Depth nodes of the graininess integrals.
N_DEPTH_SKY = 16
#: Whether, for the glints under a directional source (counts, intensity, area), a flake crossed by both the
#: light's and the view's path hides the two together (docs/texture.md §3.3, the opposition effect of hiding), as
#: in a layer of discs, or, as in the solver's radiative transfer (paper eq. 2), twice.  True (issue 36): the
#: counts are what a camera counts; with False they were 35 % low at 8 % metallic against the discrete-flake
#: reference.  The mean keeps the BSDF's paths (:data:`CORRELATED_MEAN`); ``hot_spot_factor`` reports the ratio.
CORRELATED_PATHS = True
#: The same for ``flake_luminance_factor``, the mean of all flakes' mirror reflections: False, the BSDF's
#: single-flake term (paper eq. 2), so previews and exports that swap it for glints keep the BSDF's mean.
CORRELATED_MEAN = False
#: The same for the flakes under the uniform sky (graininess).  True: the graininess is a ratio to the paint's
#: mean, which the composed BSDF gives, and no preview draws it, so it keeps the geometry of discs (the
#: independent paths put metallic 8 % graininess at 0.17 against the simulation's 0.51; docs/texture.md §4).
CORRELATED_SKY_PATHS = True


def _both_paths(stack, z, gap, lam_l, lam_v, correlated):
    """λ_b: the expected number of flakes crossed by both paths of a flake at depths ``z`` (nz,) (eq. S4 when
    ``correlated``, else 0: independent paths), at most either path's own count."""
    if not correlated:
        return np.zeros(np.size(z))
    return np.minimum(_shared(stack, z, gap), np.minimum(lam_l, lam_v))


@dataclass(frozen=True, eq=False)
class FlakeLayer:
    """One flake species in one layer.  ``z_top_um``: depth of the layer's top in the binder (µm);
    ``thickness_um``: the layer's; ``number_density_per_um3``: flakes per µm³; diameters log-normal
    in number with ``diameter_median_um`` and geometric standard deviation ``diameter_gsd`` (≥ 1;
    1 = one size); ``flake_thickness_um``; ``alpha`` the spread of the orientation density named
    ``distribution`` (a key of :data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS`; Beckmann, paper eq. 5,
    by default); ``c`` (nc,) ascending flake cosines with ``R``, ``T`` (C, nc) per channel (linear
    interpolation in c)."""

    name: str
    z_top_um: float
    thickness_um: float
    number_density_per_um3: float
    diameter_median_um: float
    diameter_gsd: float
    flake_thickness_um: float
    alpha: float
    c: np.ndarray
    R: np.ndarray
    T: np.ndarray
    distribution: str = DEFAULT_DISTRIBUTION

    @property
    def orientation(self):
        """The :class:`flakedb.rt.scattering.microflake.FlakeDistribution` of the flake normals (registry lookup)."""
        return flake_distribution(self.distribution)

    def reflectance(self, c):
        """R per channel at flake cosines ``c`` (any shape) → (C, *c.shape)."""
        return _interp_rows(self.c, self.R, c)

    def transmittance(self, c):
        return _interp_rows(self.c, self.T, c)

    def mean_crossed_transmittance(self, mu, projected=None):
        """T̄(μ) per channel (C, *mu.shape): the mean transmittance of the flakes a path at cosine μ crosses,
        1 − σ_t(μ)/(aρ P(μ)) with the solver's σ_t per unit loading and P (``projected``, if already known).
        Kept per layer for each (μ, P) asked (read-only): a report asks the same few cosines again and again."""
        mu = np.asarray(mu, float)
        if not np.any(self.T):
            return np.zeros((np.atleast_2d(self.T).shape[0],) + mu.shape)
        pr = None if projected is None else np.asarray(projected, float)
        key = (mu.shape, mu.tobytes(), None if pr is None else (pr.shape, pr.tobytes()))
        memo = self.__dict__.setdefault("_crossed_memo", {})  # the frozen dataclass's own dict: not a field
        if key not in memo:
            if pr is None:
                pr = np.asarray(projected_area(mu, self.alpha, distribution=self.distribution), float)
            optics = FlakeOptics(np.asarray(self.c, float), np.atleast_2d(self.R), np.atleast_2d(self.T))
            st = extinction_Ergun(mu, self.alpha, optics, 1.0, distribution=self.distribution)
            out = np.clip(1.0 - st / pr, 0.0, 1.0)
            out.setflags(write=False)
            memo[key] = out
        return memo[key]

    def diameters(self, n=N_DIAMETER):
        """(D nodes µm, number fractions) of the log-normal: Gauss–Hermite in ln D (exact for the
        moments ⟨D^k⟩ = D_m^k exp(k² s²/2) up to polynomial degree 2n − 1 in ln D)."""
        s = np.log(float(self.diameter_gsd))
        if s == 0.0:
            return np.array([float(self.diameter_median_um)]), np.array([1.0])
        x, w = hermegauss(n)
        return float(self.diameter_median_um) * np.exp(s * x), w / w.sum()

    def mean_area_um2(self):
        """⟨π D²/4⟩ of the number distribution (closed form), µm²."""
        s = np.log(float(self.diameter_gsd))
        return 0.25 * np.pi * float(self.diameter_median_um) ** 2 * np.exp(2.0 * s * s)

    @property
    def areal_density_per_um2(self):
        """Flakes per µm² of panel, N_A = ρ d."""
        return float(self.number_density_per_um3) * float(self.thickness_um)


@dataclass(frozen=True, eq=False)
class Absorber:
    """Direction-independent extinction (1/µm, per channel (C,)) of the direct beam in
    [z_top_um, z_top_um + thickness_um]: pigments (ρ⟨C_ext⟩), an absorbing coat."""

    z_top_um: float
    thickness_um: float
    sigma_per_um: np.ndarray


@dataclass(frozen=True, eq=False)
class TextureStack:
    """``eta``: the binder's (and coat's) real index; ``y_weights`` (C,): luminance weights of the
    channels (Σ = 1: a white reflectance has luminance factor 1)."""

    eta: float
    y_weights: np.ndarray
    flakes: tuple = ()
    absorbers: tuple = ()
    #: the channels' wavelengths (nm), for colour (None: grey channels)
    wavelength_nm: np.ndarray | None = None


def _interp_rows(xp, table, x):
    """np.interp of every row of ``table`` (C, nc) at ``x`` (any shape) on the shared ascending nodes
    ``xp`` (values beyond the ends held): the nodes and weights found once for all rows → (C, *x.shape)."""
    x = np.asarray(x, float)
    xp = np.asarray(xp, float)
    table = np.atleast_2d(np.asarray(table, float))
    if xp.size == 1:
        return np.repeat(table[:, :1], x.size, axis=1).reshape((table.shape[0],) + x.shape)
    xc = np.clip(x.ravel(), xp[0], xp[-1])
    i = np.clip(np.searchsorted(xp, xc, side="right") - 1, 0, xp.size - 2)
    t = (xc - xp[i]) / (xp[i + 1] - xp[i])
    out = table[:, i] * (1.0 - t) + table[:, i + 1] * t
    return out.reshape((table.shape[0],) + x.shape)


# ----------------------------------------------------------------------------------------------
# Geometry helpers
# ----------------------------------------------------------------------------------------------


def binder_cosine(theta_air_deg, eta):
    """cos θ' inside the binder of a direction at polar angle θ in air (Snell: sin θ = η sin θ')."""
    s = np.sin(np.radians(np.asarray(theta_air_deg, float))) / float(eta)
    return np.sqrt(1.0 - s * s)


def coat_transmittance(mu_air, eta):
    """1 − F(μ) of the smooth coat for light from the air at cosine μ (unpolarised Fresnel)."""
    return 1.0 - fresnel_dielectric(np.asarray(mu_air, float), float(eta)).R


def cone_solid_angle(half_angle_rad):
    """Solid angle (sr) of a cone of angular radius r: 2π(1 − cos r)."""
    return 2.0 * np.pi * (1.0 - np.cos(np.asarray(half_angle_rad, float)))


def lens_area(d, r1, r2):
    """Area of the intersection of two discs of radii r1, r2 (> 0) whose centres are d apart (planar).
    ``r1``, ``r2``: scalars, or arrays that broadcast with ``d`` (the result has the broadcast shape).
    Equal radii (r1 == r2 everywhere): 2r² arccos(d/2r) − (d/2)√(4r² − d²); otherwise the two-arc formula
    r1² arccos((d² + r1² − r2²)/(2dr1)) + r2² arccos((d² + r2² − r1²)/(2dr2)) − ½√((−d+r1+r2)(d+r1−r2)(d−r1+r2)(d+r1+r2)),
    π min(r1, r2)² where one disc holds the other and 0 where they are apart.  The formula is evaluated on
    every element and the case selected after (no masked gathers), each element as the scalar formula.
    The hot loops use :func:`_lens_area_sq`, the same formula with d² given."""
    d = np.asarray(d, float)
    r1, r2 = np.asarray(r1, float), np.asarray(r2, float)
    if r1.shape == r2.shape and np.array_equal(r1, r2):
        # d ≥ 2r gives exactly 0 here (arccos(1) = 0, √0 = 0); d = 0 is the whole disc
        part = 2.0 * r1 * r1 * np.arccos(np.minimum(d / (2.0 * r1), 1.0)) - 0.5 * d * np.sqrt(
            np.maximum(4.0 * r1 * r1 - d * d, 0.0))
        return np.where(d <= 0.0, np.pi * r1 * r1, part)
    small, big = np.minimum(r1, r2), np.maximum(r1, r2)
    with np.errstate(divide="ignore", invalid="ignore"):  # d = 0 lies inside: replaced below
        a1 = r1 * r1 * np.arccos(np.minimum(np.maximum((d * d + r1 * r1 - r2 * r2) / (2 * d * r1), -1.0), 1.0))
        a2 = r2 * r2 * np.arccos(np.minimum(np.maximum((d * d + r2 * r2 - r1 * r1) / (2 * d * r2), -1.0), 1.0))
        k = 0.5 * np.sqrt(np.maximum((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2), 0.0))
    return np.where(d <= big - small, np.pi * small * small, np.where(d < r1 + r2, a1 + a2 - k, 0.0))


def _lens_area_sq(d, d2, r1, r2, equal=False):
    """:func:`lens_area` from the distances ``d`` ≥ 0 and their squares ``d2`` (same shape), radii r1, r2
    (scalars or arrays that broadcast with d): the formulas without the case selection.  Both are exact
    outside their branch: one disc inside the other clips the arccos arguments to ∓1 (π r_small², d = 0
    included: ±∞ clipped) and zeroes the root; discs apart clip both to 1.  ``equal`` (r1 == r2, which the
    two-arc formula cannot take at d = 0): 2r² arccos(d/2r) − (d/2)√(4r² − d²).  In-place passes on three buffers (few temporaries: the indices call it on ~10⁴ elements
    at a time).  Agrees with :func:`lens_area` to rounding (reassociated; test_model.py)."""
    if equal:
        out = np.divide(d, 2.0 * r1)
        np.minimum(out, 1.0, out=out)
        np.arccos(out, out=out)
        out *= 2.0 * r1 * r1
        t = np.subtract(4.0 * r1 * r1, d2)
        np.maximum(t, 0.0, out=t)
        np.sqrt(t, out=t)
        t *= d
        t *= 0.5
        out -= t
        return out
    c = r1 * r1 - r2 * r2
    den = np.multiply(d, 2.0 * r1)
    out = np.add(d2, c)
    with np.errstate(divide="ignore"):  # d = 0: ±∞, clipped below
        out /= den
    np.maximum(out, -1.0, out=out)
    np.minimum(out, 1.0, out=out)
    np.arccos(out, out=out)
    out *= r1 * r1
    np.multiply(d, 2.0 * r2, out=den)
    t = np.subtract(d2, c)
    with np.errstate(divide="ignore"):
        t /= den
    np.maximum(t, -1.0, out=t)
    np.minimum(t, 1.0, out=t)
    np.arccos(t, out=t)
    t *= r2 * r2
    out += t
    np.subtract((r1 + r2) * (r1 + r2), d2, out=den)
    np.subtract(d2, (r1 - r2) * (r1 - r2), out=t)
    den *= t
    np.maximum(den, 0.0, out=den)
    np.sqrt(den, out=den)
    den *= 0.5
    out -= den
    return out


#: Gauss–Legendre nodes of :func:`lens_outside_mean`'s radial integral (in the angle θ of ρ = a + (b − a)(1 − cos θ)/2,
#: which smooths the square-root ends: 12 nodes agree with 96 to 2e-7 over 0 ≤ s ≤ 5, |s − u| ≤ 2).
N_LENS_OUTSIDE = 12


def lens_outside_mean(s, u, n=N_LENS_OUTSIDE):
    """⟨|D(s e_x) ∩ D(u e_ψ) \\ D(0)|⟩_ψ for unit discs D(c) = {q : |q − c| < 1}, ψ uniform on (0, 2π): the area of
    the centres of a unit disc that covers a point s away from the origin and a point u away at a uniformly random
    angle, but not the origin (dimensionless; for radius r: r² × the value at s/r, u/r).  Used by the mosaic's sky
    coupling (docs/texture.md §4, eq. G6).  In polar coordinates about the origin the circle of radius ρ lies in
    D(a e_x) over the angle 2φ(ρ, a), φ = arccos((ρ² + a² − 1)/(2ρa)) (clipped to [0, π]), and P_ψ(|q − u e_ψ| < 1)
    = φ(|q|, u)/π, so the area is (2/π) ∫ ρ φ(ρ, s) φ(ρ, u) dρ over max(1, |s − 1|, |u − 1|) < ρ < 1 + min(s, u);
    symmetric in s and u, 0 where either is 0.  ``s``, ``u`` ≥ 0 broadcast together."""
    s, u = np.broadcast_arrays(np.asarray(s, float), np.asarray(u, float))
    a = np.maximum(np.maximum(np.abs(s - 1.0), np.abs(u - 1.0)), 1.0)
    span = np.maximum(1.0 + np.minimum(s, u) - a, 0.0)[..., None]
    x, w = leggauss(n)
    th = 0.5 * np.pi * (x + 1.0)
    rho = a[..., None] + 0.5 * span * (1.0 - np.cos(th))
    jac = (0.25 * np.pi) * span * np.sin(th) * w  # dρ = ½ span sin θ dθ, dθ = ½π dx

    def phi(c):
        c = np.maximum(c, 1e-300)[..., None]
        return np.arccos(np.clip((rho * rho + c * c - 1.0) / (2.0 * rho * c), -1.0, 1.0))

    return (2.0 / np.pi) * np.sum(jac * rho * phi(s) * phi(u), axis=-1)


#: Gauss–Legendre nodes per direction of :func:`shared_crossings_mean`'s integral over the lens (each half).
N_SHARED_CROSSINGS = 16


def _arc_half_angle(d, u):
    """Half the angle of the circle of radius u (> 0) about a point whose part lies inside a unit disc d away
    (0 … π)."""
    return np.arccos(np.clip((u * u + d * d - 1.0) / np.maximum(2.0 * u * d, 1e-300), -1.0, 1.0))


def shared_crossings_mean(s, u, n=N_SHARED_CROSSINGS):
    """⟨|D(w) ∩ D(s e_x + w) \\ (D(0) ∪ D(s e_x))|⟩_ψ, w = u e_ψ, ψ uniform, for unit discs (dimensionless; radius
    r: r² × the value at s/r, u/r): the centres of the unit discs that cover both points of two parallel sky paths
    from the rays 0 and s e_x, drifted by w, but neither ray (the crossings the two paths share when no flake
    above covers either ray; docs/texture.md §4, eq. G6).  Substituting q = p + w it is the integral over p in
    the lens D(0) ∩ D(s e_x) of P_ψ(p + u e_ψ ∉ D(0) ∪ D(s e_x)) = 1 − (2β0 + 2β1 − overlap)/2π, β the half-angles
    of the circle of radius u about p inside each disc and overlap their arcs' common length (closed form);
    Gauss–Legendre over the lens, split at x = s/2 where its height changes form.  0 at u = 0, the lens area
    for u ≥ 2; ``s`` ≤ 2 (beyond, the lens is empty: 0)."""
    s, u = np.broadcast_arrays(np.asarray(s, float), np.asarray(u, float))
    s_, u_ = s[..., None, None], np.maximum(u, 1e-12)[..., None, None]
    x, w = leggauss(n)
    out = 0.0
    for lo, hi, c in ((s - 1.0, 0.5 * s, s), (0.5 * s, np.ones_like(s), np.zeros_like(s))):
        # x in (lo, hi): the height is that of the disc about c (√(1 − (x − c)²)); cos-substitution at the ends
        span = np.maximum(hi - lo, 0.0)[..., None, None]
        th = 0.5 * np.pi * (x + 1.0)
        px = lo[..., None, None] + 0.5 * span * (1.0 - np.cos(th))[:, None]  # (…, n, 1)
        jx = 0.25 * np.pi * span * (np.sin(th) * w)[:, None]
        hgt = np.sqrt(np.maximum(1.0 - (px - c[..., None, None]) ** 2, 0.0))
        py = hgt * x[None, :]  # (…, n, n)
        jy = hgt * w[None, :]
        d0 = np.sqrt(px * px + py * py)
        d1 = np.sqrt((px - s_) ** 2 + py * py)
        b0, b1 = _arc_half_angle(d0, u_), _arc_half_angle(d1, u_)
        # angular distance between the two discs' directions seen from p
        a0 = np.arctan2(-py, -px)
        a1 = np.arctan2(-py, s_ - px)
        dl = np.abs(np.angle(np.exp(1j * (a0 - a1))))
        o1 = np.maximum(np.minimum(np.minimum(b0 + b1 - dl, 2.0 * b0), 2.0 * b1), 0.0)
        o2 = np.maximum(b0 + b1 - (2.0 * np.pi - dl), 0.0)
        union = 2.0 * b0 + 2.0 * b1 - np.minimum(o1 + o2, 2.0 * np.minimum(b0, b1))
        out = out + np.sum(jx * jy * (1.0 - union / (2.0 * np.pi)), axis=(-2, -1))
    return np.where((s < 2.0) & (u > 0.0), out, 0.0)


def diffraction_radius(diameter_um, eta, wavelength_nm=DIFFRACTION_WAVELENGTH_NM):
    """Angular radius (rad, in the binder) of the uniform cone with the peak radiant intensity of a
    disc's Airy pattern: Ω = λ²/A (A = πD²/4, λ in the binder), r = 2λ/(πD).  The Mitsuba route's lobe width
    (flakedb.render.mitsuba_sparkle); the indices use the Airy pattern itself (:func:`beam_collected`)."""
    lam_um = float(wavelength_nm) * 1e-3 / float(eta)
    return 2.0 * lam_um / (np.pi * np.asarray(diameter_um, float))


def _k_max(lam_max, T_max):
    """Largest crossing count kept: beyond it the Poisson tail (λ + 6√λ + 6: < 1e-7) or the
    transmitted fraction (T_max^k < 1e-7) is negligible; 0 for opaque flakes."""
    lam_max, T_max = float(lam_max), float(T_max)
    k = int(np.ceil(lam_max + 6.0 * np.sqrt(lam_max) + 6.0))
    if T_max <= 0.0:
        return 0
    if T_max < 1.0:
        k = min(k, int(np.ceil(np.log(1e-7) / np.log(T_max))))
    return k


def _depth_nodes(layer, n=N_DEPTH):
    x, w = leggauss(n)
    z = layer.z_top_um + 0.5 * layer.thickness_um * (x + 1.0)
    return z, 0.5 * w  # weights of the uniform depth distribution (Σ = 1)


def _path(stack, z, mu):
    """Along a path from depth z (nz,) to the surface at cosine μ (scalar or (nz,)): absorber optical
    depth per channel (C, nz), the expected number of flakes crossed (nz,) and the crossing-rate-
    weighted flake transmittance per channel (C, nz).  A path crosses flakes of normal m at the rate
    ρ⟨A⟩ |ω·m| D(m)/μ, so the crossed flakes' mean transmittance is at their true angles,
    T̄(μ) = ∫ T(|ω·m|) |ω·m| D dm / ∫ |ω·m| D dm = 1 − σ_t(μ)/(aρ P(μ)): the solver's own extinction
    (:func:`flakedb.rt.scattering.microflake.extinction_Ergun`, paper eq. 2) over its projected area, so a path's mean
    attenuation e^{−λ(1 − T̄)} is the RT's e^{−σ_t s} exactly (T at c = μ was 4 % low on 5 % pearlescent)."""
    z = np.asarray(z, float)
    # one cosine for all depths: the flakes' crossing rate and transmittance evaluated once
    mu_f = np.asarray(mu, float).reshape(1) if np.ndim(mu) == 0 else np.broadcast_to(np.asarray(mu, float), z.shape)
    mu = np.broadcast_to(np.asarray(mu, float), z.shape)
    C = np.asarray(stack.y_weights).size
    tau = np.zeros((C, z.size))
    for a in stack.absorbers:
        seg = np.clip(z - a.z_top_um, 0.0, a.thickness_um)
        tau += np.asarray(a.sigma_per_um, float).reshape(C, 1) * seg / mu
    lam = np.zeros(z.size)
    lamT = np.zeros((C, z.size))
    for f in stack.flakes:
        seg = np.clip(z - f.z_top_um, 0.0, f.thickness_um)
        P = projected_area(mu_f, f.alpha, distribution=f.distribution)
        lam_f = f.number_density_per_um3 * f.mean_area_um2() * P / mu_f * seg
        lam += lam_f
        lamT += lam_f * f.mean_crossed_transmittance(mu_f, P)
    with np.errstate(invalid="ignore", divide="ignore"):
        T = np.where(lam > 0, lamT / np.where(lam > 0, lam, 1.0), 0.0)
    return tau, lam, T


def _shared(stack, z, slope_gap, n=16):
    """Expected number of flakes crossed by *both* paths of a flake at depth z (nz,) whose two paths
    drift apart by ``slope_gap`` (nz,) µm per µm of height (|l'_xy/l'_z − v'_xy/v'_z|): flakes (as
    horizontal discs) above it at height Δ are crossed by both when their centre lies in the lens of
    two discs of the flake's radius whose centres are Δ·gap apart (docs/texture.md eq. S4)."""
    z = np.asarray(z, float)
    gap = np.broadcast_to(np.asarray(slope_gap, float), z.shape)
    x, wx = leggauss(n)
    out = np.zeros(z.size)
    for f in stack.flakes:
        lo = f.z_top_um
        hi = np.minimum(z, f.z_top_um + f.thickness_um)
        span = np.maximum(hi - lo, 0.0)
        if not np.any(span > 0):
            continue
        zp = lo + 0.5 * span[:, None] * (x[None, :] + 1.0)  # (nz, n) depths of the flakes above
        sep = (z[:, None] - zp) * gap[:, None]
        Dn, Dw = f.diameters()
        r = 0.5 * Dn[:, None, None]
        acc = np.empty(z.size)
        blk = max(1, 8192 // (Dn.size * n))  # depths per block: ~8000 lens evaluations at a time
        for lo_ in range(0, z.size, blk):
            sp = sep[None, lo_:lo_ + blk]
            acc[lo_:lo_ + blk] = Dw @ (_lens_area_sq(sp, sp * sp, r, r, equal=True) @ wx)
        out += f.number_density_per_um3 * (acc * 0.5 * span)
    return out


def _gap(u, v):
    """|u_xy/u_z − v_xy/v_z| of upward directions u (…, 3) and v (3,)."""
    u = np.asarray(u, float)
    d = u[..., :2] / u[..., 2:3] - np.asarray(v, float)[:2] / float(v[2])
    return np.sqrt(np.sum(d * d, axis=-1))


# ----------------------------------------------------------------------------------------------
# Glints under a directional source (docs/texture.md §3)
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Geometry:
    """Derived quantities of one directional geometry (docs/texture.md §3.1)."""

    mu_l: float
    mu_v: float
    mu_l_b: float
    mu_v_b: float
    cos_h: float
    c: float
    t_in: float
    t_out: float
    omega_s: float
    omega_a: float
    r_s: float
    r_a: float
    #: semi-axes (rad, binder) of the refracted source and aperture cones in the plane of incidence (∥) and
    #: across it (⊥): an air cone of radius r becomes the ellipse r μ/(η μ') × r/η (Snell, small cones)
    s_par: float = 0.0
    s_perp: float = 0.0
    a_par: float = 0.0
    a_perp: float = 0.0
    eta: float = 1.0


def directional_geometry(eta, light_deg, view_deg, source_half_angle_deg, aperture_half_angle_rad) -> Geometry:
    """Binder directions, half-vector, coat transmittances and the source / aperture cones mapped
    into the binder (Ω' = Ω μ/(η² μ'), étendue; radii r = √(Ω'/π)) of docs/texture.md §3.1."""
    eta = float(eta)
    mu_l, mu_v = np.cos(np.radians(light_deg)), np.cos(np.radians(view_deg))
    mu_lb, mu_vb = float(binder_cosine(light_deg, eta)), float(binder_cosine(view_deg, eta))
    lb = np.array([np.sqrt(1 - mu_lb**2), 0.0, mu_lb])
    vb = np.array([-np.sqrt(1 - mu_vb**2), 0.0, mu_vb])
    h = lb + vb
    h /= np.linalg.norm(h)
    om_s = float(cone_solid_angle(np.radians(source_half_angle_deg)))
    om_a = float(cone_solid_angle(aperture_half_angle_rad))
    om_sb = om_s * mu_l / (eta * eta * mu_lb)
    om_ab = om_a * mu_v / (eta * eta * mu_vb)
    r_s, r_a = float(np.radians(source_half_angle_deg)), float(aperture_half_angle_rad)
    return Geometry(float(mu_l), float(mu_v), mu_lb, mu_vb, float(h[2]), float(lb @ h),
                    float(coat_transmittance(mu_l, eta)), float(coat_transmittance(mu_v, eta)),
                    om_s, om_a, float(np.sqrt(om_sb / np.pi)), float(np.sqrt(om_ab / np.pi)),
                    r_s * float(mu_l) / (eta * mu_lb), r_s / eta, r_a * float(mu_v) / (eta * mu_vb), r_a / eta, eta)


#: Side (cells) of the grid on which a flake's beam is collected by the aperture (:func:`_beam_levels`), and
#: the luminance levels at which the regions above a threshold are tabulated.
BEAM_GRID, BEAM_LEVELS = 384, 4096
#: Airy core radii (λ'/D of the longest wavelength) the beam grid reaches beyond the source and aperture.
BEAM_AIRY_REACH = 6.0
#: Nodes of the tabulated transfer-function mixture in :func:`beam_collected` (linear interpolation: the
#: OTF's curvature is largest at s → 1, where it falls as (1 − s)^{3/2}; 4097 nodes err < 1e-5).
_OTF_TABLE = 4097
#: Most wavelength groups of a flake's spectral diffraction pattern (bands merged, weights kept).
N_DIFFRACTION_BANDS = 8


#: Spacing and reach of the tabulated 2 J1(r)/r (:func:`_jinc`): linear interpolation errs < 2e-6.
_JINC_STEP, _JINC_MAX = 0.004, 2048.0


@lru_cache(maxsize=1)
def _jinc_table():
    r = np.arange(0.0, _JINC_MAX + 2 * _JINC_STEP, _JINC_STEP)
    t = np.ones_like(r)
    t[1:] = 2.0 * j1(r[1:]) / r[1:]
    t.setflags(write=False)
    return t


def _jinc(r):
    """2 J1(r)/r (→ 1 at r = 0): the Fourier transform of the uniform unit-area disc in ρ = 2π a |ν|; from a
    table (:data:`_JINC_STEP`) up to :data:`_JINC_MAX`, the Bessel function itself beyond."""
    r = np.asarray(r, float)
    t = _jinc_table()
    x = r / _JINC_STEP
    i = np.minimum(x.astype(np.int64), t.size - 2)
    out = t[i] + (x - i) * (t[i + 1] - t[i])
    far = r > _JINC_MAX
    if np.any(far):
        out[far] = 2.0 * j1(r[far]) / r[far]
    return out


def airy_otf(s):
    """The optical transfer function of a circular aperture, the Fourier transform of its unit-integral Airy
    pattern: (2/π)(arccos s − s √(1 − s²)) at the frequency s = |ν| λ/D ≤ 1, 0 beyond (Goodman, *Introduction
    to Fourier Optics*, eq. 7-34)."""
    s = np.clip(np.asarray(s, float), 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(s) - s * np.sqrt(1.0 - s * s))


def airy_pattern(theta_rad, diameter_um, wavelength_um):
    """The Fraunhofer pattern of a disc of diameter D (a flake) at wavelength λ (both in the medium), as a
    density over solid angle with unit integral (1/sr): (A/λ²) [2 J1(x)/x]², x = π D θ/λ, A = π D²/4; its half
    maximum lies at θ = 0.514 λ/D (x = 1.6163) and its first zero at 1.22 λ/D (Born & Wolf §8.5.2)."""
    D = float(diameter_um)
    lam = float(wavelength_um)
    x = np.atleast_1d(np.pi * D * np.asarray(theta_rad, float) / lam)
    xs = np.where(x > 0, x, 1.0)
    jinc = np.where(x > 0, 2.0 * j1(xs) / xs, 1.0)
    out = 0.25 * np.pi * D * D / lam**2 * jinc**2
    return out.reshape(np.shape(theta_rad)) if np.ndim(theta_rad) else float(out[0])


def _diffraction_bands(stack, yR):
    """(λ' µm (k,), weights (k,), Σ = 1): the wavelengths in the binder at which a flake's Airy patterns are
    mixed, weighted by its luminance-weighted mirror reflectance yR (C,) per channel; contiguous channels merged
    into at most :data:`N_DIFFRACTION_BANDS` groups (each at its weighted mean wavelength: the mixture's
    transfer function is smooth in λ).  Grey channels (no wavelengths): :data:`DIFFRACTION_WAVELENGTH_NM`."""
    yR = np.clip(np.asarray(yR, float), 0.0, None)
    if stack.wavelength_nm is None or yR.sum() <= 0.0:
        return np.array([DIFFRACTION_WAVELENGTH_NM * 1e-3 / float(stack.eta)]), np.ones(1)
    wl = np.asarray(stack.wavelength_nm, float)
    groups = np.array_split(np.arange(wl.size), min(N_DIFFRACTION_BANDS, wl.size))
    w = np.array([yR[gi].sum() for gi in groups])
    lam = np.array([(yR[gi] @ wl[gi]) / max(yR[gi].sum(), 1e-300) for gi in groups])
    keep = w > 0
    return lam[keep] * 1e-3 / float(stack.eta), w[keep] / w[keep].sum()


def beam_collected(g, diameter_um, lam_um, lam_w, n=BEAM_GRID):
    """f(δ): the fraction of a flake's reflected beam that the aperture collects when the beam's centre is
    offset by δ from the aperture's centre (ω_o space in the binder, rad; axis 0 in the plane of incidence),
    on the n × n grid of :func:`_beam_levels`.  The beam is the refracted source (the ellipse ``g.s_par`` ×
    ``g.s_perp``, unit integral) ⊛ the Airy pattern of the flake's projection (D c × D) at the wavelengths
    ``lam_um`` (binder, µm) mixed with weights ``lam_w``; f = beam ⊛ aperture (the ellipse ``g.a_par`` ×
    ``g.a_perp``).  Returns (x (n,) the grid's offsets along either axis, rad, in FFT order: x[0] = 0;
    f (n, n))."""
    lam_um, lam_w = np.atleast_1d(np.asarray(lam_um, float)), np.atleast_1d(np.asarray(lam_w, float))
    D, c = float(diameter_um), float(g.c)
    reach = BEAM_AIRY_REACH * float(lam_um.max()) / (D * c)
    E = 1.25 * (max(g.s_par, g.s_perp) + max(g.a_par, g.a_perp)) + reach  # grid half-width, rad
    h = 2.0 * E / n
    # the OTF vanishes beyond u = 1/λ'_min (|ν_x| ≤ c D/λ'_min, |ν_y| ≤ D/λ'_min): the spectrum is formed on
    # that block of low frequencies only (a few % of the grid), zero elsewhere as the product there is
    kx = min(int(np.ceil(c * D * n * h / float(lam_um.min()))) + 1, n // 2 - 1)
    ky = min(int(np.ceil(D * n * h / float(lam_um.min()))) + 1, n // 2)
    rows = np.r_[0:kx + 1, n - kx:n]
    nu_x = np.fft.fftfreq(n, h)[rows, None]
    nu_y = np.fft.rfftfreq(n, h)[None, :ky + 1]
    F = _jinc(2.0 * np.pi * np.sqrt((g.s_par * nu_x) ** 2 + (g.s_perp * nu_y) ** 2))
    F *= (np.pi * g.a_par * g.a_perp) * _jinc(2.0 * np.pi * np.sqrt((g.a_par * nu_x) ** 2 + (g.a_perp * nu_y) ** 2))
    # the mixture Σ_k w_k OTF(λ_k u) of the elliptical frequency u = |(ν_x/c, ν_y)|/D, tabulated in u (1-D)
    u = np.sqrt((nu_x / c) ** 2 + nu_y**2) / D
    u_tab = np.linspace(0.0, 1.0 / float(lam_um.min()), _OTF_TABLE)
    mix = sum(w * airy_otf(lam * u_tab) for lam, w in zip(lam_um, lam_w))
    spec = np.zeros((n, ky + 1))
    spec[rows] = F * np.interp(u, u_tab, mix, right=0.0)
    # irfft2's two passes (numpy.fft.irfftn), the first over the nonzero columns only (the others stay zero)
    half = np.zeros((n, n // 2 + 1), complex)
    half[:, :ky + 1] = np.fft.ifft(spec, axis=0)
    f = np.fft.irfft(half, n, axis=1) / (h * h)
    return np.fft.fftfreq(n, 1.0 / n) * h, f


def _beam_levels(g, diameters_um, lam_um, lam_w, alpha, distribution=DEFAULT_DISTRIBUTION, n=BEAM_GRID,
                 n_levels=BEAM_LEVELS):
    """The collected fraction of a flake's beam against the offset of its centre, and the normal density over
    the offsets above each level (docs/texture.md eq. S1b, S2).

    In ω_o space (binder; tangent plane at the aperture's centre, axis 0 in the plane of incidence) the beam
    of a flake of diameter D is the refracted source (the ellipse ``g.s_par`` × ``g.s_perp``, unit integral)
    convolved with the flake's Fraunhofer pattern (:func:`airy_pattern` of its projection, D c × D, mixed over
    the wavelengths ``lam_um`` with weights ``lam_w``); the aperture (the ellipse ``g.a_par`` × ``g.a_perp``)
    collects f(δ) = (beam ⊛ aperture)(δ) of a beam centred at δ.  All three have closed-form Fourier
    transforms (:func:`_jinc`, :func:`airy_otf`), and the Airy factor is band-limited (|ν| ≤ D/λ'), so one
    inverse FFT on an n × n grid of spacing h < λ'/(2D) gives f exactly at the grid points, up to the
    periodic wrap of its far tails (which keeps Σ f h² = the aperture's area exactly).

    A beam offset δ = (δ∥, δ⊥) belongs to the flake normal h' + (δ∥/2) e∥ + (δ⊥/(2c)) e⊥ (the half-vector
    map, dω_o = 4c dm), of density p = 2 D(m) (``distribution``).  Returns (S, I, f_max): with φ = f/f_max,
    S[i, k] = ∫_{φ ≥ k/n_levels} p dδ and I[i, k] = ∫_{φ ≥ k/n_levels} p φ dδ (levels 0 … n_levels; the
    integrals over a level set, binned), per diameter (nD, n_levels + 1), and f_max = f(0) (nD,)."""
    D_all = np.atleast_1d(np.asarray(diameters_um, float))
    ndf = flake_distribution(distribution).ndf
    th = np.arccos(np.clip(g.cos_h, -1.0, 1.0))
    S = np.zeros((D_all.size, n_levels + 1))
    I = np.zeros_like(S)
    f_max = np.zeros(D_all.size)
    # f and the density are even in δ⊥ (ellipses, Airy pattern; m_z holds δ⊥²): the columns 0 … n/2 of the grid,
    # those with a mirror column (1 … n/2 − 1) counted twice
    m = n // 2 + 1
    twice = np.full(m, 2.0)
    twice[0] = twice[-1] = 1.0
    for i, D in enumerate(D_all):
        x, f = beam_collected(g, D, lam_um, lam_w, n)
        h = x[1] - x[0]
        fm = float(f[0, 0])
        a = 0.5 * x[:, None]
        b = 0.5 * x[None, :m] / g.c
        mz = (np.cos(th) - a * np.sin(th)) / np.sqrt(1.0 + a * a + b * b)
        p = 2.0 * ndf(mz, alpha) * (h * h) * twice
        phi = f[:, :m] / fm
        k = np.clip((phi * n_levels).astype(np.int64), 0, n_levels - 1).ravel()
        S[i, :-1] = np.cumsum(np.bincount(k, p.ravel(), n_levels)[::-1])[::-1]
        I[i, :-1] = np.cumsum(np.bincount(k, (p * phi).ravel(), n_levels)[::-1])[::-1]
        f_max[i] = fm
    return S, I, f_max


class TextureModelLimit(ValueError):
    """A flake layer too thick or dense in transmitting flakes for the model's crossing-count sums."""


#: Most crossing-count combinations (:func:`_combinations`) the model evaluates: their weights are
#: (depths × channels × combinations) arrays, and K = 60 crossings (37 820 combinations) already spans
#: λ ≈ 33 crossed flakes or T^K = 1e-7 at T = 0.76.  A 5000 µm layer of pearlescent flakes asked for
#: K = 153 (620 620 combinations, 153 GiB).
MAX_COMBINATIONS = 40_000


def _combinations(lam_l, lam_v, lam_b, T_l, T_v):
    """The crossing-count combinations (k_l, k_v, k_b) with k_l + k_v + k_b ≤ K (:func:`_k_max` of the
    largest λ and T), in lexicographic order: three int arrays.  :class:`TextureModelLimit` beyond
    :data:`MAX_COMBINATIONS`."""
    T_max = max(float(np.max(T_l, initial=0.0)), float(np.max(T_v, initial=0.0)))
    lam_max = max(float(lam_l.max()), float(lam_v.max()), float(lam_b.max()))
    K = _k_max(lam_max, T_max)
    if (K + 1) * (K + 2) * (K + 3) // 6 > MAX_COMBINATIONS:
        raise TextureModelLimit(
            f"a path crosses up to {K} flakes that transmit (expected {lam_max:.0f} crossings, largest flake "
            f"transmittance {T_max:.2f}): beyond the model's {MAX_COMBINATIONS} crossing combinations "
            "(docs/texture.md §4, Validity)")
    i, j, b = np.indices((K + 1,) * 3).reshape(3, -1)
    keep = i + j + b <= K
    return i[keep], j[keep], b[keep]


def _poisson_each(k, lam):
    """P(k; λ) elementwise for integer counts k and means λ that broadcast."""
    k = np.asarray(k, float)
    lam = np.asarray(lam, float)
    kmax = int(k.max(initial=0))
    lg = np.concatenate([[0.0], np.cumsum(np.log(np.arange(1.0, kmax + 1.0)))])[k.astype(int)]  # ln k!
    with np.errstate(divide="ignore"):
        logp = k * np.log(np.where(lam > 0, lam, 1.0)) - lam - lg
    return np.where(lam > 0, np.exp(logp), (k == 0).astype(float))


def _path_weights(yR, R_Y, att, lam_l, lam_v, lam_b, T_l, T_v, combos):
    """Luminance-weighted transmissions w and their probabilities for the crossing-count ``combos``
    (:func:`_combinations`): k_l, k_v flakes crossed by one path only (Poisson λ_l, λ_v), k_b by both
    (λ_b, transmitting T_l T_v).  ``yR`` (C,) luminance weights × R; ``att`` (C, *S) absorber transmission;
    λ (*S); T (C, *S), S the depths' shape, whose last axis is the combination's (one column of depths per
    combination) or 1 (the same depths for all).  Returns (w, P), each (*S[:-1], combinations)."""
    i, j, b = combos
    if np.shape(T_l)[-1] == 1 and np.size(i) > 1:
        # the same depths for all combinations: powers T^e and P(k; λ) for e, k = 0 … K once, and
        # w(e_l, e_v) = Σ_c yR_c att_c T_l,c^e_l T_v,c^e_v for every exponent pair by one matrix product
        e_l, e_v = i + b, j + b
        e = np.arange(int(max(e_l.max(), e_v.max())) + 1)
        Tl = np.moveaxis(T_l[..., 0, None] ** e, 0, -2)  # (*S[:-1], C, K + 1)
        Tv = np.moveaxis(T_v[..., 0, None] ** e, 0, -2)
        ya = np.moveaxis(yR.reshape((-1,) + (1,) * (att.ndim - 1)) * att, 0, -1)  # (*S[:-1], 1, C)
        W = np.matmul(np.swapaxes(Tl, -1, -2) * ya, Tv) / R_Y  # (*S[:-1], K + 1, K + 1)
        k = np.arange(int(max(i.max(), j.max(), b.max())) + 1)
        P = (_poisson_each(k, lam_l)[..., i] * _poisson_each(k, lam_v)[..., j] * _poisson_each(k, lam_b)[..., b])
        return W[..., e_l, e_v], P
    tr = T_l ** (i + b) * T_v ** (j + b) * att  # (C, ..., combinations)
    w = np.tensordot(yR, tr, axes=(0, 0)) / R_Y
    return w, _poisson_each(i, lam_l) * _poisson_each(j, lam_v) * _poisson_each(b, lam_b)


#: Obstacle configurations and points per flake disc of the partial-occlusion distribution (:func:`_occlusion`).
N_OCCLUSION, N_OCCLUSION_POINTS = 512, 12
#: Phases of the occlusion rule's Kronecker points (:func:`_occlusion_points`): None, ½ for every coordinate (the
#: rule); an integer, uniform random phases from that seed (a randomised rule, to measure the rule's own error:
#: docs/texture.md §3.3).
OCCLUSION_SHIFT = None


#: Most flakes touching one flake's paths the occlusion evaluates per configuration.
N_OCCLUSION_MAX = 2048


@lru_cache(maxsize=4)
def _kronecker_alphas(n):
    """frac(√s) of the first n squarefree integers s ≥ 2: rationally independent (Besicovitch), so the points
    i ↦ frac(i α) are jointly equidistributed in every finite set of coordinates."""
    m = int(1.7 * n) + 16
    sf = np.ones(m, bool)
    for p in range(2, int(np.sqrt(m)) + 1):
        sf[p * p::p * p] = False
    s = np.flatnonzero(sf)[2:2 + n].astype(float)  # skip 0 and 1
    a = np.sqrt(s) % 1.0
    a.setflags(write=False)
    return a


@lru_cache(maxsize=8)
def _occlusion_points(n_cfg, n_slots, stream, shift=None):
    """The occlusion rule's uniforms (5 attributes, n_slots obstacle slots, n_cfg configurations) of one set
    (``stream``) and (n_cfg,) the uniforms of its obstacle count: Kronecker points frac(φ + i α), i the
    configuration, one rationally independent α per (stream, slot, attribute) (:func:`_kronecker_alphas`).
    Every run of consecutive configurations is itself equidistributed, so the configurations with the same
    number of obstacles (a run of i where the count is the ordered stratum midpoints) are a quadrature of the
    obstacles' attributes on their own; the first n_slots slots are the same whatever n_slots."""
    block = 5 * N_OCCLUSION_MAX + 1  # per stream: the slots' attributes, then (last) the count
    alphas = _kronecker_alphas(block * (stream + 1))
    al = np.append(alphas[block * stream:block * stream + 5 * n_slots], alphas[block * (stream + 1) - 1])
    ph = np.random.default_rng([shift, stream]).random(block)[np.r_[0:5 * n_slots, block - 1]] if shift is not None \
        else np.full(al.size, 0.5)
    i = np.arange(n_cfg, dtype=float)
    u = (ph[:, None] + i[None, :] * al[:, None]) % 1.0
    count, u = u[-1], u[:-1].reshape(n_slots, 5, n_cfg).transpose(1, 0, 2)
    u.setflags(write=False)
    count.setflags(write=False)
    return u, count


def _disc_points(n):
    """n points of the unit disc, equal areas (Vogel's spiral) → (n, 2)."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    t = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(t), r * np.sin(t)], -1)


def _touching(rho, r, rn, rw, lo, hi, t_a, t_b):
    """The flakes above that can cross a path of a flake of radius r (docs/texture.md §3.3, the occlusion rule).

    A flake above at height Δ of radius r_j (nodes ``rn`` with number fractions ``rw``) crosses the path of some
    point of the flake's disc along drift t exactly when its centre lies within r + r_j of Δ t; for the two paths
    of one set (drifts ``t_a``, ``t_b``: equal for a single path) the centres that can matter fill the stadium of
    radius R = r + r_j around the segment Δ t_a … Δ t_b, area πR² + 2RΔG (G = |t_b − t_a|).  Centres outside it
    cross nothing, so the flakes in it are the whole Poisson process of the ones that matter, split into two
    independent Poisson parts: the two half-discs (``A``: Δ uniform on [lo, hi], r_j ∝ rw R²) and the rectangle
    (``B``: Δ ∝ Δ, r_j ∝ rw R).  Returns their expected counts μ_A, μ_B (nz,) (``rho`` per µm³, heights lo, hi
    (nz,)) and the radius CDFs of the two parts."""
    R = r + rn
    G = float(np.linalg.norm(np.asarray(t_b) - np.asarray(t_a)))
    mu_A = rho * np.pi * float(rw @ (R * R)) * (hi - lo)
    mu_B = rho * G * float(rw @ R) * (hi * hi - lo * lo)
    cdf_A = np.cumsum(rw * R * R) / float(rw @ (R * R))
    cdf_B = np.cumsum(rw * R) / float(rw @ R)
    return mu_A, mu_B, cdf_A, cdf_B


def _place(u, r, rn, lo, hi, t_a, t_b, mu_A, mu_B, cdf_A, cdf_B):
    """Heights, centres (x, y) and radii of the obstacles of :func:`_touching` from five uniforms each (``u``
    (5, …) with lo, hi, μ_A, μ_B broadcast): part A or B by the first, then Δ, r_j (inversion of the part's
    radius CDF), and the centre uniform in the part (a point of the disc of radius R folded onto the half-disc
    beyond either end; the rectangle's length and width)."""
    t_a, t_b = np.asarray(t_a, float), np.asarray(t_b, float)
    G = float(np.linalg.norm(t_b - t_a))
    e = (t_b - t_a) / G if G > 0 else np.array([1.0, 0.0])
    en = np.array([-e[1], e[0]])
    in_A = u[0] * (mu_A + mu_B) < mu_A
    dA = lo + u[1] * (hi - lo)
    dB = np.sqrt(lo * lo + u[1] * (hi * hi - lo * lo))
    dlt = np.where(in_A, dA, dB)
    iA = np.minimum(np.searchsorted(cdf_A, u[2]), rn.size - 1)
    iB = np.minimum(np.searchsorted(cdf_B, u[2]), rn.size - 1)
    rj = rn[np.where(in_A, iA, iB)]
    R = r + rj
    # A: a point of the disc of radius R; the half towards t_b sits at the segment's end Δ t_b, the other at Δ t_a
    px = R * np.sqrt(u[3]) * np.cos(2.0 * np.pi * u[4])
    py = R * np.sqrt(u[3]) * np.sin(2.0 * np.pi * u[4])
    end = np.where(px * e[0] + py * e[1] >= 0.0, 1.0, 0.0)
    ax = dlt * (t_a[0] + end * (t_b[0] - t_a[0])) + px
    ay = dlt * (t_a[1] + end * (t_b[1] - t_a[1])) + py
    # B: along the segment (length Δ G), across it ±R
    s, h = u[3] * dlt * G, (2.0 * u[4] - 1.0) * R
    bx = dlt * t_a[0] + s * e[0] + h * en[0]
    by = dlt * t_a[1] + s * e[1] + h * en[1]
    return dlt, np.where(in_A, ax, bx), np.where(in_A, ay, by), rj


def _occlusion(stack, g, z, radii, correlated, n_cfg=N_OCCLUSION, n_pts=N_OCCLUSION_POINTS, weights=None):
    """Partial occlusion (docs/texture.md §3.3): the distribution of a flake's path transmission over its area.

    A flake of radius r (``radii`` (nR,), as a horizontal disc) at depth z (``z`` (nz,)) sends the light it
    mirrors from each point x of its disc along the light path l' and the view path v'; a flake j above it at
    height Δ (a horizontal disc of radius r_j, centre c_j) crosses the light path of x when |x + Δ t_l − c_j| < r_j
    (t = ω_xy/ω_z the paths' drift per µm of height) and the view path when |x + Δ t_v − c_j| < r_j, each crossing
    transmitting T̄_c(μ) (:meth:`FlakeLayer.mean_crossed_transmittance`).  The flakes above are Poisson (ρ per
    µm³, diameters the layer's log-normal nodes, crossing rate scaled by P(μ)/μ, the solver's projected area);
    ``correlated``: one set of flakes crosses both paths (a layer of discs: a flake above may cover both), else
    two independent sets (the solver's RT).  Only the flakes that can cross a path of the disc enter
    (:func:`_touching`: the stadium around the two paths, in closed form), and the rule over their
    configurations is deterministic: :data:`N_OCCLUSION` equal-weight configurations whose number of such
    flakes is the Poisson quantile of the stratum midpoints (i + ½)/n (so P(none) = e^{−μ} to 1/n), their
    attributes Kronecker points (:func:`_occlusion_points`), equidistributed within each run of configurations
    with the same count; the same points for every depth, radius and geometry (smooth in the inputs).
    Returns t (C, nR, nz, n_cfg): per channel, the mean over :data:`N_OCCLUSION_POINTS` points of the disc of
    Π_j T^{crossings}: a partly covered flake is dimmed by the share covered, not all or nothing.  ``weights``
    (C, nz): Σ_c weights[c, z] t[c] instead, (nR, nz, n_cfg) (the glints' luminance-weighted transmission).

    A point's transmission depends on its crossing counts alone, so it is formed once per distinct combination
    of counts (the same products as point by point, to rounding)."""
    z = np.asarray(z, float)
    radii = np.atleast_1d(np.asarray(radii, float))
    lb = np.array([np.sqrt(1 - g.mu_l_b**2), 0.0, g.mu_l_b])
    vb = np.array([-np.sqrt(1 - g.mu_v_b**2), 0.0, g.mu_v_b])
    t_l, t_v = lb[:2] / lb[2], vb[:2] / vb[2]
    C = np.asarray(stack.y_weights).size
    pts = _disc_points(n_pts)  # (Q, 2)
    # evaluated at each requested radius within the flakes' 1–99 % quantiles (the outer Gauss–Hermite nodes, of
    # negligible weight, reach 9× the median at σ_g 1.5), the nearest of them beyond; not interpolated between
    # radii: each radius has its own configurations, and a blend of two unrelated ones narrows the distribution
    # (4 radii blended: metallic-silver's count 3 % low)
    s_g0 = np.log(float(stack.flakes[0].diameter_gsd)) if stack.flakes else 0.0
    r_med = float(np.exp(np.mean(np.log(radii))))
    lo_r, hi_r = max(radii.min(), r_med * np.exp(-2.33 * s_g0)), min(radii.max(), r_med * np.exp(2.33 * s_g0))
    radii, back = np.unique(np.clip(radii, lo_r, hi_r), return_inverse=True)
    if weights is None:  # per channel: the identity at every depth
        W = np.broadcast_to(np.eye(C)[:, :, None], (C, C, z.size))
    else:
        W = np.asarray(weights, float).reshape(1, C, z.size)
    rows = W.shape[0]
    out = np.empty((rows, radii.size, z.size, n_cfg))
    nzc = z.size * n_cfg
    # per species and set: its density, the paths it crosses (drift, T per channel) and the heights above each depth
    sets = []
    for f in stack.flakes:
        lo = np.clip(z - (f.z_top_um + f.thickness_um), 0.0, None)  # heights Δ of this species above each depth
        hi = np.clip(z - f.z_top_um, 0.0, None)
        if not np.any(hi > lo):
            continue
        mus = np.array([g.mu_l_b, g.mu_v_b])
        P = projected_area(mus, f.alpha, distribution=f.distribution) / mus
        T = f.mean_crossed_transmittance(mus)  # (C, 2): light, view
        Dn, Dw = f.diameters()
        rho = float(f.number_density_per_um3)
        if correlated:
            sets.append((rho * 0.5 * (P[0] + P[1]), ((t_l, T[:, 0]), (t_v, T[:, 1])), lo, hi, 0.5 * Dn, Dw))
        else:
            sets += [(rho * P[s], ((t, T[:, s]),), lo, hi, 0.5 * Dn, Dw) for s, t in enumerate((t_l, t_v))]
    v = 0.5 if OCCLUSION_SHIFT is None else float(np.random.default_rng([OCCLUSION_SHIFT, 99]).random())
    mid = (np.arange(n_cfg) + v) / n_cfg
    q_idx = np.arange(n_pts)
    for ir, r in enumerate(radii):
        drawn = []
        for stream, (rho, paths, lo, hi, rn, rw) in enumerate(sets):
            t_a, t_b = paths[0][0], paths[-1][0]
            mu_A, mu_B, cdf_A, cdf_B = _touching(rho, r, rn, rw, lo, hi, t_a, t_b)
            # the number touching: Poisson quantiles of the stratum midpoints (in order for the first set, in a
            # fixed order of their own for the others, so that two sets' counts are unrelated)
            qk = mid if stream == 0 else _occlusion_points(n_cfg, 1, stream, OCCLUSION_SHIFT)[1]
            N = _poisson_ppf(qk[None, :], (mu_A + mu_B)[:, None])  # (nz, n_cfg)
            n_max = int(N.max(initial=0))
            if n_max > N_OCCLUSION_MAX:
                raise TextureModelLimit(f"a flake's paths meet up to {n_max} flakes above it: beyond the occlusion's "
                                        f"{N_OCCLUSION_MAX} (docs/texture.md §3.3)")
            if n_max == 0:
                continue
            u = _occlusion_points(n_cfg, 1 << max(4, (n_max - 1).bit_length()), stream, OCCLUSION_SHIFT)[0]
            iz, ic, ij = np.nonzero(np.arange(n_max)[None, None, :] < N[:, :, None])  # the obstacles present
            dlt, cx, cy, rj = _place(u[:, ij, ic], r, rn, lo[iz], hi[iz], t_a, t_b, mu_A[iz], mu_B[iz], cdf_A, cdf_B)
            for tvec, tp in paths:
                ox, oy = dlt * tvec[0] - cx, dlt * tvec[1] - cy
                near = ox * ox + oy * oy < (r + rj) ** 2  # reaches this path of some point of the disc
                drawn.append((ox[near], oy[near], rj[near], (iz * n_cfg + ic)[near], tp))
        # per (species, path): the crossings of each point's path, (cells × points)
        counts, tables = [], []
        for ox, oy, rr, cell, tp in drawn:
            px = r * pts[:, 0] + ox[:, None]  # (flakes, Q)
            py = r * pts[:, 1] + oy[:, None]
            hit = px * px + py * py < (rr ** 2)[:, None]
            n = np.bincount((cell[:, None] * n_pts + q_idx).ravel(), hit.ravel(), nzc * n_pts).astype(np.int64)
            k = int(n.max(initial=0))
            counts.append(n)
            tables.append(tp[:, None] ** np.arange(k + 1)[None, :])  # (C, k + 1); 0^0 = 1
        # a point's transmission Π T^crossings depends on its crossing counts alone: per distinct combination of
        # counts once, then the disc mean per cell as the points' histogram over the combinations
        code = np.zeros(nzc * n_pts, np.int64)
        for n, pw in zip(counts, tables):
            code = code * pw.shape[1] + n
        n_code = int(np.prod([pw.shape[1] for pw in tables]))
        if n_code <= 1 << 16:  # few possible combinations: found by a table (np.unique sorts)
            seen = np.bincount(code, minlength=n_code) > 0
            uniq = np.flatnonzero(seen)
            inv = (np.cumsum(seen) - 1)[code]
        else:
            uniq, inv = np.unique(code, return_inverse=True)
        digits, rest = [], uniq
        for pw in tables[::-1]:
            rest, d = np.divmod(rest, pw.shape[1])
            digits.append(d)
        prod = np.ones((C, uniq.size))
        for pw, d in zip(tables, digits[::-1]):  # the factors in the order species, light path, view path
            prod *= pw[:, d]
        # per point its (weighted) transmission, then the disc's mean per (depth, configuration)
        val = np.einsum("rcz,cu->rzu", W, prod)[:, np.arange(nzc * n_pts) // (n_cfg * n_pts), inv]
        out[:, ir] = val.reshape(rows, z.size, n_cfg, n_pts).sum(axis=-1) / n_pts
    out = out[:, back]  # each requested radius at its own value (the nearest of the 1–99 % quantiles beyond them)
    return out if weights is None else out[0]


#: Uniform depths at which :func:`_glint_paths` finds where the absorbers stop every flake glinting.
N_CUT = 33
#: Depth nodes (Gauss–Legendre) of the glint counts' occlusion draws.
N_DEPTH_OCCLUSION = 12


def _glint_paths(stack, f, g):
    """The part of :func:`sparkle_indices` for flake layer ``f`` that depends on the light and view
    directions only (not on the observer's spot, aperture or source size), or None where the flakes'
    mirror reflectance at the half-vector has no luminance (R_Y = 0).  Returns ``(full, glint, R_Y)``:
    ``full`` = (wz (nz,), w, P (nz, combinations)) on the layer's Gauss depths (:func:`_depth_nodes`), for
    the mean of all flakes; ``glint`` = (wz, w, P), each (N_DEPTH, glinting combinations), for the counts;
    w, P the luminance-weighted transmission and probability of each crossing combination
    (:func:`_combinations`, :func:`_path_weights`).

    A flake glints only while w ≥ :data:`GLINT_FRACTION` (its threshold q = GLINT_FRACTION / w ≤ 1), and w
    falls with depth (the absorbers' and crossed flakes' attenuation), so each combination's count integrand
    stops at the depth z* where w = GLINT_FRACTION, with a jump where the beam has a flat top (source wider
    than the diffraction disc and the aperture: φ = 1 up to an offset).  A Gauss rule over the whole layer
    converged as 1/N across that jump (glints at 75° of the 3-species benchmark paint off by 11 % with 24
    nodes, 1–4 % with 48–64); ``glint`` holds, for each combination that glints at all, a Gauss rule on
    [z_top, z*] instead (z* by log-linear interpolation of w on :data:`N_CUT` uniform depths; w is
    non-increasing in depth), exact for the jump."""
    y = np.asarray(stack.y_weights, float)
    R_h = f.reflectance(np.array([g.c]))[:, 0]  # (C,)
    R_Y = float(y @ R_h)
    if R_Y <= 0.0:
        return None
    lb = np.array([np.sqrt(1 - g.mu_l_b**2), 0.0, g.mu_l_b])
    vb = np.array([-np.sqrt(1 - g.mu_v_b**2), 0.0, g.mu_v_b])
    gap = _gap(lb, vb)
    yR, top, d, C = y * R_h, f.z_top_um, f.thickness_um, y.size

    def weights(z, combos, correlated):  # (w, P) (*z.shape[:-1], combinations) at depths z (…, 1 or combinations)
        shape = z.shape
        tau_l, lam_l, T_l = _path(stack, z.ravel(), g.mu_l_b)
        tau_v, lam_v, T_v = _path(stack, z.ravel(), g.mu_v_b)
        lam_b = _both_paths(stack, z.ravel(), np.full(z.size, gap), lam_l, lam_v, correlated)
        cs = (C,) + shape
        inputs = (np.exp(-(tau_l + tau_v)).reshape(cs), (lam_l - lam_b).reshape(shape), (lam_v - lam_b).reshape(shape),
                  lam_b.reshape(shape), T_l.reshape(cs), T_v.reshape(cs))
        out = None if combos is None else _path_weights(yR, R_Y, *inputs, combos)
        return out, (lam_l - lam_b, lam_v - lam_b, lam_b, T_l, T_v), inputs

    z, wz = _depth_nodes(f)
    means = []
    for correlated in (CORRELATED_MEAN, True):  # the mean as the BSDF has it, and as a layer of discs (hot spot)
        _, (ll, lv, lbb, Tl, Tv), inputs = weights(z[:, None], None, correlated)
        combos = _combinations(ll, lv, lbb, Tl, Tv)
        w, P = _path_weights(yR, R_Y, *inputs, combos)
        means.append(float(np.sum(wz[:, None] * P * w)))
    # the counts: the distribution of w over each flake's area (partial occlusion, :func:`_occlusion`); the
    # absorbers' transmission w_a(z) bounds it, so nothing glints below z* where w_a = GLINT_FRACTION
    radii = 0.5 * f.diameters()[0]

    def absorbed(zz):
        tau_l, _, _ = _path(stack, zz, g.mu_l_b)
        tau_v, _, _ = _path(stack, zz, g.mu_v_b)
        return np.exp(-(tau_l + tau_v))  # (C, nz)

    def samples(zz):  # w (nD, nz, configurations) at depths zz
        return _occlusion(stack, g, zz, radii, CORRELATED_PATHS, weights=(yR / R_Y)[:, None] * absorbed(zz))

    zf = top + d * np.linspace(0.0, 1.0, N_CUT)
    wa = (yR / R_Y) @ absorbed(zf)  # (N_CUT,) non-increasing
    below = np.flatnonzero(wa < GLINT_FRACTION)
    if below.size == 0:
        z_end = top + d
    elif below[0] == 0:
        z_end = top
    else:
        k = below[0]
        t = np.clip(np.log(wa[k - 1] / GLINT_FRACTION) / np.log(wa[k - 1] / max(wa[k], 1e-300)), 0.0, 1.0)
        z_end = zf[k - 1] + t * (zf[k] - zf[k - 1])
    x, wx = leggauss(N_DEPTH_OCCLUSION)
    zl = top + 0.5 * (x + 1.0) * d
    fixed = (0.5 * wx, samples(zl))
    glint = None
    if z_end >= top + d:  # nothing stops glinting inside the layer: the layer's draws serve both counts
        glint = fixed
    elif z_end > top:
        zg = top + 0.5 * (x + 1.0) * (z_end - top)
        glint = (0.5 * wx * (z_end - top) / d, samples(zg))
    return tuple(means), glint, fixed, R_Y


def reference_peak(g) -> float:
    """β_peak of an aligned, unattenuated, perfectly reflecting (R = 1) surface flake of
    :data:`GLINT_REFERENCE_DIAMETER_UM` at 555 nm in the geometry ``g`` (eq. S1 with w = 1, d = 0): the
    luminance factor against which the fixed-threshold glint count is taken."""
    lam = DIFFRACTION_WAVELENGTH_NM * 1e-3 / g.eta
    x, f = beam_collected(g, GLINT_REFERENCE_DIAMETER_UM, [lam], [1.0])
    return float(np.pi * g.t_in * g.t_out * f[0, 0] * g.c / (g.mu_l_b * g.mu_v * g.omega_a))


#: Disc points per flake and centre positions per spot side of :func:`spot_fill`.
_FILL_POINTS, _FILL_OFFSETS = 1024, 16


def spot_fill(diameter_um, spot_um):
    """The mean, over a flake disc's position relative to a grid of p × p spots, of the largest fraction of one
    spot the disc covers (0 … 1): the part of a glint's luminance the brightest spot of a panel image holds
    (→ A/p² for flakes much smaller than the spot, → 1 for much larger ones).  Disc points on Vogel's
    spiral (:data:`_FILL_POINTS`) binned into spots for :data:`_FILL_OFFSETS`² centre positions in one spot.
    ``diameter_um``: any shape."""
    D = np.atleast_1d(np.asarray(diameter_um, float))
    out = np.array([_spot_fill_one(float(d), float(spot_um)) for d in D.ravel()])
    return out.reshape(np.shape(diameter_um)) if np.ndim(diameter_um) else float(out[0])


@lru_cache(maxsize=4096)
def _spot_fill_one(d, p):
    if d >= 2.0 * np.sqrt(2.0) * p:
        # the spot holding the disc's centre lies within √2 p of it: inside the disc, wholly covered (exact; the
        # binning below, whose grid grows as (d/p)², asked for 40 GiB at d = 27 mm, p = 15 µm)
        return 1.0
    k = np.arange(_FILL_POINTS) + 0.5
    r = np.sqrt(k / _FILL_POINTS)
    t = k * np.pi * (3.0 - np.sqrt(5.0))
    pts = np.stack([r * np.cos(t), r * np.sin(t)], -1)  # unit disc, equal areas
    u = (np.arange(_FILL_OFFSETS) + 0.5) / _FILL_OFFSETS * p
    # a point's spot column depends on the centre's x alone, its row on the centre's y alone: (offsets, points) each
    x = np.floor((u[:, None] + 0.5 * d * pts[None, :, 0]) / p).astype(np.int64)
    y = np.floor((u[:, None] + 0.5 * d * pts[None, :, 1]) / p).astype(np.int64)
    span = int(np.ceil(d / p)) + 3
    side = 2 * span + 1
    n_c = _FILL_OFFSETS * _FILL_OFFSETS  # centres (x offset major, as meshgrid's "ij")
    cell = (((x[:, None, :] + span) * side + (y[None, :, :] + span)).reshape(n_c, -1)
            + np.arange(n_c)[:, None] * side * side)
    counts = np.bincount(cell.ravel(), minlength=n_c * side * side).reshape(n_c, -1)
    frac = counts.max(axis=1) / _FILL_POINTS * (0.25 * np.pi * d * d) / (p * p)
    return min(float(frac.mean()), 1.0)


def sparkle_indices(stack: TextureStack, observer, light_deg, ground_luminance_factor=None, memo=None) -> dict:
    """The glint statistics of docs/texture.md §3 for one directional geometry.

    Returns a dict (units in the keys): ``glints_per_mm2`` (expected glints per mm² of panel: flakes
    at least :data:`GLINT_FRACTION` as bright as an aligned, unattenuated surface flake of their
    kind), ``glints_per_spot``, ``sparkle_area_fraction`` (probability that a resolved spot holds
    a glint), ``sparkle_intensity`` (mean excess luminance factor of a spot holding one glint),
    ``peak_luminance_factor`` (an aligned surface flake of the median diameter filling the spot),
    ``flake_luminance_factor`` (the mean luminance factor that all flakes' single mirror reflections
    give the panel: the part of the smooth BSDF the glints carry, π f_ss), ``sparkle_contrast``
    (sparkle_intensity over the ground: ``ground_luminance_factor`` if given (the smooth BSDF's π f),
    else the flake part), and ``sparkle`` (False when no flake can outshine a white diffuser).
    ``memo``: an optional dict shared by calls on the same ``stack`` (:func:`texture_indices` of several
    observers) that keeps the parts that depend on the light and view only (:func:`_glint_paths`).

    Doubling the loading of a 10 µm layer of aluminium-like flakes at most doubles the glints (the added
    flakes also hide some of those below), and their mirror reflections stay below the flakes' R = 0.9:

    >>> from flakedb.texture.instruments import PRESETS
    >>> c = np.linspace(0.0, 1.0, 5)
    >>> def stack(rho):
    ...     f = FlakeLayer("al", 0.0, 10.0, rho, 15.0, 1.3, 0.3, 0.2, c, np.full((1, 5), 0.9), np.zeros((1, 5)))
    ...     return TextureStack(1.5, np.array([1.0]), (f,))
    >>> a, b = (sparkle_indices(stack(rho), PRESETS["byk-mac-like"], 15.0) for rho in (1e-4, 2e-4))
    >>> a["sparkle"], 1.5 < b["glints_per_mm2"] / a["glints_per_mm2"] <= 2.0, a["flake_luminance_factor"] < 0.9
    (True, True, True)
    """
    g = directional_geometry(stack.eta, light_deg, observer.view_deg, observer.source_half_angle_deg,
                             observer.aperture_half_angle_rad)
    a_spot = float(observer.spot_um) ** 2
    p = float(observer.spot_um)
    n_g = 0.0
    n_fixed = 0.0
    b_ref = GLINT_FRACTION * reference_peak(g)
    flux = 0.0  # Σ over glints of β_px (per µm²)
    mean_all = 0.0
    mean_discs = 0.0
    mink = 0.0
    peak = 0.0
    for i_f, f in enumerate(stack.flakes):
        key = ("glint", i_f, g.mu_l_b, g.mu_v_b)
        if memo is None or key not in memo:
            paths = _glint_paths(stack, f, g)
            if memo is not None:
                memo[key] = paths
        else:
            paths = memo[key]
        if paths is None:
            continue
        (mean_w, mean_w_discs), glint, (wz_f, w_f), R_Y = paths
        Dn, Dw = f.diameters()
        Nz = f.number_density_per_um3 * f.thickness_um  # flakes per µm² in the layer
        # the beam of each diameter node (its Airy pattern at the flake's own colours), and the median's for the peak
        R_h = f.reflectance(np.array([g.c]))[:, 0]
        lam_um, lam_w = _diffraction_bands(stack, np.asarray(stack.y_weights, float) * R_h)
        S_P, I_P, f_max = _beam_levels(g, np.append(Dn, f.diameter_median_um), lam_um, lam_w, f.alpha,
                                       f.distribution)
        levels = np.linspace(0.0, 1.0, S_P.shape[1])
        b_all = np.pi * g.t_in * g.t_out * R_Y * f_max * g.c / (g.mu_l_b * g.mu_v * g.omega_a)
        b_peak = b_all[:-1]  # (nD,)
        A = 0.25 * np.pi * Dn * Dn
        dens = Nz * Dw / (4.0 * g.c)  # flakes per µm² per unit ω_o-space area and unit density
        if glint is not None:
            wz, w = glint  # (nz,), (nD, nz, draws): each draw one flake's area-mean transmission
            q = GLINT_FRACTION / np.maximum(w, 1e-300)
            S_q = np.stack([np.interp(q[i], levels, S_P[i], right=0.0) for i in range(Dn.size)])
            I_q = np.stack([np.interp(q[i], levels, I_P[i], right=0.0) for i in range(Dn.size)])
            wP = wz[:, None] / w.shape[-1]
            cnt = dens * np.einsum("zk,dzk->d", wP, S_q)
            n_g += float(cnt.sum())
            flux += float(np.sum(dens * b_peak * spot_fill(Dn, p) * np.einsum("zk,dzk,dzk->d", wP, w, I_q)))
            mink += float(np.sum(cnt * (a_spot + 2.0 * p * Dn + 0.25 * np.pi * Dn * Dn)))
        # above the fixed luminance β_ref: draws over the whole layer (the cut depth differs per diameter)
        S_f = np.stack([np.interp(b_ref / np.maximum(b_peak[i] * w_f[i], 1e-300), levels, S_P[i], right=0.0)
                        for i in range(Dn.size)])
        n_fixed += float(np.sum(dens * np.einsum("zk,dzk->d", wz_f[:, None] / w_f.shape[-1], S_f)))
        mean_all += float(np.sum(dens * b_peak * A * mean_w * I_P[:-1, 0]))
        mean_discs += float(np.sum(dens * b_peak * A * mean_w_discs * I_P[:-1, 0]))
        peak = max(peak, float(b_all[-1]))
    sparkle = bool(stack.flakes) and bool(peak >= SPARKLE_MIN_PEAK) and bool(n_g > 0)
    intensity = flux / n_g if n_g > 0 else 0.0
    if sparkle:
        why = ""
    elif not stack.flakes:
        why = "no flakes"
    elif not n_g > 0:   # checked before the peak: a bright peak with no flake tilted to show it is still no glint
        why = (f"no flake is tilted to mirror the light at {light_deg:g}° towards the observer at "
               f"{observer.view_deg:g}° (expected glints 0; the flakes' orientation spread holds no such normal)")
    else:
        why = f"peak luminance factor {peak:.3g} < {SPARKLE_MIN_PEAK:g} (no flake outshines a white diffuser)"
    return sparkle_grounded({
        "light_deg": float(light_deg), "view_deg": float(observer.view_deg),
        "sparkle": sparkle, "no_sparkle_reason": why,
        "glints_per_mm2": float(n_g * 1e6) if sparkle else 0.0,
        "glints_per_mm2_above_threshold": float(n_fixed * 1e6) if sparkle else 0.0,
        "glint_threshold_luminance_factor": float(b_ref),
        "glints_per_spot": float(n_g * a_spot) if sparkle else 0.0,
        "sparkle_area_fraction": float(-np.expm1(-mink)) if sparkle else 0.0,
        "sparkle_intensity": float(intensity) if sparkle else 0.0,
        "peak_luminance_factor": float(peak),
        "flake_luminance_factor": float(mean_all),
        # the same mean in a layer of discs, whose light and view paths share the flakes above a flake (the
        # opposition effect of hiding, eq. S4): the glints' counts and intensities have it, the BSDF has not
        "flake_luminance_factor_discs": float(mean_discs),
        "hot_spot_factor": float(mean_discs / mean_all) if mean_all > 0 else 1.0,
    }, ground_luminance_factor)


def sparkle_grounded(row: dict, ground_luminance_factor=None) -> dict:
    """A :func:`sparkle_indices` row with its contrast taken against ``ground_luminance_factor`` (the
    smooth BSDF's π f at the row's geometry), or, when None, against the flakes' own mean
    (``flake_luminance_factor``; not a bound: it can exceed the paint's): ``sparkle_contrast`` = sparkle_intensity / ground
    (docs/texture.md §3.4) and ``ground`` ("bsdf" or "flakes").  The ground enters nothing else, so
    the glint statistics can be computed before the BSDF is solved and grounded after."""
    ground = float(ground_luminance_factor) if ground_luminance_factor is not None else row["flake_luminance_factor"]
    contrast = row["sparkle_intensity"] / ground if row["sparkle"] and ground > 0 else 0.0
    return dict(row, sparkle_contrast=float(contrast), ground="bsdf" if ground_luminance_factor is not None else "flakes")


# ----------------------------------------------------------------------------------------------
# Graininess under a uniform sky (docs/texture.md §4)
# ----------------------------------------------------------------------------------------------


def overlap_integral(diameter_um, spot_um, n=48):
    """∫ (area of a disc of diameter D inside a p × p square, as a fraction of p²)² over the disc's
    centre position x (µm²; docs/texture.md eq. G2): = p⁻⁴ ∫ g(δ) K(δ) dδ with g the disc's set
    covariogram (lens area of two discs d apart) and K(δ) = (p − |δ_x|)(p − |δ_y|) the square's,
    by n × n Gauss–Legendre on [0, min(p, D)]² (× 4 by symmetry; K is separable, so it joins the
    weights).  Limits: A²/p² (D ≪ p), A (D ≫ p).  ``diameter_um``: a scalar (→ float) or an array
    of diameters (→ its shape)."""
    D_all = np.asarray(diameter_um, float)
    p = float(spot_um)
    x, w = leggauss(n)
    out = np.empty(D_all.size)
    Df = D_all.ravel()
    for lo in range(0, Df.size, 4):  # four diameters (4 n² elements) at a time: few, small temporaries
        D = Df[lo:lo + 4, None]
        h = np.minimum(p, D)
        u = 0.5 * h * (x + 1.0)  # (k, n)
        a = 0.5 * h * w * (p - u)  # Gauss weights × K's factor
        d2 = u[:, :, None] ** 2 + u[:, None, :] ** 2
        g = _lens_area_sq(np.sqrt(d2), d2, 0.5 * D[:, :, None], 0.5 * D[:, :, None], equal=True)
        out[lo:lo + 4] = 4.0 * np.einsum("ki,kij,kj->k", a, g, a) / p**4
    return float(out[0]) if D_all.ndim == 0 else out.reshape(D_all.shape)


#: Bisection steps that find, per azimuth, the tilt beyond which a flake mirrors no sky (2⁻⁴⁰ in u1).
N_CUT_BISECT = 40


def _sky_normals(alpha, vb, eta, n_t=N_TILT, n_p=N_AZIMUTH, distribution=DEFAULT_DISTRIBUTION):
    """Upper-hemisphere flake normals m (M, 3) and weights (Σ ≤ 1) for the density 2D(m) of
    ``distribution`` (:data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS`) over the normals that mirror the
    view ``vb`` (3,) (binder, pointing up) into the coat's escape cone (the sky; cos θ' > √(1 − 1/η²)):
    the others mirror nothing (total internal reflection at the coat), so leaving them out is exact.

    Through the registry's own inverse (``sample(u1, u2, α)``: u1 ↦ the tilt's cumulative probability,
    u2 ↦ the azimuth), whatever the family: azimuths 2π u2 uniform on (0, π) (midpoint rule; φ and −φ
    give the same values for a view in the x–z plane); per azimuth, the cut u1* where the mirrored
    direction leaves the escape cone (bisection, the mirrored direction's height falling with the tilt),
    and Gauss–Legendre on (0, u1*): the integrand is smooth there, where a rule over the whole (0, 1)
    converged slowly across the jump (GGX, α 0.2: graininess 1.335 / 1.304 / 1.278 at 12 / 16 / 24 nodes)."""
    vb = np.asarray(vb, float)
    mu_c = np.sqrt(max(1.0 - 1.0 / float(eta) ** 2, 0.0))
    sample = flake_distribution(distribution).sample
    u2 = (np.arange(n_p) + 0.5) * 0.5 / n_p  # azimuths 2π u2 in (0, π)

    def sky(u1):  # the normal at (u1, u2) mirrors the view into the escape cone
        m = sample(u1, u2, float(alpha))
        return (2.0 * (m @ vb)[..., None] * m - vb)[..., 2] > mu_c

    lo, hi = np.zeros(n_p), np.full(n_p, 1.0 - 1e-15)
    all_sky = sky(hi)
    for _ in range(N_CUT_BISECT):
        mid = 0.5 * (lo + hi)
        ok = sky(mid)
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    cut = np.where(all_sky, 1.0, 0.5 * (lo + hi))  # (n_p,)
    x, wx = leggauss(n_t)
    u1 = 0.5 * (x[:, None] + 1.0) * cut[None, :]  # (n_t, n_p)
    m = sample(u1, u2[None, :], float(alpha))
    w = 0.5 * wx[:, None] * cut[None, :] / n_p
    return m.reshape(-1, 3), w.ravel()


def _sky_terms(stack, f, view_deg):
    """The part of :func:`graininess_indices` for flake layer ``f`` that depends on the view only (not on
    the observer's spot): E[b], E[b²] over normals and depths (docs/texture.md eq. G3), the depth nodes,
    the unhidden mean luminance factor per depth b0, the view path's crossings λ_v and the luminance of
    T² of a flake crossed by both vertical paths, and the mosaic's depth profiles (:func:`mosaic_variance`).  A view along the
    normal (v' = z) sees every azimuth of a normal alike (v'·m, the mirrored direction's polar angle and the
    paths' drift depend on the tilt only), so there the normals are the tilts alone (one azimuth each, the
    weight of all: the azimuth average of equal terms)."""
    eta = float(stack.eta)
    y = np.asarray(stack.y_weights, float)
    mu_v = float(np.cos(np.radians(view_deg)))
    mu_vb = float(binder_cosine(view_deg, eta))
    vb = np.array([-np.sqrt(1 - mu_vb**2), 0.0, mu_vb])
    t_out = float(coat_transmittance(mu_v, eta))
    m, wm = _sky_normals(f.alpha, vb, eta, n_p=1 if vb[2] == 1.0 else N_AZIMUTH, distribution=f.distribution)
    cv = m @ vb
    lm = 2.0 * cv[:, None] * m - vb  # mirrored direction (toward the sky)
    mu_lb = lm[:, 2]
    s2 = np.maximum(1.0 - mu_lb**2, 0.0) * eta * eta
    ok = (mu_lb > 1e-6) & (s2 < 1.0)
    mu_air = np.sqrt(np.clip(1.0 - s2, 0.0, 1.0))
    t_in = np.where(ok, coat_transmittance(mu_air, eta), 0.0)
    R = f.reflectance(np.abs(cv))  # (C, M)
    # depth nodes: N_DEPTH_SKY, or 4 per flake a vertical ray meets in the layer (thick, dense layers: the mosaic
    # is made near the top, which 16 nodes over 120 µm of 8 % metallic resolved to 1 %)
    coverage = float(f.number_density_per_um3 * f.mean_area_um2() * f.thickness_um)
    z, wz = _depth_nodes(f, int(min(max(N_DEPTH_SKY, np.ceil(4.0 * coverage)), 128)))
    mu_lb_s = np.where(ok, mu_lb, 1.0)
    # paths: in along each m's mirrored direction, out along v'
    tau_v, lam_v, T_v = _path(stack, z, mu_vb)  # (C, nz), (nz,), (C, nz)
    M, nz = m.shape[0], z.size
    zz = np.repeat(z[None, :], M, axis=0).ravel()
    mm = np.repeat(mu_lb_s[:, None], nz, axis=1).ravel()
    tau_l, lam_l, T_l = _path(stack, zz, mm)
    C = y.size
    tau_l, lam_l, T_l = tau_l.reshape(C, M, nz), lam_l.reshape(M, nz), T_l.reshape(C, M, nz)
    gap = np.repeat(_gap(np.where(ok[:, None], lm, vb[None, :]), vb)[:, None], nz, axis=1).ravel()
    lam_b = _both_paths(stack, zz, gap, lam_l.ravel(), np.repeat(lam_v[None, :], M, 0).ravel(), CORRELATED_SKY_PATHS)
    lam_b = lam_b.reshape(M, nz)
    lo_l, lo_v = lam_l - lam_b, lam_v[None, :] - lam_b  # one path only
    # per channel: amp = T_in T_out R e^{−τ}; Poisson crossings average exactly (docs/texture.md eq. G3):
    # E[b_c] = a_c exp(−λ_l'(1−T_l) − λ_v'(1−T_v) − λ_b(1−T_l T_v)),
    # E[b_c b_c'] = a_c a_c' exp(−λ_l'(1−T_l T_l') − λ_v'(1−T_v T_v') − λ_b(1−T_l T_v T_l' T_v'))
    # a flake of normal m covers A |v'·m| / μ_v' of the panel seen along v' (its foreshortened footprint): the
    # solver's kernel carries the same |ω·m| (paper eq. 2); leaving it out put the sky mean 1.5–3 % high (α 0.2–0.7)
    fore = np.abs(cv) / mu_vb
    amp = (t_in * t_out * fore)[None, :, None] * R[:, :, None] * np.exp(-(tau_l + tau_v[:, None, :]))  # (C, M, nz)
    Tv = np.broadcast_to(T_v[:, None, :], T_l.shape)
    Eb_c = amp * np.exp(-lo_l * (1 - T_l) - lo_v * (1 - Tv) - lam_b * (1 - T_l * Tv))
    b1 = np.einsum("c,cmz->mz", y, Eb_c)
    ya = y[:, None, None] * amp
    # the exponent is symmetric in (c, c'): the pairs c' > c counted twice, the diagonal once
    base = -(lo_l + lo_v + lam_b)
    A_l, A_v, TT = lo_l * T_l, lo_v * Tv, T_l * Tv
    A_b = lam_b * TT
    b2 = np.zeros((M, nz))
    for c1 in range(C):
        ex = base + A_l[c1] * T_l[c1:] + A_v[c1] * Tv[c1:] + A_b[c1] * TT[c1:]
        np.exp(ex, out=ex)
        ex *= ya[c1:]
        ex[1:] *= 2.0
        b2 += ya[c1] * np.sum(ex, axis=0)
    wgt = wm[:, None] * wz[None, :]
    Eb, Eb2 = float(np.sum(wgt * b1)), float(np.sum(wgt * b2))
    b0 = np.einsum("c,cmz,m->z", y, amp, wm)  # unhidden mean luminance factor per depth
    tau_y = float(y @ (T_v[:, -1] ** 2))  # a flake crossed by both (vertical) paths transmits T²
    # the mosaic (docs/texture.md §4): per depth, the flakes' sky luminance before the view path's crossings
    # (which the mosaic counts itself), B1 = Σ_m w_m Y[amp e^{−λ_l'(1 − T_l)}] (amp carries the footprint), and
    # B2 = Σ_m w_m Y[amp]² e^{−λ_l'(1 − T̄_l²)}/fore (a ray's second moment: the footprint weights the normals once)
    a_l = np.exp(-lo_l * (1 - T_l))  # (C, M, nz)
    yamp = np.einsum("c,cmz->mz", y, amp)
    B1 = np.einsum("c,cmz,m->z", y, amp * a_l, wm)
    Tl_y = np.einsum("c,cmz->mz", y, amp * T_l) / np.maximum(yamp, 1e-300)
    Q = (wm / np.maximum(fore, 1e-12))[:, None] * yamp**2
    B2 = np.sum(Q * np.exp(-lo_l * (1 - Tl_y**2)), axis=0)
    # a crossed flake's luminance transmittance on the view path (weighted by the light it dims)
    # (a flake above that covers the ray and also lies on the light path, λ_b of λ_v, dims the light twice)
    ya_mz = np.einsum("c,cmz->mz", y, amp) * wm[:, None]
    T_vy = float(np.sum(np.einsum("c,cmz,m->cz", y, amp, wm) * T_v) / max(float(np.sum(ya_mz)), 1e-300))
    T_ly = float(np.sum(np.einsum("c,cmz,m->mz", y, amp * T_l, wm)) / max(float(np.sum(ya_mz)), 1e-300))
    f_b = float(np.sum(ya_mz * lam_b) / max(float(np.sum(ya_mz * lam_v[None, :])), 1e-300))
    T_vy *= 1.0 - min(f_b, 1.0) * (1.0 - T_ly)
    P_v = float(projected_area(np.array([mu_vb]), f.alpha, distribution=f.distribution)[0]) / mu_vb
    # per normal, for the sky paths' coupling to the mosaic (eq. G6): its share of B1 and its sky path's drift
    # per µm of height away from the view ray (|l'_xy/l'_z − v'_xy/v'_z|)
    B1m = wm[:, None] * np.einsum("c,cmz->mz", y, amp * a_l)
    drift = np.where(ok, _gap(np.where(ok[:, None], lm, vb[None, :]), vb), 0.0)
    return Eb, Eb2, z, wz, b0, lam_v, tau_y, (B1, B2, T_vy, P_v, (Q, lo_l, Tl_y, B1m, drift))


#: Least uniform depth cells, and the offset nodes per interval between kinks, of the mosaic's covariance
#: (:func:`mosaic_variance`).
N_MOSAIC_DEPTH, N_MOSAIC_OFFSET = 96, 8


@lru_cache(maxsize=64)
def _square_ring(p, s_key):
    """K̄(s) = ∫_0^{2π} (p − s|cos θ|)₊ (p − s|sin θ|)₊ dθ (µm²): the p × p square's set covariogram around a
    circle of radius s (2πp² − 8ps + 2s² for s ≤ p; 1024 midpoint angles)."""
    s = np.frombuffer(s_key)
    th = (np.arange(1024) + 0.5) * (2.0 * np.pi / 1024)
    c, sn = np.abs(np.cos(th)), np.abs(np.sin(th))
    k = np.maximum(p - s[:, None] * c, 0.0) * np.maximum(p - s[:, None] * sn, 0.0)
    return k.mean(axis=1) * 2.0 * np.pi


#: The sky paths' coupling to the mosaic (eq. G6) on or off (off: G5's luminances independent of the mosaic).
SKY_COUPLING = True
#: Its coarse depth grid (cells at most, ρ A_e dz at most) and the drift grid of its area tables.
N_COUPLING_DEPTH, COUPLING_DZ, N_COUPLING_DRIFT = 96, 0.05, 129
#: Λ (the view ray's expected crossings) below which the coupling's depth grid ends: e^{−9.2} = 1e-4 of the rays.
COUPLING_DEPTH_REACH = 9.2


#: Nodes per side of the cached table of :func:`shared_crossings_mean` (σ, υ in [0, 2]; bilinear between them).
N_SHARED_TABLE = 65


@lru_cache(maxsize=1)
def _shared_unit_table():
    """:func:`shared_crossings_mean` on the N_SHARED_TABLE² grid σ, υ ∈ [0, 2] (read-only)."""
    g = np.linspace(0.0, 2.0, N_SHARED_TABLE)
    out = np.stack([shared_crossings_mean(si, g) for si in g])
    out.setflags(write=False)
    return out


def _shared_unit(sig, ups):
    """:func:`shared_crossings_mean` at σ = s/r, υ = u/r (broadcast) from its cached table: 0 for σ ≥ 2, the
    lens area for υ ≥ 2 (where the table's last column is exactly it)."""
    t = _shared_unit_table()
    step = 2.0 / (N_SHARED_TABLE - 1)
    a = np.clip(np.asarray(sig, float) / step, 0.0, N_SHARED_TABLE - 1.0)
    b = np.clip(np.asarray(ups, float) / step, 0.0, N_SHARED_TABLE - 1.0)
    i, j = np.minimum(a.astype(int), N_SHARED_TABLE - 2), np.minimum(b.astype(int), N_SHARED_TABLE - 2)
    fa, fb = a - i, b - j
    return ((t[i, j] * (1.0 - fb) + t[i, j + 1] * fb) * (1.0 - fa) + (t[i + 1, j] * (1.0 - fb) + t[i + 1, j + 1] * fb) * fa)


def _cumulative(g, dw):
    """∫_0^w g dw' (trapezoid) of each row of ``g`` (…, nw) on the uniform grid of step ``dw``."""
    c = np.cumsum(0.5 * dw * (g[..., 1:] + g[..., :-1]), axis=-1)
    return np.concatenate([np.zeros(g.shape[:-1] + (1,)), c], axis=-1)


def _coupling_depth(f, T, kappa):
    """The depth below the layer's top that the sky coupling (eq. G6) covers (µm): the layer, or where the view
    ray's expected crossings Λ = ρ h A_e (1 − T) reach ``COUPLING_DEPTH_REACH`` (rays go no deeper)."""
    rate = float(f.number_density_per_um3) * kappa * f.mean_area_um2() * max(1.0 - T, 1e-12)
    return min(float(f.thickness_um), COUPLING_DEPTH_REACH / rate)


def _coupling_reach(f, T, kappa, light):
    """The largest drift of a sky path (µm) over :func:`_coupling_depth`: the reach of the coupling's offsets."""
    return _coupling_depth(f, T, kappa) * float(np.max(light[4], initial=0.0))


def _coupling_table(f, ss, kappa, w_max):
    """The area tables of the sky coupling (eq. G6) on a uniform grid 0 ≤ w ≤ ``w_max`` of the drift w = u|t| (µm)
    at the offsets ``ss`` (ns,): (dw, ⟨G⟩ (ns, nw) µm², H (ns, nw) µm³, (⟨S⟩, H_S), (N, H_N)).  ⟨G⟩(s, w) = κ Σ_D n_D
    r² G1(s/r, w/r) the footprint area (footprints as discs of area κA, as the lens L) of the flakes that cover a
    point w away (at a random angle) and the ray s away but not the ray itself (G1 :func:`lens_outside_mean`);
    H = ∫_0^w ⟨G⟩ dw'; (⟨S⟩, H_S) the same for :func:`shared_crossings_mean` (two parallel sky paths' common
    crossings that cover neither ray) and (N, H_N) (1, nw) for κ⟨A − lens(w)⟩ (one path's crossings that do not
    cover its ray)."""
    Dn, Dw = f.diameters()
    r = 0.5 * Dn
    w = np.linspace(0.0, max(float(w_max), 1e-9), N_COUPLING_DRIFT)
    dw = float(w[1] - w[0])
    sig, ups = np.broadcast_arrays(ss[None, :, None] / r[:, None, None], w[None, None, :] / r[:, None, None])
    # G1 is 0 outside the strip |σ − υ| < 2 (and where either is 0): evaluated where it is not
    on = (np.abs(sig - ups) < 2.0) & (sig > 0.0) & (ups > 0.0)
    g1 = np.zeros(sig.shape)
    g1[on] = lens_outside_mean(sig[on], ups[on])
    g = kappa * np.einsum("d,dsw->sw", Dw * r * r, g1)
    sh = kappa * np.einsum("d,dsw->sw", Dw * r * r, _shared_unit(sig, ups))
    own = kappa * (Dw * r * r) @ (np.pi - lens_area(2.0 * w[None, :] / (2.0 * r[:, None]), 1.0, 1.0))
    return dw, g, _cumulative(g, dw), (sh, _cumulative(sh, dw)), (own[None, :], _cumulative(own[None, :], dw))


def _integral_rows(g, H, dw, q):
    """∫_0^q of each row of ``g`` (ns, nw) taken linear between its nodes (spacing ``dw``), at ``q`` (any shape),
    from its cumulative ``H``: exact for that piecewise-linear integrand (a linear interpolation of H read
    H(q)/q wrongly near q = 0, where the integrand starts from 0: 0.3 % of a thick layer's G); held beyond
    the end → (ns, *q.shape)."""
    nw = g.shape[1]
    q = np.clip(np.asarray(q, float), 0.0, (nw - 1) * dw)
    i = np.minimum((q / dw).astype(int), nw - 2)
    d = q - i * dw
    return H[:, i] + g[:, i] * d + (g[:, i + 1] - g[:, i]) * (d * d / (2.0 * dw))


def _lerp_rows(table, dw, q):
    """Each row of ``table`` (ns, nw), a function on the uniform grid 0, dw, …, linearly interpolated at ``q`` (any
    shape; held beyond the end) → (ns, *q.shape)."""
    pos = np.clip(np.asarray(q, float) / dw, 0.0, table.shape[1] - 1.0)
    i = np.minimum(pos.astype(int), table.shape[1] - 2)
    fr = pos - i
    return table[:, i] * (1.0 - fr) + table[:, i + 1] * fr


def _drift_integral(tab, drift, h):
    """F(s, m, h) = ∫_0^h ⟨G⟩(s, u g_m) du = H(s, h g_m)/g_m (µm³) for sky paths drifting g_m (M,) µm per µm of
    height, at heights ``h`` (nh,) → (ns, M, nh); 0 for a vertical path (⟨G⟩(s, 0) = 0)."""
    dw, G, H = tab[:3]
    g = np.asarray(drift, float)[:, None]
    gs = np.where(g > 1e-12, g, 1.0)
    return np.where(g > 1e-12, _integral_rows(G, H, dw, gs * np.asarray(h, float)[None, :]) / gs, 0.0)


def _coupling_two_flakes(f, z, light, T, kappa, L, tab):
    """What the sky paths' coupling to the mosaic adds to G5's two-flake term at the offsets of ``L`` (ns,)
    (docs/texture.md §4, eq. G6): the upper flake F1 (top at x, depth z1) and the lower F2 (top at y = x + s, z2 =
    z1 + Δ) are two points of the Poisson process conditioned by the mosaic (their Palm distribution), so

    * F1 blocks F2's sky path where its centre also covers y + Δ t2 (t2 F2's drift) but not y: of F1's centres
      (⟨A_e⟩ of them cover x) the area ⟨G⟩(s, Δ|t2|) does, F2's light × T_l there;
    * no flake above z1 covers x or y, so F1's sky path meets none of those that cover y only, and F2's none above
      z1 of those that cover x only: each a factor exp(ρ (1 − T)(1 − T_l) ∫ ⟨G⟩(s, u|t|) du) over the heights above z1.

    Evaluated on a coarse uniform depth grid (ρ A_e dz ≤ ``COUPLING_DZ``, over the depth a ray reaches: e^{−Λ} ≥
    e^{−COUPLING_DEPTH_REACH}) as the corrected two-flake sum minus the same sum uncorrected, normals kept (the drift is per normal)."""
    Qm, lo, Tl, B1m, drift = light
    rho, A = float(f.number_density_per_um3), f.mean_area_um2()
    A_e = kappa * A
    h_end = _coupling_depth(f, T, kappa)
    nc = int(min(N_COUPLING_DEPTH, max(32, np.ceil(rho * A_e * h_end / COUPLING_DZ))))
    dz = h_end / nc
    hc = (np.arange(nc) + 0.5) * dz
    zc = f.z_top_um + hc
    b1 = rho * A * dz * np.stack([np.interp(zc, z, row) for row in B1m])  # (M, nc)
    tl = np.stack([np.interp(zc, z, row) for row in Tl])  # (M, nc)
    lam = rho * hc * A_e * (1.0 - T)
    lam_b = rho * hc[None, :] * (2.0 * (A_e - L[:, None]) * (1.0 - T) + L[:, None] * (1.0 - T * T))  # (ns, nc)
    c0 = 1.0 - (L / A_e) * (1.0 - T)  # (ns,)
    k_ex = rho * (1.0 - T) * (1.0 - tl)  # (M, nc)
    F_h = _drift_integral(tab, drift, hc)  # (ns, M, nc) over the heights above each cell
    n = np.arange(nc)
    F_d = _drift_integral(tab, drift, n * dz)  # (ns, M, nc): up to the lower flake's height Δ = n dz above the upper
    dw, g = tab[0], tab[1]
    gb = _lerp_rows(g, dw, np.asarray(drift, float)[:, None] * (n * dz)[None, :]) / A_e  # (ns, M, nc) blocking share
    up = np.exp(-lam_b + lam[None, :])  # (ns, nc)
    U1 = up * np.einsum("mk,smk->sk", b1, np.exp(k_ex[None] * F_h))  # F1's light with its exclusion
    U0 = up * b1.sum(axis=0)[None, :]
    V = b1 * np.exp(-lam)[None, :]  # (M, nc)
    k_i, l_i = np.meshgrid(n, n, indexing="ij")
    upper = l_i >= k_i
    wt = np.where(upper, np.where(l_i == k_i, 0.5, 1.0), 0.0)  # (nc, nc) k ≤ l, ½ on the diagonal
    d_i = np.where(upper, l_i - k_i, 0)
    out = np.empty(L.size)
    for s0 in range(0, L.size, 8):
        sl = slice(s0, s0 + 8)
        # F2's exclusion over the heights above z1: ∫ from Δ to Δ + h1 = F(h_l) − F(Δ)
        X2 = k_ex[None, :, None, :] * (F_h[sl][:, :, None, :] - F_d[sl][:, :, d_i])  # (s, M, k, l)
        blk = c0[sl, None, None, None] - (1.0 - tl)[None, :, None, :] * gb[sl][:, :, d_i]
        W = np.einsum("ml,smkl->skl", V, blk * np.exp(X2))  # (s, k, l)
        corr = np.einsum("sk,skl,kl->s", U1[sl], W, wt)
        base = c0[sl] * np.einsum("sk,l,kl->s", U0[sl], V.sum(axis=0), wt)
        out[sl] = 2.0 * (corr - base)
    return out


def mosaic_variance(f, z, B1n, B2n, T, kappa, spot_um, light=None, coupling=None):
    """(mean, variance) of a p × p spot's luminance factor under the sky for flake layer ``f``, each view ray
    seeing the flakes it meets in depth order (docs/texture.md §4, eq. G5): the topmost alone when they are
    opaque (a mosaic), those below through T per flake crossed when they transmit.  Valid at any coverage.

    Var = p⁻⁴ ∫ (E[ββ](s) − mean²) s K̄(s) ds (:func:`_square_ring`) with the two-point moment of
    :func:`mosaic_pair_moment` (the arguments are its), zero beyond the largest diameter (and, with the sky
    coupling, its reach).  Sparse flakes: Var → N_A⟨O(0)⟩E[b²] (eq. G2)."""
    Dn, _ = f.diameters()
    # offsets: C(s) = 0 beyond the largest flake, K̄(s) = 0 beyond √2 p; Gauss rules between the kinks (p, where
    # K̄ changes form, and each diameter node, where its covariogram ends)
    p = float(spot_um)
    coupled = (SKY_COUPLING if coupling is None else coupling) and light is not None and len(light) > 3
    # with the sky coupling (eq. G6) two rays farther apart than a flake still correlate: an upper flake over x
    # reaches the lower flake's sky path up to its drift × the depth a ray reaches away
    reach = _coupling_reach(f, T, kappa, light) if coupled else 0.0
    s_end = min(float(Dn.max()) + reach, np.sqrt(2.0) * p)
    br = np.unique(np.concatenate([[0.0, s_end], [p], Dn]))
    br = br[br <= s_end]
    x, wx = leggauss(N_MOSAIC_OFFSET)
    lo_, hi_ = br[:-1, None], br[1:, None]
    ss = (0.5 * (hi_ - lo_) * (x + 1.0) + lo_).ravel()
    ws = (0.5 * (hi_ - lo_) * wx).ravel()
    mean, moment = mosaic_pair_moment(f, z, B1n, B2n, T, kappa, ss, light, coupled)
    var = float(np.sum(ws * ss * _square_ring(p, ss.tobytes()) * (moment - mean * mean))) / p**4
    return mean, var


def mosaic_pair_moment(f, z, B1n, B2n, T, kappa, s_um, light=None, coupling=None):
    """(mean, E[β(x)β(x+s)] at the offsets ``s_um`` (ns,) µm) of the per-ray luminance factor under the sky for
    flake layer ``f``, each view ray seeing the flakes it meets in depth order (docs/texture.md §4, eqs. G5, G6):
    the topmost alone when they are opaque (a mosaic), those below through T per flake crossed when they transmit.

    The flakes are a Poisson process of discs (ρ per µm³, diameters log-normal); a view ray meets them at the
    rate ρ A_e per µm of depth, A_e = κ⟨A⟩ (κ = P(μ_v')/μ_v', the solver's projected area), and two rays s apart
    meet a common flake at the rate ρ L(s), L = κ⟨lens(s; r, r)⟩ (the footprints' covariogram, taken as discs).
    With B1(z) (per µm of depth: the luminance the flakes at z give before the view's crossings, ``B1n`` × ρ⟨A⟩)
    and B2(z) (a ray's second moment, ``B2n``) on the depth nodes ``z`` (interpolated to a uniform grid), the
    two-point moment is, by the Poisson generating functional (Λ_b = ρ h [2(A_e − L)(1 − T) + L(1 − T²)], h the
    depth below the layer's top, Λ = ρ h A_e (1 − T)):

        E[β(x)β(x+s)] = ∫ ρ L B2 e^{−Λ_b} dz + 2 ∫∫_{z1<z2} B1(z1) (1 − (L/A_e)(1 − T)) e^{−Λ_b(z1) + Λ(z1)} B1(z2) e^{−Λ(z2)} dz2 dz1,

    the first term one flake covering both points, the second two flakes, the upper one dimming the lower's
    ray where it covers both.  ``T``: a crossed flake's luminance transmittance on the view path.  ``light``:
    (Q, λ_l', T_l) per normal and depth (:func:`_sky_terms`), so that two rays on one flake share only the
    crossings of their sky paths both meet (ℓ(s) = ⟨lens⟩/⟨A⟩ of them); without it B2 (s-independent: the two
    rays' sky paths blocked together).  With (…, B1 per normal, the sky path's drift per normal) and ``coupling``
    (default :data:`SKY_COUPLING`), the sky paths' coupling to the mosaic (eq. G6, :func:`_coupling_two_flakes`):
    the upper flake blocking the lower's sky path and the flakes the mosaic excludes from both sky paths."""
    rho = float(f.number_density_per_um3)
    Dn, Dw = f.diameters()
    A_e = kappa * f.mean_area_um2()
    # cells thin against the depth a ray travels between flakes (ρ A_e dz ≤ 0.01): the midpoint rule's error
    nu = int(min(max(N_MOSAIC_DEPTH, np.ceil(rho * A_e * f.thickness_um / 0.01)), 20000))
    dz = f.thickness_um / nu
    zu = f.z_top_um + (np.arange(nu) + 0.5) * dz
    h = zu - f.z_top_um
    b1 = rho * f.mean_area_um2() * np.interp(zu, z, B1n) * dz
    b2 = np.interp(zu, z, B2n) * dz  # (nu,), or per offset below
    lam = rho * h * A_e * (1.0 - T)
    e1 = b1 * np.exp(-lam)
    mean = float(e1.sum())
    ss = np.asarray(s_um, float)
    coupled = (SKY_COUPLING if coupling is None else coupling) and light is not None and len(light) > 3
    reach = _coupling_reach(f, T, kappa, light) if coupled else 0.0
    rr = 0.5 * Dn[:, None]
    L = kappa * (Dw @ _lens_area_sq(np.broadcast_to(ss, (Dn.size, ss.size)), ss * ss, rr, rr, equal=True))  # (ns,)
    lam_b = rho * h[None, :] * (2.0 * (A_e - L[:, None]) * (1.0 - T) + L[:, None] * (1.0 - T * T))  # (ns, nu)
    if light is not None:
        # two rays on one flake s apart: their mirrored sky paths (parallel) meet a flake above in common at the
        # share ℓ(s) = ⟨lens(s)⟩/⟨A⟩ of their crossings, each its own otherwise (partial occlusion of the sky path)
        Qm, lo, Tl = light[:3]  # (M, nz): Σ_c-luminance² × weight / footprint, the light path's own crossings, its T
        ell = (L / kappa) / f.mean_area_um2()
        ex = -lo[None] * (ell[:, None, None] * (1 - Tl[None] ** 2) + 2.0 * (1.0 - ell[:, None, None]) * (1 - Tl[None]))
        if coupled:
            # eq. G6: the share of the two paths' crossings they have in common is that of the flakes covering
            # both path points but neither ray, ℓ(s, m, h) = ∫⟨S⟩/∫κ⟨A − lens⟩ along the path (ℓ = lens(s)/A
            # above is its limit far above the flake); and no flake above covers either ray, so neither sky path
            # meets the flakes that cover the other ray only (each path's own were already left out)
            tab = _coupling_table(f, ss, kappa, reach)
            hz = z - f.z_top_um
            g_m = np.asarray(light[4], float)[:, None]
            q = g_m * hz[None, :]  # (M, nz) the drift at the flake's height
            own = _integral_rows(*tab[4], tab[0], q)[0]
            ell = np.where(own > 1e-12 * kappa * f.mean_area_um2(), _integral_rows(*tab[3], tab[0], q) / np.maximum(own, 1e-300), 0.0)
            ex = -lo[None] * (2.0 * (1 - Tl[None]) - ell * (1 - Tl[None]) ** 2)
            Fz = _drift_integral(tab, light[4], hz)  # (ns, M, nz)
            ex += 2.0 * rho * (1.0 - T) * (1.0 - Tl[None]) * Fz
        B2s = np.einsum("mz,smz->sz", Qm, np.exp(ex))  # (ns, nz)
        b2 = np.stack([np.interp(zu, z, row) for row in B2s]) * dz  # (ns, nu)
        one = rho * (L / kappa) * np.sum(np.exp(-lam_b) * b2, axis=1)
    else:
        one = rho * (L / kappa) * (np.exp(-lam_b) @ b2)  # flakes covering both, ρκ⟨lens⟩, × E_hit[b²] = B2/κ
    G = np.cumsum(e1[::-1])[::-1] - 0.5 * e1  # Σ_{l ≥ k} (½ on the diagonal) B1_l e^{−Λ_l}
    two = 2.0 * (1.0 - (L / A_e) * (1.0 - T)) * (np.exp(-lam_b + lam[None, :]) @ (b1 * G))
    if coupled:
        two += _coupling_two_flakes(f, z, light, T, kappa, L, tab)
    return mean, one + two


def graininess_indices(stack: TextureStack, observer, ground_luminance_factor=None, memo=None) -> dict:
    """Graininess under a uniform sky (docs/texture.md §4): the spot-to-spot relative standard
    deviation of luminance, G = σ(β_spot)/⟨β_spot⟩, for resolved spots of side ``observer.spot_um``
    viewed at ``observer.view_deg``.

    Each flake mirrors the sky: its luminance factor is b = T_in T_out R(|v'·m|) w (0 if the mirrored
    direction is totally internally reflected at the coat or points down).  Spots collect a Poisson
    number of flakes: ⟨β⟩ = Σ N_A ⟨A⟩ E[b], Var β = Σ N_A ⟨A²/(A + a)⟩ E[b²] / a … (docs/texture.md
    eq. G2).  ``ground_luminance_factor``: the paint's total luminance factor under the sky (its
    directional albedo at the view), which replaces the flakes' mean in the denominator; without
    it G is the flake-only value (not a bound: docs/texture.md §1).  ``memo``: as :func:`sparkle_indices` (keeps
    :func:`_sky_terms`).  Returns a dict; where the variance comes out ≤ 0 (the hiding term cancels the
    single-flake term: thick, dense flake layers) ``graininess`` is None, ``valid`` False and ``note`` says why."""
    mean, var_single, var_pair = 0.0, 0.0, 0.0
    for i_f, f in enumerate(stack.flakes):
        key = ("sky", i_f, float(observer.view_deg))
        if memo is None or key not in memo:
            terms = _sky_terms(stack, f, float(observer.view_deg))
            if memo is not None:
                memo[key] = terms
        else:
            terms = memo[key]
        Eb, Eb2, z, wz, b0, lam_v, tau_y, (B1, B2, T_vy, P_v, light) = terms
        Dn, Dw = f.diameters()
        A = 0.25 * np.pi * Dn * Dn
        NA = f.areal_density_per_um2
        mean += NA * float(Dw @ A) * Eb
        var_single += NA * float(Dw @ overlap_integral(Dn, observer.spot_um)) * Eb2
        # each ray sees the flakes it meets in depth order (the mosaic, eq. G5): valid at any coverage
        _, v = mosaic_variance(f, z, B1, B2, T_vy, P_v, observer.spot_um, light)
        var_pair += v
    var_pair -= var_single  # what hiding changes: the mosaic's variance over the flakes' independent sum
    var = var_single + var_pair
    out = {
        "view_deg": float(observer.view_deg),
        "flake_luminance_factor": mean,
        # the mosaic's variance over the independent flakes' (eq. G2), minus 1: 0 for sparse flakes, → −1 where hiding dominates
        "pair_over_single": var_pair / var_single if var_single > 0 else 0.0,
    }
    if not np.isfinite(out["pair_over_single"]):  # overflowing terms (a layer of thousands of µm): no ratio to give
        out["pair_over_single"] = None
    if not (np.isfinite(var) and var > 0.0):
        # a variance that is not finite or ≤ 0 (overflowing terms: a layer of thousands of µm): no number to give
        out.update(luminance_sd=None, valid=False,
                   note=("graininess not predicted: the spot variance is not a finite positive number (mosaic "
                         + (f"{out['pair_over_single']:+.2f}×" if out["pair_over_single"] is not None else "not finite beside")
                         + " the independent-flake variance; docs/texture.md §4, Validity)"))
    else:
        out.update(luminance_sd=float(np.sqrt(var)), valid=True)
    return graininess_grounded(out, ground_luminance_factor)


def graininess_grounded(row: dict, ground_luminance_factor=None) -> dict:
    """A :func:`graininess_indices` row with G = luminance_sd / ground, the ground being
    ``ground_luminance_factor`` (the paint's luminance factor under the sky) or, when None, the flakes'
    own mean (not a bound on G); ``ground`` says which; G is None where the row is not ``valid``
    (as :func:`sparkle_grounded`: the ground enters nothing else)."""
    ground = float(ground_luminance_factor) if ground_luminance_factor is not None else row["flake_luminance_factor"]
    sd = row["luminance_sd"]
    g = None if not row["valid"] else (sd / ground if ground > 0 else 0.0)
    return dict(row, ground="bsdf" if ground_luminance_factor is not None else "flakes", graininess=g)


def texture_indices_grounded(entry: dict, ground=None) -> dict:
    """A :func:`texture_indices` entry grounded on ``ground`` ({"directional": {light_deg: β}, "diffuse": β},
    or None: the flakes' own means), by :func:`sparkle_grounded` and :func:`graininess_grounded`."""
    ground = ground or {}
    gd = ground.get("directional", {})
    return dict(entry, directional=[sparkle_grounded(r, gd.get(float(r["light_deg"]))) for r in entry["directional"]],
                diffuse=graininess_grounded(entry["diffuse"], ground.get("diffuse")))


def texture_indices(stack: TextureStack, observer, ground=None, memo=None) -> dict:
    """Every index of one observer: one :func:`sparkle_indices` row per light angle and the
    :func:`graininess_indices`.  ``ground``: optional {"directional": {light_deg: β}, "diffuse": β}
    from the smooth BSDF.  ``memo``: an optional dict shared by the calls of several observers on the
    same ``stack``: what depends on the light and view directions only is computed once."""
    ground = ground or {}
    gd = ground.get("directional", {})
    rows = [sparkle_indices(stack, observer, a, gd.get(float(a)), memo=memo) for a in observer.light_deg]
    return {"observer": observer.name, "spot_um": float(observer.spot_um),
            "aperture_half_angle_rad": float(observer.aperture_half_angle_rad),
            "source_half_angle_deg": float(observer.source_half_angle_deg),
            "directional": rows, "diffuse": graininess_indices(stack, observer, ground.get("diffuse"), memo=memo)}
