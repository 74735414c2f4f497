"""Numba kernels of the Monte Carlo reference (:mod:`flakedb.reference.montecarlo`): one photon path at a time.

Nothing here is shared with the adding-doubling solver (:mod:`flakedb.rt`); the Fresnel factor, the
microfacet interface, the flake sampler and the RNG are written out again on purpose.  Everything
takes plain arrays so the kernels stay independent of the Python problem description.

Frame inside the kernels: a propagation direction is stored as ``(dx, dy, mu)`` where ``mu`` is the
cosine against the **downward** axis (conventions: ``mu > 0`` travels down into the stack) and
``(dx, dy)`` its horizontal part, ``φ = atan2(dy, dx)``.  Depth ``z`` (µm) grows downward from the top
interface (``z = 0``).  The incident light travels along ``(sqrt(1 - mu_i²), 0, mu_i)`` (``φ_i = 0``), so
the azimuth of an exit direction is ``phi_d`` directly (0 = mirror/forward, π = backscatter).

Random numbers: xoshiro256+ (Blackman & Vigna 2018), one independent stream per batch of paths,
seeded from :class:`numpy.random.SeedSequence`, so a result depends on ``seed`` and ``n_paths`` only
(not on the number of threads).
"""

import cmath
import math

import numpy as np
from numba import njit, prange

# ---- component / boundary codes shared with flakedb.reference.montecarlo ---------------------------------
COMP_ISOTROPIC = 0
COMP_HG = 1
COMP_TABLE = 2
COMP_FLAKE = 3
COMP_VMF = 4
COMP_FLAKE_GGX = 5  # flakes whose normals follow the GGX (Trowbridge–Reitz) density
COMP_FLAKE_STUDENT_T = 6  # flakes with Student-t slopes (shape γ in comp_g)

TOP_NONE = 0
TOP_SMOOTH = 1
TOP_ROUGH = 2

BOTTOM_NONE = 0
BOTTOM_LAMBERT = 1
BOTTOM_ROUGH_CONDUCTOR = 2

# path outcomes
_ABSORBED = 0
_EXIT_TOP = 1
_EXIT_BOTTOM = 2
_EXIT_BOTTOM_DIRECT = 3
_LOST = 4

# layout of the per-batch scalar tallies
S_R = 0          # sum of diffuse reflected weight
S_R2 = 1         # ... of its squares
S_T = 2          # scattered transmitted weight
S_T2 = 3
S_TDIR = 4       # unscattered (direct) transmitted weight
S_TDIR2 = 5
S_LOSS = 6       # weight removed by Smith shadowing-masking at a rough interface
S_LOSS2 = 7
S_LOST = 8       # paths stopped by the event cap (should stay 0)
S_EVENTS = 9     # interactions simulated (tentative collisions + boundary hits)
N_SCALARS = 10

_U11 = np.uint64(11)
_U17 = np.uint64(17)
_U45 = np.uint64(45)
_U19 = np.uint64(19)
_INV53 = 1.0 / 9007199254740992.0  # 2**-53
_TWO_PI = 2.0 * math.pi
_SQRT_PI = math.sqrt(math.pi)


@njit(cache=True)
def _uniform(s):
    """xoshiro256+ step: a double uniform on [0, 1) with 53 random bits; ``s`` is the uint64[4] state."""
    s0 = s[0]
    s1 = s[1]
    s2 = s[2]
    s3 = s[3]
    result = s0 + s3
    t = s1 << _U17
    s2 ^= s0
    s3 ^= s1
    s1 ^= s2
    s0 ^= s3
    s2 ^= t
    s3 = (s3 << _U45) | (s3 >> _U19)
    s[0] = s0
    s[1] = s1
    s[2] = s2
    s[3] = s3
    return float(result >> _U11) * _INV53


@njit(cache=True)
def fresnel_unpolarized(cos_i, eta):
    """Unpolarised Fresnel reflectance of a smooth dielectric interface (Born & Wolf §1.5.2).

    ``cos_i`` > 0: cosine of the angle of incidence; ``eta`` = n_transmitted / n_incident (real).
    Returns 1 under total internal reflection.  F = (r_s² + r_p²)/2 with
    r_s = (cos_i − η cos_t)/(cos_i + η cos_t), r_p = (η cos_i − cos_t)/(η cos_i + cos_t).
    """
    sin2_t = (1.0 - cos_i * cos_i) / (eta * eta)
    if sin2_t >= 1.0:
        return 1.0
    cos_t = math.sqrt(1.0 - sin2_t)
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return 0.5 * (rs * rs + rp * rp)


@njit(cache=True)
def smith_g1_beckmann(v_z, v_dot_m, alpha):
    """Exact Smith masking G1 for the Beckmann distribution (Walter et al. 2007, eq. 25, exact form).

    G1 = χ⁺(v·m / v·n) · 2 / (1 + erf(a) + exp(−a²)/(a √π)),  a = 1/(α tan θ_v).
    ``v_z`` = v·n (may be negative for a transmitted direction), ``v_dot_m`` = v·m.
    """
    if v_dot_m * v_z <= 0.0:
        return 0.0
    c = abs(v_z)
    s2 = 1.0 - c * c
    if s2 <= 0.0:
        return 1.0
    a = c / (alpha * math.sqrt(s2))
    if a > 8.0:  # 1 - G1 < 1e-29
        return 1.0
    return 2.0 / (1.0 + math.erf(a) + math.exp(-a * a) / (a * _SQRT_PI))


