"""The adding-doubling solver: quadrature, Fourier projection, adding, doubling, interfaces.

Guards against: quadrature rules that do not integrate what they should; a Fourier projection
with aliasing or wrong normalisation; adding equations with a transposed block or a missing
multiple-reflection term; a thin-layer start or doubling that loses or creates energy; a smooth
interface whose node mapping, Jacobian or total internal reflection is wrong; broken reciprocity;
a slab whose result depends on how it was split.
"""

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import ive

import flakedb.rt.adding.channels as rt_channels
import flakedb.rt.adding.parts as rt_parts
import flakedb.rt.adding.stack as stk
from flakedb.bsdf.convert import stack_to_table
from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.rt.basis.fourier import cosine_coefficients, phi_samples, project_azimuthal
from flakedb.rt.basis.layer import add, homogeneous_slab, identity_layer
from flakedb.rt.scattering.media import FlakeMedium, Mixture, PhaseMedium
from flakedb.rt.scattering.microflake import FlakeOptics
from flakedb.rt.basis.quadrature import (
    binder_chain_quadratures,
    default_tir_nodes,
    gauss_radau_unit,
    radau_hemisphere,
    snell_mapped_quadrature,
)
from flakedb.rt.adding.stack import (
    InnerRough,
    InnerSmooth,
    Lambertian,
    Rough,
    RoughConductor,
    Slab,
    Smooth,
    SolverSettings,
    medium_kernel_blocks,
    solve_stack,
)
from tests import tolerances as tol


# ---------------------------------------------------------------- quadrature and projection
@pytest.mark.parametrize("h", [1, 3, 8, 40])
def test_radau_exact_degree(h):
    x, w = gauss_radau_unit(h)
    assert x[-1] == 1.0 and x[0] > 0
    for k in range(2 * h - 1):
        assert abs((w * x**k).sum() - 1.0 / (k + 1)) < 1e-13


def test_snell_mapped_rule_integrates_inside_hemisphere():
    q = radau_hemisphere(24)
    qi = snell_mapped_quadrature(q, 1.5, 20)
    mu_c = np.sqrt(1 - 1 / 1.5**2)
    assert np.all(np.diff(qi.x) > 0) and qi.x[0] > 0
    assert qi.x[qi.h - qi.n_mapped] > mu_c  # mapped nodes lie beyond the critical cosine
    for f, exact in ((lambda m: m, 0.5), (lambda m: np.exp(m), np.e - 1), (lambda m: m**7, 1 / 8)):
        assert abs((qi.w * f(qi.x)).sum() - exact) < 1e-12


def test_cosine_coefficients_von_mises_closed_form():
    # exp(κ cos φ) = I_0(κ) + 2 Σ I_l(κ) cos lφ (Abramowitz & Stegun 9.6.34)
    kappa = 30.0
    a = cosine_coefficients(g := np.exp(kappa * (np.cos(phi_samples(256)) - 1.0)))
    exact = ive(np.arange(40), kappa) * np.where(np.arange(40) == 0, 1.0, 2.0)
    # DCT-I = FFT of the 512-point even extension (‖·‖₂ ≤ √2‖g‖₂), ÷ 256; the samples' own rounding (φ, cos, −1, κ·,
    # exp: relative ≤ (κ(2π + 4) + 2) u) through Σ (2/N)|g|; ive and the ÷ a few ulps
    tol.assert_within(a[:40], exact, tol.fft_tol(512, np.sqrt(2) * np.linalg.norm(g) / 256)
                      + (kappa * (2 * np.pi + 4) + 2) * tol.U * 2 * np.abs(g).mean() + tol.ulps(4, exact))


def test_projection_adapts_to_a_narrow_lobe():
    kappa = 400.0

    def fn(mi, mo, ph):
        return np.exp(kappa * (np.cos(ph) - 1.0)) * (1 + 0 * mi * mo)

    c, info = project_azimuthal(fn, np.array([0.5]), np.array([0.5]), tol=1e-8, n_start=4)
    L = c.shape[0]
    exact = ive(np.arange(L), kappa) * np.where(np.arange(L) == 0, 1.0, 2.0)
    np.testing.assert_allclose(c[:, 0, 0, 0], exact, atol=1e-10)
    assert info["converged"] and 60 < L < 200  # orders follow the lobe width ~ 1/√κ


# ---------------------------------------------------------------- adding algebra
def test_empty_layer_changes_nothing():
    med = PhaseMedium(1.0, 0.9, ("hg", 0.5))
    r = solve_stack(None, [Slab(0.7, med)], None, SolverSettings(n=16))
    from flakedb.rt.basis.layer import Layer

    lay = Layer(r.Rt, r.Ttb, r.Rb, r.Tbt)
    e = identity_layer(r.n_orders, len(r.x))
    for combined in (add(e, lay), add(lay, e)):
        for blk in ("Rt", "Ttb", "Rb", "Tbt"):
            np.testing.assert_array_equal(getattr(combined, blk), getattr(lay, blk))  # exact: I − 0·R = I, solve(I, B) = B, x·1 + 0s


def test_split_slab_equals_whole_slab():
    med = PhaseMedium(2.0, 0.95, ("hg", 0.6))
    s = SolverSettings(n=24, slice_tau=2.0**-14)
    whole = solve_stack(None, [Slab(1.0, med)], None, s)
    split = solve_stack(None, [Slab(0.3, med), Slab(0.7, med)], None, s)
    L = min(whole.n_orders, split.n_orders)
    for blk in ("Rt", "Ttb"):
        np.testing.assert_allclose(getattr(split, blk)[:L], getattr(whole, blk)[:L], atol=2e-7)


