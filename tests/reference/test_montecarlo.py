"""Tests of the Monte Carlo reference (flakedb.reference.montecarlo) against closed forms and published values.

Guards against: a wrong Fresnel factor or Snell refraction (first-surface delta, inside TIR), energy
leaks or creation (non-absorbing stacks must return every path with its weight), a wrong free-path
or delta-tracking majorant (unscattered transmission, direction-dependent flake extinction), a wrong
flake-normal sampler or acceptance |ω·m| (extinction σ_t(μ) and single-scattering lobe vs quadrature
of paper eq. 2), wrong HG / tabulated phase sampling or frame rotation (single-scattering angular
distribution, published slab values), a wrong sign convention of φ_d (mirror lobe must land at
φ_d = 0), a wrong microfacet weight (rough interface vs quadrature of Walter et al.'s BSDF), broken
determinism or channel mixing, and estimator normalisation errors (bins in 1/sr).

Statistical tests compare with ~4-5 standard errors (or a chi-square over bins), so they fail with
probability < 1e-4 for a correct code; the seeds are fixed, so they are deterministic.
"""

import numpy as np
import pytest

from flakedb.reference.montecarlo import (
    FlakeMedium,
    HenyeyGreenstein,
    Isotropic,
    Lambertian,
    PhaseMedium,
    Problem,
    Rough,
    Slab,
    Smooth,
    TabulatedPhase,
    VonMisesFisher,
    bin_average,
    compensation_table,
    sample_vmf_cosines,
    simulate,
)

# ---------------------------------------------------------------------------------------------
# closed forms written here, independently of the code under test
# ---------------------------------------------------------------------------------------------


def fresnel(cos_i, eta):
    """Unpolarised Fresnel reflectance, eta = n_t/n_i (Hecht, Optics, eqs. 4.42-4.43); 1 under TIR."""
    cos_i = np.asarray(cos_i, dtype=float)
    sin_t2 = (1 - cos_i**2) / eta**2
    cos_t = np.sqrt(np.clip(1 - sin_t2, 0, None))
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (cos_t - eta * cos_i) / (cos_t + eta * cos_i)
    return np.where(sin_t2 >= 1, 1.0, 0.5 * (rs**2 + rp**2))


def hemispherical_fresnel(eta, n=200):
    """Cosine-weighted hemispherical reflectance F̄ = 2 ∫_0^1 F(μ) μ dμ (Gauss-Legendre).

    From the dense side (eta < 1) F = 1 below μ_c = √(1 − η²) and F − 1 ∝ √(μ − μ_c) above it; the
    substitution μ = μ_c + (1 − μ_c) u² removes that square root so the rule converges fast.
    """
    x, w = np.polynomial.legendre.leggauss(n)
    if eta < 1:
        mu_c = np.sqrt(1 - eta**2)
        u = 0.5 * (x + 1)
        mu = mu_c + (1 - mu_c) * u**2
        jac = 2 * (1 - mu_c) * u
        return mu_c**2 + 2 * np.sum(0.5 * w * jac * fresnel(mu, eta) * mu)
    mu = 0.5 + 0.5 * x
    return 2 * np.sum(0.5 * w * fresnel(mu, eta) * mu)


def ndf_flake(cos_h, alpha):
    """Paper eq. 5 on the sphere: exp(-tan²θ/α²)/(2π α² |cos θ|³)."""
    c = np.abs(cos_h)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        d = np.exp(-(1 - c**2) / (c**2 * alpha**2)) / (2 * np.pi * alpha**2 * c**3)
    return np.where(c > 1e-300, d, 0.0)


def flake_sigma_t(mu, a_rho, alpha, T_of_c, n_t=96, n_phi=1024):
    """σ_t(μ) = aρ ∫_sphere (1 − T(|ω·m|)) |ω·m| D(m) dm by quadrature (docs/model.md §3).

    Substituting tan θ_m = α t, D(m) sin θ dθ = t e^{−t²}/(2π) dt, and the lower hemisphere doubles.
    """
    mu = np.atleast_1d(np.asarray(mu, dtype=float))
    x, w = np.polynomial.legendre.leggauss(n_t)
    t = 3.5 * (x + 1)
    wt = 3.5 * w
    th = np.arctan(alpha * t)
    ph = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    c = np.abs(mu[:, None, None] * np.cos(th)[None, :, None]
               + np.sqrt(1 - mu[:, None, None] ** 2) * np.sin(th)[None, :, None] * np.cos(ph)[None, None, :])
    inner = np.mean((1 - T_of_c(c)) * c, axis=2) * 2 * np.pi
    return a_rho * 2 * np.sum(wt * t * np.exp(-(t**2)) / (2 * np.pi) * inner, axis=1)


