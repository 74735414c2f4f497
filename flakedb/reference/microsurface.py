"""Explicit multiple scattering on a random Beckmann microsurface: the random walk of Heitz, Hanika,
d'Eon & Dachsbacher 2016, "Multiple-scattering microfacet BSDFs with the Smith model" (ACM TOG 35(4),
58; docs/rough-interfaces.md, "Independent check: the microsurface random walk").

A path is traced on the statistical microsurface of Smith's model (uncorrelated heights, here uniform
on [−1, 1]; the result does not depend on the height distribution, Heitz et al. §3): the height of the
next intersection is sampled from the Smith masking function (their eq. 18–20), the facet it hits
from the distribution of visible normals, D_ω(m) = G1(ω) max(0, ω·m) D(m) / ω_z (their eq. 4), and the
path reflects (conductor: weight × F) or reflects / refracts with probability F / 1 − F (dielectric;
the other side of the surface is the same random surface seen with z flipped, their §5), until it
leaves the surface.  Single and multiple scattering come out of the same walk: nothing of the
solver's compensation lobe (flakedb.rt.boundaries.microfacet) is used, and the Fresnel factors, Λ and the
visible-normal sampling are written here.

Directions are graphics vectors (pointing away from the surface for the incident direction, along
propagation for the walk's ray); the macro-normal is +z.  Everything is vectorised over paths.
"""

import math

import numpy as np
from scipy.special import erf

#: Largest number of surface events per path (a path still on the surface after it is dropped and
#: counted in ``lost``; measured: below 1e-6 of the paths for α ≤ 0.5).
MAX_EVENTS = 64