# ---------------------------------------------------------------- energy conservation
@pytest.mark.parametrize(
    "medium",
    [
        PhaseMedium(1.0, 1.0),
        PhaseMedium(1.0, 1.0, ("hg", 0.7)),
        PhaseMedium(3.0, 1.0, ("hg", -0.4)),
        FlakeMedium(0.2, FlakeOptics.constant(0.3, 0.7), 1.5),
        Mixture([FlakeMedium(0.3, FlakeOptics.constant(0.6, 0.4), 1.0), PhaseMedium(0.5, 1.0, ("hg", 0.3))]),
    ],
    ids=["isotropic", "hg0.7", "hg-0.4-thick", "flakes-R+T=1", "flakes+hg"],
)
def test_white_furnace_index_matched(medium):
    r = solve_stack(None, [Slab(1.0, medium)], None, SolverSettings(n=32))
    total = r.albedo() + r.transmittance()
    assert np.abs(total - 1.0).max() < 1e-6


def test_white_furnace_smooth_coat_white_primer():
    med = PhaseMedium(1.0, 1.0, ("hg", 0.7))
    r = solve_stack(Smooth(1.5), [Slab(1.0, med)], Lambertian(1.0), SolverSettings(n=32))
    assert np.abs(r.albedo() - 1.0).max() < 1e-9
    np.testing.assert_allclose(r.delta_F, fresnel_dielectric(r.x, 1.5).R)


def test_smooth_coat_over_lambertian_closed_form():
    """Diffuse substrate under a smooth coat (the classic geometric-series result):
    tabulated albedo = (1 − F(θ_i)) a (1 − F̄_in) / (1 − a F̄_in), F̄_in = ∫ F_in(μ) 2μ dμ."""
    a, eta = 0.6, 1.5
    Fbar_in = quad(lambda m: fresnel_dielectric(-m, eta).R * 2 * m, 0, 1, points=[np.sqrt(1 - 1 / eta**2)],
                   epsabs=1e-13, limit=200)[0]
    r = solve_stack(Smooth(eta), [], Lambertian(a), SolverSettings(n=64))
    F = fresnel_dielectric(r.x, eta).R
    expect = (1 - F) * a * (1 - Fbar_in) / (1 - a * Fbar_in)
    np.testing.assert_allclose(r.albedo(include_delta=False)[0], expect, rtol=2e-6)


def test_pure_absorber_direct_beam_and_doubling_convergence():
    """A pure absorber is the exact diagonal T = exp(−τ/μ); a scattering slab converges in the
    first-slice thickness at second order (the diamond start): the error against a very fine
    start falls ≥ 10× per two doublings (measured 16×: 1.2e-5, 7.5e-7, 4.7e-8 at 2⁻⁴, 2⁻⁶, 2⁻⁸)."""
    r = solve_stack(None, [Slab(1.0, PhaseMedium(1.0, 0.0))], None, SolverSettings(n=16))
    tol.assert_ulps(np.diagonal(r.Ttb[0, 0]), np.exp(-1.0 / r.x), 1.0 / r.x + 4)  # arg's 2 roundings ×|arg|, exp ≤ 1 ulp each side
    med = PhaseMedium(2.0, 0.9, ("hg", 0.7))
    dbl = dict(n=16, slab_method="doubling")
    ref = solve_stack(None, [Slab(1.0, med)], None, SolverSettings(slice_tau=2.0**-16, **dbl)).albedo()
    errs = [np.abs(solve_stack(None, [Slab(1.0, med)], None, SolverSettings(slice_tau=st, **dbl)).albedo()
                   - ref).max() for st in (2.0**-4, 2.0**-6, 2.0**-8)]
    assert errs[0] / errs[1] > 10 and errs[1] / errs[2] > 10 and errs[2] < 1e-7, errs


@pytest.mark.parametrize("albedo,tau", [(0.9, 2.0), (1.0, 2.0), (1.0 - 1e-9, 50.0), (0.999, 100.0), (0.5, 0.01)])
def test_eigen_slab_is_the_limit_of_doubling(albedo, tau):
    """The eigen-solution of a slab (the default) is the limit of doubling as the first slice → 0:
    against doubling from a 2⁻¹⁸ slice (error ~1e-10 by the second-order convergence above) every
    block of every order agrees to 1e-7 of its largest entry, conservative (k = 0) and optically thick
    (τ = 100, no overflow) included; and it conserves energy exactly for albedo 1."""
    x, w = radau_hemisphere(12).x, radau_hemisphere(12).w
    med = PhaseMedium(1.0, albedo, ("hg", 0.7))
    K_T, K_R, _ = medium_kernel_blocks(med, x, w, 1e-6, 32)
    sig = med.sigma_t(x)
    e = homogeneous_slab(x, w, sig, K_T, K_R, tau)
    d = homogeneous_slab(x, w, sig, K_T, K_R, tau, slice_tau=2.0**-18, method="doubling")
    for a, b in ((e.Rt, d.Rt), (e.Ttb, d.Ttb)):
        assert np.all(np.isfinite(a))
        assert np.abs(a - b).max() <= 1e-7 * np.abs(b).max()
    if albedo == 1.0:
        flux = np.einsum("oi,o->i", (e.Rt + e.Ttb)[0, 0], w * x) / (w * x)
        assert np.abs(flux - 1.0).max() < 1e-12