def hg(cos_t, g):
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * cos_t) ** 1.5)


def slab(thickness, *media):
    return Slab(thickness, tuple(media))


def agree(mc, se, ref, k=4.5, abs_tol=0.0):
    mc, se, ref = (np.asarray(a, dtype=float) for a in (mc, se, ref))
    assert np.all(np.abs(mc - ref) <= k * se + abs_tol), f"MC {mc} ± {se} vs reference {ref}"


# ---------------------------------------------------------------------------------------------
# smooth coat, no medium
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mu_i", [1.0, 0.5, 0.1])
def test_black_bottom_gives_fresnel_exactly(mu_i):
    p = Problem((slab(5.0),), top=Smooth(1.5), bottom=Lambertian(0.0))
    r = simulate(p, mu_i, 2000, seed=1)
    assert r.specular[0] == pytest.approx(float(fresnel(mu_i, 1.5)), rel=1e-12)
    assert r.diffuse_albedo[0] == 0.0 and r.transmittance[0] == 0.0
    assert r.albedo[0] == pytest.approx(float(fresnel(mu_i, 1.5)), rel=1e-12)


@pytest.mark.parametrize("mu_i", [1.0, 0.3])
def test_white_lambertian_under_smooth_coat_returns_everything(mu_i):
    p = Problem((slab(5.0),), top=Smooth(1.5), bottom=Lambertian(1.0))
    r = simulate(p, mu_i, 20000, seed=2)
    assert abs(r.albedo[0] - 1.0) < 1e-12
    assert r.albedo_se[0] < 1e-9  # weights are conserved path by path: zero variance
    assert r.n_lost[0] == 0


def test_lambertian_under_smooth_coat_closed_form():
    """R = F(θ_i) + (1 − F(θ_i)) a (1 − F̄_i) / (1 − a F̄_i), F̄_i the inside hemispherical reflectance."""
    eta, a, mu_i = 1.5, 0.5, 0.7
    Fi_bar = hemispherical_fresnel(1 / eta)
    Fe_bar = hemispherical_fresnel(eta)
    assert 1 - Fi_bar == pytest.approx((1 - Fe_bar) / eta**2, rel=1e-9)  # checks the quadrature itself
    F = float(fresnel(mu_i, eta))
    ref = F + (1 - F) * a * (1 - Fi_bar) / (1 - a * Fi_bar)
    r = simulate(Problem((slab(1.0),), top=Smooth(eta), bottom=Lambertian(a)), mu_i, 200_000, seed=3)
    agree(r.albedo[0], r.albedo_se[0], ref)
    assert r.albedo_se[0] < 1.5e-3


# ---------------------------------------------------------------------------------------------
# phase media: closed forms and published values
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mu_i", [1.0, 0.4])
def test_pure_absorber_beer_lambert(mu_i):
    tau = 0.8
    p = Problem((slab(2.0, PhaseMedium(tau / 2.0, 0.0, Isotropic())),))
    r = simulate(p, mu_i, 100_000, seed=4)
    agree(r.transmittance_direct[0], r.transmittance_direct_se[0], np.exp(-tau / mu_i))
    assert r.albedo[0] == 0.0 and r.transmittance[0] == r.transmittance_direct[0]


def test_single_scattering_isotropic_closed_form():
    """R_1(μ_i) = (ω/2) ∫_0^1 μ (1 − exp(−τ(1/μ_i + 1/μ))) / (μ_i + μ) dμ (fraction of incident power).

    Derivation: the collimated flux at depth τ' is e^{−τ'/μ_i} per unit area; it scatters (ω/4π) per sr
    per unit τ' along the beam (1/μ_i per unit depth); the escape factor is e^{−τ'/μ}; the radiance
    leaving is integrated against μ dω = 2π μ dμ.
    """
    tau, omega, mu_i = 0.5, 0.9, 0.6
    x, w = np.polynomial.legendre.leggauss(400)
    mu = 0.5 * (x + 1)
    R1 = 0.5 * omega * np.sum(0.5 * w * mu * (1 - np.exp(-tau * (1 / mu_i + 1 / mu))) / (mu_i + mu))
    p = Problem((slab(1.0, PhaseMedium(tau, omega, Isotropic())),))
    r = simulate(p, mu_i, 200_000, seed=5, max_scattering_orders=1)
    agree(r.albedo[0], r.albedo_se[0], R1)


