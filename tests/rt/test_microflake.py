"""The translucent micro-flake medium (flakedb.rt.scattering.microflake; paper eq. 2, 5-8; docs/model.md §3).

Guards against: a Beckmann density normalised over the wrong domain (π vs 2π, hemisphere vs
sphere); a half-vector formula (eq. 6-7) in the wrong angle convention (μ' ↔ −μ', cos φ sign,
φ_d = 0 forward vs backward) or with the paper's typos copied; NaN at degenerate geometries; a
kernel whose half-vector Jacobian (the 1/4) or two-sided flake factor is wrong, so that it does
not integrate to σ_s; broken reciprocity; σ_t/σ_s quadratures that are inaccurate (the |ω·m| kink,
the kinks of a tabulated R(c), narrow flake distributions) or that are not even in μ; the pigment
reduction (eq. 8) with a wrong 8π or uniform density; a flake-normal sampler that does not follow
D; a Fourier-bandwidth estimate that is too small.  All references here are written independently
of the module's internals (other coordinates, other quadratures, Monte Carlo).
"""

import numpy as np
import pytest
from scipy import integrate, stats

from flakedb.rt.scattering.microflake import (
    UNIFORM_NDF_PER_SR,
    FlakeOptics,
    extinction_Ergun,
    flake_ndf_Beckmann,
    kernel_Ergun,
    kernel_phi_bandwidth,
    ndf_halfvector_Ergun,
    phase_HG,
    pigment_extinction_Ergun,
    pigment_kernel_Ergun,
    pigment_scattering_Ergun,
    projected_area_Beckmann,
    sample_flake_normal_Beckmann,
    scattering_Ergun,
)
from tests import tolerances as tol

A_RHO = 0.37  # aρ in 1/µm, arbitrary


def direction(mu, phi):
    """Propagation direction in flakedb's conventions: (s cos φ, s sin φ, −μ), z up."""
    mu, phi = np.broadcast_arrays(np.asarray(mu, float), np.asarray(phi, float))
    s = np.sqrt(1.0 - mu**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), -mu], axis=-1)


def mu_phi(w):
    return -w[..., 2], np.arctan2(w[..., 1], w[..., 0])


def gl(a, b, n):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (b - a) * x + 0.5 * (a + b), 0.5 * (b - a) * w


def panels(breaks, n):
    breaks = np.unique(np.asarray(breaks, float))
    xs, ws = zip(*(gl(a, b, n) for a, b in zip(breaks[:-1], breaks[1:])))
    return np.concatenate(xs), np.concatenate(ws)


def tabulated_optics():
    """Two channels, R and T piecewise linear in c with kinks at interior nodes."""
    c = np.array([0.0, 0.15, 0.4, 0.7, 0.85, 1.0])
    R = np.array([[0.9, 0.5, 0.3, 0.25, 0.2, 0.18], [0.1, 0.2, 0.05, 0.4, 0.3, 0.6]])
    T = np.array([[0.05, 0.3, 0.5, 0.6, 0.65, 0.7], [0.0, 0.6, 0.8, 0.3, 0.5, 0.2]])
    return FlakeOptics(c, R, T)


# ------------------------------------------------------------------------------------------------
# Flake normal density, eq. 5
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("alpha", [0.05, 0.1, 0.3, 0.6, 1.0])
def test_beckmann_integrates_to_one_over_the_sphere(alpha):
    # θ quadrature with panels at multiples of α; both hemispheres explicitly (cos θ < 0 too).
    th, w = panels(np.concatenate([[0.0, np.pi / 2], np.clip(alpha * np.array([0.5, 1, 2, 3, 4, 6, 9]), 0, np.pi / 2)]), 60)
    upper = np.sum(w * 2 * np.pi * np.sin(th) * flake_ndf_Beckmann(np.cos(th), alpha))
    lower = np.sum(w * 2 * np.pi * np.sin(th) * flake_ndf_Beckmann(np.cos(np.pi - th), alpha))
    # 2π (not π) in eq. 5: each hemisphere carries 1/2, the sphere 1 (both ±m carry density)
    assert upper == pytest.approx(0.5, rel=1e-12)
    assert upper + lower == pytest.approx(1.0, rel=1e-12)