def test_eigen_slab_threads_and_non_reciprocal_fallback():
    """Threads split orders or channels with identical results; a kernel that is not reciprocal
    (K ≠ Kᵀ beyond EIGEN_SYMMETRY_TOL) is doubled instead of silently symmetrised."""
    x, w = radau_hemisphere(10).x, radau_hemisphere(10).w
    med = PhaseMedium(np.ones(5), np.linspace(0.5, 0.99, 5), ("hg", 0.6))
    K_T, K_R, _ = medium_kernel_blocks(med, x, w, 1e-6, 32)
    sig = med.sigma_t(x)
    one = homogeneous_slab(x, w, sig, K_T, K_R, 3.0)
    for L in (K_T.shape[0], 1):
        a = homogeneous_slab(x, w, sig, K_T[:L], K_R[:L], 3.0, threads=1)
        b = homogeneous_slab(x, w, sig, K_T[:L], K_R[:L], 3.0, threads=2)
        np.testing.assert_array_equal(b.Rt, a.Rt)  # exact by construction: the same LAPACK calls on the same matrices
        np.testing.assert_array_equal(b.Ttb, a.Ttb)
    skew = K_T.copy()
    skew[..., 0, 1] *= 1.01
    dbl = homogeneous_slab(x, w, sig, skew, K_R, 3.0, method="doubling")
    got = homogeneous_slab(x, w, sig, skew, K_R, 3.0)
    np.testing.assert_array_equal(got.Rt, dbl.Rt)  # exact by construction: the fallback is the same doubling call
    assert np.abs(one.Rt - dbl.Rt).max() > 0


# ---------------------------------------------------------------- reciprocity
@pytest.mark.parametrize("case", ["smooth-hg-primer", "flakes-smooth"])
def test_reciprocity(case):
    if case == "smooth-hg-primer":
        r = solve_stack(Smooth(1.5), [Slab(1.0, PhaseMedium(1.0, 0.9, ("hg", 0.7)))], Lambertian(0.5),
                        SolverSettings(n=24))
    else:
        m = FlakeMedium(0.25, FlakeOptics.constant(0.5, 0.3), 1.0)
        r = solve_stack(Smooth(1.5), [Slab(2.0, m)], Lambertian(0.3), SolverSettings(n=24))
    f = r.f_coefficients("Rt")  # f_l(μ_i → μ_o) [l, c, o, i]
    scale = np.abs(f).max()
    # exact up to the per-column energy renormalisation of the kernel (medium_kernel_blocks)
    assert np.abs(f - np.swapaxes(f, -1, -2)).max() < 1e-10 * scale


def test_transmission_reciprocity_with_eta_squared_rule():
    """Through a smooth coat into the binder and back.  Radiance BSDFs obey the η² rule
    f(i→o)/η_o² = f(o→i)/η_i² (Veach 1997, eq. 5.14); with f_basic = f (η_i/η_o)² (conventions)
    that reads f_basic(i→o)/η_i² = f_basic(o→i)/η_o²."""
    eta = 1.33
    med = PhaseMedium(1.0, 0.8, ("hg", 0.5))
    r = solve_stack(Smooth(eta), [Slab(0.5, med)], None, SolverSettings(n=20))
    ft = r.f_coefficients("Ttb")  # basic radiance, air → binder, [l, c, o(binder), i(air)]
    fb = r.f_coefficients("Tbt")  # binder → air, [l, c, o(air), i(binder)]
    f_rad_ab = ft * eta**2  # radiance BSDF air → binder
    f_rad_ba = fb / eta**2  # binder → air
    np.testing.assert_allclose(f_rad_ab / eta**2, np.swapaxes(f_rad_ba, -1, -2) / 1.0**2,
                               atol=1e-10 * np.abs(f_rad_ab).max())


# ---------------------------------------------------------------- published values
@pytest.mark.parametrize("g, ur1, ut1", [(0.0, 0.21085, 0.54140), (0.8, 0.03041, 0.76388)])
def test_prahl_adding_doubling_values(g, ur1, ut1):
    """Index-matched slab, albedo 0.8, optical thickness 1, normal incidence: total reflection UR1
    and total transmission UT1 (unscattered included) from S. Prahl's adding-doubling program, as
    quoted in iadpython's tests (tests/test_iadc.py, test_04_finite / test_05_finite_anisotropic).
    Five published digits: agreement to 1e-5 absolute."""
    r = solve_stack(None, [Slab(2.0, PhaseMedium(0.5, 0.8, ("hg", g)))], None, SolverSettings(n=64))
    assert r.x[-1] == 1.0
    assert abs(r.albedo()[0, -1] - ur1) < 1e-5
    assert abs(r.transmittance()[0, -1] - ut1) < 1e-5


def test_van_de_hulst_table12_isotropic():
    """van de Hulst, *Multiple Light Scattering* (1980) vol. 1, Table 12, pp. 260-261: isotropic
    scattering, albedo 0.8, optical thickness 2: reflection function R(μ, μ0) = π f_r and
    transmission function T(μ, μ0) = π f_t (values as quoted in Mitsuba's layer tests)."""
    from flakedb.bsdf import table_evaluator

    r = solve_stack(None, [Slab(1.0, PhaseMedium(2.0, 0.8))], None, SolverSettings(n=96))
    bs = table_evaluator(stack_to_table(r))
    # f·|μ_o| from the table (Catmull–Rom between nodes, docs/bsdf-format.md) → π f
    for mu0, mu, ref, transmit in [(1.0, 0.5, 0.28616, False), (0.5, 0.5, 0.39102, False),
                                   (1.0, 0.5, 0.14864, True)]:
        val = bs.eval(mu0, mu if transmit else -mu, 0.0)[0] / mu * np.pi
        assert abs(val - ref) < 2e-5, (mu0, mu, val, ref)


