"""Flake orientation with a shape (issue #35 item 3): the Student-t family ``student_t(γ)`` and
two-population mixtures ``mix(first, w, second, α₂)`` of :data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS`.

Guards against: a Student-t density in the microfacet convention or with the wrong slope scale (it must be
GGX at γ = 2 and tend to Beckmann as γ → ∞, at the rate 1/γ); an inverse-CDF sampler that follows its
own (wrong) algebra instead of the density — checked against an **independent sampler** (the Student t
as a Gamma scale mixture of Gaussians, numpy's Gamma/exponential generators: tan²θ = α²(γ−1) E/G,
E ~ Exp(1), G ~ Gamma(γ−1)), χ² against ∫ 2 D(m) dm on bins; a CDF-space moment quadrature that misses the
heavy tail (γ = 1.5: D does not vanish at horizontal normals); mixtures whose moments, densities, samples
or names are not the weighted ones of their populations; canonical names that alias different parameters
(the store keys its factors by them); parameters outside their physical bounds accepted silently.
"""

import functools

import numpy as np
import pytest
from scipy import integrate, stats

from flakedb.rt.scattering.media import FlakeMedium
from flakedb.rt.scattering.microflake import (
    FLAKE_DISTRIBUTIONS,
    FlakeOptics,
    extinction_Ergun,
    flake_distribution,
    flake_ndf_Beckmann,
    flake_ndf_GGX,
    flake_ndf_StudentT,
    kernel_Ergun,
    kernel_phi_bandwidth,
    projected_area,
    sample_flake_normal,
    scattering_Ergun,
)
from tests.rt.test_flake_distributions import kernel_sphere_integral, reference_cosine_integral
from tests.rt.test_microflake import A_RHO, direction, gl, panels, tabulated_optics

SHAPES = [1.5, 1.75, 3.0, 20.0]
MIX = "mix(beckmann,0.3,student_t(1.75),0.5)"


def std(g):
    return f"student_t({g!r})"


def ndf_of(g):
    return functools.partial(flake_ndf_StudentT, gamma=g)


def independent_tan2(rng, n, alpha, g):
    """tan²θ_m of Student-t slopes drawn as a Gamma scale mixture of Gaussian (Beckmann) slopes:
    given the precision λ ~ Gamma(γ−1, rate γ−1), tan²θ/α² · λ ~ Exp(1) (Beckmann with α/√λ), and
    E[e^{−λx}] = (1 + x/(γ−1))^{1−γ} is the Student-t tail.  Shares nothing with the module's inverse CDF."""
    return alpha**2 * (g - 1.0) * rng.exponential(size=n) / rng.gamma(g - 1.0, size=n)


def theta_bin_probs(edges, ndf, alpha):
    """P(θ_m ∈ bin) on the upper hemisphere, ∫ 2 D(m) dm by Gauss-Legendre on each bin."""
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        th, w = gl(a, b, 60)
        out.append(np.sum(w * 2 * np.pi * np.sin(th) * 2 * ndf(np.cos(th), alpha)))
    return np.array(out)


def chi2_pvalue(theta, edges, probs):
    counts, _ = np.histogram(theta, bins=edges)
    n = theta.size
    keep = probs * n > 5
    chi2 = np.sum((counts[keep] - n * probs[keep]) ** 2 / (n * probs[keep]))
    return stats.chi2.sf(chi2, keep.sum() - 1)


# ------------------------------------------------------------------------------------------------
# The density: closed forms, limits, normalisation
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("alpha", [0.02, 0.3, 2.0])
def test_student_t_is_ggx_at_shape_2(alpha):
    c = np.linspace(0.0, 1.0, 2001)
    np.testing.assert_allclose(flake_ndf_StudentT(c, alpha, 2.0), flake_ndf_GGX(c, alpha), rtol=1e-13, atol=0)
    mu, lev = np.array([0.0, 0.3, 0.8, 1.0]), np.array([0.2, 0.7, 1.0])
    # the moments: CDF-space quadrature (student_t) against the θ-space one (GGX), independent codes
    np.testing.assert_allclose(flake_distribution("student_t(2)").abs_cosine_moments(mu, alpha, lev, 24),
                               flake_distribution("ggx").abs_cosine_moments(mu, alpha, lev, 24), rtol=1e-12, atol=1e-16)