@pytest.mark.parametrize("phase", [Isotropic(), HenyeyGreenstein(0.7), VonMisesFisher(50.0)])
def test_conservative_slab_conserves_energy_exactly(phase):
    p = Problem((slab(3.0, PhaseMedium(0.5, 1.0, phase)),))
    r = simulate(p, 0.7, 20_000, seed=6)
    assert abs(r.albedo[0] + r.transmittance[0] - 1.0) < 1e-12
    assert abs(r.absorbed[0]) < 1e-12


@pytest.mark.parametrize("g, ur1, ut1", [(0.0, 0.21085, 0.54140), (0.8, 0.03041, 0.76388)])
def test_prahl_adding_doubling_values(g, ur1, ut1):
    """Index-matched slab, albedo 0.8, optical thickness 1, normal incidence: total reflection UR1 and
    total transmission UT1 (unscattered included) from S. Prahl's adding-doubling program, as quoted
    in iadpython's tests (tests/test_iadc.py, basic_forward.test_04_finite / test_05_finite_anisotropic).
    """
    p = Problem((slab(2.0, PhaseMedium(0.5, 0.8, HenyeyGreenstein(g))),))
    r = simulate(p, 1.0, 200_000, seed=7)
    agree(r.albedo[0], r.albedo_se[0], ur1, abs_tol=2e-4)
    agree(r.transmittance[0], r.transmittance_se[0], ut1, abs_tol=2e-4)


def test_van_de_hulst_table12_isotropic():
    """van de Hulst, *Multiple Light Scattering* (1980) vol. 1, Table 12, pp. 260-261, isotropic
    scattering, albedo 0.8, optical thickness 2 (as quoted in Mitsuba's layer tests, test01_isotropic):
    reflection function R(μ=0.5, μ0) = π f_r and transmission function T(μ=0.5, μ0=1) = π f_t.

    The bin |μ| ∈ [0.47, 0.53] averages f|μ|; for isotropic scattering f does not depend on φ_d.  The
    bin average of f|μ| differs from f(0.5)·0.5 by O(Δμ²/24 · (f μ)''), far below the MC error.
    """
    p = Problem((slab(1.0, PhaseMedium(2.0, 0.8, Isotropic())),))
    edges = [0.0, 0.47, 0.53, 1.0]
    phis = [0.0, np.pi]
    for mu0, R_ref in [(1.0, 0.28616), (0.5, 0.39102)]:
        r = simulate(p, mu0, 300_000, seed=8, mu_edges=edges, phi_edges=phis)
        agree(r.reflectance_binned[0, 1, 0], r.reflectance_binned_se[0, 1, 0], R_ref / np.pi * 0.5)
        if mu0 == 1.0:
            agree(r.transmittance_binned[0, 1, 0], r.transmittance_binned_se[0, 1, 0], 0.14864 / np.pi * 0.5)


def test_split_slab_is_the_same_slab():
    one = Problem((slab(2.0, PhaseMedium(0.6, 0.9, HenyeyGreenstein(0.5))),), top=Smooth(1.5), bottom=Lambertian(0.4))
    two = Problem((slab(1.3, PhaseMedium(0.6, 0.9, HenyeyGreenstein(0.5))),
                   slab(0.7, PhaseMedium(0.6, 0.9, HenyeyGreenstein(0.5)))), top=Smooth(1.5), bottom=Lambertian(0.4))
    a = simulate(one, 0.8, 100_000, seed=9)
    b = simulate(two, 0.8, 100_000, seed=10)
    agree(a.albedo[0] - b.albedo[0], np.hypot(a.albedo_se[0], b.albedo_se[0]), 0.0)


# ---------------------------------------------------------------------------------------------
# single-scattering angular distributions (binned, chi-square against quadrature)
# ---------------------------------------------------------------------------------------------