# ---------------------------------------------------------------- convergence
def test_convergence_in_nodes():
    """A BSDF value of a smooth-coated flake paint converges as n grows: successive differences
    shrink.  (The albedo converges much faster, ~1e-7 already at n = 16, thanks to the kernel's
    energy renormalisation; the angular shape is the demanding part.)"""
    from flakedb.bsdf import table_evaluator

    m = FlakeMedium(0.3, FlakeOptics.constant(0.6, 0.2), 1.0)
    vals = []
    for n in (16, 32, 64):
        r = solve_stack(Smooth(1.5), [Slab(2.0, m)], Lambertian(0.5), SolverSettings(n=n))
        vals.append(table_evaluator(stack_to_table(r)).eval(1.0, -0.6, 0.5)[0])
    # measured: 0.0559015 (n=16), 0.0559129 (32), 0.0559035 (64): converged to ~2e-4 relative,
    # the remaining wobble being the Catmull–Rom interpolation between nodes
    assert max(vals) - min(vals) < 5e-4 * abs(vals[2]), vals


def test_convergence_in_orders():
    """Keeping fewer Fourier orders changes the BSDF by an amount that falls at a stated rate with the
    order count (order cap of SolverSettings): at least 100× per 8 orders for this α = 0.15 mirror-
    flake paint (measured: 3.7e-2, 7.9e-5, 1.4e-8, 5.6e-13 at 8, 16, 24, 32 orders, relative to the
    BSDF's maximum); the energy (order 0) barely depends on it."""
    m = FlakeMedium(0.15, FlakeOptics.constant(0.8, 0.0), 1.0)
    plain = dict(n=32, filter_capped_kernels=False)  # plain truncation (the cap's Jackson filter is tested apart)
    full = solve_stack(Smooth(1.5), [Slab(2.0, m)], Lambertian(0.3), SolverSettings(**plain))
    phi = np.linspace(0, np.pi, 181)
    ref = full.eval_nodes(phi)
    errs = []
    for L in (8, 16, 24, 32):
        r = solve_stack(Smooth(1.5), [Slab(2.0, m)], Lambertian(0.3), SolverSettings(max_orders=L, **plain))
        if L >= 16:
            np.testing.assert_allclose(r.albedo(), full.albedo(), rtol=1e-5)
        errs.append(np.abs(r.eval_nodes(phi) - ref).max() / np.abs(ref).max())
    for a, b in zip(errs, errs[1:]):
        assert b <= 1e-2 * a, errs
    assert errs[-1] < 1e-10, errs


def test_fast_fresnel_of_rough_interface_matches_reference():
    from flakedb.optics.fresnel import fresnel_dielectric_real

    c = np.linspace(1e-6, 1.0, 20001)
    for eta in (1.5, 1 / 1.5, 1.33, 2.4):
        np.testing.assert_allclose(fresnel_dielectric_real(c, eta), fresnel_dielectric(c, eta).R, atol=1e-14)


def test_convergence_in_tir_nodes():
    """Nodes in the totally internally reflected range below a smooth coat: the albedo converges at
    least at first order in their count (error against a fine reference h_tir = 128 falls by ≥ 1.8×
    per doubling; measured 1.6e-5, 3.2e-6, 1.6e-6, 7.9e-7 at 4, 8, 16, 32 nodes)."""
    med = Mixture([FlakeMedium(0.2, FlakeOptics.constant(0.5, 0.3), 1.0), PhaseMedium(1.0, 0.9, ("hg", 0.5))])
    ref = solve_stack(Smooth(1.5), [Slab(5.0, med)], Lambertian(0.5), SolverSettings(n=32, h_tir=128)).albedo()
    errs = [np.abs(solve_stack(Smooth(1.5), [Slab(5.0, med)], Lambertian(0.5),
                               SolverSettings(n=32, h_tir=k)).albedo() - ref).max() for k in (4, 8, 16, 32)]
    for a, b in zip(errs, errs[1:]):
        assert b <= a / 1.8, errs
    assert errs[0] < 2e-5, errs


def test_channel_groups_equal_one_solve(monkeypatch):
    """A problem too large for the memory budget is solved in groups of channels; the result is the
    same as solving all channels together (channels are independent) up to the discretisation
    choices that depend on the group (φ sampling, doubling count from the group's largest σ_t):
    measured 2e-8 relative."""
    c = np.linspace(0, 1, 9)
    R = np.stack([0.2 + 0.1 * k * c for k in range(5)])
    med = Mixture([FlakeMedium(0.25, FlakeOptics(c, R, 0.3 * np.ones_like(R)), 1.0),
                   PhaseMedium(np.linspace(0.5, 1.5, 5), np.linspace(0.5, 0.9, 5), ("hg", np.linspace(0.1, 0.6, 5)))])
    args = (Smooth(1.5), [Slab(2.0, med)], Lambertian(np.linspace(0.1, 0.9, 5)))
    whole = solve_stack(*args, SolverSettings(n=16))
    from flakedb.rt.adding import stack as st

    monkeypatch.setattr(st, "MEMORY_BUDGET_BYTES", 2.5 * st._bytes_per_channel(16, 8 + 3, 32))
    grouped = solve_stack(*args, SolverSettings(n=16))
    assert len(grouped.info["channel_groups"]) == 3
    L = min(whole.n_orders, grouped.n_orders)
    np.testing.assert_allclose(grouped.Rt[:L], whole.Rt[:L], rtol=1e-6, atol=1e-9 * np.abs(whole.Rt).max())