def test_beckmann_is_even_and_finite():
    rng = np.random.default_rng(1)
    m = rng.normal(size=(1000, 3))
    m /= np.linalg.norm(m, axis=-1, keepdims=True)
    for alpha in (0.05, 0.5, 2.0):
        np.testing.assert_array_equal(flake_ndf_Beckmann(m[:, 2], alpha), flake_ndf_Beckmann(-m[:, 2], alpha))  # exact: of |cos θ_m|
    with np.errstate(divide="raise", invalid="raise", over="raise"):
        d = flake_ndf_Beckmann(np.array([0.0, 1e-300, -1e-10, 1.0, -1.0]), 0.05)
    assert d[0] == 0.0 and d[1] == 0.0 and np.all(np.isfinite(d))
    assert d[3] == pytest.approx(1.0 / (2 * np.pi * 0.05**2))
    with pytest.raises(ValueError, match="alpha"):
        flake_ndf_Beckmann(0.5, 0.0)


# ------------------------------------------------------------------------------------------------
# D at the half vector, eq. 6-7
# ------------------------------------------------------------------------------------------------


def scattered_pairs(rng, n, alpha):
    """Random ω_i and ω_o = reflection of ω_i by a Beckmann flake (either face, both hemispheres of
    ω_o occur), plus uniformly random pairs."""
    wi = direction(rng.uniform(-1, 1, n), rng.uniform(0, 2 * np.pi, n))
    m = sample_flake_normal_Beckmann(rng.random(n), rng.random(n), alpha) * rng.choice([-1.0, 1.0], n)[:, None]
    wo = wi - 2 * np.sum(wi * m, -1, keepdims=True) * m
    wr = direction(rng.uniform(-1, 1, n), rng.uniform(0, 2 * np.pi, n))
    return np.concatenate([wi, wi]), np.concatenate([wo, wr])


@pytest.mark.parametrize("alpha", [0.05, 0.3, 1.0])
def test_halfvector_closed_form_matches_direct_evaluation(alpha):
    rng = np.random.default_rng(2)
    wi, wo = scattered_pairs(rng, 4000, alpha)
    mu_i, phi_i = mu_phi(wi)
    mu_o, phi_o = mu_phi(wo)
    h = wo - wi
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    direct = flake_ndf_Beckmann(h[:, 2], alpha)
    closed = ndf_halfvector_Ergun(mu_i, mu_o, phi_o - phi_i, alpha)
    refl = mu_i * mu_o < 0
    assert refl.sum() > 1000 and (~refl).sum() > 1000  # both kinds of configuration are tested
    big = direct > 1e-250
    np.testing.assert_allclose(closed[big], direct[big], rtol=1e-9)
    np.testing.assert_allclose(closed[~big], direct[~big], atol=1e-250)


def test_halfvector_literal_paper_formula():
    """Eq. 6-7 exactly as printed (A + B cos φ, f_rem), with μ = μ_i, μ' = μ_o of propagation
    directions and φ = φ_d: no sign flips needed, no typos (moderate α, where A + B cos φ has no
    catastrophic cancellation)."""
    rng = np.random.default_rng(3)
    mu, mup, phi = rng.uniform(-1, 1, 500), rng.uniform(-1, 1, 500), rng.uniform(0, 2 * np.pi, 500)
    alpha = 0.7
    sq = np.sqrt((1 - mu**2) * (1 - mup**2))
    f_rem = (1 - mu * mup - sq * np.cos(phi)) ** 1.5
    A = (mu**2 + mup**2 - 2) / (alpha**2 * (mu - mup) ** 2)
    B = 2 * sq / (alpha**2 * (mu - mup) ** 2)
    paper = 2**0.5 * f_rem * np.exp(A + B * np.cos(phi)) / (alpha**2 * np.pi * np.abs(mu - mup) ** 3)
    np.testing.assert_allclose(ndf_halfvector_Ergun(mu, mup, phi, alpha), paper, rtol=1e-9, atol=1e-300)


