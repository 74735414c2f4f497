"""GGX flakes: the adding-doubling solver against the independent Monte Carlo (docs/model.md §7.2, issue #21).

Guards against a GGX path that is wrong somewhere the unit tests of rt/scattering/microflake.py cannot see: the
σ_t/σ_s moments, the kernel and its projection, the φ-bandwidth guess, all against the Monte Carlo's
own GGX flake sampler (flakedb/reference/kernels.py, written independently: normals drawn in closed
form, accepted with |ω·m|, passing with T, reflecting with R).  Acceptance as for Beckmann
(tests/reference/test_solver_vs_montecarlo.py): |solver − MC| ≤ 3σ_MC + 0.5 % of the value, on the
directional albedo and on binned reflectance.  :func:`test_the_comparison_tells_the_distributions_apart`
shows that the acceptance bites: the Beckmann solve of the same problem fails it.

Measured (400 000 paths per incidence; 800 000 for the bins at θ_i ≈ 45°): GGX solver vs GGX Monte Carlo
within 1.4 σ on every albedo and transmittance (|Δ| ≤ 0.26 %), binned reflectance within 0.55 of the
tolerance; the Beckmann solve of the same problems is 12-49 σ off on the albedo (2-11 %) and up to 26×
the tolerance on the bins.
"""

import numpy as np
import pytest

import flakedb.reference.montecarlo as mc
from flakedb.bsdf import table_evaluator
from flakedb.bsdf.convert import stack_to_table
from flakedb.rt.scattering import media as rm
from flakedb.rt.scattering.microflake import FlakeOptics
from flakedb.rt.adding.stack import Lambertian, Slab, Smooth, SolverSettings, solve_stack
from tests.cases import N_PATHS

MU_EDGES = np.array([0.3, 0.5, 0.7, 0.85, 1.0])
PHI_EDGES = np.array([0.0, np.pi / 6, np.pi / 2, np.pi])


def ggx_case(name, distribution="ggx"):
    """(solver top, slabs, bottom, MC problem, n); ``distribution`` of the solver's flakes (the Monte
    Carlo's are GGX)."""
    if name == "ggx-flake-slab":  # index-matched slab, no bottom: albedo and transmittance
        return None, [Slab(2.0, rm.FlakeMedium(0.3, FlakeOptics.constant(0.7, 0.2), 1.0, distribution))], None, \
            mc.Problem([mc.Slab(2.0, [mc.FlakeMedium(1.0, 0.3, 0.7, 0.2, distribution="ggx")])]), 64
    if name == "ggx-paint":  # smooth coat, GGX flakes + HG pigment in one layer, gray primer
        med = rm.Mixture([rm.FlakeMedium(0.2, FlakeOptics.constant(0.7, 0.1), 0.8, distribution),
                          rm.PhaseMedium(1.5, 0.85, ("hg", 0.6))])
        return Smooth(1.5), [Slab(2.0, med)], Lambertian(0.3), mc.Problem(
            [mc.Slab(2.0, [mc.FlakeMedium(0.8, 0.2, 0.7, 0.1, distribution="ggx"),
                           mc.PhaseMedium(1.5, 0.85, mc.HenyeyGreenstein(0.6))])],
            top=mc.Smooth(1.5), bottom=mc.Lambertian(0.3)), 64
    raise KeyError(name)


def _albedo_rows(name, distribution="ggx", node_fracs=(1.0, 0.55, 0.25)):
    top, slabs, bottom, problem, n = ggx_case(name, distribution)
    r = solve_stack(top, slabs, bottom, SolverSettings(n=n))
    a_solver = r.albedo(include_delta=False)[0]
    t_solver = r.transmittance()
    rows = []
    for frac in node_fracs:
        k = int(np.argmin(np.abs(r.x - frac)))
        res = mc.simulate(problem, float(r.x[k]), N_PATHS, seed=4321 + k)
        rows.append(("albedo", r.x[k], a_solver[k], float(res.diffuse_albedo[0]), float(res.albedo_se[0])))
        if t_solver is not None and bottom is None:
            rows.append(("T", r.x[k], t_solver[0, k], float(res.transmittance[0]), float(res.transmittance_se[0])))
    return rows


def _binned(name, distribution="ggx"):
    top, slabs, bottom, problem, n = ggx_case(name, distribution)
    r = solve_stack(top, slabs, bottom, SolverSettings(n=n))
    bs = table_evaluator(stack_to_table(r))
    mu_i = float(r.x[int(np.argmin(np.abs(r.x - 0.7)))])
    res = mc.simulate(problem, mu_i, 2 * N_PATHS, seed=77, mu_edges=MU_EDGES, phi_edges=PHI_EDGES)
    pred = mc.bin_average(lambda m, p: bs.eval(np.full_like(m, mu_i), -m, p)[..., 0], MU_EDGES, PHI_EDGES, n_quad=12)
    return pred, res.reflectance_binned[0], res.reflectance_binned_se[0]


def _within(pred, ref, se):
    return np.abs(np.asarray(pred) - ref) <= 3 * np.asarray(se) + 0.005 * np.abs(ref) + 1e-12


@pytest.mark.parametrize("name", ["ggx-flake-slab", "ggx-paint"])
def test_ggx_albedo_matches_monte_carlo(name):
    for what, mu, solver, ref, se in _albedo_rows(name):
        assert _within(solver, ref, se), (name, what, mu, solver, ref, se)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ggx-flake-slab", "ggx-paint"])
def test_ggx_binned_reflectance_matches_monte_carlo(name):
    pred, ref, se = _binned(name)
    assert np.all(_within(pred, ref, se)), (name, pred, ref, se)


@pytest.mark.slow
def test_the_comparison_tells_the_distributions_apart():
    """The same problems solved with Beckmann flakes (same α) fail the acceptance against the GGX
    Monte Carlo: the comparison sees the distribution."""
    fails = 0
    for name in ("ggx-flake-slab", "ggx-paint"):
        fails += sum(not _within(s, r, e) for _, _, s, r, e in _albedo_rows(name, "beckmann"))
        pred, ref, se = _binned(name, "beckmann")
        fails += int(np.sum(~_within(pred, ref, se)))
    assert fails >= 4, fails
