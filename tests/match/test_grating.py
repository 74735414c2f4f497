"""Grating (diffractive) flakes in single scattering (flakedb.match.grating, docs/validation.md §4a): the cone
formula against an independent Monte Carlo of random flake normals and grating azimuths, its m -> 0 limit against
the specular flake BRDF, reciprocity, and energy (the order's albedo) against the grating equation's closed form."""

import numpy as np
import pytest

from flakedb.match.grating import (binder_directions, grating_brdf, grating_brdf_montecarlo, mean_flake_cosine,
                                   projected_density)
from flakedb.rt.scattering.microflake import flake_ndf


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.mark.parametrize("alpha,dist,order,geom,lam,period", [
    (0.2, "beckmann", 1, (45, 25), 550, 1000), (0.2, "beckmann", 1, (15, 45), 550, 1000),
    (0.2, "beckmann", 2, (45, 75), 550, 1000), (0.3, "ggx", 1, (45, -15), 550, 1000),
    (0.15, "student_t(2.9)", 1, (45, 45), 550, 1000), (0.2, "beckmann", 0, (15, 45), 550, 1000),
    (0.6, "beckmann", 1, (15, 45), 650, 420),   # a wide cone (β₀ 31°): cos β₀ 0.86 matters
])
def test_cone_formula_matches_brute_force_flakes(alpha, dist, order, geom, lam, period):
    # 1 million flakes, each diffracted by the grating equation solved in its own frame, binned in a 2° cone: the
    # estimate carries its standard error plus the cone's averaging (f is smooth: second order in 2°, < 1 %)
    wi, wo, _, _ = binder_directions([geom])
    f = grating_brdf(wi, wo, [lam], period, alpha, dist, orders=(order,))[0, 0, 0]
    mc, se = grating_brdf_montecarlo(wi[0], wo[0], lam, period, alpha, order, dist, n_samples=1_000_000,
                                     cone_deg=2.0, seed=7)
    assert f > 0.02
    assert abs(mc - f) < 4.0 * se + 0.01 * f


def test_first_order_tends_to_the_specular_flake_as_the_period_grows():
    # r = λ/(n Λ) -> 0 closes the cone on h: f_1 -> D_p(h)/(4 μ_i μ_o), the m = 0 (microfacet) form
    wi, wo, _, _ = binder_directions([(45, 15), (15, 45), (45, 45)])
    f0 = grating_brdf(wi, wo, [550.0], 1e3, 0.2, orders=(0,))[0, :, 0]
    h = _unit(wi + wo)
    np.testing.assert_allclose(f0, projected_density(h[:, 2], 0.2) / (4 * wi[:, 2] * wo[:, 2]), rtol=1e-12)
    f1 = grating_brdf(wi, wo, [550.0], 1e7, 0.2, orders=(1,))[0, :, 0]
    np.testing.assert_allclose(f1, f0, rtol=2e-4)


def test_projected_density_covers_the_coat_once():
    # ∫ D_p (m·z) dm = 1 by construction; ⟨m·z⟩ for Beckmann has the closed form
    # ∫ 2D cos = E[1/√(1+t²)] over the Gaussian slope: checked against a 1-D quadrature in t
    for a in (0.05, 0.3):
        t = np.linspace(0, 40 * a, 200001)
        dens = np.exp(-t * t / a ** 2) * 2 * t / a ** 2                  # pdf of tan θ_m
        ref = np.trapezoid(dens / np.sqrt(1 + t * t), t)
        assert mean_flake_cosine(a, "beckmann") == pytest.approx(ref, rel=1e-8)