def test_halfvector_degenerate_cases_without_nan():
    mu = np.array([0.3, 0.3, -0.8, 1.0, 1.0, 0.0, -1.0])
    mo = np.array([0.3, 0.3, -0.8, 1.0, -1.0, 0.0, 1.0])
    ph = np.array([0.0, 1.0, np.pi, 0.7, 0.3, 2.0, 0.0])
    with np.errstate(divide="raise", invalid="raise", over="raise"):
        d = ndf_halfvector_Ergun(mu, mo, ph, 0.2)
        k = kernel_Ergun(mu, mo, ph, 0.2, FlakeOptics.constant(0.8, 0.1), A_RHO)
    assert np.all(np.isfinite(d)) and np.all(np.isfinite(k))
    # ω_o = ω_i: 0 by definition; μ_o = μ_i, φ_d ≠ 0: horizontal h, D → 0
    assert d[0] == 0 and d[1] == 0 and d[2] == 0 and d[3] == 0 and d[5] == 0
    # exact backscatter along the normal: h = ±z, D = 1/(2πα²)
    assert d[4] == pytest.approx(1 / (2 * np.pi * 0.04)) and d[6] == pytest.approx(1 / (2 * np.pi * 0.04))
    # continuity: μ_o → μ_i at φ_d ≠ 0 tends to the returned 0
    assert ndf_halfvector_Ergun(0.3, 0.3 + 1e-7, 1.0, 0.2) == 0.0


# ------------------------------------------------------------------------------------------------
# σ_t and σ_s (eq. 2)
# ------------------------------------------------------------------------------------------------


def reference_cosine_integral(mu, alpha, F, edges, nc=64, npsi=1024):
    """∫_{S²} F(|ω·m|) |ω·m| D(m) dm in coordinates around ω: m = c ω + √(1−c²)(cos ψ e1 + sin ψ e2),
    dm = dc dψ; GL in c on each segment where F is linear (split at c = 0), trapezoid in ψ."""
    s = np.sqrt(1 - mu**2)
    psi = np.arange(npsi) * 2 * np.pi / npsi
    tot = 0.0
    for a, b in zip(edges[:-1], edges[1:]):
        c, wc = gl(a, b, nc)
        for sign in (1.0, -1.0):
            mz = -sign * c[:, None] * mu + np.sqrt(1 - c[:, None] ** 2) * s * np.cos(psi)  # e1_z = s
            P = 2 * np.pi * flake_ndf_Beckmann(mz, alpha).mean(axis=1)
            tot = tot + np.sum(wc * F(c) * c * P, axis=-1)
    return tot


@pytest.mark.parametrize("alpha", [0.3, 1.0])
def test_sigma_against_independent_quadrature_tabulated_optics(alpha):
    opt = tabulated_optics()
    mus = np.array([0.05, 0.45, 0.93])
    st = extinction_Ergun(mus, alpha, opt, A_RHO)
    ss = scattering_Ergun(mus, alpha, opt, A_RHO)
    assert st.shape == ss.shape == (2, 3)
    edges = opt.c
    for ch in range(2):
        for j, mu in enumerate(mus):
            ref_t = reference_cosine_integral(mu, alpha, lambda c: 1 - np.interp(c, opt.c, opt.T[ch]), edges)
            ref_s = reference_cosine_integral(mu, alpha, lambda c: np.interp(c, opt.c, opt.R[ch]), edges)
            assert st[ch, j] == pytest.approx(A_RHO * ref_t, rel=1e-10)
            assert ss[ch, j] == pytest.approx(A_RHO * ref_s, rel=1e-10)


def test_sigma_against_monte_carlo():
    rng = np.random.default_rng(4)
    alpha, n = 0.5, 200_000
    opt = tabulated_optics()
    m = sample_flake_normal_Beckmann(rng.random(n), rng.random(n), alpha)  # sign irrelevant: |ω·m|
    for mu in (0.2, -0.7):
        c = np.abs(m @ direction(mu, 0.4))
        for vals, fn in ((1 - opt.transmittance(c), extinction_Ergun), (opt.reflectance(c), scattering_Ergun)):
            sample = A_RHO * vals * c
            est, err = sample.mean(axis=1), sample.std(axis=1) / np.sqrt(n)
            assert np.all(np.abs(fn(mu, alpha, opt, A_RHO) - est) < 5 * err)