def _directions(mu_abs, phi, down):
    s = np.sqrt(np.clip(1 - mu_abs**2, 0, None))
    return np.stack([s * np.cos(phi), s * np.sin(phi), mu_abs if down else -mu_abs], axis=-1)


def _chi2_check(mc, se, ref, min_rel=0.02):
    """Chi-square of MC bins against reference bins (bins whose reference is tiny are skipped)."""
    keep = (ref > min_rel * ref.max()) & (se > 0)
    chi2 = np.sum(((mc[keep] - ref[keep]) / se[keep]) ** 2)
    dof = int(keep.sum())
    assert dof >= 20
    assert chi2 < dof + 5 * np.sqrt(2 * dof), f"chi2 = {chi2:.1f} for {dof} bins"
    return chi2, dof


def test_single_scattering_flakes_and_hg_mixture_binned():
    """Flakes (paper eq. 2) + an HG medium in one slab; single scattering only.

    f|μ_o| = k(ω_i→ω_o)/μ_i · (1 − e^{−L s})/s (reflection), s = σ_t(μ_i)/μ_i + σ_t(μ_o)/|μ_o|, and
    f|μ_o| = k/μ_i · (e^{−σ_o L/μ_o} − e^{−σ_i L/μ_i})/(σ_i/μ_i − σ_o/μ_o) (transmission), with
    k = (aρ/4) R(|ω_i·h|)(D(h)+D(−h)) + σ_s p_HG(ω_i·ω_o), h = normalize(ω_o − ω_i).
    """
    L, mu_i = 1.0, 0.6
    a_rho, alpha = 0.8, 0.4
    sig_hg, alb_hg, g = 0.3, 0.9, 0.5
    cg = np.linspace(0, 1, 5)
    Rt = 0.3 + 0.4 * cg**2
    Tt = 0.25 * (1 - cg)
    flakes = FlakeMedium(a_rho, alpha, Rt, Tt, c_grid=cg)
    p = Problem((slab(L, flakes, PhaseMedium(sig_hg, alb_hg, HenyeyGreenstein(g))),))
    mu_edges = np.linspace(0, 1, 11)
    phi_edges = np.linspace(0, np.pi, 9)
    r = simulate(p, mu_i, 400_000, seed=11, mu_edges=mu_edges, phi_edges=phi_edges, max_scattering_orders=1)

    T_of_c = lambda c: np.interp(c, cg, Tt)  # noqa: E731
    mu_tab = np.linspace(1e-4, 1, 400)
    sig_tab = flake_sigma_t(mu_tab, a_rho, alpha, T_of_c) + sig_hg
    sig = lambda m: np.interp(m, mu_tab, sig_tab)  # noqa: E731
    wi = _directions(np.array(mu_i), np.array(0.0), down=True)
    si = float(sig(mu_i))

    def kernel(wo):
        h = wo - wi
        h = h / np.linalg.norm(h, axis=-1, keepdims=True)
        c = np.abs(np.sum(wi * h, axis=-1))
        kf = a_rho / 4 * np.interp(c, cg, Rt) * 2 * ndf_flake(h[..., 2], alpha)
        return kf + sig_hg * alb_hg * hg(np.sum(wi * wo, axis=-1), g)

    def refl(mu_abs, phi):
        wo = _directions(mu_abs, phi, down=False)
        s = si / mu_i + sig(mu_abs) / mu_abs
        return kernel(wo) / mu_i * (-np.expm1(-L * s)) / s

    def trans(mu_abs, phi):
        wo = _directions(mu_abs, phi, down=True)
        a, b = si / mu_i, sig(mu_abs) / mu_abs
        x = (a - b) * L
        ratio = np.where(np.abs(x) < 1e-12, 1.0, np.expm1(x) / np.where(x == 0, 1, x))
        return kernel(wo) / mu_i * np.exp(-a * L) * L * ratio

    ref_r = bin_average(refl, mu_edges, phi_edges, n_quad=12)
    ref_t = bin_average(trans, mu_edges, phi_edges, n_quad=12)
    _chi2_check(r.reflectance_binned[0], r.reflectance_binned_se[0], ref_r)
    _chi2_check(r.transmittance_binned[0], r.transmittance_binned_se[0], ref_t)
    # the bins add up to the hemispherical totals (estimator normalisation, 1/sr)
    omega = 2 * np.diff(mu_edges)[:, None] * np.diff(phi_edges)[None, :]
    assert np.sum(r.reflectance_binned[0] * omega) == pytest.approx(r.albedo[0], rel=1e-12)


