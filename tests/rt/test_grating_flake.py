"""Grating flakes as a scattering medium (flakedb.rt.scattering.grating_flake, issue 35): (a) without grooves the
kernel is the specular flakes' kernel_Ergun, and an order's cone closes on the mirror term as the period grows;
(b) energy: the kernel integrated over outgoing directions is the specular flakes' σ_s (the grating only
redistributes the flake's reflectance); (c) reciprocity and the z -> -z symmetry the solver relies on; (d) the
kernel against an independent brute-force sampler of flakes (random normals, grating azimuths, every order), and
single scattering through the adding-doubling solver against the same sampler."""

import numpy as np
import pytest
from scipy.special import jv

from flakedb.rt.adding.stack import Slab, SolverSettings, solve_stack
from flakedb.rt.scattering.grating_flake import (GratingFlakeMedium, _bessel_j, grating_flake_kernel,
                                                 highest_order, mirror_order_efficiency, sinusoidal_order_efficiency)
from flakedb.rt.scattering.microflake import FlakeOptics, kernel_Ergun, sample_flake_normal, scattering_Ergun
from tests.tolerances import U

C_GRID = np.linspace(0.0, 1.0, 6)
R_ROWS = np.vstack([0.78 + 0.12 * C_GRID, np.full(6, 0.85)])     # an Al-like R(c) rising to grazing; a flat one


def _kernel(mi, mo, ph, amp, alpha=0.2, dist="beckmann", period=690.0, lam=(450.0, 620.0), **kw):
    return grating_flake_kernel(mi, mo, ph, alpha, C_GRID, R_ROWS, list(lam), period, amp, 1.5, 1.3, dist, **kw)


def test_bessel_series_is_scipys():
    x = np.linspace(0.0, 8.0, 20001)
    for k in range(7):
        np.testing.assert_allclose(_bessel_j(k, x), jv(k, x), rtol=0, atol=1e-13)


@pytest.mark.parametrize("dist", ["beckmann", "ggx", "student_t(3)"])
def test_without_grooves_it_is_the_specular_flake_kernel(dist):
    # amplitude 0: J_0 = 1, every other order carries nothing -> (aρ/2) R(c) D(h), the same function; h from the
    # vector difference here, from kernel_Ergun's cancellation-free terms there: the far tail (D ~ 1e-60, where
    # exp(−tan²θ/α²) multiplies the rounding of tan²θ by tan²θ/α² ~ 300) agrees to ~1e-7 relative
    rng = np.random.default_rng(1)
    mi, mo = rng.uniform(-1, 1, 300), rng.uniform(-1, 1, 300)
    ph = rng.uniform(0, np.pi, 300)
    ref = kernel_Ergun(mi, mo, ph, 0.2, FlakeOptics(C_GRID, R_ROWS, 0 * R_ROWS), 1.3, dist)
    k = _kernel(mi, mo, ph, 0.0, dist=dist)
    assert ref.max() > 1.0
    np.testing.assert_allclose(k, ref, rtol=1e-6, atol=1e3 * U * ref.max())
    near = ref > 1e-3 * ref.max()
    np.testing.assert_allclose(k[near], ref[near], rtol=1e-11)


def test_an_order_tends_to_the_mirror_term_as_the_period_grows():
    # r = λ/(n_b Λ) -> 0 closes the cone on h: the order-1 term -> 2 J_1²(Φ(c, c)) × the mirror term (flat R)
    mi, mo, ph = np.array([0.9, 0.6, 0.8]), np.array([-0.8, -0.9, -0.7]), np.array([0.1, 0.2, 0.0])
    R = np.full((1, 6), 0.85)
    big = 1e6
    k1 = grating_flake_kernel(mi, mo, ph, 0.2, C_GRID, R, [500.0], big, 60.0, 1.5, 1.0, orders=(1,))
    k0 = grating_flake_kernel(mi, mo, ph, 0.2, C_GRID, R, [500.0], big, 0.0, 1.5, 1.0)
    s_i, s_o = np.sqrt(1 - mi ** 2), np.sqrt(1 - mo ** 2)
    c = 0.5 * np.sqrt(2 * (1 - mi * mo - s_i * s_o * np.cos(ph)))
    np.testing.assert_allclose(k1, k0 * 2 * sinusoidal_order_efficiency(1, c, c, 500.0, 60.0), rtol=1e-5)