@njit(cache=True)
def _sample_beckmann_normal(alpha, s):
    """Microflake / microfacet normal with density exp(−tan²θ/α²)/(π α² cos³θ) on the upper hemisphere.

    This is both the paper's flake density D (eq. 5, ∫_sphere D = 1) folded onto one hemisphere
    (m and −m act alike) and Walter's D(m) cos θ_m (eq. 28 with his eq. 35 sampling):
    tan²θ = −α² ln(1 − u₁), φ = 2π u₂.  Returns (mx, my, mz) with mz = cos θ > 0 along the axis.
    """
    u1 = _uniform(s)
    u2 = _uniform(s)
    tan2 = -alpha * alpha * math.log(1.0 - u1)
    cos_t = 1.0 / math.sqrt(1.0 + tan2)
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    phi = _TWO_PI * u2
    return sin_t * math.cos(phi), sin_t * math.sin(phi), cos_t


@njit(cache=True)
def _sample_ggx_flake_normal(alpha, s):
    """Flake normal with the GGX (Trowbridge–Reitz) density folded onto the upper hemisphere,
    2 D(m) = α² / (π cos³θ (α² + tan²θ)²) (flake convention: D on the sphere integrates to 1).

    In X = tan²θ this is the density α² / (α² + X)² dX × dφ/(2π) (sin θ dθ = t dt/(1 + t²)^{3/2}
    cancels the cos³θ), whose CDF is X/(α² + X): X = α² u₁/(1 − u₁), cos θ = 1/√(1 + X), φ = 2π u₂.
    Returns (mx, my, mz), mz = cos θ > 0.
    """
    u1 = _uniform(s)
    u2 = _uniform(s)
    x = alpha * alpha * u1 / (1.0 - u1)
    cos_t = 1.0 / math.sqrt(1.0 + x)
    sin_t = math.sqrt(x) * cos_t
    phi = _TWO_PI * u2
    return sin_t * math.cos(phi), sin_t * math.sin(phi), cos_t


@njit(cache=True)
def _gamma_variate(k, s):
    """A Gamma(k, 1) variate (k > 0): Marsaglia & Tsang 2000 (ACM TOMS 26, 363) for k ≥ 1 with a
    Box–Muller normal; k < 1 by G(k) = G(k + 1) U^{1/k} (their §6)."""
    boost = k < 1.0
    kk = k + 1.0 if boost else k
    d = kk - 1.0 / 3.0
    c = 1.0 / math.sqrt(9.0 * d)
    while True:
        x = math.sqrt(-2.0 * math.log(1.0 - _uniform(s))) * math.cos(_TWO_PI * _uniform(s))
        v = 1.0 + c * x
        if v <= 0.0:
            continue
        v = v * v * v
        u = 1.0 - _uniform(s)
        if math.log(u) < 0.5 * x * x + d - d * v + d * math.log(v):
            break
    if boost:
        return d * v * (1.0 - _uniform(s)) ** (1.0 / k)
    return d * v


@njit(cache=True)
def _sample_student_t_flake_normal(alpha, shape, s):
    """Flake normal with Student-t slopes of shape γ (STD, Ribardière et al. 2017) folded onto the
    upper hemisphere, 2 D(m) = (1 + tan²θ/(α²(γ−1)))^{−γ} / (π α² cos³θ), drawn as a Gamma scale
    mixture of Beckmann normals (no inverse CDF): given G ~ Gamma(γ − 1, 1), tan²θ = α² (γ − 1) E / G with
    E ~ Exp(1) (Beckmann of spread α √((γ−1)/G)), whose tail E_G[exp(−G X/(α²(γ−1)))] =
    (1 + X/(α²(γ−1)))^{1−γ} is the Student-t one.  Returns (mx, my, mz), mz = cos θ > 0."""
    g = _gamma_variate(shape - 1.0, s)
    x = alpha * alpha * (shape - 1.0) * (-math.log(1.0 - _uniform(s))) / g
    cos_t = 1.0 / math.sqrt(1.0 + x)
    sin_t = math.sqrt(x) * cos_t if x < 1e300 else 1.0
    phi = _TWO_PI * _uniform(s)
    return sin_t * math.cos(phi), sin_t * math.sin(phi), cos_t


@njit(cache=True)
def sample_student_t_normals_array(alpha, shape, n, state):
    """``n`` normals of :func:`_sample_student_t_flake_normal` from the xoshiro ``state`` (uint64[4],
    advanced in place), (n, 3) (for the sampling test)."""
    out = np.empty((n, 3))
    for i in range(n):
        out[i, 0], out[i, 1], out[i, 2] = _sample_student_t_flake_normal(alpha, shape, state)
    return out


@njit(cache=True)
def _interp_column(tab, off, n, base, x):
    """Linear interpolation in a table whose grid is tab[off:off+n] and whose values are
    tab[off+base:off+base+n] (clamped at the ends; binary search)."""
    lo = off
    hi = off + n - 1
    if x <= tab[lo]:
        return tab[lo + base]
    if x >= tab[hi]:
        return tab[hi + base]
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if tab[mid] <= x:
            lo = mid
        else:
            hi = mid
    t = (x - tab[lo]) / (tab[hi] - tab[lo])
    return tab[lo + base] * (1.0 - t) + tab[hi + base] * t


