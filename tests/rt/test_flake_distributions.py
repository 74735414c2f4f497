"""The registry of flake orientation distributions (flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS; docs/model.md §3
"Flake orientation distributions"): Beckmann (paper eq. 5) and GGX (Trowbridge–Reitz, flake convention).

Guards against: a GGX density normalised in the microfacet convention (over one hemisphere with cos θ)
instead of the flake one (1 over the whole sphere, even); σ_t/σ_s moments that cut GGX's heavy slope
tail or miss its |cos θ_m| kink at the horizon; a kernel that does not integrate to σ_s or is not
reciprocal with GGX; a GGX sampler that does not follow its density; a φ-bandwidth guess below what the
kernel needs; a ``distribution=`` argument that is dropped somewhere between the functions (GGX silently
computed as Beckmann), or Beckmann numbers that change with the registry.  References are written here,
independently of the module's quadratures (other coordinates, other splits, Monte Carlo, FFT).
"""

import numpy as np
import pytest
from scipy import integrate, stats

from flakedb.rt.scattering.media import FlakeMedium
from flakedb.rt.scattering.microflake import (
    FLAKE_DISTRIBUTIONS,
    FlakeOptics,
    extinction_Ergun,
    flake_distribution,
    flake_ndf,
    flake_ndf_at_halfvector,
    flake_ndf_GGX,
    kernel_Ergun,
    kernel_Ergun_basis,
    kernel_phi_bandwidth,
    projected_area,
    projected_area_Beckmann,
    sample_flake_normal,
    sample_flake_normal_GGX,
    scattering_Ergun,
)
from tests.rt.test_microflake import A_RHO, direction, gl, mu_phi, panels, tabulated_optics

DISTS = sorted(FLAKE_DISTRIBUTIONS)


# ------------------------------------------------------------------------------------------------
# The densities
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dist", DISTS)
@pytest.mark.parametrize("alpha", [0.02, 0.1, 0.5, 1.0, 2.0])
def test_density_integrates_to_one_over_the_sphere(dist, alpha):
    # θ panels at arctan(k α) (the core and GGX's algebraic tail), both hemispheres explicitly
    br = np.concatenate([[0.0, np.pi / 2], np.arctan(alpha * np.array([0.25, 0.5, 1, 2, 4, 8, 16, 64, 256]))])
    th, w = panels(br, 60)
    upper = np.sum(w * 2 * np.pi * np.sin(th) * flake_ndf(np.cos(th), alpha, dist))
    lower = np.sum(w * 2 * np.pi * np.sin(th) * flake_ndf(np.cos(np.pi - th), alpha, dist))
    assert upper == pytest.approx(0.5, rel=1e-12)
    assert upper + lower == pytest.approx(1.0, rel=1e-12)


def test_ggx_closed_form_and_properties():
    alpha = 0.3
    th = np.linspace(0.0, np.pi / 2 - 1e-9, 2001)
    # the form α² / (2π |cos θ|³ (α² + tan²θ)²), evaluated literally (θ < π/2)
    literal = alpha**2 / (2 * np.pi * np.cos(th) ** 3 * (alpha**2 + np.tan(th) ** 2) ** 2)
    np.testing.assert_allclose(flake_ndf_GGX(np.cos(th), alpha), literal, rtol=1e-12)
    # = the microfacet GGX (Walter et al. 2007 eq. 33) × cos θ / 2
    walter = alpha**2 / (np.pi * np.cos(th) ** 4 * (alpha**2 + np.tan(th) ** 2) ** 2)
    np.testing.assert_allclose(flake_ndf_GGX(np.cos(th), alpha), 0.5 * np.cos(th) * walter, rtol=1e-12)
    rng = np.random.default_rng(11)
    m = rng.normal(size=(1000, 3))
    m /= np.linalg.norm(m, axis=-1, keepdims=True)
    np.testing.assert_array_equal(flake_ndf_GGX(m[:, 2], 0.4), flake_ndf_GGX(-m[:, 2], 0.4))  # even
    with np.errstate(divide="raise", invalid="raise", over="raise"):
        d = flake_ndf_GGX(np.array([0.0, 1e-300, 1.0, -1.0]), 0.05)
    assert d[0] == 0.0 and np.all(np.isfinite(d)) and d[2] == pytest.approx(1 / (2 * np.pi * 0.05**2))
    with pytest.raises(ValueError, match="alpha"):
        flake_ndf_GGX(0.5, -1.0)


