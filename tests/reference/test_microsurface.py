"""The explicit microsurface random walk (flakedb/reference/microsurface.py; Heitz, Hanika, d'Eon &
Dachsbacher 2016) and the solver's rough interfaces against it (docs/rough-interfaces.md,
"Independent check: the microsurface random walk").

The walk is checked on its own first (energy on a perfect mirror surface, the smooth limit, the
single-bounce albedo against the height-correlated Smith integral by quadrature), then the solver's
rough conductor, rough dielectric and coat-over-Lambertian stack per angle.  The solver's Kulla–Conty
style lobe (flakedb.rt.boundaries.microfacet.dielectric_compensation) is not used by the walk.

Before issue 26's fix (2026-12-02, solver − walk, n = 64, η 1.5): the rough dielectric's R from the air
was 5–7 % low at 80–85° (the lobe's fixed split, Σ m g_a / Z, reflected about 3× too little at grazing),
a coat over a Lambertian 0.5 −1.2 … −3.5 % at 80–85°, the Kulla–Conty conductor lobe +0.5 … +0.7 % at
61–70° for α ≥ 0.3.  With the split of flakedb.rt.boundaries.microfacet.multiple_scattering_escape everything below
is within 3σ + 0.5 % per angle (the measured table: docs/rough-interfaces.md).  From the binder the walk
averages over the node's flux cell (``walk_dielectric(cell=...)``), the value the solver's node carries: T
falls steeply past the critical angle, and against point walks the node whose cell holds it (43.5°, α 0.05:
0.145 against 0.122) and T at α 0.3, 60.8° (+0.0019) fail, so these were skipped / allowed 0.002 before
(issue 36 item 6).  Since issue 36 the split is the height chain's; tests/reference/
test_rough_walk_table.py checks the bare interface at 10⁶ paths per angle.
"""

import numpy as np
import pytest

from flakedb.reference import microsurface as ms
from flakedb.rt.boundaries import microfacet as mf
from flakedb.rt.basis.quadrature import radau_hemisphere
from flakedb.rt.adding.stack import (
    Lambertian,
    Rough,
    RoughConductor,
    SolverSettings,
    solve_stack,
)


def _fresnel(mu, eta):
    s2 = (1 - mu**2) / eta**2
    ct = np.sqrt(1 - s2)
    rs, rp = (mu - eta * ct) / (mu + eta * ct), (eta * mu - ct) / (eta * mu + ct)
    return 0.5 * (rs**2 + rp**2)


@pytest.mark.parametrize("alpha", [0.1, 0.5])
@pytest.mark.parametrize("mu", [0.2, 0.9])
def test_walk_on_a_perfect_mirror_surface_keeps_all_energy(alpha, mu):
    """F ≡ 1 (|N| → ∞): every path leaves the surface eventually, with all its weight; a lossless
    dielectric sends every path up or down."""
    r = ms.walk_conductor(mu, alpha, 1e5j, 20_000, 1)
    assert r["lost"] == 0 and abs(r["albedo"] - 1.0) <= 1e-8
    d = ms.walk_dielectric(mu, alpha, 1.5, 20_000, 2)
    assert d["lost"] == 0 and d["R"] + d["T"] == 1.0


@pytest.mark.parametrize("mu", [0.95, 0.6, 0.3])
def test_walk_smooth_limit_is_fresnel(mu):
    """α = 0.005: the walk's reflectance is the smooth interface's Fresnel factor (within 3σ + 0.5 %)."""
    d = ms.walk_dielectric(mu, 0.005, 1.5, 200_000, 3)
    F = _fresnel(mu, 1.5)
    assert abs(d["R"] - F) <= 3 * d["R_se"] + 0.005 * F, (d["R"], F, d["R_se"])