def test_single_scattering_tabulated_rayleigh_binned():
    """A tabulated phase function (Rayleigh, p = 3(1 + cos²Θ)/(16π)) sampled by CDF inversion."""
    ct = np.linspace(-1, 1, 201)
    pr = 3 * (1 + ct**2) / (16 * np.pi)
    sigma, L, mu_i = 1.0, 0.5, 0.8
    p = Problem((slab(L, PhaseMedium(sigma, 1.0, TabulatedPhase(ct, pr))),))
    mu_edges = np.linspace(0, 1, 11)
    phi_edges = np.linspace(0, np.pi, 7)
    r = simulate(p, mu_i, 300_000, seed=12, mu_edges=mu_edges, phi_edges=phi_edges, max_scattering_orders=1)
    wi = _directions(np.array(mu_i), np.array(0.0), down=True)

    def refl(mu_abs, phi):
        wo = _directions(mu_abs, phi, down=False)
        cos_t = np.sum(wi * wo, axis=-1)
        s = sigma / mu_i + sigma / mu_abs
        return sigma * 3 * (1 + cos_t**2) / (16 * np.pi) / mu_i * (-np.expm1(-L * s)) / s

    _chi2_check(r.reflectance_binned[0], r.reflectance_binned_se[0], bin_average(refl, mu_edges, phi_edges))


# ---------------------------------------------------------------------------------------------
# micro-flakes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mu_i", [1.0, 0.5, 0.15])
def test_flake_extinction_matches_quadrature(mu_i):
    """Opaque-reflectance-free flakes (R = 0, T(c) tabulated) plus an absorber in the same slab: the
    unscattered transmission is exp(−(σ_flakes(μ) + σ_a) L / μ) with σ_flakes(μ) = aρ∫(1−T)|ω·m|D dm."""
    a_rho, alpha, L, sig_a = 1.2, 0.5, 1.0, 0.2
    cg = np.linspace(0, 1, 11)
    Tt = 0.2 + 0.6 * cg**2
    p = Problem((slab(L, FlakeMedium(a_rho, alpha, 0.0, Tt, c_grid=cg), PhaseMedium(sig_a, 0.0)),))
    r = simulate(p, mu_i, 100_000, seed=13)
    sig = flake_sigma_t(mu_i, a_rho, alpha, lambda c: np.interp(c, cg, Tt))[0] + sig_a
    agree(r.transmittance_direct[0], r.transmittance_direct_se[0], np.exp(-sig * L / mu_i))
    assert r.albedo[0] == 0.0


def test_flake_ndf_is_normalised():
    """The test's own quadrature: ∫ D = 1 over the sphere (so σ_t with T = 0, c ≡ 1 would be aρ)."""
    # with (1 − T(c)) c ≡ 1 the extinction quadrature must return aρ ∫ D dm = aρ
    assert flake_sigma_t(0.3, 1.0, 0.3, lambda c: 1.0 - 1.0 / np.maximum(c, 1e-300))[0] == pytest.approx(1.0, rel=1e-9)
    x, w = np.polynomial.legendre.leggauss(200)
    th = np.pi / 4 * (x + 1)
    assert np.sum(np.pi / 4 * w * 2 * np.pi * np.sin(th) * ndf_flake(np.cos(th), 0.3)) * 2 == pytest.approx(1.0, rel=1e-8)


@pytest.mark.parametrize("R_flake, T_flake", [(0.3, 0.7), (0.55, 0.45)])
def test_flakes_with_R_plus_T_one_conserve_energy(R_flake, T_flake):
    p = Problem((slab(2.0, FlakeMedium(1.5, 0.3, R_flake, T_flake)),))
    r = simulate(p, 0.6, 20_000, seed=14)
    assert abs(r.albedo[0] + r.transmittance[0] - 1.0) < 1e-12