@njit(cache=True)
def _interp(tab, off, n, x):
    """Linear interpolation of the table stored as tab[off:off+n] (grid) and tab[off+n:off+2n] (values)."""
    return _interp_column(tab, off, n, n, x)


@njit(cache=True)
def _interp_flake(tab, off, n, which, x):
    """R (which = 0) or T (which = 1) of a flake table stored as [c grid | R | T] at tab[off:off+3n]."""
    return _interp_column(tab, off, n, n * (1 + which), x)


@njit(cache=True)
def _sample_table_cos(tab, off, n, u):
    """Invert the CDF of a piecewise-linear pdf q(x) on x = cos Θ ∈ [−1, 1] (exactly, per interval).

    Stored as tab[off:off+n] = x grid, tab[off+n:off+2n] = q (normalised: ∫ q dx = 1),
    tab[off+2n:off+3n] = CDF at the nodes.  Within [x_k, x_k+1] the CDF is q_k t + s t²/2,
    solved in the cancellation-free form t = 2Δ / (q_k + sqrt(q_k² + 2 s Δ)).
    """
    lo = off
    hi = off + n - 1
    cdf0 = off + 2 * n
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if tab[mid - off + cdf0] <= u:
            lo = mid
        else:
            hi = mid
    x0 = tab[lo]
    h = tab[hi] - x0
    q0 = tab[lo + n]
    q1 = tab[hi + n]
    slope = (q1 - q0) / h
    delta = u - tab[lo - off + cdf0]
    disc = q0 * q0 + 2.0 * slope * delta
    if disc < 0.0:
        disc = 0.0
    den = q0 + math.sqrt(disc)
    if den <= 0.0:
        t = 0.0
    else:
        t = 2.0 * delta / den
    if t < 0.0:
        t = 0.0
    if t > h:
        t = h
    c = x0 + t
    if c > 1.0:
        c = 1.0
    if c < -1.0:
        c = -1.0
    return c


@njit(cache=True)
def sample_vmf_cos(kappa, u):
    """cos Θ of the von Mises–Fisher phase function p ∝ exp(κ cos Θ) by exact inversion of its CDF
    (Wood 1994 for the sphere S²): with v = 1 − u ∈ (0, 1],
    cos Θ = 1 + ln(v + (1 − v) e^{−2κ}) / κ  (the argument is ≥ v > 0, so no log(0) for any κ);
    κ < 1e-8 is isotropic, cos Θ = 2u − 1."""
    if kappa < 1e-8:
        return 2.0 * u - 1.0
    v = 1.0 - u
    c = 1.0 + math.log(v + (1.0 - v) * math.exp(-2.0 * kappa)) / kappa
    return min(max(c, -1.0), 1.0)


@njit(cache=True)
def sample_vmf_cos_array(kappa, u):
    """:func:`sample_vmf_cos` over an array of uniforms ``u`` (for the sampling test)."""
    out = np.empty(u.size)
    for i in range(u.size):
        out[i] = sample_vmf_cos(kappa, u[i])
    return out


@njit(cache=True)
def _rotate(dx, dy, dz, cos_t, phi):
    """Turn the unit vector (dx, dy, dz) by polar angle acos(cos_t) and azimuth phi about itself."""
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    cp = math.cos(phi)
    sp = math.sin(phi)
    if abs(dz) > 0.99999:
        nx = sin_t * cp
        ny = sin_t * sp
        nz = cos_t if dz > 0.0 else -cos_t
    else:
        tmp = math.sqrt(1.0 - dz * dz)
        nx = sin_t * (dx * dz * cp - dy * sp) / tmp + dx * cos_t
        ny = sin_t * (dy * dz * cp + dx * sp) / tmp + dy * cos_t
        nz = -sin_t * cp * tmp + dz * cos_t
    inv = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz)
    return nx * inv, ny * inv, nz * inv


@njit(cache=True)
def _snell_refract(dx, dy, cos_in, eta):
    """Refraction through a smooth interface of relative index ``eta`` (n_out / n_in) for a direction
    (dx, dy, ·) with |cos| ``cos_in`` > 0 towards it (total internal reflection already excluded by the
    caller's Fresnel draw): the tangential part scales by 1/η (Snell); returns (dx, dy, cos_out ≥ 0)."""
    sin_in = math.sqrt(max(0.0, 1.0 - cos_in * cos_in))
    sin_out = sin_in / eta
    if sin_in > 0.0:
        dx *= sin_out / sin_in
        dy *= sin_out / sin_in
    return dx, dy, math.sqrt(max(0.0, 1.0 - sin_out * sin_out))


