"""The adding-doubling solver against the independent Monte Carlo reference (docs/model.md §7.2).

Guards against any error that the invariant tests cannot see: a wrong kernel normalisation, a
wrong sign convention of φ_d or μ, an interface that conserves energy but sends it to the wrong
place, micro-flake extinction or kernels that disagree with the physics the Monte Carlo samples
directly (flake normals drawn from D, accepted with |ω·m|, passing with T, reflecting with R).

Acceptance (issues #3, #4): |solver − MC| ≤ 3σ_MC + 0.5 % of the value, on the directional albedo
(the tabulated part: the smooth coat's delta term is analytic in both) and on binned reflectance.
Incident directions are quadrature nodes, so the solver's albedo needs no interpolation.
"""

import numpy as np
import pytest

import flakedb.reference.montecarlo as mc
from flakedb.bsdf import table_evaluator
from flakedb.bsdf.convert import stack_to_table
from flakedb.rt.boundaries import microfacet as mf
from flakedb.rt.scattering.media import PhaseMedium
from flakedb.rt.adding.stack import (
    InnerRough,
    InnerSmooth,
    Lambertian,
    Rough,
    RoughConductor,
    Slab,
    Smooth,
    SolverSettings,
    solve_stack,
)
from tests.cases import C_GRID, FAST, N_PATHS, angle_dependent_flake  # noqa: E402,F401
from tests.cases import case as _case  # noqa: E402


def _compare_albedo(name, node_fracs=(1.0, 0.55, 0.25)):
    top, slabs, bottom, problem, n = _case(name)
    r = solve_stack(top, slabs, bottom, SolverSettings(n=n))
    a_solver = r.albedo(include_delta=False)[0]
    t_solver = r.transmittance()
    rows = []
    for frac in node_fracs:
        k = int(np.argmin(np.abs(r.x - frac)))
        res = mc.simulate(problem, float(r.x[k]), N_PATHS, seed=1234 + k)
        a_mc, se = float(res.diffuse_albedo[0]), float(res.albedo_se[0])
        rows.append((r.x[k], a_solver[k], a_mc, se))
        assert abs(a_solver[k] - a_mc) <= 3 * se + 0.005 * abs(a_mc) + 1e-12, (name, r.x[k], a_solver[k], a_mc, se)
        if t_solver is not None and bottom is None:
            t_mc, tse = float(res.transmittance[0]), float(res.transmittance_se[0])
            assert abs(t_solver[0, k] - t_mc) <= 3 * tse + 0.005 * t_mc, (name, "T", t_solver[0, k], t_mc, tse)
    return rows


@pytest.mark.parametrize("name", FAST)
def test_albedo_matches_monte_carlo(name):
    _compare_albedo(name)


@pytest.mark.slow
def test_rough_coat_albedo_matches_monte_carlo():
    _compare_albedo("rough-coat-lambertian", node_fracs=(1.0, 0.6))


@pytest.mark.parametrize("name", ["smooth-hg-gray", "mirror-flakes-white", "translucent-flakes-gray",
                                  "flakes-and-hg-pigment"])
def test_binned_reflectance_matches_monte_carlo(name):
    """Bin averages of f·|μ_o| over (|μ_o|, φ_d) bins away from grazing (where the file reader's
    Catmull–Rom interpolation towards the zero node is not the solver's function)."""
    top, slabs, bottom, problem, n = _case(name)
    r = solve_stack(top, slabs, bottom, SolverSettings(n=n))
    bs = table_evaluator(stack_to_table(r))
    k = int(np.argmin(np.abs(r.x - 0.7)))
    mu_i = float(r.x[k])
    mu_edges = np.array([0.3, 0.5, 0.7, 0.85, 1.0])
    phi_edges = np.array([0.0, np.pi / 6, np.pi / 2, np.pi])
    res = mc.simulate(problem, mu_i, 2 * N_PATHS, seed=99, mu_edges=mu_edges, phi_edges=phi_edges)
    ref, se = res.reflectance_binned[0], res.reflectance_binned_se[0]
    pred = mc.bin_average(lambda m, p: bs.eval(np.full_like(m, mu_i), -m, p)[..., 0], mu_edges, phi_edges, n_quad=12)
    tol = 3 * se + 0.005 * np.abs(ref)
    assert np.all(np.abs(pred - ref) <= tol), (name, pred, ref, se)