@pytest.mark.parametrize("r_flake", [1.0, 0.7])
def test_mirror_flakes_parallel_to_surface_are_a_rod_model(r_flake):
    """α → 0, T = 0: every flake is a mirror parallel to the surface; per unit depth the encounter rate
    is aρ whatever μ (rate aρ|μ| per unit path), each encounter reverses μ keeping φ.  That is the
    two-stream rod model: R = r sinh(γτ)/(γ cosh(γτ) + sinh(γτ)), γ = √(1 − r²), τ = aρL (→ τ/(1+τ)
    for r = 1), all of it in the mirror direction (|μ_o| = μ_i, φ_d = 0)."""
    a_rho, L, mu_i = 2.0, 1.0, 0.5
    tau = a_rho * L
    if r_flake == 1.0:
        ref = tau / (1 + tau)
    else:
        gam = np.sqrt(1 - r_flake**2)
        ref = r_flake * np.sinh(gam * tau) / (gam * np.cosh(gam * tau) + np.sinh(gam * tau))
    p = Problem((slab(L, FlakeMedium(a_rho, 1e-3, r_flake, 0.0)),))
    mu_edges = [0.0, 0.49, 0.51, 1.0]
    phi_edges = [0.0, 0.05, np.pi]
    r = simulate(p, mu_i, 100_000, seed=15, mu_edges=mu_edges, phi_edges=phi_edges)
    agree(r.albedo[0], r.albedo_se[0], ref)
    in_mirror_bin = r.reflectance_binned[0, 1, 0] * 2 * 0.02 * 0.05
    assert in_mirror_bin > 0.995 * r.albedo[0]


# ---------------------------------------------------------------------------------------------
# rough interface (Walter et al. 2007), checked against quadrature of the BSDF
# ---------------------------------------------------------------------------------------------


@np.errstate(divide="ignore", invalid="ignore")
def _walter_albedos(cos_i, eta_rel, alpha, n_th=64, n_ph=128):
    """Directional reflectance and transmittance of Walter's microfacet dielectric by quadrature over
    the half vector h: ∫ f(i, o(h)) |o·n| |∂o/∂h| dh with f from Walter eqs. 20-21 (Beckmann D,
    separable Smith G with the exact G1) and the Jacobians of eqs. 14 and 17.  Local frame: n = z
    points to the incident side; η_i = 1, η_o = eta_rel."""
    from scipy.special import erf

    def D(cz):
        return np.exp(-(1 - cz**2) / (cz**2 * alpha**2)) / (np.pi * alpha**2 * cz**4)

    def G1(v, m):
        vz = v[..., 2]
        ok = np.sum(v * m, axis=-1) * vz > 0
        a = np.abs(vz) / (alpha * np.sqrt(np.clip(1 - vz**2, 1e-300, None)))
        g = np.where(a > 8, 1.0, 2 / (1 + erf(a) + np.exp(-a * a) / (a * np.sqrt(np.pi))))
        return np.where(ok, g, 0.0)

    x, w = np.polynomial.legendre.leggauss(n_th)
    th_max = np.arctan(6.5 * alpha)
    th = 0.5 * th_max * (x + 1)
    wth = 0.5 * th_max * w
    ph = (np.arange(n_ph) + 0.5) * 2 * np.pi / n_ph
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    h = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], -1)
    dA = (wth[:, None] * np.sin(TH)) * (2 * np.pi / n_ph)
    i = np.array([np.sqrt(1 - cos_i**2), 0.0, cos_i])
    ih = h @ i
    front = ih > 0
    F = fresnel(np.clip(ih, 1e-300, 1), eta_rel)
    # reflection
    o = 2 * ih[..., None] * h - i
    oz = o[..., 2]
    fr = F * D(h[..., 2]) * G1(i, h) * G1(o, h) / (4 * cos_i * np.abs(oz))
    jac_r = 4 * np.abs(np.sum(o * h, -1))
    R = np.sum(np.where(front & (oz > 0), fr * np.abs(oz) * jac_r, 0.0) * dA)
    # transmission
    s2 = (1 - ih**2) / eta_rel**2
    ct = np.sqrt(np.clip(1 - s2, 0, None))
    o = -i / eta_rel + (ih / eta_rel - ct)[..., None] * h
    o = o / np.linalg.norm(o, axis=-1, keepdims=True)
    oz = o[..., 2]
    oh = np.sum(o * h, -1)
    den = (ih + eta_rel * oh) ** 2
    ft = np.abs(ih) * np.abs(oh) / (cos_i * np.abs(oz)) * eta_rel**2 * (1 - F) * D(h[..., 2]) * G1(i, h) * G1(o, h) / den
    jac_t = den / (eta_rel**2 * np.abs(oh))
    T = np.sum(np.where(front & (s2 < 1) & (oz < 0), ft * np.abs(oz) * jac_t, 0.0) * dA)
    return R, T


