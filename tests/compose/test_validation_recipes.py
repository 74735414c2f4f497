"""The Monte Carlo validation cases exist as recipes (tests/recipes/validation-*.yaml, issue #6) and
compose to the very stacks tests/reference/test_solver_vs_montecarlo.py validates against the Monte Carlo reference.

Guards against a recipe → solver mapping (flakedb/paint/mapping.py) that silently changes a validated
case: a wrong optical-depth → loading conversion (for flakes: σ_t at normal incidence times the
layer thickness), a lost phase function, a primer or coat mapped to something else.
"""

import glob
import os

import numpy as np
import pytest

from flakedb.paint.mapping import build_paint, solve_paint
from flakedb.paint.recipe import load_recipe
from flakedb.rt.adding.stack import SolverSettings, solve_stack
from tests.cases import FAST
from tests.cases import case as _case

HERE = os.path.join(os.path.dirname(__file__), "..")
RECIPES = sorted(glob.glob(os.path.join(HERE, "recipes", "validation-*.yaml")))


def test_every_validation_case_has_a_recipe():
    names = {os.path.basename(p)[len("validation-"):-len(".yaml")] for p in RECIPES}
    assert set(FAST) | {"rough-coat-lambertian"} <= names


@pytest.mark.parametrize("path", RECIPES, ids=lambda p: os.path.basename(p)[:-5])
def test_recipe_composes_to_the_validated_stack(path):
    name = os.path.basename(path)[len("validation-"):-len(".yaml")]
    top, slabs, bottom, _, _ = _case(name)
    n = 24
    direct = solve_stack(top, slabs, bottom, SolverSettings(n=n))
    paint = build_paint(load_recipe(path))
    viarecipe = solve_paint(paint, n)
    np.testing.assert_allclose(viarecipe.albedo(), direct.albedo(), rtol=1e-6, atol=1e-9)
    L = min(direct.n_orders, viarecipe.n_orders)
    scale = np.abs(direct.Rt).max()
    assert np.abs(viarecipe.Rt[:L] - direct.Rt[:L]).max() < 1e-6 * scale