def test_student_t_literal_form_and_beckmann_limit():
    alpha = 0.35
    th = np.linspace(0.0, np.pi / 2 - 1e-6, 3001)
    for g in (1.5, 2.5, 7.0):
        # the microfacet STD (γ−1)^γ / (π α² cos⁴θ ((γ−1) + tan²θ/α²)^γ) × cos θ / 2, literally
        lit = (g - 1) ** g / (np.pi * alpha**2 * np.cos(th) ** 4 * ((g - 1) + np.tan(th) ** 2 / alpha**2) ** g)
        np.testing.assert_allclose(flake_ndf_StudentT(np.cos(th), alpha, g), 0.5 * np.cos(th) * lit, rtol=1e-11)
    # γ → ∞: Beckmann, with an error falling like 1/γ ((1 + y/γ)^{−γ} = e^{−y}(1 + y²/(2γ) + O(γ⁻²)))
    c = np.cos(np.linspace(0.0, np.arctan(3 * alpha), 200))
    err = [np.max(np.abs(flake_ndf_StudentT(c, alpha, g) - flake_ndf_Beckmann(c, alpha))) for g in (100.0, 1000.0)]
    assert err[1] < 2e-3 * flake_ndf_Beckmann(1.0, alpha)
    assert err[0] / err[1] == pytest.approx(10.0, rel=0.05)


@pytest.mark.parametrize("dist", [std(g) for g in SHAPES] + [MIX])
@pytest.mark.parametrize("alpha", [0.02, 0.3, 2.0])
def test_density_is_even_and_normalised(dist, alpha):
    """∫_{S²} D dm = 1 (each hemisphere 1/2), by adaptive quadrature in θ (independent of the module's
    CDF) with the heavy tail (D ∝ |cos θ|^{2γ−3}) integrated to the horizon."""
    D = flake_distribution(dist)
    f = lambda t: 2 * np.pi * np.sin(t) * D.ndf(np.cos(t), alpha)  # noqa: E731
    pts = list(np.arctan(alpha * np.array([0.5, 1, 2, 4, 16, 64, 256, 1024])))
    upper = integrate.quad(f, 0, np.pi / 2, points=pts, epsabs=0, epsrel=1e-12, limit=500)[0]
    assert upper == pytest.approx(0.5, rel=1e-9)
    m = np.random.default_rng(1).normal(size=(500, 3))
    m /= np.linalg.norm(m, axis=-1, keepdims=True)
    np.testing.assert_array_equal(D.ndf(m[:, 2], alpha), D.ndf(-m[:, 2], alpha))
    assert np.all(np.isfinite(D.ndf(np.array([0.0, 1e-300, 1.0]), alpha)))


@pytest.mark.parametrize("dist", [std(g) for g in SHAPES] + [MIX, "mix(ggx,0.5,beckmann,0.05)"])
def test_peak_is_the_maximum(dist):
    D = flake_distribution(dist)
    c = np.linspace(0.0, 1.0, 200_001)
    for alpha in (0.05, 0.5, 1.0, 1.5, 2.0):
        top = D.ndf(c, alpha).max()
        assert D.peak(alpha) == pytest.approx(top, rel=1e-7) and D.peak(alpha) >= top * (1 - 1e-12)


# ------------------------------------------------------------------------------------------------
# Sampling against an independent sampler
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("g", [1.5, 2.5, 10.0])
@pytest.mark.parametrize("alpha", [0.1, 0.6])
def test_sampler_against_independent_sampler_and_density(g, alpha):
    n = 200_000
    rng = np.random.default_rng(int(100 * g + 10 * alpha))
    edges = np.unique(np.concatenate([[0, np.pi / 2], np.arctan(alpha * np.geomspace(0.05, 200, 24))]))
    probs = theta_bin_probs(edges, ndf_of(g), alpha)
    assert probs.sum() == pytest.approx(1.0, rel=1e-8)  # the bins' ∫ 2 D dm (upper hemisphere)
    th_indep = np.arctan(np.sqrt(independent_tan2(rng, n, alpha, g)))
    assert chi2_pvalue(th_indep, edges, probs) > 1e-3  # the density against the independent sampler
    m = sample_flake_normal(rng.random(n), rng.random(n), alpha, std(g))
    assert m.shape == (n, 3) and np.all(m[:, 2] >= 0)
    np.testing.assert_allclose(np.linalg.norm(m, axis=-1), 1, rtol=1e-14)
    assert chi2_pvalue(np.arccos(np.clip(m[:, 2], -1, 1)), edges, probs) > 1e-3  # the module's sampler
    # two-sample check of the two samplers (no density involved)
    assert stats.ks_2samp(np.arccos(m[:, 2]), th_indep).pvalue > 1e-3
    ph = np.mod(np.arctan2(m[:, 1], m[:, 0]), 2 * np.pi)
    assert stats.kstest(ph / (2 * np.pi), "uniform").pvalue > 1e-3