def test_reciprocity():
    rng = np.random.default_rng(3)
    wi = _unit(np.c_[rng.normal(size=(50, 2)), rng.uniform(0.2, 1, 50)])
    wo = _unit(np.c_[rng.normal(size=(50, 2)), rng.uniform(0.2, 1, 50)])
    a = grating_brdf(wi, wo, [450.0, 620.0], 800.0, 0.25, orders=(0, 1, 2))
    b = grating_brdf(wo, wi, [450.0, 620.0], 800.0, 0.25, orders=(0, 1, 2))
    assert np.abs(a).max() > 0.1
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("g,expected", [(0.6, 1.0), (1.3, 0.0)])
def test_first_order_albedo_is_the_grating_equations(g, expected):
    # normal incidence on nearly aligned flakes (α 0.03): order 1 leaves at sin θ = g when g < 1 (all the order's
    # power, albedo 1) and is evanescent when g > 1 (albedo 0, up to flakes tilted enough to let it out:
    # none at α 0.03 for g = 1.3); ∫ f μ_o dω_o, the azimuth by symmetry (normal incidence, uniform grating
    # azimuth: f does not depend on φ_o), the polar angle on a fine grid in cos θ_o
    lam, n_b = 550.0, 1.5
    period = lam / (n_b * g)
    mu = np.linspace(1e-4, 1, 4000)
    wo = np.stack([np.sqrt(1 - mu * mu), np.zeros_like(mu), mu], axis=-1)
    wi = np.tile([0.0, 0.0, 1.0], (len(wo), 1))
    f = grating_brdf(wi, wo, [lam], period, 0.03, orders=(1,), n_binder=n_b, n_phi=256)[0, :, 0]
    alb = np.trapezoid(f * 2 * np.pi * mu, mu)
    # the grid resolves the lobe (width ~2α in sin θ): 1 % from the quadrature
    assert alb == pytest.approx(expected, abs=0.015)


def test_sinusoidal_efficiencies_conserve_power_and_have_the_shallow_limit():
    from flakedb.match.grating import sinusoidal_efficiency
    c = np.linspace(0.2, 1, 7)
    tot = sum(sinusoidal_efficiency(m, c, c[::-1], 520.0, 140.0) for m in range(60))
    np.testing.assert_allclose(tot, 1.0, rtol=1e-12)
    # shallow grooves: J_1(Φ) = Φ/2 − Φ³/16 + O(Φ⁵), η_±1 = 2 J_1², Φ = 2π n a (c_in + c_out)/λ (= 0.069 here)
    phi = 2 * np.pi * 1.5 * 2.0 * 2.0 / 550.0
    assert sinusoidal_efficiency(1, 1.0, 1.0, 550.0, 2.0) == pytest.approx(2 * (phi / 2 - phi ** 3 / 16) ** 2,
                                                                           rel=1e-6)


@pytest.mark.parametrize("order,geom", [(0, (45, 15)), (1, (45, 45)), (2, (15, 45))])
def test_grooved_flakes_match_brute_force(order, geom):
    # the efficiency taken at each flake's own cosines on the cone, against flakes weighted one by one
    wi, wo, _, _ = binder_directions([geom])
    f = grating_brdf(wi, wo, [480.0], 900.0, 0.2, orders=(order,), depth_nm=90.0)[0, 0, 0]
    mc, se = grating_brdf_montecarlo(wi[0], wo[0], 480.0, 900.0, 0.2, order, n_samples=1_000_000, cone_deg=2.0,
                                     seed=11, depth_nm=90.0)
    assert f > 0.02
    assert abs(mc - f) < 4.0 * se + 0.01 * f


def test_binder_directions_agree_with_the_half_angle_test():
    # the same refracted geometry as flakedb.match.halfangle (whose θ_d' groups motivate the grating flake)
    from flakedb.match.halfangle import binder_half_angles_deg
    g = [(45, -15), (45, 15), (45, 25), (45, 45), (45, 75), (45, 110), (15, -45), (15, -15), (15, 15), (15, 45),
         (15, 80)]
    wi, wo, mu_i, mu_v = binder_directions(g)
    h = _unit(wi + wo)
    th, td = binder_half_angles_deg(g)
    np.testing.assert_allclose(np.degrees(np.arccos(np.clip(h[:, 2], -1, 1))), th, atol=1e-6)
    np.testing.assert_allclose(np.degrees(np.arccos(np.sum(wi * h, axis=1))), td, atol=1e-6)
    np.testing.assert_allclose(mu_v, np.cos(np.radians(np.array(g)[:, 0] - np.array(g)[:, 1])), rtol=1e-15)