def test_projected_area_limits_and_constant_optics():
    mus = np.linspace(-1, 1, 21)
    # α → 0: flakes parallel to the surface, projected area → |μ| (error O(α) at grazing μ)
    for alpha in (1e-2, 1e-3):
        pa = projected_area_Beckmann(mus, alpha)
        assert np.max(np.abs(pa - np.abs(mus))) < 1.5 * alpha
    assert projected_area_Beckmann(0.6, 1e-3) == pytest.approx(0.6 * (1 - 0.5e-6), rel=1e-9)  # |μ| E[cos θ_m]
    # at normal incidence it is E|cos θ_m| = ∫ e^{-u}/√(1+α²u) du exactly
    ref = integrate.quad(lambda u: np.exp(-u) / np.sqrt(1 + 0.8**2 * u), 0, np.inf, epsabs=0, epsrel=1e-13)[0]
    assert projected_area_Beckmann(1.0, 0.8) == pytest.approx(ref, rel=1e-12)
    # constant T, R: σ_t = (1 − T) aρ × area, σ_s = R aρ × area; even in μ
    opt = FlakeOptics.constant([0.6, 0.2], [0.3, 0.0])
    pa = projected_area_Beckmann(mus, 0.25)
    np.testing.assert_allclose(extinction_Ergun(mus, 0.25, opt, A_RHO), A_RHO * np.array([[0.7], [1.0]]) * pa, rtol=1e-13)
    np.testing.assert_allclose(scattering_Ergun(mus, 0.25, opt, A_RHO), A_RHO * np.array([[0.6], [0.2]]) * pa, rtol=1e-13)
    np.testing.assert_array_equal(projected_area_Beckmann(-mus, 0.25), pa)  # even in μ


@pytest.mark.parametrize("alpha", [0.02, 0.2, 2.0])
def test_sigma_quadrature_converges(alpha):
    opt = tabulated_optics()
    mus = np.array([[0.0, 0.1, 0.5], [0.77, 0.99, 1.0]])
    lo = extinction_Ergun(mus, alpha, opt, A_RHO, n_quad=16)
    mid = extinction_Ergun(mus, alpha, opt, A_RHO, n_quad=24)
    hi = extinction_Ergun(mus, alpha, opt, A_RHO, n_quad=48)
    assert mid.shape == (2, 2, 3)
    np.testing.assert_allclose(mid, hi, rtol=1e-12)
    np.testing.assert_allclose(lo, hi, rtol=1e-9)
    np.testing.assert_array_equal(extinction_Ergun(-mus, alpha, opt, A_RHO), mid)  # even in μ


def test_flake_optics_validation():
    with pytest.raises(ValueError, match="R \\+ T <= 1"):
        FlakeOptics.constant(0.7, 0.4)
    with pytest.raises(ValueError, match="R >= 0"):
        FlakeOptics.constant(-0.1, 0.4)
    with pytest.raises(ValueError, match="ascending"):
        FlakeOptics([0.5, 0.2], [[0.1, 0.1]], [[0.1, 0.1]])
    with pytest.raises(ValueError, match="shape"):
        FlakeOptics([0.0, 1.0], [[0.1, 0.1, 0.1]], [[0.1, 0.1, 0.1]])
    FlakeOptics.constant(0.6, 0.4 + 1e-13)  # within the 1e-12 tolerance
    opt = FlakeOptics.constant(0.5, 0.2, channels=3)
    assert opt.R.shape == (3, 2) and opt.reflectance(np.zeros((4, 5))).shape == (3, 4, 5)


# ------------------------------------------------------------------------------------------------
# The kernel σ_s f_p (eq. 2)
# ------------------------------------------------------------------------------------------------