@njit(cache=True)
def _rough_interface(dx, dy, mu, from_above, eta, alpha, s):
    """One hit of a Beckmann microfacet dielectric interface (Walter et al. 2007), both sides.

    Propagation direction (dx, dy, mu); ``from_above``: the light comes from the air side.
    ``eta`` = n_binder / n_air.  A microfacet normal is drawn from D(m)|m·n| (Walter eq. 35), the
    branch is chosen with probability F(i·m) (reflect) / 1 − F (refract), and the path weight is
    multiplied by Walter's eq. 41, w = |i·m| G1(i,m) G1(o,m) / (|i·n| |m·n|), the same for both
    branches (separable Smith G, exact Beckmann G1).  Returns (dx', dy', mu', weight_factor);
    weight_factor = 0 when the sample is masked/shadowed (the single-scattering microfacet model
    loses that energy).
    """
    # local frame: z_l along the normal pointing into the incident side.
    if from_above:
        eta_rel = eta
        wz = -mu
    else:
        eta_rel = 1.0 / eta
        wz = mu
    ix = -dx
    iy = -dy
    iz = -wz  # i = −ω points back to where the light came from; iz > 0
    mx, my, mz = _sample_beckmann_normal(alpha, s)
    c = ix * mx + iy * my + iz * mz
    if c <= 0.0:
        return dx, dy, mu, 0.0
    F = fresnel_unpolarized(c, eta_rel)
    if _uniform(s) < F:
        ox = 2.0 * c * mx - ix
        oy = 2.0 * c * my - iy
        oz = 2.0 * c * mz - iz
        if oz <= 0.0:
            return dx, dy, mu, 0.0
        o_dot_m = c
    else:
        sin2_t = (1.0 - c * c) / (eta_rel * eta_rel)
        cos_t = math.sqrt(max(0.0, 1.0 - sin2_t))
        k = c / eta_rel - cos_t
        ox = -ix / eta_rel + k * mx
        oy = -iy / eta_rel + k * my
        oz = -iz / eta_rel + k * mz
        if oz >= 0.0:
            return dx, dy, mu, 0.0
        o_dot_m = -cos_t
    inv = 1.0 / math.sqrt(ox * ox + oy * oy + oz * oz)
    ox *= inv
    oy *= inv
    oz *= inv
    g = smith_g1_beckmann(iz, c, alpha) * smith_g1_beckmann(oz, o_dot_m, alpha)
    w = c * g / (iz * mz)
    mu_new = -oz if from_above else oz
    return ox, oy, mu_new, w


@njit(cache=True)
def fresnel_conductor_unpolarized(cos_i, n, k):
    """Unpolarised Fresnel reflectance of a conductor of complex relative index N = n + ik seen from
    the dielectric (Born & Wolf §14.2): q = sqrt(N² − 1 + c²) (decaying branch, Im q ≥ 0),
    r_s = (c − q)/(c + q), r_p = (N² c − q)/(N² c + q), F = (|r_s|² + |r_p|²)/2.

    At normal incidence R = ((n − 1)² + k²) / ((n + 1)² + k²) (aluminium in a binder, N ≈ 0.96 + 6.69i / 1.5):

    >>> n, k = 0.96 / 1.5, 6.69 / 1.5
    >>> round(fresnel_conductor_unpolarized(1.0, n, k), 12) == round(((n - 1) ** 2 + k * k) / ((n + 1) ** 2 + k * k), 12)
    True
    >>> fresnel_conductor_unpolarized(0.0, n, k)           # grazing: total reflection
    1.0
    """
    N2 = complex(n, k) ** 2
    q = cmath.sqrt(N2 - 1.0 + cos_i * cos_i)
    if q.imag < 0.0:
        q = -q
    rs = (cos_i - q) / (cos_i + q)
    rp = (N2 * cos_i - q) / (N2 * cos_i + q)
    return 0.5 * (abs(rs) ** 2 + abs(rp) ** 2)


@njit(cache=True)
def _rough_conductor(dx, dy, mu, n, k, alpha, s):
    """One reflection off a Beckmann microfacet conductor below the binder (Walter et al. 2007).

    The light travels down, (dx, dy, mu > 0).  In a frame whose z points up (into the binder),
    i = (−dx, −dy, mu); a facet normal m is drawn from D(m)(m·n) (Walter eq. 35), o = 2(i·m)m − i,
    and the weight is Walter's eq. 41 times the conductor's Fresnel factor,
    F(i·m) |i·m| G1(i) G1(o) / (i_z m_z); zero for a back-facing facet or o below the surface.
    Returns the new propagation direction (travelling up, mu' < 0) and the weight factor."""
    ix = -dx
    iy = -dy
    iz = mu
    mx, my, mz = _sample_beckmann_normal(alpha, s)
    c = ix * mx + iy * my + iz * mz
    if c <= 0.0:
        return dx, dy, mu, 0.0
    ox = 2.0 * c * mx - ix
    oy = 2.0 * c * my - iy
    oz = 2.0 * c * mz - iz
    if oz <= 0.0:
        return dx, dy, mu, 0.0
    inv = 1.0 / math.sqrt(ox * ox + oy * oy + oz * oz)
    ox *= inv
    oy *= inv
    oz *= inv
    g = smith_g1_beckmann(iz, c, alpha) * smith_g1_beckmann(oz, c, alpha)
    w = fresnel_conductor_unpolarized(c, n, k) * c * g / (iz * mz)
    return ox, oy, -oz, w


