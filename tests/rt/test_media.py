"""The von Mises–Fisher phase function of flakedb.rt.scattering.media (docs/model.md §3) against closed forms and
quadrature.

Guards against: a wrong normalisation (2π ∫ p dcosΘ ≠ 1) or overflow for large κ, a wrong mean
cosine or κ ↔ g conversion, Legendre moments that are not those of p (checked against Gauss–Legendre
quadrature of p itself and, independently, against scipy's spherical_in), a solver kernel that is not
the vMF phase function (the φ-sampled projection against the addition theorem with the closed-form
moments), and energy created or lost by a vMF slab (white furnace).
"""

import numpy as np
import pytest
from numpy.polynomial.legendre import leggauss
from scipy.special import eval_legendre, spherical_in

from flakedb.rt.scattering import media as rm
from flakedb.rt.basis.legendre import LegendreKernel, truncate_legendre
from flakedb.rt.basis.quadrature import radau_hemisphere
from tests import tolerances as tol
from flakedb.rt.adding.stack import (
    Lambertian,
    Slab,
    Smooth,
    SolverSettings,
    project_medium,
    solve_stack,
)

KAPPAS = [0.0, 1e-4, 0.5, 3.0, 20.0, 200.0, 1000.0]


def graded_rule(n_seg=80, per=24):
    """Composite Gauss–Legendre on [−1, 1] with segments graded geometrically towards t = 1 (a vMF
    lobe has width ~1/κ in t), exact enough for κ ≤ 2000."""
    s = np.concatenate([[0.0], np.geomspace(1e-10, 2.0, n_seg)])
    edges = np.sort(1.0 - s)
    g, w = leggauss(per)
    a, b = edges[:-1, None], edges[1:, None]
    return (0.5 * (b - a) * (g + 1) + a).ravel(), (0.5 * (b - a) * w).ravel()


T, W = graded_rule()


@pytest.mark.parametrize("kappa", KAPPAS)
def test_vmf_is_normalised_and_has_the_closed_form_mean_cosine(kappa):
    p = rm.phase_vMF(T, kappa)
    assert np.all(np.isfinite(p)) and np.all(p >= 0)
    assert abs(2 * np.pi * np.sum(W * p) - 1.0) < 1e-12
    g_quad = 2 * np.pi * np.sum(W * p * T)
    g_closed = 1.0 / np.tanh(kappa) - 1.0 / kappa if kappa > 0.1 else kappa / 3 - kappa**3 / 45
    assert abs(rm.vmf_mean_cosine(kappa) - g_closed) < 1e-13
    assert abs(g_quad - g_closed) < 1e-12


def test_vmf_matches_the_textbook_form_and_is_isotropic_at_zero():
    for kappa in (0.3, 5.0, 40.0):
        naive = kappa / (4 * np.pi * np.sinh(kappa)) * np.exp(kappa * T)
        # exp's arguments κ(t − 1) and κt rounded (relative 2u, u: ×|arg|), exp, expm1, sinh ≤ 2 ulps each, 10 more roundings
        tol.assert_ulps(rm.phase_vMF(T, kappa), naive, (kappa * (2 * np.abs(T - 1) + np.abs(T)) + 25) / 2)
    np.testing.assert_allclose(rm.phase_vMF(T, 0.0), 1 / (4 * np.pi), rtol=0)
    np.testing.assert_allclose(rm.phase_vMF(T, 1e-9), 1 / (4 * np.pi), rtol=1e-8)
    with pytest.raises(ValueError, match="kappa >= 0"):
        rm.phase_vMF(T, -1.0)


def test_kappa_from_mean_cosine_round_trip():
    g = np.array([0.0, 1e-6, 0.1, 0.5, 0.9, 0.95, 0.99, 0.9995])
    k = rm.vmf_kappa_from_mean_cosine(g)
    np.testing.assert_allclose(rm.vmf_mean_cosine(k), g, rtol=1e-12, atol=1e-15)
    assert abs(rm.vmf_kappa_from_mean_cosine(1.0 / np.tanh(20.0) - 0.05) - 20.0) < 1e-10
    with pytest.raises(ValueError, match="0 <= g < 1"):
        rm.vmf_kappa_from_mean_cosine(-0.1)


@pytest.mark.parametrize("kappa", [0.5, 3.0, 20.0, 200.0, 1000.0])
def test_legendre_moments_match_quadrature(kappa):
    """χ_k = 2π ∫ p P_k dt by quadrature of p against the closed form i_k(κ)/i_0(κ), up to the
    truncation degree and beyond."""
    K = max(40, rm.vmf_legendre_degree(kappa) + 20)
    chi = rm.vmf_legendre_moments(kappa, K)[0]
    p = rm.phase_vMF(T, kappa)
    quad = np.array([2 * np.pi * np.sum(W * p * eval_legendre(k, T)) for k in range(K + 1)])
    assert np.abs(chi - quad).max() < 1e-11, np.abs(chi - quad).max()
    assert chi[0] == pytest.approx(1.0, abs=1e-15) and chi[1] == pytest.approx(rm.vmf_mean_cosine(kappa), rel=1e-12)