def kernel_sphere_integral(mu_i, alpha, opt, n=32):
    """∫_{S²} kernel(ω_i → ω_o) dω_o in polar coordinates (β, γ) about ω_i itself (so the
    direction-dependent limit at ω_o = ω_i sits at the pole).  β panels: at the mirror lobe
    (β_r = angle between ω_i and its mirror image about the horizontal plane), at the kinks of R(c)
    (c = |ω_o − ω_i|/2 = sin(β/2)) and where the ridge μ_o = μ_i (horizontal h, where D is C∞ but
    not analytic) ends; γ panels, per β node: at the ridge cos γ = −μ_i tan(β/2)/s_i and around
    the lobe azimuth."""
    wi = direction(mu_i, 0.0)
    s_i = np.sqrt(1 - mu_i**2)
    e1, e2 = np.array([mu_i, 0.0, s_i]), np.array([0.0, 1.0, 0.0])
    beta_r = np.arccos(np.clip(s_i**2 - mu_i**2, -1, 1))
    w = 2 * alpha * np.array([0.5, 1, 2, 4, 8])
    beta_end = 2 * np.arctan(s_i / abs(mu_i))
    bb = np.concatenate([[0, np.pi, beta_end], beta_r + w, beta_r - w, 2 * np.arcsin(opt.c)])
    beta, wb = panels(np.clip(bb, 0, np.pi), n)
    g_r = 0.0 if mu_i > 0 else np.pi  # azimuth of the lobe about ω_i
    gw = np.minimum(w / max(np.sin(beta_r), 1e-3), np.pi)
    ridge = np.arccos(np.clip(-mu_i * np.tan(beta / 2) / s_i, -1, 1))
    gb = np.concatenate([np.broadcast_to(np.clip([0, np.pi, *(g_r + gw), *(g_r - gw)], 0, np.pi), (beta.size, 12)),
                         ridge[:, None]], axis=1)
    gb.sort(axis=1)
    x, wx = np.polynomial.legendre.leggauss(n)
    ga, gbb = gb[:, :-1, None], gb[:, 1:, None]
    G = (0.5 * (gbb - ga) * x + 0.5 * (gbb + ga)).reshape(beta.size, -1)
    WG = (0.5 * (gbb - ga) * wx).reshape(beta.size, -1)
    B = np.broadcast_to(beta[:, None], G.shape)
    wo = (np.cos(B)[..., None] * wi + np.sin(B)[..., None] * (np.cos(G)[..., None] * e1 + np.sin(G)[..., None] * e2))
    mu_o, phi_o = mu_phi(wo)
    k = kernel_Ergun(mu_i, mu_o, phi_o, alpha, opt, A_RHO)
    return 2 * np.einsum("cij,ij,i->c", k * np.sin(B), WG, wb)  # ×2: γ ∈ [−π, 0] by symmetry


@pytest.mark.parametrize("alpha", [0.05, 0.2, 1.0])
def test_kernel_integrates_to_sigma_s(alpha):
    opt = tabulated_optics()
    for mu_i in (0.2, 0.6, 0.95, -0.45):
        total = kernel_sphere_integral(mu_i, alpha, opt)
        np.testing.assert_allclose(total, scattering_Ergun(mu_i, alpha, opt, A_RHO), rtol=1e-9)


def test_kernel_reciprocity_and_evenness():
    rng = np.random.default_rng(5)
    mu_i, mu_o, ph = rng.uniform(-1, 1, 3000), rng.uniform(-1, 1, 3000), rng.uniform(-np.pi, np.pi, 3000)
    opt = tabulated_optics()
    for alpha in (0.1, 0.5):
        k = kernel_Ergun(mu_i, mu_o, ph, alpha, opt, A_RHO)
        # ω_i → ω_o versus −ω_o → −ω_i: (μ, φ) → (−μ, φ + π), so φ_d → −φ_d
        np.testing.assert_allclose(kernel_Ergun(-mu_o, -mu_i, -ph, alpha, opt, A_RHO), k, rtol=1e-12, atol=1e-300)
        np.testing.assert_allclose(kernel_Ergun(mu_i, mu_o, -ph, alpha, opt, A_RHO), k, rtol=1e-12, atol=1e-300)
        assert np.all(k >= 0) and k.shape == (2, 3000)