# ---- multiple-scattering energy compensation (docs/rough-interfaces.md) ---------------------------
# Tables on the grid μ_k = (k/K)², k = 0 … K.  ``ms_E[r, k]``: rows 0 (rough dielectric, light from the
# air), 1 (from the binder), 2 (rough conductor with F ≡ 1): the single-scattering albedo E_r(μ_k);
# row 3: the probability that the dielectric lobe, entered from the air, reflects (r_a / g_a); row 4:
# that it transmits when entered from the binder (t_b / g_b); row 5: the conductor lobe's weight
# a / (1 − E₁) (docs/rough-interfaces.md, "Multiple-scattering split").  ``ms_cdf[r, k]``: the CDF over
# the intervals [μ_k, μ_{k+1}] of an outgoing pdf ∝ μ × (row 0: r_a, 1: r_b, 2: the conductor's a,
# 3: t_a, 4: t_b).  ``ms_par`` = [dielectric compensation on, unused, conductor compensation on, unused].


@njit(cache=True)
def single_scatter_albedo(mu_grid, eta_rel, alpha, white, xs, ws):
    """Expected weight of one hit of :func:`_rough_interface` (``white`` False, relative index
    ``eta_rel``) or of a rough reflector with F ≡ 1 (``white`` True) for light arriving at cosine μ,
    for every μ of ``mu_grid``: the integral over the sampled normal (u₁, φ) of Walter's eq. 41 weight
    summed over both branches with their probabilities F and 1 − F, by a tensor rule (``xs``, ``ws``:
    nodes and weights on [0, 1], Σ ws = 1) in u₁ and in φ/π (the integrand is even in φ)."""
    out = np.zeros(mu_grid.shape[0])
    for j in range(mu_grid.shape[0]):
        iz = max(mu_grid[j], 1e-9)
        ix = math.sqrt(max(0.0, 1.0 - iz * iz))
        total = 0.0
        for a in range(xs.shape[0]):
            tan2 = -alpha * alpha * math.log(1.0 - xs[a])
            mz = 1.0 / math.sqrt(1.0 + tan2)
            sm = math.sqrt(max(0.0, 1.0 - mz * mz))
            for b in range(xs.shape[0]):
                mx = sm * math.cos(math.pi * xs[b])
                c = ix * mx + iz * mz
                if c <= 0.0:
                    continue
                base = ws[a] * ws[b] * c * smith_g1_beckmann(iz, c, alpha) / (iz * mz)
                F = 1.0 if white else fresnel_unpolarized(c, eta_rel)
                oz = 2.0 * c * mz - iz
                if oz > 0.0:
                    total += F * base * smith_g1_beckmann(oz, c, alpha)
                if not white and F < 1.0:
                    sin2_t = (1.0 - c * c) / (eta_rel * eta_rel)
                    cos_t = math.sqrt(max(0.0, 1.0 - sin2_t))
                    oz = -iz / eta_rel + (c / eta_rel - cos_t) * mz
                    if oz < 0.0:
                        total += (1.0 - F) * base * smith_g1_beckmann(oz, -cos_t, alpha)
        out[j] = total
    return out


@njit(cache=True)
def _table_E(ms_E, row, mu):
    """E_row(μ), linear in √μ between the nodes μ_k = (k/K)²."""
    K = ms_E.shape[1] - 1
    t = math.sqrt(max(mu, 0.0)) * K
    k = int(t)
    if k >= K:
        k = K - 1
    f = t - k
    return ms_E[row, k] * (1.0 - f) + ms_E[row, k + 1] * f


@njit(cache=True)
def _sample_ms_mu(ms_grid, ms_cdf, row, s):
    """μ from the pdf ∝ μ (1 − E_row(μ)): an interval by its CDF, then ∝ μ inside it."""
    u = _uniform(s)
    lo = 0
    hi = ms_cdf.shape[1] - 1
    while lo < hi:
        mid = (lo + hi) >> 1
        if ms_cdf[row, mid] > u:
            hi = mid
        else:
            lo = mid + 1
    a = ms_grid[lo]
    b = ms_grid[lo + 1]
    return math.sqrt(a * a + _uniform(s) * (b * b - a * a))


@njit(cache=True)
def _rough_interface_ms(dx, dy, mu, from_above, eta, alpha, ms_grid, ms_E, ms_cdf, ms_par, s):
    """One hit of the rough dielectric with the multiple-scattering compensation: with probability
    p = E(μ) (the table) the single-scattering event of :func:`_rough_interface` with its weight
    divided by p; otherwise the compensation lobe, weight (1 − E)/(1 − p) = 1: from the air it
    reflects with probability r_a/g_a (row 3; μ ∝ μ r_a) or enters the binder (μ ∝ μ t_b); from the
    binder it leaves into the air with probability t_b/g_b (row 4; μ ∝ μ t_a) or reflects (μ ∝ μ r_b);
    φ uniform.  Expected weight E_true + 1 − E_table: lossless up to the table's quadrature error."""
    cos_in = mu if from_above else -mu
    p = _table_E(ms_E, 0 if from_above else 1, cos_in)
    if _uniform(s) < p:
        dx, dy, mu, f = _rough_interface(dx, dy, mu, from_above, eta, alpha, s)
        return dx, dy, mu, f / p
    if from_above:
        air = _uniform(s) < _table_E(ms_E, 3, cos_in)
        row = 0 if air else 4
    else:
        air = _uniform(s) < _table_E(ms_E, 4, cos_in)
        row = 3 if air else 1
    m = _sample_ms_mu(ms_grid, ms_cdf, row, s)
    ph = _TWO_PI * _uniform(s)
    st = math.sqrt(max(0.0, 1.0 - m * m))
    return st * math.cos(ph), st * math.sin(ph), (-m if air else m), 1.0