def _height_correlated_single(mu_i, alpha, n_mu=400, n_phi=400):
    """∫ D(h) G2 / (4 μ_i) dω_o over the upper hemisphere, F ≡ 1, G2 = 1/(1 + Λ(i) + Λ(o)) (Heitz 2014
    eq. 99), by Gauss–Legendre in μ_o and the midpoint rule in φ_o."""
    x, w = np.polynomial.legendre.leggauss(n_mu)
    mu_o, w_mu = 0.5 * (x + 1), 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    so = np.sqrt(1 - mu_o**2)[:, None]
    si = np.sqrt(1 - mu_i**2)
    o = np.stack([so * np.cos(phi), so * np.sin(phi), np.broadcast_to(mu_o[:, None], so.shape * np.array([1, n_phi]))])
    i = np.array([si, 0.0, mu_i])[:, None, None]
    hv = i + o
    hz = hv[2] / np.linalg.norm(hv, axis=0)
    tan2 = (1 - hz**2) / hz**2
    D = np.exp(-tan2 / alpha**2) / (np.pi * alpha**2 * hz**4)
    G2 = 1.0 / (1.0 + ms.smith_lambda(np.array(mu_i), alpha) + ms.smith_lambda(mu_o, alpha))[:, None]
    f = D * G2 / (4 * mu_i)  # f μ_o with f = D G2 / (4 μ_i μ_o)
    return float((f * w_mu[:, None]).sum() * 2 * np.pi / n_phi)


@pytest.mark.parametrize("alpha,mu", [(0.3, 0.5), (0.5, 0.2), (0.5, 0.8)])
def test_walk_single_bounce_is_the_height_correlated_smith_integral(alpha, mu):
    """The paths that leave after one event carry the single-scattering albedo of the height-correlated
    Smith model (F ≡ 1): the walk's masking and visible-normal sampling are right."""
    r = ms.walk_conductor(mu, alpha, 1e5j, 200_000, 4)
    ref = _height_correlated_single(mu, alpha)
    se = np.sqrt(ref * (1 - ref) / 200_000)
    assert abs(r["single"] - ref) <= 3 * se + 1e-3 * ref, (r["single"], ref, se)


ANGLES = (0.0, 45.0, 61.0, 70.0, 80.0, 85.0)
ETA = 1.5
N_COND = 1.2 + 7.0j
#: paths per walk: σ ≈ √(R(1 − R)/n) for the dielectric (3σ ≈ 1.6 % of R = 0.25, 4 % of R = 0.04),
#: far smaller for the conductor (its weight is F, not 0/1): 50 000 are plenty there
N_PATHS, N_PATHS_COND = 100_000, 50_000


def _nodes(x):
    return [int(np.argmin(np.abs(x - np.cos(np.radians(t))))) for t in ANGLES]


def _interface_albedos(q, alpha):
    """(R_a, T_a, R_b, T_b) at the nodes of the rule ``q`` (both sides on the same rule) from the solver's
    rough-dielectric blocks (order 0, S_0[o, i] = 2π m_i f̃[o, i]; across the interface the flux carries
    η² into the binder and 1/η² out of it, docs/rough-interfaces.md)."""
    blocks, _ = mf.rough_dielectric_cells(q.x, q.w, ETA, alpha)
    Rt, Ttb, Rb, Tbt = (b[0, 0] for b in blocks)
    m = q.w * q.x
    col = lambda S, k: (S * m[:, None]).sum(axis=0) / m * k
    return col(Rt, 1.0), col(Ttb, ETA**2), col(Rb, 1.0), col(Tbt, ETA**-2)




def _check(what, alpha, theta, solver, ref, se, n, failures, extra=0.0):
    """The issue's tolerance: 3σ of the walk plus 0.5 % of its value, plus 3/n (the rule of three: a
    fraction the walk saw 0 times of n is below 3/n at 95 %, where σ = 0 says nothing) and ``extra``."""
    if abs(solver - ref) > 3.0 * se + 0.005 * ref + 3.0 / n + extra:
        failures.append(f"{what} α {alpha} θ {theta:.1f}°: solver {solver:.5f}, walk {ref:.5f} ± {se:.5f}")


