"""Index steps between binders through the shipped path (issue 26 item 4): recipes composed by
``flakedb.compose.orchestrate.compose`` (its ``check_physical`` included) at ``auto`` and at n = 32 … 256,
and the composed albedo against the independent Monte Carlo (flakedb/reference/montecarlo.py, its own
Fresnel / Snell per path).

Before: a smooth 1.5 coat over a 1.6 basecoat over a primer was refused as a "negative BSDF" at every
n (its inner mirror rang in the Fourier table), and auto chose n = 32 for a rise/fall stack that compose
then refused (−0.54 against a maximum 2.87)."""

import numpy as np
import pytest

import flakedb.reference.montecarlo as mc
from flakedb.compose.orchestrate import compose
from flakedb.solve.pipeline import check_physical
from flakedb.paint.recipe import parse_recipe

HEAD = "flakedb: 1\nname: {name}\nspectral: {{mode: mono}}\nresolution: auto\nlayers:\n"
COAT = "  - clearcoat: {{thickness_um: 40, ior: {ior}, roughness: {rough}}}\n"
BASE = ("  - basecoat:\n      thickness_um: 10\n      ior: {ior}\n{extra}      particles:\n"
        "        - custom: {{kind: medium, name: {pname}, albedo: {alb}, phase: {{hg: {g}}}}}\n"
        "          optical_depth: 1.0\n")

RECIPES = {
    # smooth clear 1.5 over a 1.6 basecoat over a primer: nothing scatters above the inner interface
    "rise": HEAD.format(name="rise") + COAT.format(ior=1.5, rough=0)
    + BASE.format(ior=1.6, extra="", pname="hg-a", alb=0.9, g=0.7) + "  - primer: {albedo: 0.5}\n",
    # a rise 1.5 → 1.6 into an HG slab and a fall 1.6 → 1.45 into another, over a Lambertian
    "rise-fall": HEAD.format(name="rise-fall") + COAT.format(ior=1.5, rough=0)
    + BASE.format(ior=1.6, extra="", pname="hg-a", alb=0.9, g=0.7)
    + BASE.format(ior=1.45, extra="", pname="hg-b", alb=0.8, g=0.3) + "  - primer: {albedo: 0.5}\n",
    # the same with rough inner interfaces
    "rise-fall-rough": HEAD.format(name="rise-fall-rough") + COAT.format(ior=1.5, rough=0)
    + BASE.format(ior=1.6, extra="      interface_roughness: 0.2\n", pname="hg-a", alb=0.9, g=0.7)
    + BASE.format(ior=1.45, extra="      interface_roughness: 0.1\n", pname="hg-b", alb=0.8, g=0.3)
    + "  - primer: {albedo: 0.5}\n",
    # an index step over a metal base, under a rough coat
    "step-over-metal": HEAD.format(name="step-over-metal") + COAT.format(ior=1.5, rough=0.1)
    + BASE.format(ior=1.6, extra="", pname="hg-a", alb=0.9, g=0.5) + "  - metal: {material: {n: 1.2, k: 7.0}, roughness: 0.2}\n",
}


def _mc_problem(name):
    hg = lambda a, g: (mc.PhaseMedium(0.1, a, mc.HenyeyGreenstein(g)),)  # noqa: E731  (τ 1 over 10 µm)
    slabs = {"rise": (mc.Slab(1.0, (), eta=1.5), mc.Slab(10.0, hg(0.9, 0.7), eta=1.6)),
             "rise-fall": (mc.Slab(1.0, (), eta=1.5), mc.Slab(10.0, hg(0.9, 0.7), eta=1.6),
                           mc.Slab(10.0, hg(0.8, 0.3), eta=1.45))}[name]
    return mc.Problem(slabs, top=mc.Smooth(1.5), bottom=mc.Lambertian(0.5))


@pytest.mark.slow
@pytest.mark.parametrize("name", list(RECIPES))
def test_index_steps_compose_at_auto_and_every_n(name, tmp_path):
    """compose (its check_physical refuses a negative BSDF, albedo > 1, unconverged orders) accepts
    every stack at auto and at n = 32, 64, 128 (and 256 for the smooth steps)."""
    rec = parse_recipe(RECIPES[name])
    ns = [None, 32, 64, 128] + ([256] if name in ("rise", "rise-fall") else [])
    for n in ns:
        res = compose(rec, tmp_path / f"n{n}", n=n)
        assert check_physical(res.stack) == []
        assert np.all(res.stack.albedo() <= 1.0)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["rise", "rise-fall"])
def test_composed_index_steps_match_monte_carlo(name, tmp_path):
    """The albedo of the file compose writes at auto (tabulated part: the smooth coat's delta is
    analytic in both) within 3σ + 0.5 % of the Monte Carlo at normal, 45° and 70° incidence."""
    res = compose(parse_recipe(RECIPES[name]), tmp_path)
    st = res.stack
    A = st.albedo(include_delta=False)[0]
    prob = _mc_problem(name)
    for j, frac in enumerate((1.0, 0.7, 0.35)):
        k = int(np.argmin(np.abs(st.x - frac)))
        r = mc.simulate(prob, float(st.x[k]), 100_000, seed=71 + j)
        tol = 3 * r.albedo_se[0] + 0.005 * r.diffuse_albedo[0]
        assert abs(A[k] - r.diffuse_albedo[0]) <= tol, (name, res.n, float(st.x[k]), A[k], r.diffuse_albedo[0], tol)