@njit(cache=True)
def _rough_conductor_ms(dx, dy, mu, n, k, alpha, ms_grid, ms_E, ms_cdf, ms_par, s):
    """One hit of the rough conductor with its multiple-scattering lobe: with probability p = E₁(μ)
    the single-scattering reflection (weight / p), otherwise the lobe μ ∝ μ a(μ), φ uniform,
    travelling up, weight a(μ_i) / (1 − E₁(μ_i)) (row 5)."""
    p = _table_E(ms_E, 2, mu)
    if _uniform(s) < p:
        dx, dy, mu, f = _rough_conductor(dx, dy, mu, n, k, alpha, s)
        return dx, dy, mu, f / p
    wgt = _table_E(ms_E, 5, mu)
    m = _sample_ms_mu(ms_grid, ms_cdf, 2, s)
    ph = _TWO_PI * _uniform(s)
    st = math.sqrt(max(0.0, 1.0 - m * m))
    return st * math.cos(ph), st * math.sin(ph), -m, wgt


@njit(cache=True)
def _trace(s, mu_i, top_type, eta, top_alpha, bot_type, bot_albedo, bot_n, bot_k, bot_alpha, z_edges, sigma_bar, comp_start,
           comp_type, comp_sigma, comp_albedo, comp_g, comp_alpha, comp_off, comp_n, tab,
           w_start, max_orders, max_events, rr_threshold, ms_grid, ms_E, ms_cdf, ms_par, slab_eta, slab_alpha):
    """Trace one path; returns (outcome, weight, dx, dy, mu, interface_loss, events).  ``slab_eta``
    (n_slabs,): each slab's binder index; where neighbours differ, a smooth inner interface (Fresnel
    reflection or Snell refraction, total internal reflection included).  ``slab_alpha`` (n_slabs,): the
    Beckmann roughness of the interface at the top of each slab (entry 0 unused); where > 0 the inner
    interface is a rough dielectric (:func:`_rough_interface`, single scattering: the masked/shadowed
    part is lost and counted in the interface loss)."""
    n_slabs = sigma_bar.shape[0]
    w = w_start
    loss = 0.0
    events = 0
    sin_i = math.sqrt(max(0.0, 1.0 - mu_i * mu_i))
    dx = sin_i
    dy = 0.0
    mu = mu_i
    direct = True
    if top_type == TOP_SMOOTH:
        sin_t = sin_i / eta
        if sin_t >= 1.0:  # total reflection from the air side (eta < 1): nothing enters
            return _ABSORBED, 0.0, dx, dy, mu, loss, events
        dx = sin_t
        mu = math.sqrt(1.0 - sin_t * sin_t)
    elif top_type == TOP_ROUGH:
        if ms_par[0] > 0.0:
            dx, dy, mu, f = _rough_interface_ms(dx, dy, mu, True, eta, top_alpha, ms_grid, ms_E, ms_cdf, ms_par, s)
        else:
            dx, dy, mu, f = _rough_interface(dx, dy, mu, True, eta, top_alpha, s)
            loss += w * (1.0 - f)
        events += 1
        w *= f
        direct = False
        if w == 0.0:
            return _ABSORBED, 0.0, dx, dy, mu, loss, events
        if mu < 0.0:
            return _EXIT_TOP, w, dx, dy, mu, loss, events
    z = 0.0
    k = 0
    orders = 0
    while True:
        events += 1
        if events > max_events:
            return _LOST, w, dx, dy, mu, loss, events
        sb = sigma_bar[k]
        if mu > 0.0:
            dist = (z_edges[k + 1] - z) / mu
        elif mu < 0.0:
            dist = (z - z_edges[k]) / (-mu)
        else:
            dist = np.inf
        if sb > 0.0:
            t = -math.log(1.0 - _uniform(s)) / sb
        else:
            t = np.inf
        if t >= dist:
            if dist == np.inf:
                return _LOST, w, dx, dy, mu, loss, events
            if mu > 0.0:
                z = z_edges[k + 1]
                if k < n_slabs - 1:
                    er = slab_eta[k + 1] / slab_eta[k]
                    if slab_alpha[k + 1] > 0.0:  # rough inner interface, from above
                        dx, dy, mu, f = _rough_interface(dx, dy, mu, True, er, slab_alpha[k + 1], s)
                        loss += w * (1.0 - f)
                        w *= f
                        direct = False
                        if w == 0.0:
                            return _ABSORBED, 0.0, dx, dy, mu, loss, events
                        if mu > 0.0:
                            k += 1
                        continue
                    if er != 1.0:  # smooth inner interface, from above
                        if _uniform(s) < fresnel_unpolarized(mu, er):
                            mu = -mu
                            direct = False
                            continue
                        dx, dy, mu = _snell_refract(dx, dy, mu, er)
                    k += 1
                    continue
                # bottom of the stack
                if bot_type == BOTTOM_LAMBERT:
                    w *= bot_albedo
                    if w == 0.0:
                        return _ABSORBED, 0.0, dx, dy, mu, loss, events
                    if w < rr_threshold and bot_albedo < 1.0:  # Russian roulette (see below)
                        if _uniform(s) < 0.1:
                            w *= 10.0
                        else:
                            return _ABSORBED, 0.0, dx, dy, mu, loss, events
                    direct = False
                    u1 = _uniform(s)
                    u2 = _uniform(s)
                    mu = -math.sqrt(u1)  # cosine-weighted, travelling up
                    st = math.sqrt(max(0.0, 1.0 - u1))
                    ph = _TWO_PI * u2
                    dx = st * math.cos(ph)
                    dy = st * math.sin(ph)
                elif bot_type == BOTTOM_ROUGH_CONDUCTOR:
                    if ms_par[2] > 0.0:
                        dx, dy, mu, f = _rough_conductor_ms(dx, dy, mu, bot_n, bot_k, bot_alpha, ms_grid, ms_E,
                                                            ms_cdf, ms_par, s)
                    else:
                        dx, dy, mu, f = _rough_conductor(dx, dy, mu, bot_n, bot_k, bot_alpha, s)
                    w *= f
                    direct = False
                    if w == 0.0:
                        return _ABSORBED, 0.0, dx, dy, mu, loss, events
                    if w < rr_threshold:  # Russian roulette (see below)
                        if _uniform(s) < 0.1:
                            w *= 10.0
                        else:
                            return _ABSORBED, 0.0, dx, dy, mu, loss, events
                else:
                    if direct:
                        return _EXIT_BOTTOM_DIRECT, w, dx, dy, mu, loss, events
                    return _EXIT_BOTTOM, w, dx, dy, mu, loss, events
            else:
                z = z_edges[k]
                if k > 0:
                    er = slab_eta[k - 1] / slab_eta[k]
                    if slab_alpha[k] > 0.0:  # rough inner interface, from below (η = n_below / n_above)
                        dx, dy, mu, f = _rough_interface(dx, dy, mu, False, 1.0 / er, slab_alpha[k], s)
                        loss += w * (1.0 - f)
                        w *= f
                        direct = False
                        if w == 0.0:
                            return _ABSORBED, 0.0, dx, dy, mu, loss, events
                        if mu < 0.0:
                            k -= 1
                        continue
                    if er != 1.0:  # smooth inner interface, from below
                        cos_in = -mu
                        if _uniform(s) < fresnel_unpolarized(cos_in, er):
                            mu = cos_in
                            direct = False
                            continue
                        dx, dy, cos_out = _snell_refract(dx, dy, cos_in, er)
                        mu = -cos_out
                    k -= 1
                    continue
                # top interface from inside
                if top_type == TOP_NONE:
                    return _EXIT_TOP, w, dx, dy, mu, loss, events
                elif top_type == TOP_SMOOTH:
                    cos_in = -mu
                    F = fresnel_unpolarized(cos_in, 1.0 / eta)
                    direct = False
                    if _uniform(s) < F:
                        mu = cos_in
                    else:
                        dx, dy, cos_out = _snell_refract(dx, dy, cos_in, 1.0 / eta)
                        return _EXIT_TOP, w, dx, dy, -cos_out, loss, events
                else:
                    if ms_par[0] > 0.0:
                        dx, dy, mu, f = _rough_interface_ms(dx, dy, mu, False, eta, top_alpha, ms_grid, ms_E,
                                                            ms_cdf, ms_par, s)
                    else:
                        dx, dy, mu, f = _rough_interface(dx, dy, mu, False, eta, top_alpha, s)
                        loss += w * (1.0 - f)
                    w *= f
                    direct = False
                    if w == 0.0:
                        return _ABSORBED, 0.0, dx, dy, mu, loss, events
                    if mu < 0.0:
                        return _EXIT_TOP, w, dx, dy, mu, loss, events
            continue
        # tentative collision inside slab k
        z += t * mu
        if z < z_edges[k]:
            z = z_edges[k]
        elif z > z_edges[k + 1]:
            z = z_edges[k + 1]
        pick = _uniform(s) * sb
        j = comp_start[k]
        acc = comp_sigma[j]
        while acc < pick and j < comp_start[k + 1] - 1:
            j += 1
            acc += comp_sigma[j]
        ctype = comp_type[j]
        if ctype == COMP_FLAKE or ctype == COMP_FLAKE_GGX or ctype == COMP_FLAKE_STUDENT_T:
            if ctype == COMP_FLAKE:
                mx, my, mz = _sample_beckmann_normal(comp_alpha[j], s)
            elif ctype == COMP_FLAKE_GGX:
                mx, my, mz = _sample_ggx_flake_normal(comp_alpha[j], s)
            else:
                mx, my, mz = _sample_student_t_flake_normal(comp_alpha[j], comp_g[j], s)
            cdot = dx * mx + dy * my + mu * mz
            c = abs(cdot)
            if _uniform(s) >= c:
                continue  # null collision: flake seen edge-on in proportion 1 - |ω·m|
            Tc = _interp_flake(tab, comp_off[j], comp_n[j], 1, c)
            if Tc >= 1.0 or _uniform(s) < Tc:
                continue  # transmitted undeviated through the flake
            orders += 1
            if max_orders >= 0 and orders > max_orders:
                return _ABSORBED, 0.0, dx, dy, mu, loss, events
            Rc = _interp_flake(tab, comp_off[j], comp_n[j], 0, c)
            w *= Rc / (1.0 - Tc)
            dx -= 2.0 * cdot * mx
            dy -= 2.0 * cdot * my
            mu -= 2.0 * cdot * mz
            inv = 1.0 / math.sqrt(dx * dx + dy * dy + mu * mu)
            dx *= inv
            dy *= inv
            mu *= inv
        else:
            orders += 1
            if max_orders >= 0 and orders > max_orders:
                return _ABSORBED, 0.0, dx, dy, mu, loss, events
            w *= comp_albedo[j]
            if ctype == COMP_ISOTROPIC:
                cos_t = 2.0 * _uniform(s) - 1.0
            elif ctype == COMP_HG:
                g = comp_g[j]
                u = _uniform(s)
                if abs(g) < 1e-6:
                    cos_t = 2.0 * u - 1.0
                else:
                    q = (1.0 - g * g) / (1.0 - g + 2.0 * g * u)
                    cos_t = (1.0 + g * g - q * q) / (2.0 * g)
                    if cos_t > 1.0:
                        cos_t = 1.0
                    if cos_t < -1.0:
                        cos_t = -1.0
            elif ctype == COMP_VMF:
                cos_t = sample_vmf_cos(comp_g[j], _uniform(s))
            else:
                cos_t = _sample_table_cos(tab, comp_off[j], comp_n[j], _uniform(s))
            ph = _TWO_PI * _uniform(s)
            dx, dy, mu = _rotate(dx, dy, mu, cos_t, ph)
        direct = False
        if w == 0.0:
            return _ABSORBED, 0.0, dx, dy, mu, loss, events
        if w < rr_threshold:  # Russian roulette, survival probability 1/10 (unbiased)
            if _uniform(s) < 0.1:
                w *= 10.0
            else:
                return _ABSORBED, 0.0, dx, dy, mu, loss, events


