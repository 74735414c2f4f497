"""The translucent micro-flake medium of Ergun et al. (paper eq. 2, 5-8; docs/model.md §3), as pure functions.

Every direction, ``mu`` and ``phi_d`` here follows :mod:`flakedb.conventions` ("conventions"):
directions are *propagation* directions, ``mu > 0`` travels down, a direction is
``(sqrt(1-mu²) cos φ, sqrt(1-mu²) sin φ, -mu)`` in the frame whose z axis is the surface normal
(up), ``phi_d = phi_o - phi_i`` and ``phi_d = 0`` is forward scattering / mirror reflection.
Lengths in µm, so ``a_rho_per_um`` (flake area × number density, µm² · µm⁻³) is in 1/µm and the
coefficients σ_t, σ_s are in 1/µm; kernels ``σ_s f_p`` are in 1/(µm·sr).

The model (docs/model.md §3, paper eq. 2), flakes of area a, number density ρ, normal density D(m) on the
unit sphere (∫ D dm = 1, D(m) = D(−m)), reflectance R(c) and transmittance T(c) of the flake at
c = |ω·m| (transmitted light goes on undeviated):

    σ_t(ω) = aρ ∫ (1 − T(|ω·m|)) |ω·m| D(m) dm
    σ_s(ω) = aρ ∫ R(|ω·m|) |ω·m| D(m) dm
    σ_s f_p(ω_i → ω_o) = (aρ/4) R(|ω_i·h|) (D(h) + D(−h)),   h = normalize(ω_o − ω_i)

``ω_i`` is the propagation direction of the incoming light, so the halfway vector of the *flake
reflection* ω_o = ω_i − 2 (ω_i·m) m is ±normalize(ω_o − ω_i) (the paper's h(ω, −ω')).  The factor
1/4 is the Jacobian of the half-vector map, dω_o = 4 |ω_i·h| dh, and (D(h) + D(−h)) counts both
faces of the (two-sided) flake; with D(h) = D(−h) the kernel is (aρ/2) R D(h).  Useful identity:
the flake cosine is c = |ω_i·h| = |ω_o − ω_i| / 2 = sin(Θ/2), Θ the scattering angle.

Flake normals follow a density D from the registry :data:`FLAKE_DISTRIBUTIONS` (colour-science's
``method=`` style: every function that takes the orientation spread ``alpha`` takes
``distribution="beckmann"`` too, docs/model.md §3 "Flake orientation distributions"):

* ``"beckmann"``, the paper's density on the sphere (eq. 5), D(m) = exp(−tan²θ_m/α²) / (2π α² |cos θ_m|³)
  (:func:`flake_ndf_Beckmann`);
* ``"ggx"``, Trowbridge–Reitz (Trowbridge & Reitz 1975; Walter et al. 2007 eq. 33 as a microfacet
  density), in the flake convention D(m) = α² / (2π |cos θ_m|³ (α² + tan²θ_m)²) (:func:`flake_ndf_GGX`).

* ``"student_t(γ)"``, Student-t slopes (Ribardière et al. 2017), a tail shape 1.5 ≤ γ ≤ 1000 from heavier
  than GGX through GGX (γ = 2) to Beckmann (γ → ∞) (:func:`flake_ndf_StudentT`);
* ``"mix(first,w,second,α₂)"``, two populations: 1 − w of ``first`` at the α of the call, w of ``second``
  at α₂.

All are even, D(m) = D(−m), and integrate to 1 over the whole sphere (each hemisphere 1/2): the
microfacet density of that name times |cos θ_m|/2.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = [
    "FlakeOptics",
    "FlakeDistribution",
    "FLAKE_DISTRIBUTIONS",
    "DEFAULT_DISTRIBUTION",
    "flake_distribution",
    "flake_ndf",
    "flake_ndf_Beckmann",
    "flake_ndf_GGX",
    "flake_ndf_StudentT",
    "flake_lobe_alpha",
    "FLAKE_DISTRIBUTION_FAMILIES",
    "STUDENT_T_SHAPE_RANGE",
    "MIXTURE_WEIGHT_RANGE",
    "MIXTURE_ALPHA_RANGE",
    "FLAKE_ALPHA_RANGE",
    "projected_area",
    "ndf_halfvector_Ergun",
    "projected_area_Beckmann",
    "extinction_Ergun",
    "scattering_Ergun",
    "kernel_Ergun",
    "kernel_phi_bandwidth",
    "phase_HG",
    "pigment_kernel_Ergun",
    "pigment_extinction_Ergun",
    "pigment_scattering_Ergun",
    "UNIFORM_NDF_PER_SR",
    "sample_flake_normal",
    "sample_flake_normal_Beckmann",
    "sample_flake_normal_GGX",
    "sample_flake_normal_StudentT",
]

#: The uniform flake-normal density on the sphere used for pigments (paper eq. 8), 1/(4π) per sr.
UNIFORM_NDF_PER_SR = 1.0 / (4.0 * np.pi)

_TWO_PI = 2.0 * np.pi


# ---------------------------------------------------------------------------------------------
# Flake optics container
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FlakeOptics:
    """Reflectance R(c) and transmittance T(c) of one flake species, per spectral channel.

    ``c``: (nc,) strictly ascending grid on [0, 1] of the flake cosine c = |ω·m| (cosine between the
    light's direction and the flake normal).  ``R``, ``T``: (C, nc) arrays, channels × c, dimensionless.
    Between nodes R and T are linear in c; outside [c[0], c[-1]] they are held constant (like
    ``numpy.interp``).  Requires 0 ≤ R, 0 ≤ T and R + T ≤ 1 (+1e-12): what is neither reflected nor
    transmitted is absorbed (docs/model.md §3).
    """

    c: np.ndarray
    R: np.ndarray
    T: np.ndarray

    def __post_init__(self):
        c = np.asarray(self.c, dtype=float)
        R = np.asarray(self.R, dtype=float)
        T = np.asarray(self.T, dtype=float)
        if c.ndim != 1 or c.size < 1:
            raise ValueError(f"FlakeOptics.c must be a 1-D grid of flake cosines, got shape {c.shape}")
        if not np.all(np.isfinite(c)) or c[0] < 0.0 or c[-1] > 1.0 or np.any(np.diff(c) <= 0.0):
            raise ValueError(
                "FlakeOptics.c must be strictly ascending within [0, 1] (c = |ω·m|, the cosine of the "
                f"angle of incidence on the flake); got {c!r}. Sort it and drop duplicates."
            )
        if R.ndim == 1:
            R = R[None, :]
        if T.ndim == 1:
            T = T[None, :]
        if R.shape != T.shape or R.ndim != 2 or R.shape[1] != c.size:
            raise ValueError(
                f"FlakeOptics.R and .T must both have shape (channels, {c.size}) (channels × c), got "
                f"R {R.shape} and T {T.shape}."
            )
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(T))):
            raise ValueError("FlakeOptics.R and .T must be finite.")
        if np.any(R < 0.0) or np.any(T < 0.0):
            raise ValueError(
                f"FlakeOptics needs R >= 0 and T >= 0; min R = {R.min():.3g}, min T = {T.min():.3g}."
            )
        excess = R + T - 1.0
        if np.any(excess > 1e-12):
            ch, k = np.unravel_index(np.argmax(excess), excess.shape)
            raise ValueError(
                f"FlakeOptics needs R + T <= 1 (energy conservation); channel {ch}, c = {c[k]:.6g} has "
                f"R + T = {R[ch, k] + T[ch, k]:.15g}. Rescale the flake optics or check the thin-film solver."
            )
        object.__setattr__(self, "c", c)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "T", T)

    @classmethod
    def constant(cls, R, T, channels=1):
        """Flake optics independent of c.  ``R``, ``T``: scalars or (C,) arrays (one per channel);
        scalars are repeated over ``channels``."""
        R = np.atleast_1d(np.asarray(R, dtype=float)).ravel()
        T = np.atleast_1d(np.asarray(T, dtype=float)).ravel()
        nch = channels if (R.size == 1 and T.size == 1) else max(R.size, T.size)
        R = np.broadcast_to(R, (nch,))
        T = np.broadcast_to(T, (nch,))
        return cls(np.array([0.0, 1.0]), np.repeat(R[:, None], 2, axis=1), np.repeat(T[:, None], 2, axis=1))

    @property
    def channels(self) -> int:
        return self.R.shape[0]

    def _interp(self, table, c):
        c = np.asarray(c, dtype=float)
        xp = self.c
        if xp.size == 1:
            return np.broadcast_to(table[:, :1].reshape((-1,) + (1,) * c.ndim), (table.shape[0],) + c.shape).copy()
        cc = np.clip(c, xp[0], xp[-1])
        j = np.clip(np.searchsorted(xp, cc, side="right") - 1, 0, xp.size - 2)
        slope = np.diff(table, axis=1) / np.diff(xp)
        intercept = table[:, :-1] - slope * xp[:-1]
        out = np.empty((table.shape[0],) + c.shape)
        for k in range(table.shape[0]):  # one gather per channel: C is small, points are many
            out[k] = intercept[k].take(j) + slope[k].take(j) * cc
        return out

    def reflectance(self, c):
        """R(c) for c = |ω·m| of any shape → (C, *c.shape), linear interpolation in c."""
        return self._interp(self.R, c)

    def transmittance(self, c):
        """T(c) for c = |ω·m| of any shape → (C, *c.shape), linear interpolation in c."""
        return self._interp(self.T, c)

    def _segments(self):
        """Edges e (K+1,) of the pieces on which R, T are linear, with 0 and 1 included, and the
        tables evaluated there (C, K+1)."""
        e = np.unique(np.concatenate([[0.0], self.c, [1.0]]))
        return e, self.reflectance(e), self.transmittance(e)


# ---------------------------------------------------------------------------------------------
# Flake normal density (paper eq. 5) and its closed form at the half vector (eq. 6-7)
# ---------------------------------------------------------------------------------------------


def _check_alpha(alpha):
    a = np.asarray(alpha, dtype=float)
    if not np.all(np.isfinite(a)) or np.any(a <= 0.0):
        raise ValueError(f"alpha (the spread of the flake orientations) must be finite and > 0, got {alpha!r}")
    return a


def flake_ndf_Beckmann(cos_theta_m, alpha):
    """Beckmann flake-normal density on the sphere, paper eq. 5, in 1/sr:

        D(m) = exp(−tan²θ_m / α²) / (2π α² |cos θ_m|³),    cos θ_m = m·z.

    It is even, D(m) = D(−m) (a flake has no front or back), and integrates to 1 over the **whole
    sphere**: in t = tan θ_m, D dm = exp(−t²/α²) t dt dφ / (2π α²), so each hemisphere carries 1/2.
    (The factor π instead of 2π would be the microfacet convention, normalised over one hemisphere.)
    The slope tan θ_m·(cos φ_m, sin φ_m) of the upper-hemisphere normal is an isotropic Gaussian with
    variance α²/2 per component.  ``cos_theta_m`` and ``alpha`` broadcast; cos θ = 0 gives 0 (limit).
    """
    alpha = _check_alpha(alpha)
    c = np.minimum(np.abs(np.asarray(cos_theta_m, dtype=float)), 1.0)
    pos = c > 1e-150  # below, exp(−tan²θ/α²) < exp(−1e300): exactly 0 in double precision
    c_safe = np.where(pos, c, 1.0)
    with np.errstate(over="ignore", under="ignore"):
        log_d = -((1.0 - c_safe) * (1.0 + c_safe)) / (alpha * c_safe) ** 2 - 3.0 * np.log(c_safe)
        return np.where(pos, np.exp(log_d), 0.0) / (_TWO_PI * alpha**2)


def flake_ndf_GGX(cos_theta_m, alpha):
    """GGX (Trowbridge–Reitz) flake-normal density on the sphere, in 1/sr, in the flake convention of
    :func:`flake_ndf_Beckmann` (even, ∫_{S²} D dm = 1):

        D(m) = α² / (2π |cos θ_m|³ (α² + tan²θ_m)²) = α² c / (2π (α² c² + 1 − c²)²),   c = |cos θ_m|,

    the microfacet GGX density of Walter et al. 2007 (eq. 33), α²/(π cos⁴θ (α² + tan²θ)²), times
    |cos θ_m|/2.  Normalisation: in u = cos²θ_m the upper hemisphere carries
    ∫_0^1 α² du / (2 (α² u + 1 − u)²) = 1/2.  The slope tan θ_m of the upper-hemisphere normal has the
    heavy tail P(tan θ_m > t) = α²/(α² + t²).  Evaluated in the second form (no tan, no overflow at
    c = 0, where D = 0).  ``cos_theta_m`` and ``alpha`` broadcast.
    """
    alpha = _check_alpha(alpha)
    c = np.minimum(np.abs(np.asarray(cos_theta_m, dtype=float)), 1.0)
    a2 = alpha * alpha
    return a2 * c / (_TWO_PI * (a2 * c * c + (1.0 - c) * (1.0 + c)) ** 2)


def _sines(mu):
    mu = np.asarray(mu, dtype=float)
    return np.sqrt(np.maximum(0.0, (1.0 - mu) * (1.0 + mu)))


def _halfvector_terms(mu_i, mu_o, phi_d):
    """Stable pieces of h = normalize(ω_o − ω_i) (conventions): returns (dmu, num, two_f) with
    dmu = μ_i − μ_o = (ω_o − ω_i)_z, num = |(ω_o − ω_i)_xy|² = (s_i − s_o)² + 4 s_i s_o sin²(φ_d/2) and
    two_f = |ω_o − ω_i|² = dmu² + num = 2 (1 − μ_i μ_o − s_i s_o cos φ_d)."""
    mu_i, mu_o, phi_d = np.broadcast_arrays(
        np.asarray(mu_i, dtype=float), np.asarray(mu_o, dtype=float), np.asarray(phi_d, dtype=float)
    )
    s_i, s_o = _sines(mu_i), _sines(mu_o)
    dmu = mu_i - mu_o
    num = (s_i - s_o) ** 2 + 4.0 * s_i * s_o * np.sin(0.5 * phi_d) ** 2
    return dmu, num, dmu * dmu + num


def ndf_halfvector_Ergun(mu_i, mu_o, phi_d, alpha):
    """D(h(μ_i, μ_o, φ_d)) in closed form, paper eq. 6-7, in 1/sr, h = normalize(ω_o − ω_i).

    Derivation in flakedb's conventions (propagation directions, φ_d = φ_o − φ_i, 0 forward): with
    ω = (s cos φ, s sin φ, −μ), ω_o − ω_i has z component μ_i − μ_o and squared length
    2 f, f = 1 − μ_i μ_o − s_i s_o cos φ_d, so cos θ_h = (μ_i − μ_o)/√(2f) and
    tan²θ_h = (2 − μ_i² − μ_o² − 2 s_i s_o cos φ_d)/(μ_i − μ_o)².  Substituting in eq. 5 gives
    exactly the paper's form with μ = μ_i, μ' = μ_o, φ = φ_d (no sign flips are needed here):

        D = √2 f_rem exp(A + B cos φ_d) / (π α² |μ_i − μ_o|³),   f_rem = f^{3/2},
        A = (μ_i² + μ_o² − 2)/(α² (μ_i − μ_o)²),   B = 2 s_i s_o/(α² (μ_i − μ_o)²).

    The exponent A + B cos φ_d is evaluated as −[(s_i − s_o)² + 4 s_i s_o sin²(φ_d/2)]/(α²(μ_i−μ_o)²)
    (algebraically equal; no cancellation of two large terms for small α).  Symmetric in μ_i ↔ μ_o,
    even in φ_d.  Degenerate cases: μ_i = μ_o with ω_o ≠ ω_i has a horizontal h, where D → 0, and
    ω_o = ω_i (μ_i = μ_o and φ_d = 0 mod 2π, h undefined) returns 0, the limit along μ_o = μ_i.
    """
    alpha = _check_alpha(alpha)
    dmu, num, two_f = _halfvector_terms(mu_i, mu_o, phi_d)
    ok = np.abs(dmu) > 1e-150  # below, h is horizontal to double precision (or undefined): D = 0
    adm = np.where(ok, np.abs(dmu), 1.0)
    with np.errstate(over="ignore", under="ignore"):
        exponent = -num / (alpha * adm) ** 2  # = A + B cos φ_d
        f = 0.5 * two_f
        log_d = 1.5 * np.log(np.where(ok, f, 1.0)) + exponent - 3.0 * np.log(adm)
        return np.where(ok, np.sqrt(2.0) * np.exp(log_d) / (np.pi * alpha**2), 0.0)


# ---------------------------------------------------------------------------------------------
# σ_t and σ_s (paper eq. 2): 2-D quadrature over the flake normal, closed form in the azimuth
# ---------------------------------------------------------------------------------------------

_GL_CACHE: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _smoothstep_gauss_legendre(n):
    """n-point Gauss-Legendre nodes on v ∈ [0, 1] pushed through t = 3v² − 2v³ (weights include
    dt/dv = 6v(1−v)).  The map has zero slope at both ends, which turns the √-type endpoint
    behaviour of the azimuthal integrals at panel breakpoints into analytic behaviour."""
    if n not in _GL_CACHE:
        x, w = np.polynomial.legendre.leggauss(n)
        v = 0.5 * (x + 1.0)
        _GL_CACHE[n] = (v * v * (3.0 - 2.0 * v), 0.5 * w * 6.0 * v * (1.0 - v))
    return _GL_CACHE[n]


def _azimuth_moments_halves(a, b, c):
    """∫_0^π 1[lo < a + b cos φ < hi] (a + b cos φ)^j dφ, j = 0, 1, 2, in closed form (b ≥ 0), for the two
    halves (lo, hi) = (0, c) and (−c, 0) of |a + b cos φ| < c: ``((g0, g1, g2) of (0, c), (g0, g1, g2) of
    (−c, 0))``.  The set is φ ∈ (arccos x_hi, arccos x_lo), x = (level − a)/b clipped to [−1, 1], so with
    p = arccos x: ∫ dφ = Δp, ∫ cos φ dφ = Δ sin p, ∫ cos² φ dφ = Δp/2 + Δ sin 2p/4, and sin p = √(1 − x²),
    sin 2p = 2x√(1 − x²): three arccos and three square roots for both halves (the level 0 is shared) instead
    of four arccos and eight sines.  b = 0: x = sign(level − a) (the whole or none of the half-circle)."""
    pos = b > 0.0
    b_safe = np.where(pos, b, 1.0)

    def cut(level):
        x = np.clip(np.where(pos, (level - a) / b_safe, np.sign(level - a)), -1.0, 1.0)
        sq = np.sqrt(1.0 - x * x)
        return np.arccos(x), sq, x * sq

    def moments(lo, hi):  # lo, hi: (arccos x, sin p, sin p cos p) at the two levels
        dp = lo[0] - hi[0]
        ds = lo[1] - hi[1]
        ds2 = 2.0 * (lo[2] - hi[2])
        return dp, a * dp + b * ds, a * a * dp + 2.0 * a * b * ds + b * b * (0.5 * dp + 0.25 * ds2)

    top, mid, bottom = cut(c), cut(0.0), cut(-c)
    return moments(mid, top), moments(bottom, mid)


def _abs_cosine_moments_Beckmann(mu_abs, alpha, levels, n_quad):
    """Φ_j(μ, c) = ∫_{S²} 1[|ω·m| < c] |ω·m|^j D(m) dm, j = 0, 1, 2, for D of eq. 5.

    ``mu_abs`` (M,), ``levels`` (K,) in (0, 1] → array (3, M, K).  Quadrature: upper hemisphere
    (×2 by D(m) = D(−m)) in t = tan θ_m with weight exp(−t²/α²) t/(2πα²); the azimuth integral of
    the flake cosine ω·m = a + b cos φ_m (a = −|μ| cos θ_m, b = s sin θ_m) over the set where
    |ω·m| < c, split at ω·m = 0, is done in closed form (:func:`_azimuth_moments_halves`); the t integral is
    split into panels at every t where an azimuthal breakpoint enters or leaves [0, π]
    (ω·m ∈ {−c, 0, c} at φ_m = 0 or π: θ_m ∈ {γ − θ, θ − γ, θ + γ}, γ = arccos(−x)), plus a few fixed
    splits at multiples of α, and each panel uses smoothstep-mapped Gauss-Legendre (``n_quad`` nodes).
    """
    t_max = np.sqrt(40.0) * alpha  # exp(−40) ≈ 4e-18 of the weight lies beyond

    def nodes(t, dt_w):  # t = tan θ_m; weight exp(−t²/α²) t/(2πα²) dt
        inv = 1.0 / np.sqrt(1.0 + t * t)
        return dt_w * t * np.exp(-((t / alpha) ** 2)) / (_TWO_PI * alpha**2), inv, t * inv

    return _polar_panel_moments(mu_abs, levels, n_quad, np.tan, np.arctan(t_max), t_max,
                                np.minimum(alpha * np.array([0.5, 1.0, 1.5, 2.0, 3.0, 4.0]), t_max), nodes, 16)


def _polar_panel_moments(mu_abs, levels, n_quad, var_of_theta, theta_end, var_end, fixed, nodes, width):
    """Φ_j(μ, c), j = 0, 1, 2 (array (3, M, K) for ``mu_abs`` (M,), ``levels`` (K,)): the polar integral of
    an even, azimuthally symmetric density in a variable u of θ_m (``var_of_theta``, increasing, u = ``var_end``
    at θ_m = ``theta_end``), in panels between the azimuthal breakpoints (:func:`_breakpoint_angles`) that fall
    in (0, ``theta_end``) and the ``fixed`` splits (in u), each with smoothstep-mapped Gauss-Legendre
    (``n_quad`` nodes).  ``nodes(u, du_w)`` → (weight, cos θ_m, sin θ_m) at the nodes u, ``du_w`` the
    panel width × the rule's weights; the azimuth is done by :func:`_accumulate_azimuth`.  ``width`` sizes
    the chunks over μ (≈ the panels per (μ, c) row)."""
    mu_abs = np.asarray(mu_abs, dtype=float)
    levels = np.asarray(levels, dtype=float)
    M, K = mu_abs.size, levels.size
    v, wv = _smoothstep_gauss_legendre(n_quad)
    out = np.empty((3, M, K))
    chunk = max(1, int(2_000_000 // max(1, K * width * n_quad)))
    for m0 in range(0, M, chunk):
        mu = mu_abs[m0 : m0 + chunk][:, None]  # (m, 1)
        m = mu.shape[0]
        th = np.arccos(np.clip(mu, -1.0, 1.0))
        s = np.sqrt(np.maximum(0.0, 1.0 - mu * mu))
        lev = levels[None, :]  # (1, K)
        bp = _breakpoint_angles(th, lev, m, K)
        inside = (bp > 0.0) & (bp < theta_end)
        bp = np.where(inside, var_of_theta(np.where(inside, bp, 0.0)), var_end)
        bp = np.concatenate(
            [np.zeros((m, K, 1)), bp, np.broadcast_to(fixed, (m, K, fixed.size)), np.full((m, K, 1), var_end)],
            axis=-1,
        )
        bp.sort(axis=-1)
        n_used = int(np.max(np.sum(bp < var_end, axis=-1))) + 1  # columns up to the first var_end
        bp = bp[..., : n_used + 1]
        ua, ub = bp[..., :-1, None], bp[..., 1:, None]  # (m, K, P, 1)
        wt, ct, st = nodes(ua + (ub - ua) * v, (ub - ua) * wv)
        mu4, s4 = mu[..., None, None], s[..., None, None]
        _accumulate_azimuth(out, slice(m0, m0 + m), wt, -mu4 * ct, s4 * st, lev)
    return out


def _breakpoint_angles(th, lev, m, K):
    """The polar angles θ_m (m, K, 9) where an azimuthal breakpoint of the flake cosine
    ω·m = −|μ| cos θ_m + s sin θ_m cos φ_m ∈ {−c, 0, c} enters or leaves [0, π] (at φ_m = 0 or π):
    θ_m ∈ {γ − θ, θ − γ, θ + γ}, γ = arccos(−x), for ``th`` (m, 1) = arccos |μ| and ``lev`` (1, K)
    the levels c.  Candidates outside (0, π/2) are the caller's to discard."""
    cands = []
    for x in (-lev, np.zeros_like(lev), lev):
        g = np.arccos(np.clip(-x, -1.0, 1.0))
        cands += [g - th, th - g, th + g]
    return np.stack([np.broadcast_to(cc, (m, K)) for cc in cands], axis=-1)


def _accumulate_azimuth(out, rows, wt, a, b, lev):
    """out[j, rows] = Σ over the polar nodes of ``wt`` × ∫ 1[|ω·m| < c] |ω·m|^j dφ_m over the whole
    azimuth and both hemispheres, with ω·m = a + b cos φ_m (a = −|μ| cos θ_m, b = s sin θ_m; arrays
    (m, K, P, n_quad)) and ``wt`` the polar weights of the density on the upper hemisphere (D even)."""
    # the top level c = 1 must include |ω·m| = 1 exactly (μ = ±1 and θ_m → 0 give a = −1 in floats)
    c4 = np.where(lev >= 1.0, 1.0 + 1e-9, lev)[..., None, None]
    (p0, p1, p2), (n0, n1, n2) = _azimuth_moments_halves(a, b, c4)
    # ×2 for φ_m ∈ [π, 2π], ×2 for the lower hemisphere
    out[0, rows] = 4.0 * np.sum(wt * (p0 + n0), axis=(-1, -2))
    out[1, rows] = 4.0 * np.sum(wt * (p1 - n1), axis=(-1, -2))
    out[2, rows] = 4.0 * np.sum(wt * (p2 + n2), axis=(-1, -2))


#: Fixed panel splits of the GGX polar quadrature, in units of α (θ_m = arctan(k α)): the core of
#: width ≈ α and the algebraic tail ∝ α²/θ³, each panel spanning at most a factor 2 in tan θ_m.
_GGX_SPLITS = np.array([0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0])


def _abs_cosine_moments_GGX(mu_abs, alpha, levels, n_quad):
    """Φ_j(μ, c) = ∫_{S²} 1[|ω·m| < c] |ω·m|^j D(m) dm, j = 0, 1, 2, for the GGX density
    (:func:`flake_ndf_GGX`).  Same output as :func:`_abs_cosine_moments_Beckmann`; the polar
    integral is done in θ_m ∈ [0, π/2] (the slope tail of GGX is heavy, ∝ 1/t³, so no finite cut in
    t = tan θ_m is exact), with the bounded, smooth weight D sin θ_m =
    α² sin θ_m cos θ_m / (2π (α² cos²θ_m + sin²θ_m)²), panels at the same azimuthal breakpoints
    (:func:`_breakpoint_angles`) and at θ_m = arctan(k α), k in :data:`_GGX_SPLITS`."""
    a2 = alpha * alpha

    def nodes(tq, dt_w):  # θ_m; weight D sin θ_m dθ_m
        ct, st = np.cos(tq), np.sin(tq)
        return dt_w * a2 * st * ct / (_TWO_PI * (a2 * ct * ct + st * st) ** 2), ct, st

    half_pi = 0.5 * np.pi
    return _polar_panel_moments(mu_abs, levels, n_quad, lambda th: th, half_pi, half_pi,
                                np.arctan(alpha * _GGX_SPLITS), nodes, 26)


@functools.lru_cache(maxsize=16)
def _abs_cosine_moments_cached(mu_bytes, alpha, levels_bytes, n_quad, distribution="beckmann"):
    """The distribution's moments Φ_j (:attr:`FlakeDistribution.abs_cosine_moments`, e.g.
    :func:`_abs_cosine_moments_Beckmann`) of float64 arrays given as bytes, cached (read-only result):
    a flake slab's σ_t and σ_s (and their repeats per solve) integrate the same moments at the same
    nodes and c-levels (measured: 3 of the 9 s of a direct tri-coat compose at n = 64 were repeats)."""
    moments = FLAKE_DISTRIBUTIONS[distribution].abs_cosine_moments
    out = moments(np.frombuffer(mu_bytes), alpha, np.frombuffer(levels_bytes), n_quad)
    out.flags.writeable = False
    return out


def _piecewise_linear_cosine_integral(mu, alpha, table_edges, edges, n_quad, distribution="beckmann"):
    """∫ F(|ω·m|) |ω·m| D(m) dm for F linear on each [e_k, e_{k+1}] with values ``table_edges``
    (C, K+1) at ``edges`` (K+1,) → (C, *mu.shape).  Exact in F: uses the moments Φ_1, Φ_2."""
    mu = np.asarray(mu, dtype=float)
    flat = np.abs(mu).ravel()
    uniq, inverse = np.unique(flat, return_inverse=True)
    phi = _abs_cosine_moments_cached(uniq.tobytes(), float(alpha), np.asarray(edges[1:], float).tobytes(),
                                     int(n_quad), flake_distribution(distribution).name)  # (3, M, K)
    zeros = np.zeros((uniq.size, 1))
    m1 = np.diff(np.concatenate([zeros, phi[1]], axis=1), axis=1)  # (M, K) segment moments
    m2 = np.diff(np.concatenate([zeros, phi[2]], axis=1), axis=1)
    slope = np.diff(table_edges, axis=1) / np.diff(edges)  # (C, K)
    intercept = table_edges[:, :-1] - slope * edges[None, :-1]
    val = intercept @ m1.T + slope @ m2.T  # (C, M)
    return val[:, inverse].reshape((table_edges.shape[0],) + mu.shape)


def projected_area(mu, alpha, n_quad=24, distribution="beckmann"):
    """Mean projected area of a unit two-sided flake, ∫_{S²} |ω·m| D(m) dm (dimensionless), for D of
    ``distribution`` (:data:`FLAKE_DISTRIBUTIONS`); even in μ, → |μ| as α → 0 (flakes parallel to the
    surface).  Shape of ``mu``."""
    alpha = float(_check_alpha(alpha))
    edges = np.array([0.0, 1.0])
    return _piecewise_linear_cosine_integral(mu, alpha, np.ones((1, 2)), edges, n_quad, distribution)[0]


def projected_area_Beckmann(mu, alpha, n_quad=24):
    """:func:`projected_area` of the Beckmann density (eq. 5)."""
    return projected_area(mu, alpha, n_quad, "beckmann")


def extinction_Ergun(mu, alpha, optics: FlakeOptics, a_rho_per_um, n_quad=24, distribution="beckmann"):
    """Extinction coefficient σ_t(μ) = aρ ∫ (1 − T(|ω·m|)) |ω·m| D(m) dm (paper eq. 2), in 1/µm.

    ``mu`` (any shape, conventions; the result is even in μ and independent of φ since D is
    azimuthally symmetric), ``alpha`` the orientation spread of D (``distribution``, a key of
    :data:`FLAKE_DISTRIBUTIONS`; Beckmann: eq. 5), ``optics`` a :class:`FlakeOptics`,
    ``a_rho_per_um`` flake area × number density (µm²/µm³ = 1/µm).  Returns (C, *mu.shape).
    The integral is exact in the piecewise-linear T (moments of |ω·m| on each c-segment) and the
    quadrature over the flake normal reaches ~1e-13 relative at the default ``n_quad`` = 24
    (tests/rt/test_microflake.py; GGX: tests/rt/test_flake_distributions.py, 4e-14 against an independent
    quadrature).
    """
    alpha = float(_check_alpha(alpha))
    edges, _, T_e = optics._segments()
    return a_rho_per_um * _piecewise_linear_cosine_integral(mu, alpha, 1.0 - T_e, edges, n_quad, distribution)


def scattering_Ergun(mu, alpha, optics: FlakeOptics, a_rho_per_um, n_quad=24, distribution="beckmann"):
    """Scattering coefficient σ_s(μ) = aρ ∫ R(|ω·m|) |ω·m| D(m) dm (paper eq. 2), in 1/µm.

    Same arguments and accuracy as :func:`extinction_Ergun`; returns (C, *mu.shape).  Equals
    ∫_{S²} :func:`kernel_Ergun` dω_o (the kernel's normalisation).
    """
    alpha = float(_check_alpha(alpha))
    edges, R_e, _ = optics._segments()
    return a_rho_per_um * _piecewise_linear_cosine_integral(mu, alpha, R_e, edges, n_quad, distribution)


# ---------------------------------------------------------------------------------------------
# The scattering kernel σ_s f_p (paper eq. 2)
# ---------------------------------------------------------------------------------------------


def kernel_Ergun(mu_i, mu_o, phi_d, alpha, optics: FlakeOptics, a_rho_per_um, distribution="beckmann"):
    """Flake scattering kernel σ_s f_p(ω_i → ω_o) = (aρ/4) R(|ω_i·h|) (D(h) + D(−h)), paper eq. 2, in
    1/(µm·sr), with h = normalize(ω_o − ω_i) of the propagation directions (conventions).

    ``mu_i``, ``mu_o``, ``phi_d`` broadcast (conventions: μ > 0 travels down, φ_d = 0 forward);
    returns (C, *broadcast shape).  Both reflection (μ_i μ_o < 0: light turned back by flakes near
    the surface orientation) and transmission-like scattering (μ_i μ_o > 0: steep flakes) occur.
    The flake cosine is c = |ω_i·h| = |ω_o − ω_i|/2.  ω_o = ω_i (h undefined, c = 0) gives 0, the
    limit along μ_o = μ_i, where h is horizontal and D(h) = 0.  Reciprocal:
    kernel(μ_i, μ_o, φ_d) = kernel(−μ_o, −μ_i, φ_d).  ``distribution``: D, a key of
    :data:`FLAKE_DISTRIBUTIONS` (Beckmann: eq. 5).
    """
    ndf = flake_distribution(distribution).ndf
    alpha = _check_alpha(alpha)
    dmu, _, two_f = _halfvector_terms(mu_i, mu_o, phi_d)
    ok = two_f > 0.0
    length = np.sqrt(np.where(ok, two_f, 1.0))
    cos_h = np.where(ok, dmu / length, 0.0)  # h_z of h = (ω_o − ω_i)/|ω_o − ω_i|
    c = np.where(ok, 0.5 * length, 0.0)
    d = ndf(cos_h, alpha)  # D(h) = D(−h)
    return (0.25 * a_rho_per_um) * optics.reflectance(c) * (2.0 * d)


def _beckmann_peak(alpha):
    """max_m D(m) of eq. 5: D = (1+x)^{3/2} e^{−x/α²}/(2πα²) in x = tan²θ peaks at x = max(0, 1.5α² − 1)."""
    x = np.maximum(0.0, 1.5 * alpha**2 - 1.0)
    return (1.0 + x) ** 1.5 * np.exp(-x / alpha**2) / (_TWO_PI * alpha**2)


def _ggx_peak(alpha):
    """max_m D(m) of :func:`flake_ndf_GGX`: D = α² (1+x)^{3/2} / (2π (α² + x)²) in x = tan²θ peaks at
    x = max(0, 3α² − 4) (d log D/dx = 3/(2(1+x)) − 2/(α²+x))."""
    alpha = np.asarray(alpha, dtype=float)
    x = np.maximum(0.0, 3.0 * alpha**2 - 4.0)
    return alpha**2 * (1.0 + x) ** 1.5 / (_TWO_PI * (alpha**2 + x) ** 2)


def kernel_phi_bandwidth(alpha, mu_i, mu_o, eps=1e-6, distribution="beckmann"):
    """First guess of the number L of cosine orders in φ_d needed for the kernel at (μ_i, μ_o), for
    the flake distribution ``distribution`` (:data:`FLAKE_DISTRIBUTIONS`; Beckmann:
    :func:`_kernel_phi_bandwidth_Beckmann`, GGX: :func:`_kernel_phi_bandwidth_GGX`).  Returns an int
    array of the broadcast shape of (mu_i, mu_o, alpha)."""
    return flake_distribution(distribution).kernel_bandwidth(alpha, mu_i, mu_o, eps)


def _kernel_phi_bandwidth_Beckmann(alpha, mu_i, mu_o, eps=1e-6):
    """First guess of the number L of cosine orders in φ_d needed for the Beckmann kernel at (μ_i, μ_o).

    Criterion: the neglected coefficients of D(h(μ_i, μ_o, ·)) beyond order L are below
    ``eps`` × max_m D(m) (the kernel's global peak scale; for constant R this is the relative error
    of the kernel in the sup norm).  From eq. 6-7, D(φ) = (1 + x(φ))^{3/2} e^{−x(φ)/α²}/(2πα²) with
    x = tan²θ_h = x_0 + κ sin²(φ/2), x_0 = (s_i − s_o)²/(μ_i − μ_o)², κ = 4 s_i s_o/(μ_i − μ_o)²:

    * the Gaussian factor e^{−κ sin²(φ/2)/α²} = e^{−B(1 − cos φ)} (B of eq. 7) has exact cosine
      coefficients 2 I_l(B) e^{−B}; its lobe width in φ is ≈ 1/√B = α|μ_i − μ_o|/√(2 s_i s_o)
      (for mirror reflection μ_o = −μ_i: √2 α μ/s = √2 α cot θ, which is narrow at grazing angles);
      L_B is the first l with (P/D_max) 2 I_{l+1}(B) e^{−B} ≤ eps, P the pair's peak of D over φ;
    * the factor (1 + x)^{3/2} is analytic with geometric decay r^l, r = q − √(q² − 1),
      q = (1 − μ_i μ_o)/(s_i s_o); L_f = log(eps D_max/P)/log r;

    and L = L_B + L_f (spectra of a product convolve).  For transmission-like pairs close to the
    diagonal (μ_o → μ_i, same sign) B grows like 1/(μ_i − μ_o)² and so does L: the kernel has a
    bounded but direction-dependent limit at ω_o = ω_i (near-forward scattering by steep flakes);
    cap L as the solver's error budget allows.  A tabulated R(c) with kinks adds an algebraic tail
    this estimate does not cover: check convergence in the projector.  Returns int array of the
    broadcast shape of (mu_i, mu_o, alpha).
    """
    from scipy.special import ive  # lazy: scipy.special takes 0.15 s to import (flakedb.rt.basis.special); only this bandwidth estimate needs it
    alpha = _check_alpha(alpha)
    mu_i, mu_o, alpha = np.broadcast_arrays(np.asarray(mu_i, float), np.asarray(mu_o, float), alpha)
    s_i, s_o = _sines(mu_i), _sines(mu_o)
    dmu = mu_i - mu_o
    adm2 = np.maximum(dmu * dmu, 1e-300)
    x0 = (s_i - s_o) ** 2 / adm2
    kappa = 4.0 * s_i * s_o / adm2
    x_star = np.clip(np.maximum(0.0, 1.5 * alpha**2 - 1.0), x0, x0 + kappa)
    peak = (1.0 + x_star) ** 1.5 * np.exp(-x_star / alpha**2) / (_TWO_PI * alpha**2)
    ratio = np.where(dmu != 0.0, peak / _beckmann_peak(alpha), 0.0)
    B = 0.5 * kappa / alpha**2
    need = ratio > eps
    # L_B by vectorised bisection on the monotone sequence I_l(B) e^{-B}
    lo = np.zeros(mu_i.shape)
    hi = np.ceil(np.sqrt(2.0 * B * np.log(2.0 / eps)) + 4.0 * np.log(2.0 / eps) + 2.0)
    for _ in range(64):
        mid = np.floor(0.5 * (lo + hi))
        bad = ratio * 2.0 * ive(mid + 1.0, B) > eps
        lo = np.where(bad, mid + 1.0, lo)
        hi = np.where(bad, hi, mid)
        if np.all(lo >= hi):
            break
    L_B = hi
    q = np.where(s_i * s_o > 0.0, (1.0 - mu_i * mu_o) / np.maximum(s_i * s_o, 1e-300), np.inf)
    log_r = -np.arccosh(np.maximum(q, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        L_f = np.where(need & (log_r < 0.0), np.ceil(np.log(eps / np.maximum(ratio, 1e-300)) / log_r), 0.0)
    L = np.where(need, L_B + np.maximum(L_f, 0.0), 0.0)
    L = np.where(s_i * s_o > 0.0, L, 0.0)  # μ = ±1: D(h) does not depend on φ_d
    return L.astype(np.int64)


def _kernel_phi_bandwidth_GGX(alpha, mu_i, mu_o, eps=1e-6):
    """First guess of the number L of cosine orders in φ_d needed for the GGX kernel at (μ_i, μ_o), by
    the criterion of :func:`_kernel_phi_bandwidth_Beckmann` (neglected coefficients of D(h(μ_i, μ_o, ·))
    below ``eps`` × max_m D).  With x = tan²θ_h = x_0 + κ sin²(φ/2) (same x_0, κ),

        D(φ) = α² (1 + x)^{3/2} / (2π (α² + x)²) = α² (1 + x)^{3/2} / (2π (a − b cos φ)²),
        a = α² + x_0 + κ/2,  b = κ/2,

    and the rational factor has exact cosine coefficients: from 1/(a − b cos φ) = (1 + 2 Σ r^l cos lφ)/√Δ,
    Δ = a² − b² = (α² + x_0)(α² + x_0 + κ), r = b/(a + √Δ), differentiating in a gives
    c_l = 2 r^l (l/Δ + a/Δ^{3/2}) (l ≥ 1).  Geometric, not Gaussian: GGX needs more orders than Beckmann
    at the same α.  L_G is the first L whose tail Σ_{l>L} c_l (closed form, decreasing in L), relative
    to the factor's peak 1/(a − b)² and times (P/D_max), is ≤ ``eps`` (P the pair's peak of D over φ);
    L_f of the (1 + x)^{3/2} factor as for Beckmann; L = L_G + L_f.  A tabulated R(c) with kinks adds
    a tail this does not cover: the projector checks convergence.
    """
    alpha = _check_alpha(alpha)
    mu_i, mu_o, alpha = np.broadcast_arrays(np.asarray(mu_i, float), np.asarray(mu_o, float), alpha)
    s_i, s_o = _sines(mu_i), _sines(mu_o)
    dmu = mu_i - mu_o
    adm2 = np.maximum(dmu * dmu, 1e-300)
    x0 = (s_i - s_o) ** 2 / adm2
    kappa = 4.0 * s_i * s_o / adm2
    a2 = alpha**2
    x_star = np.clip(np.maximum(0.0, 3.0 * a2 - 4.0), x0, x0 + kappa)
    peak = a2 * (1.0 + x_star) ** 1.5 / (_TWO_PI * (a2 + x_star) ** 2)
    ratio = np.where(dmu != 0.0, peak / _ggx_peak(alpha), 0.0)
    need = (ratio > eps) & (s_i * s_o > 0.0)
    amb = a2 + x0  # a − b
    a = amb + 0.5 * kappa
    sq = np.sqrt(amb * (amb + kappa))  # √Δ
    r = np.where(kappa > 0.0, 0.5 * kappa / (a + sq), 0.0)
    one_r = (amb + sq) / (a + sq)  # 1 − r without cancellation (r → 1 for narrow lobes)
    norm = amb * amb  # 1/(a − b)², the factor's value at φ = 0, inverted

    def tail(L):  # Σ_{l>L} c_l (a − b)², c_l = 2 r^l (l/Δ + a/Δ^{3/2})
        with np.errstate(under="ignore", over="ignore", invalid="ignore"):
            rl = r ** (L + 1.0)
            s0 = rl / one_r
            s1 = rl * ((L + 1.0) - L * r) / one_r**2
            return np.where(r > 0.0, 2.0 * norm * (s1 / sq**2 + a * s0 / sq**3), 0.0)

    hi = np.ones(mu_i.shape)
    for _ in range(80):  # doubling until the tail bound holds, then bisection
        bad = need & (ratio * tail(hi) > eps)
        if not np.any(bad):
            break
        hi = np.where(bad, 2.0 * hi, hi)
    lo = np.where(need, np.floor(0.5 * hi), 0.0)
    for _ in range(64):
        mid = np.floor(0.5 * (lo + hi))
        bad = need & (ratio * tail(mid) > eps)
        lo = np.where(bad, mid + 1.0, lo)
        hi = np.where(bad, hi, np.maximum(mid, lo))
        if np.all(lo >= hi):
            break
    L_G = np.where(need, hi, 0.0)
    q = np.where(s_i * s_o > 0.0, (1.0 - mu_i * mu_o) / np.maximum(s_i * s_o, 1e-300), np.inf)
    log_r = -np.arccosh(np.maximum(q, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        L_f = np.where(need & (log_r < 0.0), np.ceil(np.log(eps / np.maximum(ratio, 1e-300)) / log_r), 0.0)
    L = np.where(need, L_G + np.maximum(L_f, 0.0), 0.0)
    return L.astype(np.int64)


# ---------------------------------------------------------------------------------------------
# Student-t slopes (STD, Ribardière et al. 2017): a shape γ from GGX (γ = 2) to Beckmann (γ → ∞)
# ---------------------------------------------------------------------------------------------

#: Bounds of the Student-t shape γ.  γ ≥ 1.5: below, D(m) ∝ |cos θ_m|^{2γ−3} is unbounded at
#: horizontal normals (a singular kernel along μ_o = μ_i that no Fourier projection resolves; also
#: Ribardière et al.'s bound for a finite Smith Λ).  γ ≤ 1000: the density differs from Beckmann's by
#: O(x²/γ) in the core (x = tan²θ/α²); beyond, name the limit ``beckmann`` itself.
STUDENT_T_SHAPE_RANGE = (1.5, 1000.0)


def _check_shape(gamma):
    g = float(gamma)
    lo, hi = STUDENT_T_SHAPE_RANGE
    if not (np.isfinite(g) and lo <= g <= hi):
        raise ValueError(f"the Student-t shape gamma must be in [{lo:g}, {hi:g}] (1.5: heavier tail than GGX, "
                         f"2: GGX, large: Beckmann), got {gamma!r}")
    return g


def flake_ndf_StudentT(cos_theta_m, alpha, gamma):
    """Student-t flake-normal density on the sphere (STD, Ribardière et al. 2017), in 1/sr, in the flake
    convention of :func:`flake_ndf_Beckmann` (even, ∫_{S²} D dm = 1), shape ``gamma`` = γ ≥ 1.5:

        D(m) = (1 + tan²θ_m / (α² (γ − 1)))^{−γ} / (2π α² |cos θ_m|³)
             = k^γ c^{2γ−3} / (2π α² (k c² + 1 − c²)^γ),   k = α² (γ − 1),  c = |cos θ_m|,

    the microfacet STD, (γ−1)^γ / (π α² cos⁴θ ((γ−1) + tan²θ/α²)^γ), times |cos θ_m|/2.  The slope
    tan θ_m (cos φ, sin φ) of the upper-hemisphere normal is a bivariate Student t with ν = 2(γ − 1)
    degrees of freedom and scale α/√2 per component, so P(tan²θ_m > X) = (1 + X/k)^{1−γ} (the
    normalisation: each hemisphere 1/2).  γ = 2 is GGX exactly (:func:`flake_ndf_GGX`, k = α²);
    γ → ∞ gives Beckmann ((1 + y/γ)^{−γ} → e^{−y}, :func:`flake_ndf_Beckmann`); 1.5 ≤ γ < 2 has a
    heavier tail than GGX.  Evaluated as exp(−γ log1p(X/k) − 3 log c) (log1p(X/k) rewritten as
    log(k c² + s²) − log k − 2 log c where X/k > 1, no overflow at c → 0); c = 0 gives the limit,
    0 for γ > 1.5 and k^{3/2}/(2π α²) at γ = 1.5.  ``cos_theta_m`` and ``alpha`` broadcast.
    """
    alpha = _check_alpha(alpha)
    g = _check_shape(gamma)
    c = np.minimum(np.abs(np.asarray(cos_theta_m, dtype=float)), 1.0)
    k = alpha * alpha * (g - 1.0)
    s2 = (1.0 - c) * (1.0 + c)
    pos = c > 0.0
    cs = np.where(pos, c, 1.0)
    with np.errstate(over="ignore", under="ignore", divide="ignore"):
        q = s2 / (k * cs * cs)  # X/k = tan²θ/k (inf for c → 0 is not used)
        big = q > 1.0
        l1p = np.where(big, np.log(k * cs * cs + s2) - np.log(k) - 2.0 * np.log(cs), np.log1p(np.where(big, 0.0, q)))
        d = np.exp(-g * l1p - 3.0 * np.log(cs)) / (_TWO_PI * alpha**2)
    at0 = (k**1.5 / (_TWO_PI * alpha**2)) if g == 1.5 else 0.0
    return np.where(pos, d, at0)


def _student_t_tan2_of_p(p, alpha, gamma):
    """tan²θ_m at upper-hemisphere probability ``p`` = P(tan²θ_m ≤ X) of :func:`flake_ndf_StudentT`:
    X = k ((1 − p)^{−1/(γ−1)} − 1) = k expm1(−log1p(−p)/(γ − 1)), k = α² (γ − 1)."""
    with np.errstate(over="ignore", divide="ignore"):
        return alpha * alpha * (gamma - 1.0) * np.expm1(-np.log1p(-np.asarray(p, float)) / (gamma - 1.0))


def _student_t_p_of_tan2(x, alpha, gamma):
    """P(tan²θ_m ≤ x) = 1 − (1 + x/k)^{1−γ} on the upper hemisphere of :func:`flake_ndf_StudentT`."""
    return -np.expm1((1.0 - gamma) * np.log1p(np.asarray(x, float) / (alpha * alpha * (gamma - 1.0))))


def sample_flake_normal_StudentT(u1, u2, alpha, gamma):
    """Flake normals m distributed as :func:`flake_ndf_StudentT` restricted to the upper hemisphere
    (density 2 D(m)).  Closed-form inversion of P(tan²θ_m ≤ X) = 1 − (1 + X/k)^{1−γ}:
    tan²θ_m = k ((1 − u1)^{−1/(γ−1)} − 1), k = α²(γ − 1); φ_m = 2π u2.  Arguments and result as
    :func:`sample_flake_normal_Beckmann`."""
    alpha = _check_alpha(alpha)
    g = _check_shape(gamma)
    u1, u2 = np.broadcast_arrays(np.asarray(u1, float), np.asarray(u2, float))
    x = _student_t_tan2_of_p(u1, alpha, g)
    cos_t = 1.0 / np.sqrt(1.0 + x)
    sin_t = np.where(np.isfinite(x), np.sqrt(x) * cos_t, 1.0)
    phi = _TWO_PI * u2
    return np.stack(np.broadcast_arrays(sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t), axis=-1)


def _student_t_peak(alpha, gamma):
    """max_m D(m) of :func:`flake_ndf_StudentT`: in x = tan²θ, log D = (3/2) log(1 + x) − γ log(1 + x/k)
    + const has d/dx = 3/(2(1 + x)) − γ/(k + x), zero at x* = (2γ − 3k)/(3 − 2γ) (γ > 1.5:
    max(0, (3k − 2γ)/(2γ − 3)); γ = 2: 3α² − 4 as GGX); at γ = 1.5 D grows towards horizontal
    normals when k < 1 and the supremum is the limit at c = 0, k^{3/2}/(2π α²)."""
    alpha = np.asarray(alpha, dtype=float)
    g = float(gamma)
    k = alpha**2 * (g - 1.0)
    if g == 1.5:
        return np.maximum(1.0, k**1.5) / (_TWO_PI * alpha**2)
    x = np.maximum(0.0, (3.0 * k - 2.0 * g) / (2.0 * g - 3.0))
    return (1.0 + x) ** 1.5 * np.exp(-g * np.log1p(x / k)) / (_TWO_PI * alpha**2)


#: Fixed panel splits of the CDF-space polar quadrature (:func:`_abs_cosine_moments_cdf`), in units of
#: α (tan θ_m = k α): :data:`_GGX_SPLITS` and, for the heavier tails (γ < 2), further out to 16384 α.
_CDF_SPLITS = np.concatenate([_GGX_SPLITS, [1024.0, 4096.0, 16384.0]])


def _abs_cosine_moments_cdf(mu_abs, alpha, levels, n_quad, p_of_tan2, tan2_of_p):
    """Φ_j(μ, c) = ∫_{S²} 1[|ω·m| < c] |ω·m|^j D(m) dm, j = 0, 1, 2 (as :func:`_abs_cosine_moments_Beckmann`),
    for an azimuthally symmetric, even D given by its upper-hemisphere CDF in x = tan²θ_m,
    ``p_of_tan2(x)`` = P(tan²θ_m ≤ x) ∈ [0, 1], and its inverse ``tan2_of_p``.

    The polar integral is done in the probability p (the weight is then exactly uniform:
    D dm = dp dφ_m / (4π) on each hemisphere), so no density enters the quadrature and heavy tails
    (D ∝ |cos θ|^{2γ−3} near horizontal normals) cost nothing; panels in p at the azimuthal breakpoints
    (:func:`_breakpoint_angles`) and at tan θ_m = k α, k in :data:`_CDF_SPLITS`, each with
    smoothstep-mapped Gauss-Legendre (``n_quad`` nodes), which also regularises θ(p) ∝ √p at p = 0
    and the algebraic tail at p = 1."""

    def nodes(p, dp_w):  # p = P(tan²θ_m ≤ x); D dm = dp dφ_m / (4π) on each hemisphere
        x = tan2_of_p(p)
        ct = np.where(np.isfinite(x), 1.0 / np.sqrt(1.0 + np.where(np.isfinite(x), x, 0.0)), 0.0)
        return dp_w / (4.0 * np.pi), ct, np.sqrt(np.maximum(0.0, (1.0 - ct) * (1.0 + ct)))

    return _polar_panel_moments(mu_abs, levels, n_quad, lambda th: p_of_tan2(np.tan(th) ** 2), 0.5 * np.pi, 1.0,
                                p_of_tan2((alpha * _CDF_SPLITS) ** 2), nodes, 29)


def _abs_cosine_moments_StudentT(mu_abs, alpha, levels, n_quad, gamma):
    """Φ_j of :func:`flake_ndf_StudentT` (:func:`_abs_cosine_moments_cdf` with its closed-form CDF)."""
    return _abs_cosine_moments_cdf(mu_abs, alpha, levels, n_quad,
                                   lambda x: _student_t_p_of_tan2(x, alpha, gamma),
                                   lambda p: _student_t_tan2_of_p(p, alpha, gamma))


def _kernel_phi_bandwidth_numeric(ndf, peak, alpha, mu_i, mu_o, eps=1e-6):
    """The number L of cosine orders in φ_d of D(h(μ_i, μ_o, ·)), by the criterion of
    :func:`_kernel_phi_bandwidth_Beckmann` (Σ_{l>L} |a_l| ≤ ``eps`` × max_m D), for any density
    ``ndf(cos θ, α)`` with supremum ``peak(α)``: the cosine coefficients a_l from the FFT of N samples
    over [0, 2π) (N doubled from 64 until the top quarter of the spectrum is below eps/100 × the peak, at
    most 2^16).  Used where no closed form of the coefficients is known (Student-t, mixtures); vectorised
    over the pairs.  Returns an int array of the broadcast shape."""
    alpha = _check_alpha(alpha)
    mu_i, mu_o, alpha = np.broadcast_arrays(np.asarray(mu_i, float), np.asarray(mu_o, float), alpha)
    shape = mu_i.shape
    mi, mo, al = mu_i.ravel(), mu_o.ravel(), alpha.ravel()
    L = np.zeros(mi.size, dtype=np.int64)
    ok = (_sines(mi) * _sines(mo) > 0.0) & (mi != mo)
    todo = np.flatnonzero(ok)
    n = 64
    while todo.size and n <= 2**16:
        phi = _TWO_PI * np.arange(n) / n
        dmu, _, two_f = _halfvector_terms(mi[todo, None], mo[todo, None], phi[None, :])
        good = two_f > 0.0
        cos_h = np.where(good, dmu / np.sqrt(np.where(good, two_f, 1.0)), 0.0)
        d = ndf(cos_h, al[todo, None])
        a = np.abs(np.fft.rfft(d, axis=-1)) / n
        a[:, 1:] *= 2.0
        scale = eps * np.asarray(peak(al[todo]), float)[:, None]
        tail = np.cumsum(a[:, ::-1], axis=-1)[:, ::-1]  # tail[l] = Σ_{l' ≥ l} |a_l'|
        resolved = a[:, 3 * a.shape[1] // 4 :].max(axis=-1) <= 0.01 * scale[:, 0] / a.shape[1]
        if n == 2**16:
            resolved[:] = True
        below = tail <= scale
        first = np.where(below.any(axis=-1), np.argmax(below, axis=-1), a.shape[1])  # first l with Σ_{l'≥l} ≤ eps
        L[todo[resolved]] = np.maximum(first[resolved] - 1, 0)
        todo = todo[~resolved]
        n *= 2
    return L.reshape(shape)


def _numeric_peak(ndf, alpha, extra_cos=()):
    """sup_m D(m) of a density ``ndf(cos θ, α)`` (scalar α): the maximum over 4097 θ_m in [0, π/2] uniform
    in arctan(tan θ_m / α) (dense where the lobe is) and ``extra_cos``, refined by a bounded Brent search
    around the best node.  Used for mixtures, whose peak has no closed form."""
    from scipy.optimize import minimize_scalar  # lazy: scipy.optimize is slow to import; only mixtures need it
    a = float(alpha)
    u = np.linspace(0.0, 0.5 * np.pi, 4097)
    th = np.arctan(a * np.tan(np.minimum(u, 0.5 * np.pi - 1e-12)))
    th = np.concatenate([th, [0.5 * np.pi], np.arccos(np.clip(np.asarray(extra_cos, float), 0.0, 1.0))])
    d = ndf(np.cos(th), a)
    j = int(np.argmax(d))
    srt = np.sort(th)
    k = int(np.searchsorted(srt, th[j]))
    lo, hi = srt[max(k - 1, 0)], srt[min(k + 1, srt.size - 1)]
    best = float(d[j])
    if hi > lo:
        r = minimize_scalar(lambda t: -float(ndf(np.cos(t), a)), bounds=(lo, hi), method="bounded",
                            options={"xatol": 1e-12})
        best = max(best, -float(r.fun))
    return best


# ---------------------------------------------------------------------------------------------
# Pigments as micro-flakes (paper eq. 8)
# ---------------------------------------------------------------------------------------------


def phase_HG(cos_theta, g):
    """Henyey-Greenstein phase function p(cos Θ) = (1 − g²)/(4π (1 + g² − 2 g cos Θ)^{3/2}) in 1/sr,
    normalised to 1 over the sphere, mean cosine g; cos Θ = ω_i·ω_o of propagation directions
    (conventions: cos Θ = 1 is forward).  ``cos_theta`` and ``g`` (|g| < 1) broadcast.

    It integrates to 1 over the sphere and its mean cosine is g:

    >>> t, w = np.polynomial.legendre.leggauss(64)
    >>> p = phase_HG(t, 0.5)
    >>> round(float(2 * np.pi * np.sum(w * p)), 12), round(float(2 * np.pi * np.sum(w * p * t)), 12)
    (1.0, 0.5)
    """
    g = np.asarray(g, dtype=float)
    if np.any(np.abs(g) >= 1.0):
        raise ValueError(f"phase_HG needs |g| < 1 (mean cosine), got {g!r}")
    return (1.0 - g * g) / (4.0 * np.pi * (1.0 + g * g - 2.0 * g * np.asarray(cos_theta, float)) ** 1.5)


def _cos_scattering(mu_i, mu_o, phi_d):
    mu_i, mu_o, phi_d = np.broadcast_arrays(np.asarray(mu_i, float), np.asarray(mu_o, float), np.asarray(phi_d, float))
    return mu_i * mu_o + _sines(mu_i) * _sines(mu_o) * np.cos(phi_d)


def _per_channel(x, ndim):
    x = np.atleast_1d(np.asarray(x, dtype=float))
    if x.ndim != 1:
        raise ValueError(f"expected a scalar or a (channels,) array, got shape {x.shape}")
    return x.reshape((-1,) + (1,) * ndim)


def pigment_kernel_Ergun(mu_i, mu_o, phi_d, number_density_per_um3, c_sca_um2, phase):
    """Spherical pigments written as micro-flakes (paper eq. 8), kernel in 1/(µm·sr).

    Construction: uniform flake normals D(m) = 1/(4π) (:data:`UNIFORM_NDF_PER_SR`) and a flake
    "reflectance" depending on the direction pair, a R(ω_i → ω_o) = 8π C_sca p(ω_i·ω_o) (eq. 8 with
    the flake area a folded in: the paper's σ_s is the scattering cross section C_sca, its g the
    normalised phase function p).  Eq. 2's kernel then gives
    (ρ/4) · 8π C_sca p · (1/(4π) + 1/(4π)) = ρ C_sca p(cos Θ): the isotropic medium, so the paper's
    factor 8π is the right one for the properly normalised uniform density 1/(4π).  The matching
    σ_s = ρ ∫ a R |ω·m| D dm is ρ C_sca (half-vector Jacobian, see module docstring).
    The kernel is evaluated through that micro-flake construction (not short-cut).

    ``number_density_per_um3`` ρ (1/µm³), ``c_sca_um2`` C_sca (µm², scalar or (C,)), ``phase`` a
    callable p(cos Θ) in 1/sr (normalised over the sphere; cos Θ = ω_i·ω_o, 1 forward) returning
    the shape of its argument or (C, *shape).  Returns (C, *broadcast shape of the directions).
    """
    cos_t = _cos_scattering(mu_i, mu_o, phi_d)
    p = np.asarray(phase(cos_t), dtype=float)
    if p.ndim == cos_t.ndim:
        p = p[None]
    a_R = 8.0 * np.pi * _per_channel(c_sca_um2, cos_t.ndim) * p  # eq. 8 (area × reflectance, µm²)
    d = UNIFORM_NDF_PER_SR
    return 0.25 * number_density_per_um3 * a_R * (d + d)


def pigment_extinction_Ergun(mu, number_density_per_um3, c_ext_um2):
    """σ_t = ρ C_ext (1/µm) of pigments in the micro-flake form (paper eq. 2 with uniform D).

    Representation: with D = 1/(4π), ∫ |ω·m| D dm = 1/2 for every ω, so eq. 2 gives
    σ_t = aρ (1 − T)/2; the pigment is carried as opaque flakes (T = 0) of area a = 2 C_ext, so that
    σ_t = ρ C_ext, independent of direction, and eq. 8's a R = 8π C_sca p then means R = 4π ϖ p with
    ϖ = C_sca/C_ext the single-scattering albedo.  Returns (C, *mu.shape).
    """
    mu = np.asarray(mu, dtype=float)
    a_um2 = 2.0 * _per_channel(c_ext_um2, mu.ndim)
    T = 0.0
    return number_density_per_um3 * a_um2 * (1.0 - T) * 0.5 * np.ones_like(mu)


def pigment_scattering_Ergun(mu, number_density_per_um3, c_sca_um2):
    """σ_s = ρ C_sca (1/µm) of pigments in the micro-flake form: ρ ∫ a R(ω → ω_o(m)) |ω·m| D dm with
    a R = 8π C_sca p and D = 1/(4π) equals ρ C_sca for any normalised p.  Returns (C, *mu.shape)."""
    mu = np.asarray(mu, dtype=float)
    return number_density_per_um3 * _per_channel(c_sca_um2, mu.ndim) * np.ones_like(mu)


# ---------------------------------------------------------------------------------------------
# Sampling
# ---------------------------------------------------------------------------------------------


def sample_flake_normal_Beckmann(u1, u2, alpha):
    """Flake normals m distributed as eq. 5 restricted to the upper hemisphere (density 2 D(m)).

    Closed-form inversion: in t = tan θ_m the density is exp(−t²/α²) 2t/α² dt dφ/(2π), so
    tan²θ_m = −α² log(1 − u1) and φ_m = 2π u2.  ``u1``, ``u2`` ∈ [0, 1) broadcast with ``alpha``;
    returns unit vectors (..., 3) = (x, y, z), z the surface normal (up), z > 0.  For the full
    sphere flip the sign with probability 1/2 (D is even).
    """
    alpha = _check_alpha(alpha)
    u1, u2 = np.broadcast_arrays(np.asarray(u1, float), np.asarray(u2, float))
    tan2 = -(alpha**2) * np.log1p(-u1)
    cos_t = 1.0 / np.sqrt(1.0 + tan2)
    sin_t = np.sqrt(tan2) * cos_t
    phi = _TWO_PI * u2
    return np.stack(np.broadcast_arrays(sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t), axis=-1)


def sample_flake_normal_GGX(u1, u2, alpha):
    """Flake normals m distributed as :func:`flake_ndf_GGX` restricted to the upper hemisphere
    (density 2 D(m)).  Closed-form inversion: P(tan²θ_m ≤ X) = X/(α² + X), so
    tan²θ_m = α² u1/(1 − u1), i.e. cos θ_m = √((1 − u1)/(1 − u1 + α² u1)),
    sin θ_m = α √(u1/(1 − u1 + α² u1)), and φ_m = 2π u2.  Arguments and result as
    :func:`sample_flake_normal_Beckmann`."""
    alpha = _check_alpha(alpha)
    u1, u2 = np.broadcast_arrays(np.asarray(u1, float), np.asarray(u2, float))
    den = 1.0 - u1 + alpha**2 * u1
    cos_t = np.sqrt((1.0 - u1) / den)
    sin_t = alpha * np.sqrt(u1 / den)
    phi = _TWO_PI * u2
    return np.stack(np.broadcast_arrays(sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t), axis=-1)


def sample_flake_normal(u1, u2, alpha, distribution="beckmann"):
    """Upper-hemisphere flake normals (density 2 D(m)) of ``distribution`` (:data:`FLAKE_DISTRIBUTIONS`)
    from uniforms ``u1``, ``u2`` ∈ [0, 1); see :func:`sample_flake_normal_Beckmann`."""
    return flake_distribution(distribution).sample(u1, u2, alpha)


def flake_ndf_at_halfvector(mu_i, mu_o, phi_d, alpha, distribution="beckmann"):
    """D(h) of ``distribution`` (:data:`FLAKE_DISTRIBUTIONS`; Beckmann: eq. 5) at h = normalize(ω_o − ω_i)
    (conventions), in 1/sr, evaluated as :func:`kernel_Ergun` does (stable half-vector terms, then
    the density); for Beckmann the same value as the closed form :func:`ndf_halfvector_Ergun`
    (eq. 6-7).  Used by media whose R comes from elsewhere (the store)."""
    ndf = flake_distribution(distribution).ndf
    alpha = _check_alpha(alpha)
    dmu, _, two_f = _halfvector_terms(mu_i, mu_o, phi_d)
    ok = two_f > 0.0
    cos_h = np.where(ok, dmu / np.sqrt(np.where(ok, two_f, 1.0)), 0.0)
    return ndf(cos_h, alpha)


# ---------------------------------------------------------------------------------------------
# Spectral basis of the kernel (projection once for all channels; docs/projection.md)
# ---------------------------------------------------------------------------------------------


def table_basis(table, rtol=1e-13):
    """A low-rank factorisation of a per-channel table (C, n) → (M (C, B), basis (B, n)) with
    table = M @ basis up to ``rtol`` × its largest singular value (truncated SVD; B = numerical rank).

    Used to project kernels that are *linear* in a tabulated function of one variable (a flake's R(c),
    a phase function p(cos Θ)): the kernels of the B basis rows are projected once and the C channel
    kernels are their combinations M (docs/projection.md).  Rows equal up to a factor give B = 1.
    """
    table = np.atleast_2d(np.asarray(table, dtype=float))
    if not np.any(table):
        return np.zeros((table.shape[0], 1)), np.zeros((1, table.shape[1]))
    U, S, Vt = np.linalg.svd(table, full_matrices=False)
    B = max(1, int(np.sum(S > rtol * S[0])))
    return U[:, :B], S[:B, None] * Vt[:B]


def interp_rows(table, xp, x):
    """Linear interpolation of every row of ``table`` (B, n) on the ascending grid ``xp`` (n,) at ``x``
    (any shape), held constant outside [xp[0], xp[-1]] (as ``numpy.interp`` and
    :meth:`FlakeOptics.reflectance`), → (B, *x.shape).  The grid search is done once for all rows."""
    table = np.atleast_2d(np.asarray(table, dtype=float))
    x = np.asarray(x, dtype=float)
    if xp.size == 1:
        return np.broadcast_to(table[:, :1].reshape((-1,) + (1,) * x.ndim), (table.shape[0],) + x.shape).copy()
    xc = np.clip(x, xp[0], xp[-1])
    j = np.clip(np.searchsorted(xp, xc, side="right") - 1, 0, xp.size - 2)
    t = (xc - xp.take(j)) / (xp.take(j + 1) - xp.take(j))
    out = np.empty((table.shape[0],) + x.shape)
    for b in range(table.shape[0]):  # B basis rows (a handful): one gather each
        lo = table[b].take(j)
        out[b] = lo + (table[b].take(j + 1) - lo) * t
    return out


def kernel_Ergun_basis(mu_i, mu_o, phi_d, alpha, c_grid, R_basis, a_rho_per_um, distribution="beckmann"):
    """:func:`kernel_Ergun` for B basis rows ``R_basis`` (B, nc) of R(c) on ``c_grid`` (any sign; not a
    :class:`FlakeOptics`): (aρ/2) R_b(c) D(h), c = |ω_o − ω_i|/2, with the geometry (c, D(h))
    computed once for all rows.  Returns (B, *broadcast shape).  Linear in R, so a channel's kernel
    with R = Σ_b M[c, b] R_b is Σ_b M[c, b] × this (paper eq. 2).  ``distribution``: D, a key of
    :data:`FLAKE_DISTRIBUTIONS`."""
    ndf = flake_distribution(distribution).ndf
    alpha = _check_alpha(alpha)
    dmu, _, two_f = _halfvector_terms(mu_i, mu_o, phi_d)
    ok = two_f > 0.0
    length = np.sqrt(np.where(ok, two_f, 1.0))
    cos_h = np.where(ok, dmu / length, 0.0)
    c = np.where(ok, 0.5 * length, 0.0)
    d = ndf(cos_h, alpha)
    return (0.5 * a_rho_per_um) * interp_rows(R_basis, np.asarray(c_grid, dtype=float), c) * d[None]


# ---------------------------------------------------------------------------------------------
# The registry of flake orientation distributions (docs/model.md §3)
# ---------------------------------------------------------------------------------------------


def _phi_samples_Beckmann(alpha):
    """First number of φ intervals for projecting a Beckmann flake kernel: the mirror lobe's width in φ
    at 45° is ≈ √2 α (:func:`_kernel_phi_bandwidth_Beckmann`); a few samples per lobe width, a power of
    2 in [8, 2^20] (the projection refines adaptively)."""
    return int(2 ** np.ceil(np.log2(min(max(8.0, 8.0 * np.pi / (np.sqrt(2.0) * alpha)), 2.0**20))))


#: GGX's first guess of φ intervals over Beckmann's at the same α.  Measured with
#: :func:`kernel_phi_bandwidth` (eps 1e-6) at the 45° mirror pair μ_i = −μ_o = cos 45°: GGX needs
#: 1.3× (α = 1) to 2.5× (α = 0.02) the orders of Beckmann (its coefficients decay geometrically, the
#: Gaussian's faster), so twice the samples keep the first guess above the Nyquist count 2 L of that
#: lobe for α ∈ [0.02, 2] (tests/rt/test_microflake.py), as Beckmann's own guess is.
GGX_PHI_FACTOR = 2


def _phi_samples_GGX(alpha):
    """First number of φ intervals for projecting a GGX flake kernel: :data:`GGX_PHI_FACTOR` × the
    Beckmann guess at the same α (capped at 2^20).  Only a first guess: the projection doubles the
    samples until its coefficients converge (:func:`flakedb.rt.basis.fourier.project_azimuthal`)."""
    return int(min(GGX_PHI_FACTOR * _phi_samples_Beckmann(alpha), 2**20))


@dataclass(frozen=True)
class FlakeDistribution:
    """One flake orientation distribution of :data:`FLAKE_DISTRIBUTIONS`: a density D of flake normals
    on the unit sphere, even (D(m) = D(−m)), normalised (∫_{S²} D dm = 1, each hemisphere 1/2),
    azimuthally symmetric about the surface normal, with a spread ``alpha`` > 0 passed to every call
    (the distribution's other parameters, e.g. a Student-t shape or a mixture's second population, are
    bound in the entry).  The interface a generic consumer (solver, store, texture, references) uses:

    * ``ndf(cos_theta_m, alpha)`` → D in 1/sr, broadcasting (any sign of cos θ_m);
    * ``sample(u1, u2, alpha)`` → upper-hemisphere normals (..., 3), z up, of density 2 D(m), from
      uniforms u1, u2 ∈ [0, 1) (the slope tan θ_m = √(1 − z²)/z and φ_m follow); flip the sign with
      probability 1/2 for the full sphere;
    * ``abs_cosine_moments(mu_abs (M,), alpha, levels (K,), n_quad)`` → Φ_j(μ, c) =
      ∫ 1[|ω·m| < c] |ω·m|^j D dm, array (3, M, K), j = 0, 1, 2 (σ_t, σ_s, projected area; paper eq. 2);
      levels in (0, 1], the top level 1 includes |ω·m| = 1;
    * ``peak(alpha)`` → sup_m D (the scale of the bandwidth criterion);
    * ``kernel_bandwidth(alpha, mu_i, mu_o, eps)`` → cosine orders in φ_d of D(h) (:func:`kernel_phi_bandwidth`);
    * ``phi_samples(alpha)`` → the projection's first number of φ intervals (it refines adaptively);
    * ``name`` the canonical name (the store's key, the recipe's and the metadata's spelling);
      ``source`` the citation; ``family`` (``beckmann``, ``ggx``, ``student_t``, ``mix``) and
      ``parameters`` ((name, value) pairs of the bound parameters)."""

    name: str
    ndf: Callable
    peak: Callable
    abs_cosine_moments: Callable
    kernel_bandwidth: Callable
    phi_samples: Callable
    sample: Callable
    source: str
    family: str = ""
    parameters: tuple = ()


def _phi_samples_StudentT(alpha, gamma):
    """First number of φ intervals for projecting a Student-t flake kernel: γ ≥ 2 lies between GGX and
    Beckmann and takes GGX's guess (:func:`_phi_samples_GGX`); a heavier tail (γ < 2) has the pole of
    D(h(φ)) of GGX at α√(γ−1) instead of α (:func:`_kernel_phi_bandwidth_GGX`: α² + x = 0 becomes
    α²(γ − 1) + x = 0), so GGX's guess at α √(γ − 1).  Measured against
    :func:`_kernel_phi_bandwidth_numeric` in tests/rt/test_flake_shape.py."""
    return _phi_samples_GGX(alpha * min(1.0, np.sqrt(gamma - 1.0)))


def _format_number(x) -> str:
    """The canonical text of a parameter in a distribution's name: the shortest repr that round-trips
    the float (so equal parameters give equal names, the store's keys, and different ones differ)."""
    return repr(float(x))


def _student_t(gamma) -> "FlakeDistribution":
    g = _check_shape(gamma)
    return FlakeDistribution(
        f"student_t({_format_number(g)})",
        functools.partial(_ndf_student_t_bound, gamma=g),
        functools.partial(_student_t_peak, gamma=g),
        functools.partial(_abs_cosine_moments_StudentT, gamma=g),
        functools.partial(_kernel_bandwidth_student_t, gamma=g),
        functools.partial(_phi_samples_StudentT, gamma=g),
        functools.partial(_sample_student_t_bound, gamma=g),
        "Ribardière et al. 2017 (STD: Student's t-distribution of slopes), times |cos θ_m|/2 (flake convention)",
        family="student_t", parameters=(("gamma", g),))


def _ndf_student_t_bound(cos_theta_m, alpha, gamma):
    return flake_ndf_StudentT(cos_theta_m, alpha, gamma)


def _sample_student_t_bound(u1, u2, alpha, gamma):
    return sample_flake_normal_StudentT(u1, u2, alpha, gamma)


def _kernel_bandwidth_student_t(alpha, mu_i, mu_o, eps=1e-6, gamma=2.0):
    return _kernel_phi_bandwidth_numeric(functools.partial(flake_ndf_StudentT, gamma=gamma),
                                         functools.partial(_student_t_peak, gamma=gamma), alpha, mu_i, mu_o, eps)


#: Bounds of a two-population mixture's weight w of the second population (exclusive: w = 0 or 1 is
#: one population; name that distribution instead).
MIXTURE_WEIGHT_RANGE = (0.0, 1.0)
#: Bounds of a flake distribution's spread α (a recipe's ``orientation_alpha``, a mixture's α₂, ``build --alpha``;
#: the schemas restate them, tests/paint/test_limits.py checks): narrower than 0.001 no quadrature resolves.
FLAKE_ALPHA_RANGE = (0.001, 2.0)
#: Bounds of the second population's spread α₂: those of every flake spread.
MIXTURE_ALPHA_RANGE = FLAKE_ALPHA_RANGE


@dataclass(frozen=True)
class _Mixture:
    """D = (1 − w) D₁(·, α) + w D₂(·, α₂): the first population at the α every function is called with,
    the second at its own α₂ (bound here).  Every entry point is linear in D, so each is the weighted sum
    of the components' (moments, D) or a choice of component (sampling)."""

    first: "FlakeDistribution"
    weight: float
    second: "FlakeDistribution"
    alpha2: float

    def ndf(self, cos_theta_m, alpha):
        return (1.0 - self.weight) * self.first.ndf(cos_theta_m, alpha) + self.weight * self.second.ndf(
            cos_theta_m, self.alpha2)

    def abs_cosine_moments(self, mu_abs, alpha, levels, n_quad):
        return ((1.0 - self.weight) * self.first.abs_cosine_moments(mu_abs, alpha, levels, n_quad)
                + self.weight * self.second.abs_cosine_moments(mu_abs, self.alpha2, levels, n_quad))

    def sample(self, u1, u2, alpha):
        """u1 < 1 − w picks the first population (u1 rescaled to [0, 1) within it), else the second."""
        alpha = _check_alpha(alpha)
        u1, u2 = np.broadcast_arrays(np.asarray(u1, float), np.asarray(u2, float))
        w1 = 1.0 - self.weight
        first = u1 < w1
        m1 = self.first.sample(np.where(first, u1 / w1, 0.0), u2, alpha)
        m2 = self.second.sample(np.where(first, 0.0, np.minimum((u1 - w1) / self.weight, np.nextafter(1.0, 0.0))),
                                u2, self.alpha2)
        return np.where(first[..., None], m1, m2)

    def peak(self, alpha):
        a = np.asarray(alpha, dtype=float)
        if a.ndim:
            return np.array([self.peak(float(x)) for x in a.ravel()]).reshape(a.shape)
        return _numeric_peak(self.ndf, float(a), extra_cos=[1.0])

    def kernel_bandwidth(self, alpha, mu_i, mu_o, eps=1e-6):
        return _kernel_phi_bandwidth_numeric(self.ndf, self.peak, alpha, mu_i, mu_o, eps)

    def phi_samples(self, alpha):
        return max(self.first.phi_samples(alpha), self.second.phi_samples(self.alpha2))


def _mixture(first, weight, second, alpha2) -> "FlakeDistribution":
    w, a2 = float(weight), float(alpha2)
    lo, hi = MIXTURE_WEIGHT_RANGE
    if not (np.isfinite(w) and lo < w < hi):
        raise ValueError(f"a mixture's weight of the second population must be in ({lo:g}, {hi:g}) "
                         f"(exclusive: 0 or 1 is one population), got {weight!r}")
    lo, hi = MIXTURE_ALPHA_RANGE
    if not (np.isfinite(a2) and lo <= a2 <= hi):
        raise ValueError(f"a mixture's second spread alpha must be in [{lo:g}, {hi:g}], got {alpha2!r}")
    d1, d2 = flake_distribution(first), flake_distribution(second)
    if d1.family == "mix" or d2.family == "mix":
        raise ValueError("a mixture's populations must be single distributions (beckmann, ggx, student_t(γ)), "
                         "not mixtures")
    mx = _Mixture(d1, w, d2, a2)
    return FlakeDistribution(
        f"mix({d1.name},{_format_number(w)},{d2.name},{_format_number(a2)})",
        mx.ndf, mx.peak, mx.abs_cosine_moments, mx.kernel_bandwidth, mx.phi_samples, mx.sample,
        f"two populations: (1 − w) × [{d1.source}] + w × [{d2.source}]",
        family="mix", parameters=(("first", d1.name), ("weight", w), ("second", d2.name), ("alpha2", a2)))


def _split_arguments(text):
    """'a,b(c,d),e' → ['a', 'b(c,d)', 'e'] (commas at parenthesis depth 0)."""
    out, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        depth += (ch == "(") - (ch == ")")
        if depth < 0:
            raise ValueError("unbalanced parentheses")
        if ch == "," and depth == 0:
            out.append(text[start:i])
            start = i + 1
    if depth:
        raise ValueError("unbalanced parentheses")
    return [s.strip() for s in out + [text[start:]]]


@functools.lru_cache(maxsize=256)
def _parse_distribution(key: str) -> "FlakeDistribution":
    """The parametrised distribution named ``key`` (lower case, no spaces): ``student_t(γ)`` or
    ``mix(first, w, second, α₂)``; raises ValueError (the caller names the field)."""
    if "(" not in key or not key.endswith(")"):
        raise KeyError(key)
    family, args = key[: key.index("(")], _split_arguments(key[key.index("(") + 1 : -1])
    if family not in FLAKE_DISTRIBUTION_FAMILIES:
        raise KeyError(key)
    make, arity = FLAKE_DISTRIBUTION_FAMILIES[family]
    if len(args) != arity:
        raise ValueError(f"{family}(...) takes {arity} parameter(s), got {len(args)} in {key!r}")
    d = make(float(args[0])) if family == "student_t" else make(args[0], float(args[1]), args[2], float(args[3]))
    return _CANONICAL.setdefault(d.name, d)  # one object per canonical name, however it was spelled


#: The parametrised entries built so far, by canonical name (:func:`_parse_distribution`).
_CANONICAL: dict = {}


#: The parametrised families, name → (factory, number of parameters), spelled in a distribution's name
#: as ``family(p1,p2,…)`` (see :data:`FLAKE_DISTRIBUTIONS`).
FLAKE_DISTRIBUTION_FAMILIES = {
    "student_t": (_student_t, 1),
    "mix": (_mixture, 4),
}


class _Registry(dict):
    """:data:`FLAKE_DISTRIBUTIONS`: the fixed entries (``beckmann``, ``ggx``) as dict items, and every
    parametrised name (``student_t(γ)``, ``mix(…)``) built on lookup (``registry[name]``,
    ``name in registry``; cached), not listed by iteration (there are infinitely many)."""

    def __missing__(self, key):
        try:
            return _parse_distribution(str(key).replace(" ", "").lower())
        except ValueError as exc:
            raise ValueError(f"flake orientation distribution {key!r}: {exc}") from None

    def __contains__(self, key):
        try:
            self[key]
        except (KeyError, ValueError):
            return False
        return True


#: The flake orientation distributions by name (a recipe's orientation fields map to one of these names,
#: :func:`flakedb.paint.components.recipe_distribution`): ``beckmann`` (paper eq. 5), ``ggx``
#: (Trowbridge–Reitz), ``student_t(γ)`` (Student-t slopes, :func:`flake_ndf_StudentT`, 1.5 ≤ γ ≤ 1000:
#: γ = 2 is GGX, γ → ∞ Beckmann) and ``mix(first,w,second,α₂)`` (two populations: weight 1 − w of
#: ``first`` at the α of the call, w of ``second`` at α₂; populations are single distributions).  Names are
#: case-insensitive and canonicalised (numbers as their shortest round-trip repr, no spaces): the entry's
#: ``name``.  Iteration lists the fixed entries; parametrised names are built on lookup (``[name]``, ``in``).
#: Each entry is a :class:`FlakeDistribution` (its docstring lists the interface).
FLAKE_DISTRIBUTIONS = _Registry({
    "beckmann": FlakeDistribution(
        "beckmann", flake_ndf_Beckmann, _beckmann_peak, _abs_cosine_moments_Beckmann,
        _kernel_phi_bandwidth_Beckmann, _phi_samples_Beckmann, sample_flake_normal_Beckmann,
        "Ergun et al. 2016 eq. 5 (Beckmann, on the sphere)", family="beckmann"),
    "ggx": FlakeDistribution(
        "ggx", flake_ndf_GGX, _ggx_peak, _abs_cosine_moments_GGX, _kernel_phi_bandwidth_GGX,
        _phi_samples_GGX, sample_flake_normal_GGX,
        "Trowbridge & Reitz 1975; Walter et al. 2007 eq. 33, times |cos θ_m|/2 (flake convention)",
        family="ggx"),
})
#: The distribution of a flake that states none (every store and file written before the registry).
DEFAULT_DISTRIBUTION = "beckmann"


def flake_distribution(distribution) -> FlakeDistribution:
    """The :class:`FlakeDistribution` named ``distribution`` (case-insensitive; None: the default,
    Beckmann).  Raises ValueError naming the known ones."""
    key = DEFAULT_DISTRIBUTION if distribution is None else str(distribution).lower()
    try:
        return FLAKE_DISTRIBUTIONS[key]
    except KeyError:
        raise ValueError(f"unknown flake orientation distribution {distribution!r}; known: "
                         f"{', '.join(FLAKE_DISTRIBUTIONS)}, student_t(gamma) with "
                         f"{STUDENT_T_SHAPE_RANGE[0]:g} <= gamma <= {STUDENT_T_SHAPE_RANGE[1]:g}, and "
                         f"mix(first,weight,second,alpha2)") from None


def flake_lobe_alpha(alpha, distribution="beckmann") -> float:
    """The spread, on the scale of the α of ``beckmann`` and ``ggx``, of the narrowest lobe of
    ``distribution``'s flake normals: what a node-count rule measured for Beckmann and GGX at α
    (:func:`flakedb.paint.mapping.auto_resolution`) is applied to.  Beckmann, GGX: α.  Student-t: its core
    is Gaussian, D ∝ (1 + t²/(α²(γ−1)))^{−γ} ≈ exp(−γ t²/(α²(γ−1))), of width α √((γ−1)/γ); GGX's (γ = 2)
    is α/√2, so γ < 2 is narrower than GGX by √(2(γ−1)/γ) (0.82 at γ = 1.5) and γ ≥ 2 is taken as α (its
    core lies between GGX's and Beckmann's, both measured at α).  Mixtures: the narrowest population."""
    d = flake_distribution(distribution)
    alpha = float(_check_alpha(alpha))
    p = dict(d.parameters)
    if d.family == "student_t":
        g = p["gamma"]
        return alpha * min(1.0, float(np.sqrt(2.0 * (g - 1.0) / g)))
    if d.family == "mix":
        return min(flake_lobe_alpha(alpha, p["first"]), flake_lobe_alpha(p["alpha2"], p["second"]))
    return alpha


def flake_ndf(cos_theta_m, alpha, distribution="beckmann"):
    """The flake-normal density D of ``distribution`` (:data:`FLAKE_DISTRIBUTIONS`) in 1/sr."""
    return flake_distribution(distribution).ndf(cos_theta_m, alpha)