# ------------------------------------------------------------------------------------------------
# Inner interface (issue 12 item 3(a)): a smooth interface between two binders, η_below / η_above > 1
# ------------------------------------------------------------------------------------------------

def _hg(albedo, g=0.7, sigma=0.1):
    return PhaseMedium(np.array([sigma]), np.array([albedo]), ("hg", g))


@pytest.mark.parametrize("top", [Smooth(1.5), Rough(1.5, 0.1), None])
@pytest.mark.parametrize("settings", [SolverSettings(n=32), SolverSettings.product(32)])
def test_inner_interface_white_furnace(top, settings):
    """Lossless stack (HG slabs of albedo 1, white primer) with a 1.5 → 1.6 inner interface: every photon
    comes back, whatever the rules' mismatch (the interface conserves energy by construction)."""
    eta_in = (1.6 / 1.5) if top is not None else 1.6
    r = solve_stack(top, [Slab(10.0, _hg(1.0)), InnerSmooth(eta_in), Slab(10.0, _hg(1.0, 0.3))], Lambertian(1.0),
                    settings)
    assert np.abs(r.albedo() - 1.0).max() < 1e-3
    assert np.abs(r.albedo() - 1.0).max() < 1e-10  # measured 1.5e-13
    assert r.info["inner_interfaces"][0]["nodes_below"] > len(r.x)  # TIR nodes in the denser binder


def test_inner_interface_reciprocity_and_equal_index_reduction():
    slabs = [Slab(10.0, _hg(0.9)), InnerSmooth(1.6 / 1.5), Slab(10.0, _hg(0.9, 0.3))]
    r = solve_stack(Smooth(1.5), slabs, Lambertian(0.5), SolverSettings(n=32))
    f = r.f_coefficients("Rt")
    assert np.allclose(f, np.swapaxes(f, -1, -2), rtol=1e-9, atol=1e-12 * np.abs(f).max())
    a = solve_stack(Smooth(1.5), [slabs[0], InnerSmooth(1.0), slabs[2]], Lambertian(0.5), SolverSettings(n=32))
    b = solve_stack(Smooth(1.5), [slabs[0], slabs[2]], Lambertian(0.5), SolverSettings(n=32))
    assert np.abs(a.Rt - b.Rt).max() <= 1e-13 * np.abs(b.Rt).max()
    # a change of index changes the result (the test above is not vacuous)
    assert np.abs(r.Rt[0] - b.Rt[0]).max() > 1e-3 * np.abs(b.Rt[0]).max()


def test_kernel_cut_by_the_order_cap_is_jackson_filtered():
    """Perfect mirror flakes α 0.15 in air (no coat) at n = 32: the kernel's series is cut by the 2n cap
    and rang to −3.5 % of the BSDF's maximum; the Jackson filter keeps it ≥ −1e-4 (measured −2.4e-5) and
    keeps the energy (order 0) exactly; a kernel that converges below the cap is left alone."""
    m = FlakeMedium(0.15, FlakeOptics.constant(1.0, 0.0), 3.0)
    phi = np.linspace(0, np.pi, 181)
    out = {}
    for filt in (True, False):
        r = solve_stack(None, [Slab(1.0, m)], Lambertian(0.0), SolverSettings.product(32, filter_capped_kernels=filt))
        g = r.eval_nodes(phi) * (r.x[:, None] * r.x[None, :])[None, :, :, None]
        out[filt] = (g.min() / g.max(), r)
    assert out[False][0] < -0.02 and out[True][0] > -1e-4, (out[False][0], out[True][0])
    assert out[True][1].info["slab0"].get("jackson_damped")
    np.testing.assert_allclose(out[True][1].albedo(), out[False][1].albedo(), rtol=0, atol=1e-12)
    wide = solve_stack(None, [Slab(1.0, PhaseMedium(1.0, 0.9, ("hg", 0.5)))], Lambertian(0.0), SolverSettings.product(32))
    assert not wide.info["slab0"].get("jackson_damped")




# ------------------------------------------------------------------------------------------------
# Inner interface into a less dense binder (a fall, η_below / η_above < 1): the chain of rules on the
# Snell invariant (flakedb.rt.basis.quadrature.binder_chain_quadratures, docs/model.md §4 "Inner interface")
# ------------------------------------------------------------------------------------------------