@njit(cache=True)
def _bin_index(edges, v):
    n = edges.shape[0]
    if v < edges[0] or v > edges[n - 1]:
        return -1
    if v == edges[n - 1]:
        return n - 2
    i = np.searchsorted(edges, v, side="right") - 1
    return i


@njit(parallel=True, cache=True)
def simulate_kernel(path_counts, seeds, mu_i, top_type, eta, top_alpha, bot_type, bot_albedo, bot_n, bot_k,
                    bot_alpha, z_edges,
                    sigma_bar, comp_start, comp_type, comp_sigma, comp_albedo, comp_g, comp_alpha,
                    comp_off, comp_n, tab, w_start, mu_edges, phi_edges, max_orders, max_events,
                    rr_threshold, ms_grid, ms_E, ms_cdf, ms_par, slab_eta, slab_alpha):
    """Run ``path_counts[b]`` paths for every batch b (in parallel, each with its own RNG stream).

    Returns per-batch tallies: ``scal`` (B, N_SCALARS) with the layout S_*; ``rbin`` / ``tbin``
    (B, n_mu, n_phi, 2): the sum and sum of squares of the weight leaving the top / (scattered)
    bottom into each (|mu|, phi_d) bin.  Diffuse reflection excludes the first-surface specular
    reflection of a smooth top, which the caller carries analytically (1 − w_start of the power).
    """
    n_batches = path_counts.shape[0]
    n_mu = mu_edges.shape[0] - 1
    n_phi = phi_edges.shape[0] - 1
    scal = np.zeros((n_batches, N_SCALARS))
    rbin = np.zeros((n_batches, n_mu, n_phi, 2))
    tbin = np.zeros((n_batches, n_mu, n_phi, 2))
    for b in prange(n_batches):
        s = seeds[b].copy()
        for _ in range(path_counts[b]):
            outcome, w, dx, dy, mu, loss, events = _trace(
                s, mu_i, top_type, eta, top_alpha, bot_type, bot_albedo, bot_n, bot_k, bot_alpha, z_edges,
                sigma_bar, comp_start,
                comp_type, comp_sigma, comp_albedo, comp_g, comp_alpha, comp_off, comp_n, tab,
                w_start, max_orders, max_events, rr_threshold, ms_grid, ms_E, ms_cdf, ms_par, slab_eta, slab_alpha)
            scal[b, S_EVENTS] += events
            if loss != 0.0:
                scal[b, S_LOSS] += loss
                scal[b, S_LOSS2] += loss * loss
            if outcome == _ABSORBED:
                continue
            if outcome == _LOST:
                scal[b, S_LOST] += 1.0
                continue
            if outcome == _EXIT_BOTTOM_DIRECT:
                scal[b, S_TDIR] += w
                scal[b, S_TDIR2] += w * w
                continue
            i = _bin_index(mu_edges, abs(mu))
            jphi = _bin_index(phi_edges, abs(math.atan2(dy, dx)))
            if outcome == _EXIT_TOP:
                scal[b, S_R] += w
                scal[b, S_R2] += w * w
                if i >= 0 and jphi >= 0:
                    rbin[b, i, jphi, 0] += w
                    rbin[b, i, jphi, 1] += w * w
            else:
                scal[b, S_T] += w
                scal[b, S_T2] += w * w
                if i >= 0 and jphi >= 0:
                    tbin[b, i, jphi, 0] += w
                    tbin[b, i, jphi, 1] += w * w
    return scal, rbin, tbin