def test_mirror_order_efficiency_against_azimuth_sampling():
    # η_0 = 1 − Σ_{k≠0} ⟨1[propagates] J_k²⟩ over the grating azimuth: the closed-form arcs against 200 000
    # uniform azimuths (a discontinuous integrand: the sampled mean carries ~1/n_ψ)
    p, lam, a, nb, period = 0.6, 480.0, 70.0, 1.5, 690.0
    g = lam / (nb * period)
    K = highest_order(lam, period, nb)
    psi = (np.arange(200_000) + 0.5) * 2 * np.pi / 200_000
    S = 0.0
    for k in [k for k in range(-K, K + 1) if k]:
        q2 = p * p + (k * g) ** 2 + 2 * k * g * p * np.cos(psi)
        prop = q2 < 1
        e = sinusoidal_order_efficiency(k, 0.8, np.sqrt(np.clip(1 - q2, 0, 1)), lam, a, nb)
        S = S + np.where(prop, e, 0.0)
    ref = np.mean(1 - S)
    got = mirror_order_efficiency(p, 0.8, g, a, lam, nb, K)
    assert got == pytest.approx(ref, abs=2e-5)
    assert 0.05 < got < 0.95


@pytest.mark.parametrize("mu_i,amp", [pytest.param(0.9, 40.0, marks=pytest.mark.slow), (0.4, 70.0),
                                      pytest.param(0.15, 70.0, marks=pytest.mark.slow)])
def test_albedo_is_the_flake_reflectance(mu_i, amp):
    # ∫ σ_s f_p dω_o over the sphere = aρ ∫ R(|ω·m|) |ω·m| D dm (scattering_Ergun): nothing absorbed but the
    # metal's.  Gauss–Legendre 300 in μ_o × 384 azimuths on the full circle, the same grid for the grooved and
    # the specular flake (whose own integral is ~9e-4 from scattering_Ergun at μ 0.15, the grazing lobe's
    # quadrature); the grating's redistribution is conserved to 2e-4 on it (measured); dropping the antipodal
    # cone's factor 2 misses ~20 %
    x, w = np.polynomial.legendre.leggauss(300)
    P = 384
    phi = np.arange(P) * 2 * np.pi / P
    integral = lambda **kw: np.einsum("cnp,n->c", _kernel(mu_i, x[:, None], phi[None, :], alpha=0.3, **kw),
                                      w) * 2 * np.pi / P
    total, specular = integral(amp=amp), integral(amp=0.0)
    ref = scattering_Ergun(np.array([mu_i]), 0.3, FlakeOptics(C_GRID, R_ROWS, 0 * R_ROWS), 1.3).ravel()
    assert np.all(integral(amp=amp, orders=(0,)) < 0.95 * ref)                 # the orders do carry light
    np.testing.assert_allclose(specular, ref, rtol=2e-3)
    np.testing.assert_allclose(total, specular, rtol=5e-4)


def test_reciprocity_and_up_down_symmetry():
    # k(ω_i -> ω_o) = k(−ω_o -> −ω_i) and the solver's z -> −z symmetry: the same cone, its nodes placed by
    # the geometry (the plane of h and z), so equal up to rounding (flat R)
    rng = np.random.default_rng(4)
    mi, mo = rng.uniform(0.05, 1, 400), -rng.uniform(0.05, 1, 400)
    ph = rng.uniform(0, np.pi, 400)
    R = np.full((1, 6), 0.85)
    f = lambda a, b, p: grating_flake_kernel(a, b, p, 0.15, C_GRID, R, [430.0], 690.0, 60.0, 1.5, 1.0,
                                             n_cone=256)
    k = f(mi, mo, ph)
    assert k.max() > 0.5
    np.testing.assert_allclose(f(-mo, -mi, ph), k, rtol=1e-11, atol=1e-13 * k.max())
    np.testing.assert_allclose(f(-mi, -mo, ph), k, rtol=1e-11, atol=1e-13 * k.max())


