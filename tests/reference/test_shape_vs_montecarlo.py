"""Flake orientation with a shape (issue #35 item 3): Student-t and two-population-mixture flakes, the
adding-doubling solver against the independent Monte Carlo (docs/model.md §7.2).

The Monte Carlo draws Student-t normals as a Gamma scale mixture of Beckmann normals
(:func:`flakedb.reference.kernels._sample_student_t_flake_normal`: no inverse CDF, no density) and a
mixture as two flake components with aρ split by the weights; it parses the distribution's name itself.
The solver goes through the registry (CDF-space σ_t/σ_s moments, the kernel's D(h), the numeric φ
bandwidth).  Acceptance as for GGX (tests/reference/test_ggx_vs_montecarlo.py): |solver − MC| ≤ 3σ_MC +
0.5 % of the value on the directional albedo and transmittance; the sampler itself by χ² against
∫ 2 D(m) dm.  :func:`test_the_comparison_tells_the_shapes_apart` shows the acceptance bites: the same
problems solved with GGX (γ = 2) or Beckmann flakes fail it.

Measured (tests.cases.N_PATHS paths per incidence, μ_i ≈ 1, 0.54, 0.25): Student-t (γ = 1.6) slab within
1.7 σ (|Δ| ≤ 0.29 %) on albedo and transmittance; mixture paint within 1.1 σ (≤ 0.27 %).  The GGX solve of
the Student-t slab is 2.3-35 σ off (0.3-6.5 %), the Beckmann solve of the mixture paint 17-65 σ (4-15 %).
"""

import numpy as np
import pytest

import flakedb.reference.montecarlo as mc
from flakedb.rt.scattering import media as rm
from flakedb.rt.scattering.microflake import FlakeOptics
from flakedb.rt.adding.stack import Lambertian, Slab, Smooth, SolverSettings, solve_stack
from tests.cases import N_PATHS
from tests.rt.test_flake_shape import chi2_pvalue, ndf_of, theta_bin_probs

STD = "student_t(1.6)"
MIX = "mix(beckmann,0.35,student_t(3.0),0.6)"


def shape_case(name, solver_dist):
    """(solver top, slabs, bottom, MC problem, n) of ``name`` with the solver's flakes in ``solver_dist``
    (the Monte Carlo's in the case's own distribution)."""
    if name == "student-t-flake-slab":  # index-matched slab, no bottom: albedo and transmittance
        return None, [Slab(2.0, rm.FlakeMedium(0.3, FlakeOptics.constant(0.7, 0.2), 1.0, solver_dist))], None, \
            mc.Problem([mc.Slab(2.0, [mc.FlakeMedium(1.0, 0.3, 0.7, 0.2, distribution=STD)])]), 64
    if name == "mixture-paint":  # smooth coat, a two-population flake + HG pigment layer, gray primer
        med = rm.Mixture([rm.FlakeMedium(0.15, FlakeOptics.constant(0.7, 0.1), 0.8, solver_dist),
                          rm.PhaseMedium(1.5, 0.85, ("hg", 0.6))])
        return Smooth(1.5), [Slab(2.0, med)], Lambertian(0.3), mc.Problem(
            [mc.Slab(2.0, [mc.FlakeMedium(0.8, 0.15, 0.7, 0.1, distribution=MIX),
                           mc.PhaseMedium(1.5, 0.85, mc.HenyeyGreenstein(0.6))])],
            top=mc.Smooth(1.5), bottom=mc.Lambertian(0.3)), 64
    raise KeyError(name)


CASES = {"student-t-flake-slab": STD, "mixture-paint": MIX}


def _rows(name, solver_dist, node_fracs=(1.0, 0.55, 0.25)):
    top, slabs, bottom, problem, n = shape_case(name, solver_dist)
    r = solve_stack(top, slabs, bottom, SolverSettings(n=n))
    a_solver = r.albedo(include_delta=False)[0]
    t_solver = r.transmittance()
    rows = []
    for frac in node_fracs:
        k = int(np.argmin(np.abs(r.x - frac)))
        res = mc.simulate(problem, float(r.x[k]), N_PATHS, seed=2468 + k)
        rows.append(("albedo", r.x[k], a_solver[k], float(res.diffuse_albedo[0]), float(res.albedo_se[0])))
        if t_solver is not None and bottom is None:
            rows.append(("T", r.x[k], t_solver[0, k], float(res.transmittance[0]), float(res.transmittance_se[0])))
    return rows


def _within(pred, ref, se):
    return np.abs(np.asarray(pred) - ref) <= 3 * np.asarray(se) + 0.005 * np.abs(ref) + 1e-12


@pytest.mark.parametrize("name", ["student-t-flake-slab",
                                  pytest.param("mixture-paint", marks=pytest.mark.slow)])  # ~10 s
def test_shape_albedo_matches_monte_carlo(name):
    for what, mu, solver, ref, se in _rows(name, CASES[name]):
        assert _within(solver, ref, se), (name, what, mu, solver, ref, se)


@pytest.mark.parametrize("g, alpha", [(1.5, 0.1), (1.6, 0.3), (2.5, 0.6), (40.0, 0.2)])
def test_monte_carlo_student_t_sampler_matches_the_density(g, alpha):
    m = mc.sample_student_t_flake_normals(alpha, g, 200_000, seed=int(10 * g))
    assert np.all(m[:, 2] > 0)
    np.testing.assert_allclose(np.linalg.norm(m, axis=-1), 1.0, rtol=1e-14)
    edges = np.unique(np.concatenate([[0, np.pi / 2], np.arctan(alpha * np.geomspace(0.05, 200, 24))]))
    assert chi2_pvalue(np.arccos(np.clip(m[:, 2], -1, 1)), edges, theta_bin_probs(edges, ndf_of(g), alpha)) > 1e-3


def test_monte_carlo_rejects_bad_distribution_names():
    for bad in ("student_t(1.0)", "mix(beckmann,1.5,ggx,0.3)", "cauchy"):
        with pytest.raises(ValueError, match=r"slabs\[0\]\.media\[0\]\.distribution"):
            mc.simulate(mc.Problem([mc.Slab(1.0, [mc.FlakeMedium(1.0, 0.3, 0.7, 0.2, distribution=bad)])]), 0.8, 100, 1)


@pytest.mark.slow
def test_the_comparison_tells_the_shapes_apart():
    """The same problems solved with GGX (= student_t(2)) or with Beckmann flakes at the same α fail the
    acceptance against the Student-t / mixture Monte Carlo."""
    fails = sum(not _within(s, r, e) for _, _, s, r, e in _rows("student-t-flake-slab", "ggx"))
    fails += sum(not _within(s, r, e) for _, _, s, r, e in _rows("mixture-paint", "beckmann"))
    assert fails >= 4, fails