def test_opaque_flakes_reduce_to_Jakob_2010():
    """T = 0: Jakob et al. 2010's specular micro-flakes (their §5, as in Jakob's Mitsuba 0.5
    phase/microflake.cpp): f_p(ω → ω') = D(h)/(2 σ(ω)) with ω pointing back toward the light,
    h = normalize(ω + ω'), σ(ω) = ∫ |ω·m| D(m) dm, and σ_s = aρ r σ(ω) for flake albedo r."""
    rng = np.random.default_rng(6)
    alpha, r = 0.3, 0.8
    wi, wo = scattered_pairs(rng, 2000, alpha)
    w_light = -wi  # graphics convention
    h = w_light + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    mu_i, phi_i = mu_phi(wi)
    mu_o, phi_o = mu_phi(wo)
    sigma = extinction_Ergun(mu_i, alpha, FlakeOptics.constant(0.0, 0.0), 1.0)[0]  # projected area
    jakob = (A_RHO * r * sigma) * flake_ndf_Beckmann(h[:, 2], alpha) / (2 * sigma)
    for T in (0.0, 0.15):  # the transmittance does not enter the kernel, only σ_t
        k = kernel_Ergun(mu_i, mu_o, phi_o - phi_i, alpha, FlakeOptics.constant(r, T), A_RHO)[0]
        np.testing.assert_allclose(k, jakob, rtol=1e-10, atol=1e-300)
    ss = scattering_Ergun(mu_i[:50], alpha, FlakeOptics.constant(r, 0.0), A_RHO)[0]
    np.testing.assert_allclose(ss, A_RHO * r * sigma[:50], rtol=1e-13)


def test_kernel_uses_the_closed_form_ndf():
    rng = np.random.default_rng(7)
    opt = tabulated_optics()
    mu_i, mu_o, ph = rng.uniform(-1, 1, 2000), rng.uniform(-1, 1, 2000), rng.uniform(0, 2 * np.pi, 2000)
    c = np.linalg.norm(direction(mu_o, ph) - direction(mu_i, 0.0), axis=-1) / 2  # |ω_i·h|
    k = kernel_Ergun(mu_i, mu_o, ph, 0.4, opt, A_RHO)
    expected = 0.5 * A_RHO * opt.reflectance(c) * ndf_halfvector_Ergun(mu_i, mu_o, ph, 0.4)
    np.testing.assert_allclose(k, expected, rtol=1e-10, atol=1e-300)


@pytest.mark.parametrize("alpha", [0.05, 0.1, 0.3, 1.0])
def test_phi_bandwidth_estimate_against_fft(alpha):
    eps = 1e-6
    opt = FlakeOptics.constant(0.7, 0.2)
    kmax = 0.5 * A_RHO * 0.7 * max(flake_ndf_Beckmann(np.linspace(1e-3, 1, 20001), alpha))
    n = 2**14
    phi = np.arange(n) * 2 * np.pi / n
    pairs = [(0.5, -0.5), (0.3, -0.7), (0.9, -0.2), (0.1, -0.1), (0.3, 0.6), (-0.4, 0.8), (0.2, 0.25)]
    for mu_i, mu_o in pairs:
        L = int(kernel_phi_bandwidth(alpha, mu_i, mu_o, eps))
        coef = np.abs(np.fft.rfft(kernel_Ergun(mu_i, mu_o, phi, alpha, opt, A_RHO)[0]).real) * 2 / n
        above = np.nonzero(coef > eps * kmax)[0]
        needed = above.max() if above.size else 0
        assert needed <= L <= 2.5 * needed + 10, (mu_i, mu_o, L, needed)
    assert kernel_phi_bandwidth(alpha, 1.0, -0.3) == 0  # μ = ±1: no φ dependence


# ------------------------------------------------------------------------------------------------
# Pigments (eq. 8) and Henyey-Greenstein
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("g", [-0.5, 0.0, 0.3, 0.9])
def test_phase_HG_normalised_with_mean_cosine_g(g):
    norm = integrate.quad(lambda x: 2 * np.pi * phase_HG(x, g), -1, 1, epsabs=0, epsrel=1e-12, limit=200)[0]
    mean = integrate.quad(lambda x: 2 * np.pi * x * phase_HG(x, g), -1, 1, epsabs=1e-13, epsrel=1e-12, limit=200)[0]
    assert norm == pytest.approx(1.0, rel=1e-10) and mean == pytest.approx(g, abs=1e-10)