def _lambda_up(mu, alpha):
    """Smith's Λ for the Beckmann distribution (Walter et al. 2007 eq. 27's form) of an up-going direction
    of cosine ``mu`` ∈ (0, 1]: a = μ / (α √(1 − μ²)), Λ = (erf(a) − 1)/2 + e^{−a²} / (2 a √π)."""
    s = np.sqrt(np.maximum(1.0 - mu * mu, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(s > 0, mu / (alpha * np.maximum(s, 1e-300)), np.inf)
        lam = 0.5 * (erf(a) - 1.0) + np.exp(-a * a) / (2.0 * a * math.sqrt(math.pi))
    return np.where(np.isfinite(a), lam, 0.0)


def smith_lambda(z, alpha):
    """Λ(ω) for any direction of cosine ``z`` against the macro-normal: Λ(ω) for up-going, and
    Λ(−ω) = −1 − Λ(ω) for down-going rays (Heitz et al. 2016 eq. 11)."""
    z = np.asarray(z, dtype=float)
    up = _lambda_up(np.abs(z), alpha)
    return np.where(z >= 0, up, -1.0 - up)


def _sample_height(z, h, alpha, u):
    """Height of the next intersection of a ray of direction cosine ``z`` from height ``h`` (uniform
    heights, C1(h) = (h + 1)/2): P(no hit before h') = (C1(h)/C1(h'))^Λ (Heitz et al. eq. 18–20).
    Returns (h', escaped)."""
    C1 = np.clip(0.5 * (h + 1.0), 0.0, 1.0)
    lam = smith_lambda(z, alpha)
    G1 = np.where(z > 0, C1 ** np.where(z > 0, lam, 1.0), 0.0)
    escaped = (z > 0.9999) | (u > 1.0 - G1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        c = np.where(z < -0.9999, C1 * u, C1 / (1.0 - u) ** (1.0 / np.where(lam == 0, 1.0, lam)))
        h_new = np.clip(2.0 * np.minimum(c, 1.0) - 1.0, -1.0, 1.0)
    h_new = np.where(np.abs(z) < 1e-4, h, h_new)
    return h_new, escaped


def _visible_slope_x(c, u):
    """Sample the x slope of the visible normals of the unit (α = 1) Beckmann distribution seen from a
    direction with cot θ = ``c``: density ∝ max(0, c − x) e^{−x²}/√π, whose integral up to x is
    F(x) = c (1 + erf x)/2 + e^{−x²}/(2√π); inverted by bisection (60 steps, to rounding)."""
    Z = c * (1.0 + erf(c)) / 2.0 + np.exp(-c * c) / (2.0 * math.sqrt(math.pi))
    target = u * Z
    lo = np.full_like(c, -9.0)
    hi = c.copy()
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        F = c * (1.0 + erf(mid)) / 2.0 + np.exp(-mid * mid) / (2.0 * math.sqrt(math.pi))
        below = F < target
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def sample_visible_normal(wi, alpha, rng):
    """Microfacet normals m (N, 3) from D_ωi(m) ∝ max(0, ωi·m) D(m) for directions ``wi`` (N, 3) (unit,
    any side of the horizon: a ray going up sees the surface from below its own horizon): stretch to
    α = 1, sample the slopes in the incidence plane (x: :func:`_visible_slope_x`, y: Gaussian), rotate
    back and unstretch (Heitz & d'Eon 2014, §4)."""
    N = wi.shape[0]
    ws = np.stack([alpha * wi[:, 0], alpha * wi[:, 1], wi[:, 2]], axis=1)
    ws /= np.linalg.norm(ws, axis=1, keepdims=True)
    sin_t = np.sqrt(np.maximum(ws[:, 0] ** 2 + ws[:, 1] ** 2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        cphi = np.where(sin_t > 1e-12, ws[:, 0] / np.maximum(sin_t, 1e-300), 1.0)
        sphi = np.where(sin_t > 1e-12, ws[:, 1] / np.maximum(sin_t, 1e-300), 0.0)
        cot = np.where(sin_t > 1e-12, ws[:, 2] / np.maximum(sin_t, 1e-300), 1e6)
    cot = np.clip(cot, -30.0, 1e6)
    sx = np.where(cot > 30.0, rng.standard_normal(N) / math.sqrt(2.0), 0.0)
    mid = cot <= 30.0
    if mid.any():
        sx[mid] = _visible_slope_x(cot[mid], rng.random(int(mid.sum())))
    sy = rng.standard_normal(N) / math.sqrt(2.0)
    # rotate to the azimuth of ωi, unstretch: slopes (α x, α y); m ∝ (−slope_x, −slope_y, 1)
    tx, ty = cphi * sx - sphi * sy, sphi * sx + cphi * sy
    m = np.stack([-alpha * tx, -alpha * ty, np.ones(N)], axis=1)
    return m / np.linalg.norm(m, axis=1, keepdims=True)


def fresnel_dielectric_cos(c, eta):
    """Unpolarised Fresnel reflectance at a facet for cosine ``c`` > 0 on the side of arrival and relative
    index ``eta`` (far side over arrival side), 1 beyond the critical angle; and the refracted cosine."""
    s2 = (1.0 - c * c) / (eta * eta)
    tir = s2 >= 1.0
    ct = np.sqrt(np.maximum(1.0 - s2, 0.0))
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return np.where(tir, 1.0, 0.5 * (rs * rs + rp * rp)), ct


def fresnel_conductor_cos(c, N):
    """Unpolarised Fresnel reflectance of a conductor of complex relative index ``N`` at cosine ``c``:
    r_s = (c − √(N² − s²)) / (c + √(N² − s²)), r_p = (N² c − √(N² − s²)) / (N² c + √(N² − s²))."""
    c = np.asarray(c, dtype=complex)
    root = np.sqrt(N * N - (1.0 - c * c))
    rs = (c - root) / (c + root)
    rp = (N * N * c - root) / (N * N * c + root)
    return (0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)).real


def _incident(mu_i, n):
    s = math.sqrt(max(0.0, 1.0 - mu_i * mu_i))
    return np.tile([s, 0.0, mu_i], (n, 1))


def walk_conductor(mu_i, alpha, N, n_paths, seed):
    """Random walk on a rough conductor (Beckmann α, complex index N relative to the medium above) lit at
    cosine ``mu_i``.  Returns dict: ``albedo`` and its standard error ``se`` (all orders), ``single``
    (first-bounce part), ``directions`` (M, 3) and ``weights`` (M,) of the escaping paths, ``lost``.

    A perfect mirror (N → i∞) loses nothing: every path escapes with its full weight, some of it only
    after several bounces.

    >>> r = walk_conductor(0.5, 0.5, 1e9j, 2000, seed=1)
    >>> abs(r["albedo"] - 1.0) < 1e-12, r["lost"], 0.5 < r["single"] < 0.99
    (True, 0, True)
    """
    rng = np.random.default_rng(seed)
    wr = -_incident(mu_i, n_paths)  # the ray propagates down
    h = np.ones(n_paths)
    wgt = np.ones(n_paths)
    alive = np.ones(n_paths, dtype=bool)
    out_w = np.zeros(n_paths)
    out_d = np.zeros((n_paths, 3))
    single = np.zeros(n_paths)
    for event in range(MAX_EVENTS + 1):
        idx = np.nonzero(alive)[0]
        if idx.size == 0:
            break
        hn, esc = _sample_height(wr[idx, 2], h[idx], alpha, rng.random(idx.size))
        if event > 0:
            e = idx[esc]
            out_w[e], out_d[e] = wgt[e], wr[e]
            if event == 1:
                single[e] = wgt[e]
            alive[e] = False
        elif esc.any():
            raise AssertionError("a down-going ray left the surface without an intersection")
        hit = idx[~esc]
        if event == MAX_EVENTS:
            break
        h[hit] = hn[~esc]
        wi = -wr[hit]
        m = sample_visible_normal(wi, alpha, rng)
        c = np.clip(np.einsum("ij,ij->i", wi, m), 0.0, 1.0)
        wgt[hit] *= fresnel_conductor_cos(c, N)
        wr[hit] = -wi + 2.0 * c[:, None] * m
    lost = int(alive.sum())
    a = out_w
    return {"albedo": float(a.mean()), "se": float(a.std(ddof=1) / math.sqrt(n_paths)),
            "single": float(single.mean()), "directions": out_d[out_w > 0], "weights": out_w[out_w > 0],
            "lost": lost}


def walk_dielectric(mu_i, alpha, eta, n_paths, seed, from_below=False, cosine_weighted=False, cell=None):
    """Random walk on a rough dielectric interface (Beckmann α, relative index ``eta`` = n_below /
    n_above), lit from above at cosine ``mu_i`` (``from_below``: from below, in the denser or less dense
    medium; ``cosine_weighted``: incident cosines drawn from 2μ dμ instead, for hemispherical averages;
    ``cell`` = (μ_lo, μ_hi): drawn from μ dμ on that interval instead, so that R and T are the flux-weighted
    cell averages ∫ R(μ) μ dμ / ∫ μ dμ, the quantity a flux-cell discretisation carries per node).
    Each facet event reflects with probability F and refracts otherwise (the other side is the same
    surface with z flipped, Heitz et al. §5).  Returns dict ``R``, ``T`` (fractions of the paths leaving
    on the side of incidence / the other side), their standard errors, ``R_single`` and ``T_single``
    (leaving after one event), ``lost``."""
    rng = np.random.default_rng(seed)
    if cosine_weighted or cell is not None:
        lo, hi = (0.0, 1.0) if cell is None else (float(cell[0]), float(cell[1]))
        if not 0.0 <= lo < hi <= 1.0 + 1e-12:  # an edge computed as 1 may round past it
            raise ValueError(f"walk_dielectric: cell = {cell}, need 0 <= mu_lo < mu_hi <= 1")
        hi = min(hi, 1.0)
        mu = np.sqrt(lo * lo + rng.random(n_paths) * (hi * hi - lo * lo))  # density ∝ μ on [lo, hi]
        s = np.sqrt(1.0 - mu * mu)
        wr = -np.stack([s, np.zeros(n_paths), mu], axis=1)
    else:
        wr = -_incident(mu_i, n_paths)
    # the walk's frame: the side the light comes from is "up"; eta_rel = far side / this side
    eta_rel = np.full(n_paths, (1.0 / eta) if from_below else float(eta))
    side = np.zeros(n_paths, dtype=int)  # 0: the side of incidence, 1: the other
    h = np.ones(n_paths)
    alive = np.ones(n_paths, dtype=bool)
    leave_side = np.full(n_paths, -1)
    events = np.zeros(n_paths, dtype=int)
    for event in range(MAX_EVENTS + 1):
        idx = np.nonzero(alive)[0]
        if idx.size == 0:
            break
        hn, esc = _sample_height(wr[idx, 2], h[idx], alpha, rng.random(idx.size))
        if event == 0 and esc.any():
            raise AssertionError("a down-going ray left the surface without an intersection")
        e = idx[esc]
        leave_side[e] = side[e]
        alive[e] = False
        hit = idx[~esc]
        if event == MAX_EVENTS:
            break
        h[hit] = hn[~esc]
        events[hit] += 1
        wi = -wr[hit]
        m = sample_visible_normal(wi, alpha, rng)
        c = np.clip(np.einsum("ij,ij->i", wi, m), 0.0, 1.0)
        F, ct = fresnel_dielectric_cos(c, eta_rel[hit])
        refl = rng.random(hit.size) < F
        r, t = hit[refl], hit[~refl]
        wr[r] = -wi[refl] + 2.0 * c[refl, None] * m[refl]
        # refraction (Walter et al. 2007 eq. 40) into the far side, then the frame flipped: z → −z, h → −h
        et = eta_rel[t]
        ci, ctt = c[~refl], ct[~refl]
        wt = -wi[~refl] / et[:, None] + (ci / et - ctt)[:, None] * m[~refl]
        wt /= np.linalg.norm(wt, axis=1, keepdims=True)
        wt[:, 2] = -wt[:, 2]
        wr[t] = wt
        h[t] = -h[t]
        side[t] = 1 - side[t]
        eta_rel[t] = 1.0 / et
    lost = int(alive.sum())
    Rw = (leave_side == 0).astype(float)
    Tw = (leave_side == 1).astype(float)
    one = events == 1
    return {"R": float(Rw.mean()), "T": float(Tw.mean()),
            "R_se": float(Rw.std(ddof=1) / math.sqrt(n_paths)), "T_se": float(Tw.std(ddof=1) / math.sqrt(n_paths)),
            "R_single": float((Rw * one).mean()), "T_single": float((Tw * one).mean()), "lost": lost}


def coat_over_lambertian_albedo(mu_i, alpha, eta, albedo, n_paths, seed, top=None, below=None):
    """Directional albedo of a rough dielectric coat (no absorption in the binder) over a Lambertian
    primer of ``albedo``, from random walks only: A = R(μ) + T(μ) · a T̄_up / (1 − a R̄_below), with
    R, T of the walk from above at μ and T̄_up, R̄_below of walks from below with cosine-weighted
    incidence (the primer re-emits diffusely whatever reaches it, so the adding of these hemispherical
    averages is exact).  ``top``, ``below``: results of those two walks to reuse (the walk from below
    does not depend on μ_i).  Returns (A, standard error by first-order propagation)."""
    top = walk_dielectric(mu_i, alpha, eta, n_paths, seed) if top is None else top
    bot = (walk_dielectric(0.5, alpha, eta, n_paths, seed + 1, from_below=True, cosine_weighted=True)
           if below is None else below)
    R, T, Tu, Rb = top["R"], top["T"], bot["T"], bot["R"]
    D = 1.0 - albedo * Rb
    A = R + T * albedo * Tu / D
    # R and T share paths (R + T = 1 − lost): dA/dR = 1 − g with g = a Tu / D; var from both walks
    g = albedo * Tu / D
    var_top = ((1.0 - g) * top["R_se"]) ** 2
    dA_dTu = T * albedo / D
    dA_dRb = T * albedo * Tu * albedo / D**2
    var_bot = (dA_dTu - dA_dRb) ** 2 * bot["T_se"] ** 2  # Rb = 1 − Tu for a lossless interface
    return A, math.sqrt(var_top + var_bot)