def test_sampler_test_detects_a_wrong_shape():
    """The χ² test has power: samples of γ = 2.5 fail against the density of γ = 3."""
    rng = np.random.default_rng(5)
    alpha, n = 0.3, 200_000
    edges = np.unique(np.concatenate([[0, np.pi / 2], np.arctan(alpha * np.geomspace(0.05, 200, 24))]))
    th = np.arctan(np.sqrt(independent_tan2(rng, n, alpha, 2.5)))
    assert chi2_pvalue(th, edges, theta_bin_probs(edges, ndf_of(3.0), alpha)) < 1e-6


def test_mixture_sampler_matches_its_density():
    D = flake_distribution(MIX)
    alpha, n = 0.15, 200_000
    rng = np.random.default_rng(6)
    m = D.sample(rng.random(n), rng.random(n), alpha)
    edges = np.unique(np.concatenate([[0, np.pi / 2], np.arctan(np.geomspace(0.005, 50, 30))]))
    probs = theta_bin_probs(edges, D.ndf, alpha)
    assert probs.sum() == pytest.approx(1.0, rel=1e-8)
    assert chi2_pvalue(np.arccos(np.clip(m[:, 2], -1, 1)), edges, probs) > 1e-3
    # the population split: the first population (Beckmann, α = 0.15) has tan θ < 0.15·√40 except e^−40
    assert abs(np.mean(np.tan(np.arccos(m[:, 2])) > 0.15 * np.sqrt(40)) - 0.3 * np.mean(
        independent_tan2(rng, n, 0.5, 1.75) > 0.15**2 * 40)) < 5 * np.sqrt(0.3 / n)


# ------------------------------------------------------------------------------------------------
# σ_t, σ_s and the kernel
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("g", SHAPES)
@pytest.mark.parametrize("alpha", [0.05, 0.4, 2.0])
def test_sigma_against_independent_quadrature(g, alpha):
    """The CDF-space moment quadrature (n_quad 24) against a tensor quadrature in coordinates about ω
    (:func:`reference_cosine_integral`, the density evaluated directly): measured ≤ 2.5e-12 relative."""
    opt = tabulated_optics()
    mus = np.array([0.05, 0.45, 1.0])
    st = extinction_Ergun(mus, alpha, opt, A_RHO, distribution=std(g))
    ss = scattering_Ergun(mus, alpha, opt, A_RHO, distribution=std(g))
    for j, mu in enumerate(mus):
        ref_t = reference_cosine_integral(mu, alpha, lambda c: 1 - np.interp(c, opt.c, opt.T[0]), opt.c, ndf_of(g))
        ref_s = reference_cosine_integral(mu, alpha, lambda c: np.interp(c, opt.c, opt.R[0]), opt.c, ndf_of(g))
        assert st[0, j] == pytest.approx(A_RHO * ref_t, rel=1e-11)
        assert ss[0, j] == pytest.approx(A_RHO * ref_s, rel=1e-11)


def test_sigma_against_monte_carlo_of_the_independent_sampler():
    rng = np.random.default_rng(7)
    alpha, g, n = 0.5, 1.6, 200_000
    t = np.sqrt(independent_tan2(rng, n, alpha, g))
    ph = rng.uniform(0, 2 * np.pi, n)
    ct = 1 / np.sqrt(1 + t * t)
    m = np.stack([t * ct * np.cos(ph), t * ct * np.sin(ph), ct], axis=-1)
    opt = tabulated_optics()
    for mu in (0.2, -0.7):
        c = np.abs(m @ direction(mu, 0.4))
        for vals, fn in ((1 - opt.transmittance(c), extinction_Ergun), (opt.reflectance(c), scattering_Ergun)):
            sample = A_RHO * vals * c
            est, err = sample.mean(axis=1), sample.std(axis=1) / np.sqrt(n)
            assert np.all(np.abs(fn(mu, alpha, opt, A_RHO, distribution=std(g)) - est) < 5 * err)