def test_pigment_kernel_is_the_isotropic_medium():
    rng = np.random.default_rng(8)
    mu_i, mu_o, ph = rng.uniform(-1, 1, 1000), rng.uniform(-1, 1, 1000), rng.uniform(0, 2 * np.pi, 1000)
    rho, csca, g = 3e-3, np.array([0.2, 0.5, 1.1]), np.array([0.6, 0.7, 0.8])
    k = pigment_kernel_Ergun(mu_i, mu_o, ph, rho, csca, lambda x: phase_HG(x, g[:, None]))
    cos_t = np.sum(direction(mu_i, 0.3) * direction(mu_o, 0.3 + ph), axis=-1)  # ω_i·ω_o
    np.testing.assert_allclose(k, rho * csca[:, None] * phase_HG(cos_t, g[:, None]), rtol=1e-12)


def test_pigment_coefficients_from_the_micro_flake_integrals():
    """Eq. 2 with the uniform density D = 1/(4π), evaluated by quadrature.  D is rotation invariant,
    so in coordinates about ω (c = ω·m, dm = dc dψ) the integrals are 1-D; the flake reflection of
    ω by m has cos Θ = ω·ω_o = 1 − 2c²."""
    rho, cext, csca = 2e-3, 1.7, 1.2
    quad = lambda f: 2 * np.pi * integrate.quad(f, -1, 1, points=[0.0], epsabs=0, epsrel=1e-13, limit=400)[0]
    # σ_t: opaque flakes (T = 0) of area a = 2 C_ext
    st = rho * 2 * cext * quad(lambda c: abs(c) * UNIFORM_NDF_PER_SR)
    assert st == pytest.approx(rho * cext, rel=1e-12)
    np.testing.assert_allclose(pigment_extinction_Ergun([0.3, -0.85], rho, cext), st, rtol=1e-12)
    for g in (0.0, 0.5, 0.85):
        # σ_s: a R(ω → ω_o(m)) = 8π C_sca p(ω·ω_o), eq. 8
        ss = rho * quad(lambda c: 8 * np.pi * csca * phase_HG(1 - 2 * c * c, g) * abs(c) * UNIFORM_NDF_PER_SR)
        assert ss == pytest.approx(rho * csca, rel=1e-10)
        np.testing.assert_allclose(pigment_scattering_Ergun([0.3, -0.85], rho, csca), ss, rtol=1e-10)


# ------------------------------------------------------------------------------------------------
# Sampling
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("alpha", [0.1, 0.7])
def test_sampler_matches_density(alpha):
    rng = np.random.default_rng(9)
    n = 200_000
    m = sample_flake_normal_Beckmann(rng.random(n), rng.random(n), alpha)
    assert m.shape == (n, 3) and np.all(m[:, 2] > 0)
    # components: cos_t 3 roundings, sin_t 5, cos φ / sin φ ≤ 2 ulps, × → ≤ 10u; |m|² ≤ 25u, √ halves it, + 1: ≤ 7 ulps
    tol.assert_ulps(np.linalg.norm(m, axis=-1), 1.0, 7)
    # bins in θ (edges at multiples of α) × 8 in φ; expected counts by quadrature of 2 D over the bin
    th_edges = np.unique(np.clip(np.concatenate([[0, np.pi / 2], alpha * np.linspace(0.25, 3, 12)]), 0, np.pi / 2))
    probs = []
    for a, b in zip(th_edges[:-1], th_edges[1:]):
        th, w = gl(a, b, 40)
        probs.append(np.sum(w * 2 * np.pi * np.sin(th) * 2 * flake_ndf_Beckmann(np.cos(th), alpha)))
    probs = np.outer(probs, np.full(8, 1 / 8)).ravel()
    assert probs.sum() == pytest.approx(1, rel=1e-10)
    th = np.arccos(np.clip(m[:, 2], -1, 1))
    ph = np.mod(np.arctan2(m[:, 1], m[:, 0]), 2 * np.pi)
    counts, _, _ = np.histogram2d(th, ph, bins=[th_edges, np.linspace(0, 2 * np.pi, 9)])
    keep = probs * n > 5
    chi2 = np.sum((counts.ravel()[keep] - n * probs[keep]) ** 2 / (n * probs[keep]))
    assert stats.chi2.sf(chi2, keep.sum() - 1) > 1e-3
    # moment: tan²θ_m is exponential with mean α²
    t2 = (1 - m[:, 2] ** 2) / m[:, 2] ** 2
    assert abs(t2.mean() - alpha**2) < 5 * t2.std() / np.sqrt(n)