def _inner_interface_vs_monte_carlo(eta_coat, eta_base, inner=None):
    """Smooth coat η_coat | inner interface η_coat → η_base | HG slab (g 0.7, ϖ 0.9, τ 1) in the η_base binder
    | diffuse 0.5, n = 64.  Albedo within 3σ + 0.5 % at three incidences, binned reflectance at θ_i ≈ 45°
    within 3σ + 2 % of the total per bin (flux per (μ cell, φ) bin of the solver's own cells).  ``inner``:
    the solver's inner interface (default InnerSmooth); an InnerRough's α is given to the Monte Carlo's
    own rough interface (its single-scattering model: the solver's must be without compensation)."""
    med = PhaseMedium(np.array([0.1]), np.array([0.9]), ("hg", 0.7))
    inner = InnerSmooth(eta_base / eta_coat) if inner is None else inner
    r = solve_stack(Smooth(eta_coat), [inner, Slab(10.0, med)], Lambertian(0.5), SolverSettings.product(64))
    prob = mc.Problem((mc.Slab(1.0, (), eta=eta_coat),
                       mc.Slab(10.0, (mc.PhaseMedium(0.1, 0.9, mc.HenyeyGreenstein(0.7)),), eta=eta_base,
                               alpha=float(getattr(inner, "alpha", 0.0)))),
                      top=mc.Smooth(eta_coat), bottom=mc.Lambertian(0.5))
    A = r.albedo(include_delta=False)[0]
    rows = []
    for j, frac in enumerate((1.0, 0.7, 0.35)):
        k = int(np.argmin(np.abs(r.x - frac)))
        res = mc.simulate(prob, float(r.x[k]), 200_000, seed=21 + j)
        tol = 3 * res.albedo_se[0] + 0.005 * res.diffuse_albedo[0]
        rows.append((float(r.x[k]), A[k], res.diffuse_albedo[0], tol))
        assert abs(A[k] - res.diffuse_albedo[0]) <= tol, rows[-1]
    k = int(np.argmin(np.abs(r.x - 0.7)))
    C = mf.flux_cell_edges(r.x, r.w)
    idx = sorted({int(np.argmin(np.abs(C - v))) for v in (0.0, 0.3, 0.55, 0.68, 0.74, 0.85, 1.0)})
    idx[0], idx[-1] = 0, len(r.x)
    phi_edges = np.array([0.0, 0.25, 0.6, np.pi / 2, np.pi])
    f = r.f_coefficients("Rt")[:, 0, :, k]
    m = r.w * r.x
    lphi = np.arange(f.shape[0])[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        Phi = np.where(lphi == 0, np.diff(phi_edges)[None, :],
                       (np.sin(lphi * phi_edges[None, 1:]) - np.sin(lphi * phi_edges[None, :-1])) / np.maximum(lphi, 1))
    flux = np.array([np.einsum("lo,o->l", f[:, idx[b]:idx[b + 1]], m[idx[b]:idx[b + 1]]) @ Phi
                     for b in range(len(idx) - 1)])  # ∫∫ f μ dμ dφ per bin (one side of ±φ)
    mu_edges = C[np.asarray(idx)]
    res = mc.simulate(prob, float(r.x[k]), 400_000, seed=99, mu_edges=mu_edges, phi_edges=phi_edges)
    omega = 2.0 * np.diff(mu_edges)[:, None] * np.diff(phi_edges)[None, :]
    ref, se = res.reflectance_binned[0] * omega, res.reflectance_binned_se[0] * omega  # flux per bin (±φ)
    pred = 2.0 * flux
    assert np.all(np.abs(pred - ref) <= 3 * se + 0.02 * ref.sum()), (pred, ref, se)
    return rows, np.abs(pred - ref).max() / ref.sum()


@pytest.mark.slow
def test_inner_interface_matches_monte_carlo():
    """Issue 12 item 3(a): smooth coat 1.5 | inner smooth interface 1.5 → 1.6 (a rise) | HG slab | diffuse.
    The Monte Carlo's inner interface is its own (Fresnel / Snell per path, flakedb/reference/kernels.py),
    not the solver's node map.  Measured: albedo within 0.07 of the tolerance."""
    _inner_interface_vs_monte_carlo(1.5, 1.6)


@pytest.mark.slow
def test_inner_interface_fall_matches_monte_carlo():
    """Issue 12 item 3(a), a fall: smooth coat 1.6 | inner smooth interface 1.6 → 1.45 | HG slab | diffuse.
    Measured: albedo differences 0.08, 0.17, 0.02 of the tolerance (3σ + 0.5 %) at μ ≈ 1, 0.7, 0.35."""
    _inner_interface_vs_monte_carlo(1.6, 1.45)


@pytest.mark.slow
@pytest.mark.parametrize("eta_coat,eta_base,alpha", [(1.6, 1.45, 0.2), (1.5, 1.6, 0.2), (1.6, 1.45, 0.05)])
def test_rough_inner_interface_matches_monte_carlo(eta_coat, eta_base, alpha):
    """A rough inner interface (Beckmann α, single scattering on both sides: the Monte Carlo samples its own
    microfacet normals, flakedb/reference/kernels.py _rough_interface) for a fall and a rise.  Measured:
    albedo differences ≤ 0.23 of the tolerance (3σ + 0.5 %), bins ≤ 0.13 % of the total."""
    _inner_interface_vs_monte_carlo(eta_coat, eta_base, inner=InnerRough(eta_base / eta_coat, alpha,
                                                                         energy_compensation=False))


def _vmf_case(kappa):
    """smooth-vmf-spectral (tests/cases.py) with concentration ``kappa``: smooth η 1.5 coat / vMF slab,
    τ 2, one albedo per band (0.95 … 0.3) / diffuse 0.6."""
    top, slabs, bottom, problem, _ = _case("smooth-vmf-spectral")
    alb = slabs[0].medium.albedo
    slabs = [type(slabs[0])(slabs[0].thickness_um, type(slabs[0].medium)(0.2, alb, ("vmf", kappa)))]
    problem = mc.Problem([mc.Slab(10.0, [mc.PhaseMedium(0.2, alb, mc.VonMisesFisher(kappa))])],
                         top=problem.top, bottom=problem.bottom)
    return top, slabs, bottom, problem


@pytest.mark.parametrize("kappa,n", [(20.0, 48), pytest.param(200.0, 64, marks=pytest.mark.slow)])
def test_vmf_slab_with_spectral_albedo_matches_monte_carlo(kappa, n):
    """Every channel (one albedo per band): directional albedo within 3σ + 0.5 % at three incidences,
    and binned reflectance at θ_i ≈ 45° within 3σ + 2 % of each bin's value (issue #12's criteria;
    the case's recipe is tests/recipes/validation-smooth-vmf-spectral.yaml)."""
    top, slabs, bottom, problem = _vmf_case(kappa)
    r = solve_stack(top, slabs, bottom, SolverSettings(n=n))
    A = r.albedo(include_delta=False)
    assert A.shape[0] == 6
    for j, frac in enumerate((1.0, 0.55, 0.25)):
        k = int(np.argmin(np.abs(r.x - frac)))
        res = mc.simulate(problem, float(r.x[k]), N_PATHS // 2, seed=4321 + j)
        tol = 3 * res.albedo_se + 0.005 * np.abs(res.diffuse_albedo)
        assert np.all(np.abs(A[:, k] - res.diffuse_albedo) <= tol), (frac, A[:, k], res.diffuse_albedo, res.albedo_se)
    bs = table_evaluator(stack_to_table(r))
    k = int(np.argmin(np.abs(r.x - 0.7)))
    mu_i = float(r.x[k])
    mu_edges = np.array([0.3, 0.5, 0.7, 0.85, 1.0])
    phi_edges = np.array([0.0, np.pi / 6, np.pi / 2, np.pi])
    # the brightest and the darkest band (2 × 12 bins: at 3σ a correct code fails with probability ~5 %
    # over all 72 bins of six bands, ~2 % over these, before the 2 % allowance)
    ends = [0, A.shape[0] - 1]
    alb = slabs[0].medium.albedo[ends]
    problem = mc.Problem([mc.Slab(10.0, [mc.PhaseMedium(0.2, alb, mc.VonMisesFisher(kappa))])],
                         top=problem.top, bottom=problem.bottom)
    res = mc.simulate(problem, mu_i, 2 * N_PATHS, seed=77, mu_edges=mu_edges, phi_edges=phi_edges)
    pred = np.array([mc.bin_average(lambda m, p, c=c: bs.eval(np.full_like(m, mu_i), -m, p)[..., c], mu_edges,
                                    phi_edges, n_quad=12) for c in ends])
    ref, se = res.reflectance_binned, res.reflectance_binned_se
    assert np.all(np.abs(pred - ref) <= 3 * se + 0.02 * np.abs(ref)), (pred, ref, se)


@pytest.mark.slow
@pytest.mark.parametrize("alpha", [0.1, 0.5])
def test_compensation_lobe_matches_monte_carlo_at_grazing(alpha):
    """The Monte Carlo samples the solver's multiple-scattering lobe (its split, docs/rough-interfaces.md),
    checked where the split matters, at 80° and 85° (n = 64 nodes): a rough coat over a Lambertian 0.5 and
    a rough conductor (N 1.2 + 7i) in air, albedo within 3σ + 0.5 %.  With the old fixed split in the
    Monte Carlo only, the coat differs by 1–2 % here (measured: this test fails)."""
    settings = SolverSettings.product(64)
    coat = solve_stack(Rough(1.5, alpha), [], Lambertian(0.5), settings)
    cond = solve_stack(None, [], RoughConductor(1.2 + 7.0j, alpha), settings)
    p_coat = mc.Problem([mc.Slab(1.0, [])], top=mc.Rough(1.5, alpha), bottom=mc.Lambertian(0.5))
    p_cond = mc.Problem([mc.Slab(1.0, [])], top=None, bottom=mc.RoughConductor(1.2 + 7.0j, alpha))
    for theta in (80.0, 85.0):
        k = int(np.argmin(np.abs(coat.x - np.cos(np.radians(theta)))))
        for r, p in ((coat, p_coat), (cond, p_cond)):
            res = mc.simulate(p, float(r.x[k]), 100_000, seed=77 + k)
            a_mc, se = float(res.albedo[0]), float(res.albedo_se[0])
            a = float(r.albedo()[0, k])
            assert abs(a - a_mc) <= 3 * se + 0.005 * a_mc, (alpha, theta, a, a_mc, se)