def test_mixture_moments_are_the_weighted_moments():
    mu, lev = np.linspace(0, 1, 7), np.array([0.1, 0.5, 1.0])
    D = flake_distribution(MIX)
    ref = (0.7 * flake_distribution("beckmann").abs_cosine_moments(mu, 0.2, lev, 24)
           + 0.3 * flake_distribution("student_t(1.75)").abs_cosine_moments(mu, 0.5, lev, 24))
    np.testing.assert_allclose(D.abs_cosine_moments(mu, 0.2, lev, 24), ref, rtol=1e-15, atol=0)
    opt = tabulated_optics()
    for fn in (extinction_Ergun, scattering_Ergun):
        np.testing.assert_allclose(
            fn(mu, 0.2, opt, A_RHO, distribution=MIX),
            0.7 * fn(mu, 0.2, opt, A_RHO) + 0.3 * fn(mu, 0.5, opt, A_RHO, distribution="student_t(1.75)"),
            rtol=1e-14)
    np.testing.assert_allclose(projected_area(mu, 0.2, distribution=MIX),
                               0.7 * projected_area(mu, 0.2) + 0.3 * projected_area(mu, 0.5, distribution="student_t(1.75)"),
                               rtol=1e-14)
    mi, mo, ph = np.random.default_rng(8).uniform(-1, 1, (3, 500))
    np.testing.assert_allclose(kernel_Ergun(mi, mo, 3 * ph, 0.2, opt, A_RHO, MIX),
                               0.7 * kernel_Ergun(mi, mo, 3 * ph, 0.2, opt, A_RHO)
                               + 0.3 * kernel_Ergun(mi, mo, 3 * ph, 0.5, opt, A_RHO, "student_t(1.75)"), rtol=1e-13)


@pytest.mark.parametrize("dist", [std(1.5), MIX])
def test_kernel_integrates_to_sigma_s_and_is_reciprocal(dist):
    opt = tabulated_optics()
    for alpha in (0.1, 0.6):
        for mu_i in (0.3, 0.9, -0.5):
            np.testing.assert_allclose(kernel_sphere_integral(mu_i, alpha, opt, dist, n=40),
                                       scattering_Ergun(mu_i, alpha, opt, A_RHO, distribution=dist), rtol=2e-7)
    rng = np.random.default_rng(9)
    mi, mo, ph = rng.uniform(-1, 1, 2000), rng.uniform(-1, 1, 2000), rng.uniform(-np.pi, np.pi, 2000)
    k = kernel_Ergun(mi, mo, ph, 0.3, opt, A_RHO, dist)
    np.testing.assert_allclose(kernel_Ergun(-mo, -mi, -ph, 0.3, opt, A_RHO, dist), k, rtol=1e-12, atol=1e-300)
    assert np.all(k >= 0) and np.all(np.isfinite(k))


# ------------------------------------------------------------------------------------------------
# φ bandwidth
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dist", [std(1.5), std(4.0), MIX])
def test_phi_bandwidth_against_the_kernel_fft(dist):
    """The numeric estimate is never below the orders the kernel itself has above eps × its peak, and
    the projection's first guess resolves the 45° mirror lobe (≥ 2 L) for α ∈ [0.02, 2]."""
    eps, alpha = 1e-6, 0.2
    opt = FlakeOptics.constant(0.7, 0.2)
    D = flake_distribution(dist)
    kmax = 0.5 * A_RHO * 0.7 * D.peak(alpha)
    n = 2**15
    phi = np.arange(n) * 2 * np.pi / n
    for mu_i, mu_o in [(0.5, -0.5), (0.3, -0.7), (0.9, -0.2), (0.3, 0.6), (-0.4, 0.8)]:
        L = int(kernel_phi_bandwidth(alpha, mu_i, mu_o, eps, distribution=dist))
        coef = np.abs(np.fft.rfft(kernel_Ergun(mu_i, mu_o, phi, alpha, opt, A_RHO, dist)[0]).real) * 2 / n
        above = np.nonzero(coef > eps * kmax)[0]
        needed = above.max() if above.size else 0
        assert needed <= L <= 2 * needed + 30, (mu_i, mu_o, L, needed)
    assert kernel_phi_bandwidth(alpha, 1.0, -0.3, distribution=dist) == 0
    mu = np.cos(np.pi / 4)
    for a in (0.02, 0.1, 0.3, 1.0, 2.0):
        L = int(kernel_phi_bandwidth(a, mu, -mu, eps, distribution=dist))
        assert FlakeMedium(a, opt, 1.0, dist).phi_bandwidth >= 2 * L, (a, L)


# ------------------------------------------------------------------------------------------------
# Names and bounds
# ------------------------------------------------------------------------------------------------