def test_legendre_moments_match_spherical_in_and_stay_finite_for_large_kappa():
    for kappa in (0.01, 1.0, 10.0, 50.0, 300.0):
        k = np.arange(30)
        ref = spherical_in(k, kappa) / spherical_in(0, kappa)
        np.testing.assert_allclose(rm.vmf_legendre_moments(kappa, 29)[0], ref, rtol=1e-10, atol=1e-300)
    big = rm.vmf_legendre_moments([200.0, 2000.0], 400)
    assert np.all(np.isfinite(big)) and np.all(big >= 0) and np.all(big <= 1)
    assert np.all(np.diff(big, axis=1) <= 0)  # the moments of a forward lobe decrease
    # large κ: χ_k → exp(−k(k + 1)/(2κ)) (the Gaussian limit of the lobe)
    k = np.arange(20)
    np.testing.assert_allclose(big[1, :20], np.exp(-k * (k + 1) / (2 * 2000.0)), rtol=2e-3)
    np.testing.assert_array_equal(rm.vmf_legendre_moments(0.0, 3)[0], [1, 0, 0, 0])


@pytest.mark.parametrize("kappa", [5.0, 200.0])
def test_solver_kernel_equals_the_addition_theorem_with_closed_form_moments(kappa):
    """The solver projects σ_s p(cos Θ) by φ sampling; the addition theorem with the closed-form
    moments gives the same cosine coefficients without any φ sampling (flakedb.rt.basis.legendre)."""
    q = radau_hemisphere(16)
    alb = np.array([0.9, 0.4])
    med = rm.PhaseMedium(0.5, alb, ("vmf", kappa))
    pk, _ = project_medium(med, q.x, q.w, 1e-7, 256, renormalize=False)
    K = rm.vmf_legendre_degree(kappa, tol=1e-12)
    ref = LegendreKernel(q.x, np.repeat(rm.vmf_legendre_moments(kappa, K), 2, axis=0), 0.5 * alb)
    L = min(pk.n_orders, ref.n_orders)
    KT, KR = pk.blocks(0, L)
    RT, RR = ref.blocks(0, L)
    scale = np.abs(RT).max()
    assert np.abs(KT - RT).max() < 1e-5 * scale and np.abs(KR - RR).max() < 1e-5 * scale
    assert L >= 8


@pytest.mark.parametrize("kappa", [0.0, 20.0, 200.0])
@pytest.mark.parametrize("n", [32, 64])
def test_white_furnace_vmf_slab(kappa, n):
    """Smooth coat / conservative vMF slab (albedo 1) / white base: nothing absorbs, so every
    channel's directional albedo (with the coat's delta) is 1."""
    med = rm.PhaseMedium(0.3, np.ones(2), ("vmf", np.array([kappa, kappa / 2])))
    r = solve_stack(Smooth(1.5), [Slab(10.0, med)], Lambertian(1.0), SolverSettings(n=n))
    assert np.abs(r.albedo() - 1.0).max() < 1e-3


def test_subset_and_kernel_basis_keep_per_channel_kappa():
    med = rm.PhaseMedium(1.0, np.array([0.9, 0.5, 0.2]), ("vmf", np.array([2.0, 2.0, 30.0])))
    kb = med.kernel_basis()
    assert kb.M.shape == (3, 2)  # one basis kernel per distinct κ
    mi, mo, ph = np.array([0.8]), np.array([0.6]), np.array([0.3])
    full = med.kernel(mi, mo, ph)
    np.testing.assert_allclose(kb.M @ kb.fn(mi, mo, ph).reshape(2, -1), full.reshape(3, -1), rtol=1e-14)
    np.testing.assert_allclose(med.subset([2]).kernel(mi, mo, ph), full[[2]], rtol=1e-14)


@pytest.mark.parametrize("g", [-0.4, 0.0, 0.7, 0.9])
def test_hg_legendre_moments_are_its_generating_function(g):
    """χ_k = g^k (Henyey & Greenstein 1941): the truncated series reproduces the closed-form phase
    function to the truncation's bound (tol × Σ (2k+1)/(4π) |χ_k| ≥ max p)."""
    tol = 1e-6
    chi, info = rm.PhaseMedium(1.0, 0.9, ("hg", g)).legendre_moments(tol)
    t = np.linspace(-1.0, 1.0, 2001)
    series = np.sum((2 * np.arange(chi.shape[1]) + 1)[:, None] / (4 * np.pi) * chi[0][:, None]
                    * eval_legendre(np.arange(chi.shape[1])[:, None], t[None, :]), axis=0)
    exact = (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * t) ** 1.5)
    bound = tol * np.sum((2 * np.arange(chi.shape[1]) + 1) / (4 * np.pi) * np.abs(chi[0]))
    assert np.abs(series - exact).max() <= 2 * bound
    assert info["converged"]
    assert rm.PhaseMedium(1.0, 0.9, ("hg", 0.999)).legendre_moments(tol) is None  # beyond LEGENDRE_K_MAX