def test_binder_chain_reproduces_the_snell_mapped_rules():
    """Smooth top and rising indices: the chain is the Snell-mapped rule (bit for bit under the top) and
    its Snell image plus Gauss–Legendre nodes in the range totally reflected from below, binder after binder."""
    q = radau_hemisphere(16)
    c = binder_chain_quadratures(q, 1.0, [1.5, 1.6])
    a = snell_mapped_quadrature(q, 1.5, default_tir_nodes(16, 1.5))
    assert np.array_equal(c.rules[0].x, a.x) and np.array_equal(c.rules[0].w, a.w) and c.rules[0].n_mapped == 16
    b = snell_mapped_quadrature(a, 1.6 / 1.5, default_tir_nodes(a.h, 1.6 / 1.5))
    # μ_b = √(1 − (1 − μ²)/η²) through n² ratios vs composed: t's ≤ 5u abs. error ÷ 2μ_b, a.x's own through ∂μ_b/∂μ_a, and
    # the TIR Gauss nodes ∝ μ_c = √(1 − (1.5/1.6)²): |Δμ| ≤ (10/μ_c² + 4) u μ; weights w μ_a/(η² μ_b) twice that + 6u
    k = 10 / (1 - (1.5 / 1.6) ** 2) + 4
    tol.assert_within(c.rules[1].x, b.x, tol.U * k * b.x)
    tol.assert_within(c.rules[1].w, b.w, tol.U * (2 * k + 6) * b.w)
    assert np.array_equal(c.pairs[0][0], np.arange(a.h)) and np.array_equal(c.pairs[0][1], b.h - a.h + np.arange(a.h))


@pytest.mark.parametrize("anchor,indices", [(1.0, [1.6, 1.45]), (1.0, [1.5, 1.7, 1.55, 1.0]), (1.45, [1.6, 1.45]),
                                            (1.0, [1.0, 1.6, 1.45])])
def test_binder_chain_rules_are_exact_and_map_node_to_node(anchor, indices):
    """Every binder's rule integrates μ exactly (Σ 2wμ = 1: a white primer returns all its light) and smooth
    functions to the accuracy of its Gauss pieces; across each interface the shared nodes keep the Snell
    invariant n sin θ and the flux weight n² w μ (so the node map is lossless); the others lie in the range
    totally reflected on their side, (0, sqrt(1 − (n_b/n_a)²)) above a fall."""
    c = binder_chain_quadratures(radau_hemisphere(16), anchor, indices)
    for r in c.rules:
        assert np.all(np.diff(r.x) > 0) and r.x[0] > 0 and r.x[-1] == pytest.approx(1.0, abs=1e-15)
        assert abs(2.0 * np.sum(r.w * r.x) - 1.0) < 1e-14
        for f, exact in ((lambda m: np.ones_like(m), 1.0), (lambda m: np.exp(m), np.e - 1), (lambda m: m**6, 1 / 7)):
            assert abs(np.sum(r.w * f(r.x)) - exact) < 1e-5  # measured ≤ 2.7e-6 at 16 anchor nodes
    for (ia, ib), na, nb, ra, rb in zip(c.pairs, indices, indices[1:], c.rules, c.rules[1:]):
        assert len(ia) == min(ra.h, rb.h)
        xa, xb = ra.x[ia], rb.x[ib]
        assert np.abs(na * np.sqrt(1 - xa**2) - nb * np.sqrt(1 - xb**2)).max() < 1e-14
        assert np.abs(na**2 * ra.w[ia] * xa - nb**2 * rb.w[ib] * xb).max() < 1e-15
        if nb < na:  # a fall: the unpaired nodes above are those totally reflected
            mu_c = np.sqrt(1 - (nb / na) ** 2)
            assert np.all(np.delete(ra.x, ia) < mu_c) and np.all(xa > mu_c)
    with pytest.raises(ValueError, match="fall below the anchor"):
        binder_chain_quadratures(radau_hemisphere(8), 1.0, [1.5, 0.9])


def _fall_stack(top):
    """coat | HG slab | fall | HG slab (no top: index-matched binder, a rise to 1.6, then the fall)."""
    if top is None:
        return [Slab(10.0, _hg(1.0)), InnerSmooth(1.6), Slab(5.0, _hg(1.0, 0.5)), InnerSmooth(1.45 / 1.6),
                Slab(10.0, _hg(1.0, 0.3))]
    return [Slab(10.0, _hg(1.0)), InnerSmooth(1.45 / 1.6), Slab(10.0, _hg(1.0, 0.3))]


@pytest.mark.parametrize("top", [Smooth(1.6), Rough(1.6, 0.1), None])
@pytest.mark.parametrize("settings", [SolverSettings(n=32), SolverSettings.product(32)])
def test_inner_interface_fall_white_furnace_and_reciprocity(top, settings):
    """A fall 1.6 → 1.45 in a lossless stack (HG slabs of albedo 1, white primer): every photon comes back
    (the rule above holds the Snell image of the whole rule below: the node map is lossless by
    construction; measured 1e-14), and the BSDF is reciprocal."""
    r = solve_stack(top, _fall_stack(top), Lambertian(1.0), settings)
    assert np.abs(r.albedo() - 1.0).max() < 1e-3
    assert np.abs(r.albedo() - 1.0).max() < 1e-12  # measured ≤ 1e-13
    f = r.f_coefficients("Rt")
    assert np.allclose(f, np.swapaxes(f, -1, -2), rtol=1e-9, atol=1e-12 * np.abs(f).max())
    fall = r.info["inner_interfaces"][-1]
    assert fall["nodes_above"] > fall["nodes_below"]  # the totally reflected range above has nodes of its own


@pytest.mark.parametrize("top,slabs", [
    (Smooth(1.6), [InnerSmooth(1.45 / 1.6), Slab(10.0, _hg(1.0))]),  # a clear coat over a less dense basecoat
    (Smooth(1.5), [Slab(10.0, _hg(1.0)), InnerSmooth(1.7 / 1.5), InnerSmooth(1.6 / 1.7), Slab(10.0, _hg(1.0))]),
    (Rough(1.6, 0.2), [InnerSmooth(1.45 / 1.6), Slab(10.0, _hg(1.0))]),
])
def test_inner_interface_fall_under_an_empty_binder(top, slabs):
    """A binder without a slab between a smooth top (or an inner interface) and a fall has directions that
    are totally reflected on both sides and that nothing reaches: the adding stays regular
    (flakedb.rt.basis.layer.solve_regular) and lossless, on both solve paths."""
    for settings in (SolverSettings(n=24), SolverSettings.product(24)):
        r = solve_stack(top, slabs, Lambertian(1.0), settings)
        assert np.abs(r.albedo() - 1.0).max() < 1e-12