@pytest.mark.slow
@pytest.mark.parametrize("alpha", [0.05, 0.1, 0.3, 0.5])
def test_solver_rough_interfaces_against_the_random_walk(alpha):
    """Per angle up to 85° (the n = 64 product rule's nodes nearest 0, 45, 61, 70, 80, 85°), each within
    3σ (the walk's) + 0.5 %: the bare rough dielectric (η 1.5) R and T lit from the air and from the
    binder, the rough conductor (N = 1.2 + 7i), and the coat over a Lambertian 0.5.  With the lobe's
    fixed étendue split (``split=None``, the lobe before issue 26) R from the air at 80–85° is 5–7 % low
    and this fails; with the Kulla–Conty conductor lobe the conductor at α ≥ 0.3 is +0.5 … +0.7 %."""
    settings = SolverSettings.product(64)
    cond = solve_stack(None, [], RoughConductor(N_COND, alpha), settings)
    coat = solve_stack(Rough(ETA, alpha), [], Lambertian(0.5), settings)
    q = radau_hemisphere(len(coat.x))
    np.testing.assert_allclose(q.x, coat.x, rtol=0, atol=1e-15)  # the same nodes
    Ra, Ta, Rb, Tb = _interface_albedos(q, alpha)
    # lossless on both sides to arithmetic (sums of O(h) terms of size ≤ 1)
    assert np.abs(Ra + Ta - 1.0).max() <= 1e-12 and np.abs(Rb + Tb - 1.0).max() <= 1e-12
    below = ms.walk_dielectric(0.5, alpha, ETA, N_PATHS, 7, from_below=True, cosine_weighted=True)
    failures = []
    edges = mf.flux_cell_edges(q.x, q.w)
    for j, k in enumerate(_nodes(q.x)):
        mu = float(q.x[k])
        theta = float(np.degrees(np.arccos(mu)))
        r = ms.walk_conductor(mu, alpha, N_COND, N_PATHS_COND, 10 + j)
        _check("conductor", alpha, theta, float(cond.albedo()[0, k]), r["albedo"], r["se"], N_PATHS_COND, failures)
        top = ms.walk_dielectric(mu, alpha, ETA, N_PATHS, 20 + j)
        _check("R from the air", alpha, theta, Ra[k], top["R"], top["R_se"], N_PATHS, failures)
        _check("T from the air", alpha, theta, Ta[k], top["T"], top["T_se"], N_PATHS, failures)
        A, se = ms.coat_over_lambertian_albedo(mu, alpha, ETA, 0.5, N_PATHS, 0, top=top, below=below)
        _check("coat/Lambertian 0.5", alpha, theta, float(coat.albedo()[0, k]), A, se, N_PATHS, failures)
        # from the binder T falls steeply past the critical angle (41.8°): the node's value is its flux cell's
        # average (docs/rough-interfaces.md, "Discretisation"), so the walk averages over the same cell
        bot = ms.walk_dielectric(None, alpha, ETA, N_PATHS, 40 + j, from_below=True, cell=(edges[k], edges[k + 1]))
        _check("R from the binder", alpha, theta, Rb[k], bot["R"], bot["R_se"], N_PATHS, failures)
        _check("T from the binder", alpha, theta, Tb[k], bot["T"], bot["T_se"], N_PATHS, failures)
    assert not failures, "\n".join(failures)


def test_walk_cell_average_smooth_limit():
    """``cell``: incident cosines drawn from μ dμ on the cell, so T is the flux-weighted cell average.  α = 0.005
    from the binder over a cell that holds the critical angle (μ 0.55–0.95; critical μ 0.745): T equals
    ∫ (1 − F(μ)) μ dμ / ∫ μ dμ of the smooth interface (Gauss–Legendre above the critical μ, T = 0 below) within
    3σ + 0.5 % (0.5176 ± 0.0011 against 0.5168); cosines drawn uniformly in μ give 0.454 (fails).  A malformed
    cell is refused."""
    lo, hi, eta = 0.55, 0.95, 1.5
    mu_c = np.sqrt(1.0 - 1.0 / eta**2)
    x, w = np.polynomial.legendre.leggauss(64)
    mu = 0.5 * (hi + mu_c) + 0.5 * (hi - mu_c) * x  # below mu_c the binder reflects totally: T = 0
    F, _ = ms.fresnel_dielectric_cos(mu, np.full(mu.shape, 1.0 / eta))
    T = (0.5 * (hi - mu_c) * w * (1.0 - F) * mu).sum() / (0.5 * (hi * hi - lo * lo))
    d = ms.walk_dielectric(None, 0.005, eta, 200_000, 11, from_below=True, cell=(lo, hi))
    assert d["lost"] == 0
    assert abs(d["T"] - T) <= 3 * d["T_se"] + 0.005 * T, (d["T"], T, d["T_se"])
    T_uniform = (0.5 * (hi - mu_c) * w * (1.0 - F)).sum() / (hi - lo)
    assert abs(T_uniform - T) > 3 * d["T_se"] + 0.005 * T  # the check can tell the two weightings apart
    with pytest.raises(ValueError, match="cell"):
        ms.walk_dielectric(None, 0.005, eta, 10, 1, cell=(0.9, 0.5))