_CT = np.cos(np.linspace(np.pi, 0.0, 361))  # 0.5° steps in Θ, as the Mie tables
_TABLE = np.stack([(1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * _CT) ** 1.5) for g in (0.2, 0.5, 0.6)])


@pytest.mark.parametrize("phase", [("hg", [0.3, 0.7, 0.85]), ("vmf", [5.0, 20.0, 60.0])])
def test_phase_kernels_by_the_addition_theorem_equal_the_azimuthal_projection(phase):
    """project_medium takes HG and vMF media through their Legendre moments (no φ sampling); the blocks
    equal the φ-sampled projection (basis=False) to its tolerance, and keep the renormalised energy."""
    q = radau_hemisphere(16)
    med = rm.PhaseMedium([1.0, 0.8, 1.2], [0.9, 0.5, 0.99], phase)
    pk, info = project_medium(med, q.x, q.w, 1e-6, 64)
    pk0, info0 = project_medium(med, q.x, q.w, 1e-6, 64, basis=False)
    assert info["kernel"].startswith("Legendre") and "n_phi" in info0
    L = min(pk.n_orders, pk0.n_orders)
    (KT, KR), (KT0, KR0) = pk.blocks(0, L), pk0.blocks(0, L)
    scale = np.abs(KT0).max()
    np.testing.assert_allclose(KT, KT0, atol=2e-5 * scale)
    np.testing.assert_allclose(KR, KR0, atol=2e-5 * scale)
    # energy: Σ_o 2π w_o (K_T + K_R)_0[o, i] = σ_s (renormalised, as the φ-sampled kernel)
    col = 2 * np.pi * np.einsum("coi,o->ci", KT[0] + KR[0], q.w)
    np.testing.assert_allclose(col, np.broadcast_to(med.sigma_s(q.x), col.shape), rtol=1e-12)


def test_a_tabulated_phase_function_by_its_moments_is_as_close_to_the_smooth_kernel_as_by_phi_sampling():
    """A table (HG g 0.2, 0.5, 0.6 sampled every 0.5° in Θ, as the Mie tables) goes through the exact
    moments of its linear interpolant and the addition theorem.  Both routes carry the table's own
    interpolation error (kinks at the grid points); measured against the exact HG kernel, the moments'
    route must be no worse than the φ-sampled projection of the same table (4.3e-5 vs 6.1e-5 of max)."""
    q = radau_hemisphere(16)
    sig, alb, G = [1.0, 0.8, 1.2], [0.9, 0.5, 0.99], [0.2, 0.5, 0.6]
    med = rm.PhaseMedium(sig, alb, ("table", _CT, _TABLE))
    pk, info = project_medium(med, q.x, q.w, 1e-6, 64, renormalize=False)
    pk0, info0 = project_medium(med, q.x, q.w, 1e-6, 64, renormalize=False, basis=False)
    pkh, _ = project_medium(rm.PhaseMedium(sig, alb, ("hg", G)), q.x, q.w, 1e-9, 64, renormalize=False)
    assert info["kernel"].startswith("Legendre") and "n_phi" in info0
    L = min(pk.n_orders, pk0.n_orders)
    (KT, KR), (KT0, KR0) = pk.blocks(0, L), pk0.blocks(0, L)
    HT, HR = pkh.blocks(0, L)
    scale = np.abs(HT).max()
    err = max(np.abs(KT - HT).max(), np.abs(KR - HR).max()) / scale
    err0 = max(np.abs(KT0 - HT).max(), np.abs(KR0 - HR).max()) / scale
    assert err <= err0 and err < 1e-4


def test_a_series_cut_at_its_last_degree_is_not_converged():
    """truncate_legendre may only call a cut converged when the dropped tail was measured: a cut at the
    last given degree leaves an unknown tail (HG g 0.99 over 65 degrees), a cut before it does not."""
    k = np.arange(65)
    _, info = truncate_legendre(0.99 ** k[None, :], 1e-6)
    assert info["degree"] == 64 and not info["converged"]
    _, info = truncate_legendre(0.3 ** k[None, :], 1e-6)
    assert info["degree"] < 64 and info["converged"]


@pytest.mark.parametrize("tol", [1e-5, 1e-6])
def test_every_vmf_lobe_goes_the_legendre_route(tol):
    """vMF moments are computed past the degree the tail asks for, so the truncation is measured and
    the kernel takes the addition theorem for every κ of the recipe range (it fell back to φ sampling
    for κ 0.5–30 when the moments stopped exactly at that degree)."""
    for kappa in (0.0, 0.5, 1.0, 3.0, 8.0, 30.0, 200.0, 2000.0):
        lm = rm.PhaseMedium(1.0, 0.5, ("vmf", kappa)).legendre_moments(tol)
        assert lm is not None and lm[1]["converged"], kappa