@pytest.mark.parametrize("dist", DISTS)
def test_peak_is_the_maximum(dist):
    c = np.linspace(0.0, 1.0, 200_001)
    for alpha in (0.05, 0.5, 1.0, 1.2, 1.5, 2.0, 3.0):
        D = FLAKE_DISTRIBUTIONS[dist]
        top = D.ndf(c, alpha).max()
        assert D.peak(alpha) == pytest.approx(top, rel=1e-8) and D.peak(alpha) >= top * (1 - 1e-14)


def test_registry_lookup():
    assert flake_distribution(None) is FLAKE_DISTRIBUTIONS["beckmann"]
    assert flake_distribution("GGX") is FLAKE_DISTRIBUTIONS["ggx"]
    with pytest.raises(ValueError, match="known: beckmann, ggx"):
        flake_distribution("phong")
    with pytest.raises(ValueError, match="FlakeMedium.distribution"):
        FlakeMedium(0.2, FlakeOptics.constant(0.5, 0.2), 1.0, "cauchy")


def test_beckmann_default_is_unchanged_and_ggx_differs():
    """The default of every ``distribution=`` is Beckmann, bit for bit; GGX reaches each function
    (a dropped argument would make the GGX column equal the Beckmann one)."""
    rng = np.random.default_rng(12)
    opt = tabulated_optics()
    mu = rng.uniform(-1, 1, 40)
    mi, mo, ph = rng.uniform(-1, 1, 300), rng.uniform(-1, 1, 300), rng.uniform(0, 2 * np.pi, 300)
    calls = [
        lambda **k: extinction_Ergun(mu, 0.3, opt, A_RHO, **k),
        lambda **k: scattering_Ergun(mu, 0.3, opt, A_RHO, **k),
        lambda **k: projected_area(mu, 0.3, **k),
        lambda **k: kernel_Ergun(mi, mo, ph, 0.3, opt, A_RHO, **k),
        lambda **k: kernel_Ergun_basis(mi, mo, ph, 0.3, opt.c, opt.R, A_RHO, **k),
        lambda **k: flake_ndf_at_halfvector(mi, mo, ph, 0.3, **k),
        lambda **k: kernel_phi_bandwidth(0.3, mi[:30], mo[:30], **k),
        lambda **k: sample_flake_normal(mi[:30] * 0.5 + 0.5, mo[:30] * 0.5 + 0.5, 0.3, **k),
    ]
    for f in calls:
        np.testing.assert_array_equal(f(), f(distribution="beckmann"))
        assert not np.array_equal(f(), f(distribution="ggx"))
    np.testing.assert_array_equal(projected_area(mu, 0.3), projected_area_Beckmann(mu, 0.3))
    assert FlakeMedium(0.3, opt, A_RHO).phi_bandwidth < FlakeMedium(0.3, opt, A_RHO, "ggx").phi_bandwidth


# ------------------------------------------------------------------------------------------------
# σ_t and σ_s: the GGX moment quadrature against an independent one
# ------------------------------------------------------------------------------------------------


def smooth_gl(a, b, n):
    """GL on [a, b] through the smoothstep map t = 3v² − 2v³ (zero slope at both ends: √-type endpoint
    behaviour becomes analytic)."""
    v, w = gl(0.0, 1.0, n)
    return a + (b - a) * v * v * (3 - 2 * v), (b - a) * w * 6 * v * (1 - v)


def reference_cosine_integral(mu, alpha, F, edges, ndf, nc=96, npsi=64):
    """∫_{S²} F(|ω·m|) |ω·m| D(m) dm in coordinates about ω: m = c ω + √(1−c²)(cos ψ e1 + sin ψ e2),
    dm = dc dψ (e1_z = s).  GL in c on each segment where F is linear, split at c = 0 and at c = s =
    √(1−μ²) (where the horizon m_z = 0 starts to cross the ψ circle), and GL in ψ ∈ [0, π] (even) split
    where m_z = 0: GGX's density has a |cos θ_m| kink there (Beckmann's is flat to all orders); both
    smoothstep-mapped (:func:`smooth_gl`)."""
    s = np.sqrt(1 - mu**2)
    x, wx = smooth_gl(0.0, 1.0, npsi)
    edges = np.unique(np.concatenate([edges, [s]]))
    tot = 0.0
    for a, b in zip(edges[:-1], edges[1:]):
        c, wc = smooth_gl(a, b, nc)
        sc = np.sqrt(1 - c**2) * s
        for sign in (1.0, -1.0):
            psi0 = np.arccos(np.clip(sign * c * mu / np.maximum(sc, 1e-300), -1, 1))
            P = 0.0
            for lo, hi in ((np.zeros_like(psi0), psi0), (psi0, np.full_like(psi0, np.pi))):
                psi = lo[:, None] + (hi - lo)[:, None] * x
                mz = -sign * c[:, None] * mu + sc[:, None] * np.cos(psi)
                P = P + 2 * np.sum((hi - lo)[:, None] * wx * ndf(mz, alpha), axis=1)
            tot = tot + np.sum(wc * F(c) * c * P, axis=-1)
    return tot