def _rough_over_lambertian(eta, alpha, a, mu_i):
    """R = R_e(μ_i) + T_e(μ_i) a T̄_i / (1 − a R̄_i): the Lambertian re-diffuses whatever comes down, so
    only the cosine-weighted inside averages R̄_i, T̄_i of the interface matter (no medium between)."""
    Re, Te = _walter_albedos(mu_i, eta, alpha)
    x, w = np.polynomial.legendre.leggauss(48)
    mus = 0.5 * (x + 1)
    Ri_Ti = np.array([_walter_albedos(m, 1 / eta, alpha) for m in mus])
    Ri_bar = 2 * np.sum(0.5 * w * mus * Ri_Ti[:, 0])
    Ti_bar = 2 * np.sum(0.5 * w * mus * Ri_Ti[:, 1])
    return Re + Te * a * Ti_bar / (1 - a * Ri_bar)


def test_rough_interface_white_furnace():
    """White Lambertian under a rough (α = 0.1) coat, nothing absorbing: R + (Smith masking loss) = 1
    path by path, R ≈ 1 within the single-scattering microfacet loss, and R matches the closed form
    built from a quadrature of Walter's BSDF (which checks the sampling weights)."""
    eta, alpha, mu_i = 1.5, 0.1, 0.6
    p = Problem((slab(1.0),), top=Rough(eta, alpha, energy_compensation=False), bottom=Lambertian(1.0))
    r = simulate(p, mu_i, 100_000, seed=16)
    assert abs(r.albedo[0] + r.interface_loss[0] - 1.0) < 1e-12  # no roulette: weights only move
    assert 0.97 < r.albedo[0] < 1.0
    agree(r.albedo[0], r.albedo_se[0], _rough_over_lambertian(eta, alpha, 1.0, mu_i), abs_tol=5e-4)


def test_rough_interface_gray_primer_and_smooth_limit():
    eta, mu_i, a = 1.5, 0.8, 0.5
    r = simulate(Problem((slab(1.0),), top=Rough(eta, 0.3, energy_compensation=False), bottom=Lambertian(a)), mu_i, 100_000,
                 seed=17)
    agree(r.albedo[0], r.albedo_se[0], _rough_over_lambertian(eta, 0.3, a, mu_i), abs_tol=5e-4)
    # α → 0: the rough code path must reproduce the smooth closed form
    Fi_bar = hemispherical_fresnel(1 / eta)
    F = float(fresnel(mu_i, eta))
    smooth_ref = F + (1 - F) * a * (1 - Fi_bar) / (1 - a * Fi_bar)
    r = simulate(Problem((slab(1.0),), top=Rough(eta, 1e-3), bottom=Lambertian(a)), mu_i, 100_000, seed=18)
    agree(r.albedo[0], r.albedo_se[0], smooth_ref, abs_tol=2e-4)


@pytest.mark.parametrize("alpha", [0.02, 0.1, 0.3])
def test_compensated_rough_interface_is_lossless(alpha):
    """With the multiple-scattering compensation (default) a white primer under a rough coat
    reflects everything, at normal and grazing incidence, and nothing is tallied as lost."""
    p = Problem((slab(1.0),), top=Rough(1.5, alpha), bottom=Lambertian(1.0))
    for j, mu_i in enumerate((1.0, 0.5, 0.18)):
        r = simulate(p, mu_i, 60_000, seed=40 + j)
        agree(r.albedo[0], r.albedo_se[0], 1.0, abs_tol=3e-4)
        assert r.interface_loss[0] == 0.0


def test_compensation_tables_match_an_independent_quadrature():
    """The tabulated single-scattering albedo E(μ) (the kernel's own expected weight) equals the
    half-vector quadrature of Walter's BSDF (_walter_albedos), both sides, α 0.3 and 0.05."""
    for alpha in (0.3, 0.05):
        for eta_rel in (1.5, 1 / 1.5):
            grid, E, cdf, Z = compensation_table(eta_rel, alpha)
            for mu in (1.0, 0.6, 0.3, 0.1):
                k = int(np.argmin(np.abs(grid - mu)))
                R, T = _walter_albedos(grid[k], eta_rel, alpha)
                assert abs(E[k] - (R + T)) < 1e-3, (alpha, eta_rel, mu, E[k], R + T)
            assert abs(cdf[-1] - 1.0) < 1e-15 and np.all(np.diff(cdf) >= 0) and Z > 0