def _brute_force_kernel(wi, wo, lam, period, amp, alpha, R, n_b=1.5, a_rho=1.0, n=1_000_000, cone_deg=2.5, seed=0,
                        dist="beckmann"):
    """σ_s f_p at propagation directions ω_i, ω_o by sampling flakes: normals of density 2D on the upper
    hemisphere (both faces: the flake reflects from whichever faces the light), a uniform grating azimuth, every
    order k solved by the grating equation in the flake's frame, its power R · e_k (η_0 = 1 − Σ_{k≠0} of the
    propagating ones), the exits that land in a cone around ω_o.  No cone formula, no ψ-arc: independent."""
    rng = np.random.default_rng(seed)
    m = sample_flake_normal(rng.random(n), rng.random(n), alpha, dist)
    ref = np.where(np.abs(m[:, :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    u = np.cross(m, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(m, u)
    psi = rng.uniform(0, 2 * np.pi, n)
    t = np.cos(psi)[:, None] * u + np.sin(psi)[:, None] * v
    cin_s = m @ wi
    cin = np.abs(cin_s)
    p_in = wi[None, :] - cin_s[:, None] * m
    g = lam / (n_b * period)
    K = highest_order(lam, period, n_b)
    hits, S = np.zeros(n), np.zeros(n)
    cos_cone = np.cos(np.radians(cone_deg))
    for k in range(-K, K + 1):
        q = p_in + (k * g) * t
        q2 = np.sum(q * q, axis=1)
        prop = q2 < 1
        cout = np.sqrt(np.clip(1 - q2, 0, 1))
        w_out = q - (np.sign(cin_s) * cout)[:, None] * m
        hit = prop & (w_out @ wo > cos_cone)
        if k == 0:
            hit0 = hit
            continue
        e = np.where(prop, sinusoidal_order_efficiency(k, cin, cout, lam, amp, n_b), 0.0)
        S += e
        hits += np.where(hit, e, 0.0)
    hits += np.where(hit0, 1.0 - S, 0.0)
    weight = a_rho * cin * R * hits
    omega = 2 * np.pi * (1 - cos_cone)
    return float(weight.mean() / omega), float(weight.std() / np.sqrt(n) / omega)


def _prop(mu, phi):
    s = np.sqrt(1 - mu * mu)
    return np.array([s * np.cos(phi), s * np.sin(phi), -mu])


@pytest.mark.parametrize("mi,mo,ph,lam,dist", [
    (0.9, -0.85, 2.6, 450.0, "beckmann"), (0.95, -0.7, 0.0, 620.0, "beckmann"), (0.7, -0.95, 0.5, 520.0, "ggx"),
    (0.8, -0.9, 0.15, 480.0, "student_t(3)"), (-0.85, 0.9, 2.2, 450.0, "beckmann"),   # the last: lit from below
])
def test_kernel_matches_brute_force_flakes(mi, mo, ph, lam, dist):
    R = np.full((1, 6), 0.85)
    k = grating_flake_kernel(mi, mo, ph, 0.25, C_GRID, R, [lam], 690.0, 55.0, 1.5, 1.0, dist)[0]
    mc, se = _brute_force_kernel(_prop(mi, 0.0), _prop(mo, ph), lam, 690.0, 55.0, 0.25, 0.85, dist=dist, seed=3)
    assert k > 0.02
    # the estimate carries its standard error plus the 2.5° cone's averaging of a smooth kernel (< 1.5 %)
    assert abs(mc - float(k)) < 4 * se + 0.015 * float(k)


@pytest.mark.slow
def test_single_scattering_through_the_solver_matches_brute_force_flakes():
    # an index-matched slab of optical depth ~0.003-0.02 (the slant paths) (no interfaces, nothing below): the solver's reflection is
    # single scattering, f = k (1 − e^{−d S}) / (S μ_i μ_o), S = σ_t(μ_i)/μ_i + σ_t(μ_o)/μ_o, up to O(τ²)
    # multiple scattering (< 1 %); k from the brute-force flakes
    lam = np.array([470.0, 610.0])
    opt = FlakeOptics.constant([0.85, 0.85], [0.0, 0.0])
    med = GratingFlakeMedium(0.25, opt, 0.003, lam, 690.0, 55.0, 1.5)
    d = 1.0
    r = solve_stack(None, [Slab(d, med)], None, SolverSettings(n=16))
    x = r.x
    phis = np.array([0.0, 0.6, 2.5])
    f = r.eval_nodes(phis)                                              # (C, h_o, h_i, P)
    # the three brightest node pairs of the direct kernel (reflection: incident down, exit up) with both μ ≥ 0.8,
    # per band.  Nearer grazing the solver's thin slab departs from this formula for the specular flakes alike
    # (f / formula 0.15 at μ 0.02, 0.93 at μ 0.65, ≥ 0.98 above 0.8 for kernel_Ergun at n = 16), so that is
    # the solver's discretisation, not the grating's
    k = med.kernel(x[None, :, None], -x[:, None, None], phis[None, None, :])   # (C, h_o, h_i, P)
    k = np.where(((x[:, None] >= 0.8) & (x[None, :] >= 0.8))[None, :, :, None], k, 0.0)
    for c in range(2):
        for flat in np.argsort(k[c].ravel())[::-1][:3]:
            io, ii, ip = np.unravel_index(flat, k[c].shape)
            mi, mo, ph = x[ii], x[io], phis[ip]
            S = med.sigma_t(np.array([mi]))[c, 0] / mi + med.sigma_t(np.array([mo]))[c, 0] / mo
            mc, se = _brute_force_kernel(_prop(mi, 0.0), _prop(-mo, ph), lam[c], 690.0, 55.0, 0.25, 0.85,
                                         a_rho=0.003, seed=5 + c)
            single = (1 - np.exp(-d * S)) / (S * mi * mo)
            assert d * S < 0.03
            assert abs(f[c, io, ii, ip] - mc * single) < 4 * se * single + 0.02 * mc * single