@pytest.mark.parametrize("alpha", [0.05, 0.4, 2.0])
def test_ggx_sigma_against_independent_quadrature(alpha):
    opt = tabulated_optics()
    mus = np.array([0.05, 0.45, 1.0])
    st = extinction_Ergun(mus, alpha, opt, A_RHO, distribution="ggx")
    ss = scattering_Ergun(mus, alpha, opt, A_RHO, distribution="ggx")
    for ch in range(2):
        for j, mu in enumerate(mus):
            ref_t = reference_cosine_integral(mu, alpha, lambda c: 1 - np.interp(c, opt.c, opt.T[ch]), opt.c, flake_ndf_GGX)
            ref_s = reference_cosine_integral(mu, alpha, lambda c: np.interp(c, opt.c, opt.R[ch]), opt.c, flake_ndf_GGX)
            assert st[ch, j] == pytest.approx(A_RHO * ref_t, rel=1e-11)
            assert ss[ch, j] == pytest.approx(A_RHO * ref_s, rel=1e-11)


@pytest.mark.parametrize("alpha", [0.01, 0.05, 0.3, 2.0])
def test_ggx_sigma_quadrature_converges(alpha):
    opt = tabulated_optics()
    mus = np.array([[0.0, 0.1, 0.5], [0.77, 0.99, 1.0]])
    lo = extinction_Ergun(mus, alpha, opt, A_RHO, n_quad=16, distribution="ggx")
    mid = extinction_Ergun(mus, alpha, opt, A_RHO, n_quad=24, distribution="ggx")
    hi = extinction_Ergun(mus, alpha, opt, A_RHO, n_quad=64, distribution="ggx")
    np.testing.assert_allclose(mid, hi, rtol=1e-13)
    np.testing.assert_allclose(lo, hi, rtol=1e-10)
    np.testing.assert_array_equal(extinction_Ergun(-mus, alpha, opt, A_RHO, distribution="ggx"), mid)


def test_ggx_projected_area_at_normal_incidence_and_small_alpha():
    # μ = 1: E|cos θ_m| = 4π ∫_0^{π/2} cos θ D sin θ dθ (1-D, adaptive)
    for alpha in (0.1, 0.8, 2.0):
        ref = 4 * np.pi * integrate.quad(lambda t: np.cos(t) * np.sin(t) * flake_ndf_GGX(np.cos(t), alpha),
                                         0, np.pi / 2, points=[np.arctan(alpha)], epsabs=0, epsrel=1e-13, limit=400)[0]
        assert projected_area(1.0, alpha, distribution="ggx") == pytest.approx(ref, rel=1e-12)
    mus = np.linspace(-1, 1, 21)
    pa = projected_area(mus, 1e-3, distribution="ggx")
    assert np.max(np.abs(pa - np.abs(mus))) < 0.05  # flakes parallel to the surface as α → 0


def test_ggx_sigma_against_monte_carlo():
    rng = np.random.default_rng(13)
    alpha, n = 0.5, 200_000
    opt = tabulated_optics()
    m = sample_flake_normal_GGX(rng.random(n), rng.random(n), alpha)
    for mu in (0.2, -0.7):
        c = np.abs(m @ direction(mu, 0.4))
        for vals, fn in ((1 - opt.transmittance(c), extinction_Ergun), (opt.reflectance(c), scattering_Ergun)):
            sample = A_RHO * vals * c
            est, err = sample.mean(axis=1), sample.std(axis=1) / np.sqrt(n)
            assert np.all(np.abs(fn(mu, alpha, opt, A_RHO, distribution="ggx") - est) < 5 * err)


# ------------------------------------------------------------------------------------------------
# The kernel
# ------------------------------------------------------------------------------------------------