# ---------------------------------------------------------------------------------------------
# API: determinism, channels, validation
# ---------------------------------------------------------------------------------------------


def test_deterministic_and_channels_are_independent():
    two = Problem((slab(2.0, PhaseMedium([0.5, 0.8], [0.5, 0.95], HenyeyGreenstein(0.6))),),
                  top=Smooth(1.5), bottom=Lambertian([0.2, 0.7]))
    one = Problem((slab(2.0, PhaseMedium(0.8, 0.95, HenyeyGreenstein(0.6))),), top=Smooth(1.5), bottom=Lambertian(0.7))
    a = simulate(two, 0.9, 5000, seed=19)
    b = simulate(two, 0.9, 5000, seed=19)
    c = simulate(one, 0.9, 5000, seed=19)
    d = simulate(one, 0.9, 5000, seed=20)
    assert two.n_channels == 2 and a.albedo.shape == (2,)
    np.testing.assert_array_equal(a.albedo, b.albedo)
    assert a.albedo[1] == c.albedo[0]
    assert d.albedo[0] != c.albedo[0]


def vmf_cdf(c, kappa):
    """P(cos Θ ≤ c) of the vMF phase function, κ/(4π sinh κ) e^{κ t} integrated in closed form:
    (e^{κ(c − 1)} − e^{−2κ}) / (1 − e^{−2κ})."""
    if kappa == 0:
        return 0.5 * (np.asarray(c) + 1.0)
    return (np.exp(kappa * (np.asarray(c) - 1.0)) - np.exp(-2 * kappa)) / -np.expm1(-2 * kappa)


@pytest.mark.parametrize("kappa", [0.0, 0.5, 5.0, 50.0, 200.0, 2000.0])
def test_vmf_sampler_histogram_matches_the_pdf(kappa):
    """The tracer's exact inverse-CDF vMF sampler: counts in bins of cos Θ (graded towards the lobe)
    against the closed-form bin probabilities (chi-square over bins, and each bin within 5σ), and the
    sample mean against g = coth κ − 1/κ."""
    n = 400_000
    c = sample_vmf_cosines(kappa, n, seed=11)
    assert np.all((c >= -1) & (c <= 1))
    s = np.unique(np.concatenate([[0.0], np.geomspace(1e-3 / max(kappa, 1.0), 2.0, 30)]))
    edges = np.sort(1.0 - s)
    edges[0] = -1.0
    prob = np.diff(vmf_cdf(edges, kappa))
    counts = np.histogram(c, bins=edges)[0]
    expected = n * prob
    keep = expected > 20
    assert keep.sum() >= 8
    z = (counts[keep] - expected[keep]) / np.sqrt(expected[keep] * (1 - prob[keep]))
    assert np.abs(z).max() < 5, z
    chi2 = np.sum(z**2)
    dof = keep.sum()
    assert chi2 < dof + 5 * np.sqrt(2 * dof), (chi2, dof)
    g = 1 / np.tanh(kappa) - 1 / kappa if kappa > 0 else 0.0
    agree(c.mean(), c.std() / np.sqrt(n), g, k=5)


def test_validation_messages():
    with pytest.raises(ValueError, match="R \\+ T <= 1"):
        simulate(Problem((slab(1.0, FlakeMedium(1.0, 0.2, 0.6, 0.5)),)), 1.0, 10, 0)
    with pytest.raises(ValueError, match="normalised to 1 over the sphere"):
        simulate(Problem((slab(1.0, PhaseMedium(1.0, 1.0, TabulatedPhase([-1, 1], [1.0, 1.0]))),)), 1.0, 10, 0)
    with pytest.raises(ValueError, match="channels"):
        simulate(Problem((slab(1.0, PhaseMedium([1.0, 2.0], [0.5, 0.5, 0.5])),)), 1.0, 10, 0)
    with pytest.raises(ValueError, match="mu_i"):
        simulate(Problem((slab(1.0),)), -0.5, 10, 0)
    with pytest.raises(ValueError, match="kappa"):
        simulate(Problem((slab(1.0, PhaseMedium(1.0, 0.5, VonMisesFisher(-1.0))),)), 1.0, 10, 0)