def test_inner_interface_fall_physics():
    """The fall changes the BSDF (not a no-op); a binder less dense than the air under a smooth top, or
    less dense than an index-matched top binder, is refused by name."""
    med = _hg(0.9)
    base = [Slab(10.0, med)]
    a = solve_stack(Smooth(1.6), [Slab(5.0, _hg(0.8)), InnerSmooth(1.45 / 1.6)] + base, Lambertian(0.5),
                    SolverSettings(n=32))
    b = solve_stack(Smooth(1.6), [Slab(5.0, _hg(0.8))] + base, Lambertian(0.5), SolverSettings(n=32))
    assert np.abs(a.Rt[0] - b.Rt[0]).max() > 1e-3 * np.abs(b.Rt[0]).max()
    with pytest.raises(ValueError, match="less dense than the air"):
        solve_stack(Smooth(1.5), [Slab(1.0, med), InnerSmooth(0.5), Slab(1.0, med)], Lambertian(0.5),
                    SolverSettings(n=16))
    with pytest.raises(ValueError, match="without a top interface"):
        solve_stack(None, [Slab(1.0, med), InnerSmooth(0.9), Slab(1.0, med)], Lambertian(0.5), SolverSettings(n=16))


# ------------------------------------------------------------------------------------------------
# Rough inner interface (InnerRough): Beckmann α between two binders' rules, a rise or a fall
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("top", [Smooth(1.6), Rough(1.6, 0.1), None])
@pytest.mark.parametrize("eta_below", [1.45, 1.75])
def test_rough_inner_interface_white_furnace_and_reciprocity(top, eta_below):
    """A rough (α 0.2) inner interface 1.6 → 1.45 (fall) or 1.75 (rise) with the compensation lobe in a
    lossless stack: every photon comes back (measured ≤ 1e-13; 6e-9 before the Newton finish of the energy
    scale), the BSDF is reciprocal, and the roughness changes the result."""
    def stack(inner):
        if top is None:
            return [Slab(10.0, _hg(1.0)), InnerSmooth(1.6), Slab(5.0, _hg(1.0, 0.5)), inner, Slab(10.0, _hg(1.0, 0.3))]
        return [Slab(10.0, _hg(1.0)), inner, Slab(10.0, _hg(1.0, 0.3))]

    for settings in (SolverSettings(n=32), SolverSettings.product(32)):
        r = solve_stack(top, stack(InnerRough(eta_below / 1.6, 0.2)), Lambertian(1.0), settings)
        assert np.abs(r.albedo() - 1.0).max() < 1e-12
        f = r.f_coefficients("Rt")
        assert np.allclose(f, np.swapaxes(f, -1, -2), rtol=1e-9, atol=1e-12 * np.abs(f).max())
    r = solve_stack(top, stack(InnerRough(eta_below / 1.6, 0.2)), Lambertian(0.5), SolverSettings(n=32))
    s = solve_stack(top, stack(InnerSmooth(eta_below / 1.6)), Lambertian(0.5), SolverSettings(n=32))
    assert np.abs(r.Rt[0] - s.Rt[0]).max() > 3e-4 * np.abs(s.Rt[0]).max()  # measured ≥ 7.8e-4 (under a rough top)
    # without the compensation lobe the single-scattering interface loses the masked/shadowed light
    lossy = solve_stack(top, stack(InnerRough(eta_below / 1.6, 0.2, energy_compensation=False)), Lambertian(1.0),
                        SolverSettings(n=32))
    assert lossy.albedo().max() < 1.0 - 1e-4


def test_rough_inner_interface_refuses_zero_roughness():
    with pytest.raises(ValueError, match="InnerRough.alpha = 0.0 is outside the allowed range"):
        solve_stack(Smooth(1.5), [Slab(1.0, _hg(0.5)), InnerRough(0.9, 0.0), Slab(1.0, _hg(0.5))], Lambertian(0.5),
                    SolverSettings(n=16))


def test_channel_groups_reuse_one_projection(monkeypatch):
    """Channel groups (memory budget) solve exactly what one group solves, and the kernel is projected
    once for all channels, not once per group (it was: 32 s against 2 s for 16 groups at n = 100)."""


    med = Mixture([FlakeMedium(0.3, FlakeOptics.constant(np.linspace(0.5, 0.8, 6), np.zeros(6)), 0.5),
                   PhaseMedium(np.full(6, 1.0), np.linspace(0.4, 0.9, 6), ("hg", 0.5))])
    calls = []
    real = stk.project_medium

    def counting(medium, *a, **k):
        calls.append(medium)
        return real(medium, *a, **k)

    monkeypatch.setattr(rt_parts, "project_medium", counting)  # where the solver and the channel groups project
    monkeypatch.setattr(rt_channels, "project_medium", counting)
    one = solve_stack(Smooth(1.5), [Slab(5.0, med)], Lambertian(0.5), SolverSettings.product(24))
    n_one = len(calls)
    assert n_one >= 1
    calls.clear()
    grouped = solve_stack(Smooth(1.5), [Slab(5.0, med)], Lambertian(0.5),
                          SolverSettings.product(24, memory_budget_bytes=1.0))  # one channel per group
    assert len(grouped.info["channel_groups"]) == 6
    assert len(calls) == n_one  # projected once, not 6 times
    L = min(one.Rt.shape[0], grouped.Rt.shape[0])
    assert np.abs(grouped.Rt[:L] - one.Rt[:L]).max() <= 1e-12 * np.abs(one.Rt).max()