def kernel_sphere_integral(mu_i, alpha, opt, dist, n=32):
    """∫_{S²} kernel dω_o in polar coordinates (β, γ) about ω_i, with the panels of
    tests/rt/test_microflake.py (mirror lobe, kinks of R(c), the ridge μ_o = μ_i where h is horizontal:
    for GGX a kink of D, split in γ at every β)."""
    wi = direction(mu_i, 0.0)
    s_i = np.sqrt(1 - mu_i**2)
    e1, e2 = np.array([mu_i, 0.0, s_i]), np.array([0.0, 1.0, 0.0])
    beta_r = np.arccos(np.clip(s_i**2 - mu_i**2, -1, 1))
    w = 2 * alpha * np.array([0.25, 0.5, 1, 2, 4, 8, 16])
    beta_end = 2 * np.arctan(s_i / abs(mu_i))
    bb = np.concatenate([[0, np.pi, beta_end], beta_r + w, beta_r - w, 2 * np.arcsin(opt.c)])
    beta, wb = panels(np.clip(bb, 0, np.pi), n)
    g_r = 0.0 if mu_i > 0 else np.pi
    gw = np.minimum(w / max(np.sin(beta_r), 1e-3), np.pi)
    ridge = np.arccos(np.clip(-mu_i * np.tan(beta / 2) / s_i, -1, 1))
    gb = np.concatenate([np.broadcast_to(np.clip([0, np.pi, *(g_r + gw), *(g_r - gw)], 0, np.pi), (beta.size, 16)),
                         ridge[:, None]], axis=1)
    gb.sort(axis=1)
    x, wx = np.polynomial.legendre.leggauss(n)
    ga, gbb = gb[:, :-1, None], gb[:, 1:, None]
    G = (0.5 * (gbb - ga) * x + 0.5 * (gbb + ga)).reshape(beta.size, -1)
    WG = (0.5 * (gbb - ga) * wx).reshape(beta.size, -1)
    B = np.broadcast_to(beta[:, None], G.shape)
    wo = (np.cos(B)[..., None] * wi + np.sin(B)[..., None] * (np.cos(G)[..., None] * e1 + np.sin(G)[..., None] * e2))
    mu_o, phi_o = mu_phi(wo)
    k = kernel_Ergun(mu_i, mu_o, phi_o, alpha, opt, A_RHO, dist)
    return 2 * np.einsum("cij,ij,i->c", k * np.sin(B), WG, wb)


@pytest.mark.parametrize("alpha", [0.05, 0.3, 1.0])
def test_ggx_kernel_integrates_to_sigma_s(alpha):
    opt = tabulated_optics()
    for mu_i in (0.2, 0.6, 0.95, -0.45):
        total = kernel_sphere_integral(mu_i, alpha, opt, "ggx")
        np.testing.assert_allclose(total, scattering_Ergun(mu_i, alpha, opt, A_RHO, distribution="ggx"), rtol=1e-8)


def test_ggx_kernel_reciprocity_evenness_positivity():
    rng = np.random.default_rng(14)
    mu_i, mu_o, ph = rng.uniform(-1, 1, 3000), rng.uniform(-1, 1, 3000), rng.uniform(-np.pi, np.pi, 3000)
    opt = tabulated_optics()
    for alpha in (0.1, 0.5):
        k = kernel_Ergun(mu_i, mu_o, ph, alpha, opt, A_RHO, "ggx")
        np.testing.assert_allclose(kernel_Ergun(-mu_o, -mu_i, -ph, alpha, opt, A_RHO, "ggx"), k, rtol=1e-12, atol=1e-300)
        np.testing.assert_allclose(kernel_Ergun(mu_i, mu_o, -ph, alpha, opt, A_RHO, "ggx"), k, rtol=1e-12, atol=1e-300)
        assert np.all(k >= 0) and np.all(np.isfinite(k))
        # (aρ/2) R(c) D(h), D from the density at h = normalize(ω_o − ω_i) computed here
        h = direction(mu_o, ph) - direction(mu_i, 0.0)
        c = np.linalg.norm(h, axis=-1) / 2
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        np.testing.assert_allclose(k, 0.5 * A_RHO * opt.reflectance(c) * flake_ndf_GGX(h[:, 2], alpha), rtol=1e-10)