def test_names_are_canonical_and_distinct():
    assert flake_distribution("Student_T( 2.50 )").name == "student_t(2.5)"
    assert flake_distribution("student_t(2.5)") is flake_distribution("student_t(2.50)")
    assert flake_distribution("student_t(2.5)").name != flake_distribution("student_t(2.5000001)").name
    d = flake_distribution("MIX(Beckmann, 0.30, student_t(3), 0.4)")
    assert d.name == "mix(beckmann,0.3,student_t(3.0),0.4)" and d.family == "mix"
    assert dict(d.parameters) == {"first": "beckmann", "weight": 0.3, "second": "student_t(3.0)", "alpha2": 0.4}
    assert "student_t(3)" in FLAKE_DISTRIBUTIONS and "student_t" not in FLAKE_DISTRIBUTIONS
    assert list(FLAKE_DISTRIBUTIONS) == ["beckmann", "ggx"]  # iteration: the fixed entries
    assert FlakeMedium(0.2, FlakeOptics.constant(0.5, 0.2), 1.0, "Student_T(3)").distribution == "student_t(3.0)"


@pytest.mark.parametrize("name, match", [
    ("student_t(1.2)", r"gamma must be in \[1.5, 1000\].*1.2"),
    ("student_t(2000)", r"gamma must be in \[1.5, 1000\]"),
    ("student_t(nan)", r"gamma must be in"),
    ("student_t(2,3)", r"takes 1 parameter"),
    ("mix(beckmann,1.0,ggx,0.3)", r"weight .* must be in \(0, 1\).*1.0"),
    ("mix(beckmann,0.2,ggx,3)", r"second spread alpha must be in \[0.001, 2\].*3"),
    ("mix(beckmann,0.2,mix(ggx,0.5,beckmann,0.1),0.3)", r"not mixtures"),
    ("mix(beckmann,0.2,phong,0.3)", r"unknown flake orientation distribution 'phong'"),
    ("student_t", r"unknown flake orientation distribution 'student_t'.*student_t\(gamma\)"),
    ("student_t(2", r"unknown flake orientation distribution"),
])
def test_bad_names_and_parameters_raise_with_the_range(name, match):
    with pytest.raises(ValueError, match=match):
        flake_distribution(name)
    with pytest.raises(ValueError, match="FlakeMedium.distribution"):
        FlakeMedium(0.2, FlakeOptics.constant(0.5, 0.2), 1.0, name)


# ------------------------------------------------------------------------------------------------
# The entry interface a generic consumer relies on (FlakeDistribution docstring)
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dist", ["beckmann", "ggx", std(1.5), std(7.0), MIX, "mix(student_t(2.5),0.5,ggx,0.02)"])
def test_every_entry_honours_the_interface(dist):
    """What the texture model and other generic consumers may assume of any entry: Φ_0(μ, 1) = ∫ D dm = 1
    for every μ; Φ_1(μ, 1) is the projected area, → the mean |ω·m| of the entry's own samples; Φ_j grow
    with the level c; the samples are unit, upper-hemisphere, and follow D (mean cos²θ_m against ∫ D);
    peak bounds D; the name round-trips."""
    D = flake_distribution(dist)
    assert flake_distribution(D.name) is D and D.family in ("beckmann", "ggx", "student_t", "mix")
    alpha = 0.3
    mu, lev = np.array([0.0, 0.2, 0.7, 1.0]), np.array([0.05, 0.3, 0.8, 1.0])
    phi = D.abs_cosine_moments(mu, alpha, lev, 24)
    assert phi.shape == (3, 4, 4)
    np.testing.assert_allclose(phi[0, :, -1], 1.0, rtol=1e-12)
    assert np.all(np.diff(phi, axis=-1) >= -1e-15)
    rng = np.random.default_rng(10)
    n = 100_000
    m = D.sample(rng.random(n), rng.random(n), alpha)
    assert m.shape == (n, 3) and np.all(m[:, 2] >= 0)
    np.testing.assert_allclose(np.linalg.norm(m, axis=-1), 1.0, rtol=1e-14)
    for k, mu_k in enumerate(mu):
        c = np.abs(m @ direction(mu_k, 0.7))
        assert abs(c.mean() - phi[1, k, -1]) < 5 * c.std() / np.sqrt(n) + 1e-12
    th = np.linspace(0, np.pi / 2, 20001)
    e_cos2 = 4 * np.pi * integrate.simpson(np.cos(th) ** 2 * np.sin(th) * D.ndf(np.cos(th), alpha), x=th)
    assert abs(np.mean(m[:, 2] ** 2) - e_cos2) < 5 * np.std(m[:, 2] ** 2) / np.sqrt(n)
    assert D.peak(alpha) >= D.ndf(np.linspace(0, 1, 10001), alpha).max() * (1 - 1e-12)
    assert D.phi_samples(alpha) >= 8