def test_channel_groups_share_one_rough_top(monkeypatch):
    """Channel groups under a rough top build the interface once and read it only: one channel per
    group (where a lone group could otherwise write its result into the top's R^t) gives the one-group
    solve, and the interface is built once."""
    calls = []
    real = stk.itf.rough_dielectric

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(stk.itf, "rough_dielectric", counting)
    args = (Rough(1.5, 0.1), [Slab(2.0, PhaseMedium(1.0, [0.9, 0.6, 0.3], ("hg", 0.6)))], Lambertian([0.5, 0.4, 0.3]))
    one = solve_stack(*args, SolverSettings.product(32))
    calls.clear()
    grouped = solve_stack(*args, SolverSettings.product(32, memory_budget_bytes=1.0))
    assert len(grouped.info["channel_groups"]) == 3 and len(calls) == 1
    L = min(one.n_orders, grouped.n_orders)
    assert np.abs(grouped.Rt[:L] - one.Rt[:L]).max() <= 1e-12 * np.abs(one.Rt).max()


@pytest.mark.parametrize("bottom", [Lambertian([0.5, 0.2, 0.8]), RoughConductor([0.2 + 3.0j, 1.0 + 6.0j, 0.5 + 2.0j], 0.2)])
def test_threads_build_the_rough_top_in_the_background_with_the_same_result(bottom, monkeypatch):
    """With threads > 1 the rough top is built in a background thread while the slabs are projected and
    the body's first order block is solved (the opaque path's order loop then waits for it): the BSDF,
    the order choice and the info must be those of the serial solve, bit for bit."""
    slab = Slab(2.0, PhaseMedium([1.0, 0.8, 1.2], [0.95, 0.7, 0.9], ("hg", 0.6)))
    one = solve_stack(Rough(1.5, 0.15), [slab], bottom, SolverSettings.product(24, threads=1))
    two = solve_stack(Rough(1.5, 0.15), [slab], bottom, SolverSettings.product(24, threads=2))
    np.testing.assert_array_equal(one.Rt, two.Rt)
    assert one.info["orders"] == two.info["orders"] and one.info["top"] == two.info["top"]
    # and an error in the background build reaches the caller as itself
    def boom(*args, **kw):
        raise RuntimeError("interface failed in the background")

    monkeypatch.setattr(stk.itf, "rough_dielectric", boom)
    with pytest.raises(RuntimeError, match="interface failed in the background"):
        solve_stack(Rough(1.5, 0.15), [slab], bottom, SolverSettings.product(24, threads=2))


@pytest.mark.parametrize("eta,alpha", [(1.02, 0.3), (0.99, 0.3)])
def test_nearly_index_matched_rough_inner_interface_is_solved_smooth(eta, alpha, monkeypatch):
    """flakedb.rt.adding.parts.near_matched: a rough inner interface whose step reflects ≤ 1e-4 at normal incidence and
    whose transmitted lobe (α |1 − 1/η|) is under a tenth of a node cell is solved as a smooth one.  Against the
    flux-cell rough solve of the same stack (30-100x slower here; 110 GiB for 1.5 → 1.501 at α 0.03): albedo
    within 1e-4, BSDF within 1e-3 of its maximum (measured 4e-5 and 4e-4); a step of 1.5 → 1.501 at α 0.03, which
    asked for 110 GiB at n = 32, solves, lossless over a white primer."""
    import flakedb.rt.adding.parts as parts

    def stack(primer=0.5, e=eta, a=alpha):
        return solve_stack(Smooth(1.5), [Slab(10.0, PhaseMedium(0.3, 0.9, ("hg", 0.6))), InnerRough(e, a),
                                         Slab(10.0, PhaseMedium(0.2, 0.8, ("hg", 0.3)))], Lambertian(primer),
                           SolverSettings.product(32))

    near = stack()
    assert near.info["inner_interfaces"][0]["solved_as"].startswith("smooth")
    monkeypatch.setattr(parts, "NEAR_MATCH_FRESNEL", -1.0)  # the rough solve, for reference
    rough = stack()
    assert "solved_as" not in rough.info["inner_interfaces"][0]
    monkeypatch.undo()
    phi = np.linspace(0.0, np.pi, 19)
    fa, fb = near.scattered().eval_nodes(phi), rough.scattered().eval_nodes(phi)
    assert np.abs(near.albedo(include_delta=False) - rough.albedo(include_delta=False)).max() < 1e-4
    assert np.abs(fa - fb).max() < 1e-3 * np.abs(fb).max()
    white = solve_stack(Smooth(1.5), [Slab(10.0, PhaseMedium(0.3, 1.0, ("hg", 0.6))), InnerRough(1.501 / 1.5, 0.03),
                                      Slab(10.0, PhaseMedium(0.2, 1.0, ("hg", 0.3)))], Lambertian(1.0),
                        SolverSettings.product(32))
    assert np.abs(white.albedo() - 1.0).max() < 1e-9