@pytest.mark.parametrize("alpha", [0.05, 0.1, 0.3, 1.0])
def test_ggx_phi_bandwidth_estimate_against_fft(alpha):
    """The GGX estimate is never below what the kernel needs, and within a factor 3.5 (+30) of it (the
    tail-sum bound is conservative for transmission-like pairs near the diagonal)."""
    eps = 1e-6
    opt = FlakeOptics.constant(0.7, 0.2)
    kmax = 0.5 * A_RHO * 0.7 * max(flake_ndf_GGX(np.linspace(1e-3, 1, 20001), alpha))
    n = 2**15
    phi = np.arange(n) * 2 * np.pi / n
    pairs = [(0.5, -0.5), (0.3, -0.7), (0.9, -0.2), (0.1, -0.1), (0.3, 0.6), (-0.4, 0.8), (0.2, 0.25)]
    for mu_i, mu_o in pairs:
        L = int(kernel_phi_bandwidth(alpha, mu_i, mu_o, eps, distribution="ggx"))
        coef = np.abs(np.fft.rfft(kernel_Ergun(mu_i, mu_o, phi, alpha, opt, A_RHO, "ggx")[0]).real) * 2 / n
        above = np.nonzero(coef > eps * kmax)[0]
        needed = above.max() if above.size else 0
        assert needed <= L <= 3.5 * needed + 30, (mu_i, mu_o, L, needed)
    assert kernel_phi_bandwidth(alpha, 1.0, -0.3, distribution="ggx") == 0


@pytest.mark.parametrize("dist", DISTS)
def test_first_phi_guess_resolves_the_mirror_lobe(dist):
    """FlakeMedium.phi_bandwidth (the projection's first number of φ intervals) is at least the Nyquist
    count 2 L of the 45° mirror pair's orders (eps 1e-6) for α ∈ [0.02, 1] (Beckmann's guess falls
    below it at α = 2: 16 intervals for L = 11)."""
    mu = np.cos(np.pi / 4)
    for alpha in (0.02, 0.05, 0.1, 0.3, 0.6, 1.0):
        L = int(kernel_phi_bandwidth(alpha, mu, -mu, 1e-6, distribution=dist))
        assert FlakeMedium(alpha, FlakeOptics.constant(0.5, 0.2), 1.0, dist).phi_bandwidth >= 2 * L, (alpha, L)


# ------------------------------------------------------------------------------------------------
# Sampling
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("alpha", [0.1, 0.7])
def test_ggx_sampler_matches_density(alpha):
    rng = np.random.default_rng(15)
    n = 200_000
    m = sample_flake_normal(rng.random(n), rng.random(n), alpha, "ggx")
    assert m.shape == (n, 3) and np.all(m[:, 2] > 0)
    np.testing.assert_allclose(np.linalg.norm(m, axis=-1), 1, rtol=1e-14)
    th_edges = np.unique(np.concatenate([[0, np.pi / 2], np.arctan(alpha * np.geomspace(0.1, 30, 14))]))
    probs = []
    for a, b in zip(th_edges[:-1], th_edges[1:]):
        th, w = gl(a, b, 40)
        probs.append(np.sum(w * 2 * np.pi * np.sin(th) * 2 * flake_ndf_GGX(np.cos(th), alpha)))
    probs = np.outer(probs, np.full(8, 1 / 8)).ravel()
    assert probs.sum() == pytest.approx(1, rel=1e-10)
    th = np.arccos(np.clip(m[:, 2], -1, 1))
    ph = np.mod(np.arctan2(m[:, 1], m[:, 0]), 2 * np.pi)
    counts, _, _ = np.histogram2d(th, ph, bins=[th_edges, np.linspace(0, 2 * np.pi, 9)])
    keep = probs * n > 5
    chi2 = np.sum((counts.ravel()[keep] - n * probs[keep]) ** 2 / (n * probs[keep]))
    assert stats.chi2.sf(chi2, keep.sum() - 1) > 1e-3
    # moment: u = cos²θ_m has density α²/(1 + k u)², k = α² − 1, so E[u] = (α² ln α² − k)/k²
    a2 = alpha**2
    k = a2 - 1
    e_u = (a2 * np.log(a2) - k) / k**2
    ref = integrate.quad(lambda u: u * a2 / (1 + k * u) ** 2, 0, 1, epsabs=0, epsrel=1e-13)[0]
    assert e_u == pytest.approx(ref, rel=1e-10)
    u = m[:, 2] ** 2
    assert abs(u.mean() - e_u) < 5 * u.std() / np.sqrt(n)
