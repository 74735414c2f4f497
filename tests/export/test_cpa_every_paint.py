"""Issue #37's first Done-when row for every catalogue paint, in CI: the files ``flakedb export-cpa`` writes for
each recipe of ``flakedb/catalog/recipes`` (composed at n = 32, as tools/cpa_catalogue.py does) reach worst ΔE00 ≤ 2
against the exact paint at the six ASTM E2194 geometries, in both routes:

* Cycles: the node group's fit (:func:`flakedb.export.cpa.fit_cpa_cycles`: GGX lobes, or Beckmann lobes where GGX
  misses); the node group renders its model to ≤ 3e-4 (tests/export/test_cpa.py renders representatives in Cycles);
* MaterialX: flakedb's prediction of what the graph renders (:func:`flakedb.export.materialx_render.cpa_materialx_rf`:
  the table as the two 8-bit planes load it, MaterialX's own energy compensation, the tilted lobe where export-cpa
  adds one), which MaterialX's GLSL renderer reproduces to ≤ 1e-4 of each geometry's brightest channel
  (tests/export/test_cpa_glsl.py renders representatives and coated-aluminium).

The renders themselves take 10-30 s a paint, so CI renders the representatives and checks every paint's route here
(each ~2-8 s); tools/cpa_catalogue.py renders all of them (docs/renderers.md, "Every catalogue recipe").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import flakedb
from flakedb.bsdf import open_bsdf
from flakedb.compose.orchestrate import compose
from flakedb.export import cpa
from flakedb.export import materialx_render as mr
from flakedb.export.registry import export
from flakedb.match.targets import E2194_GEOMETRIES
from flakedb.paint.recipe import load_recipe
from tests.compose.test_outputs import _file_checks

RECIPES = Path(flakedb.__file__).parent / "catalog" / "recipes"
#: The issue's goal at the E2194 geometries, each route.
GOAL = 2.0


@pytest.mark.slow
@pytest.mark.parametrize("recipe", sorted(p.stem for p in RECIPES.glob("*.yaml")))
def test_every_catalogue_paint_within_2_in_both_routes(recipe, tmp_path):
    res = compose(load_recipe(RECIPES / f"{recipe}.yaml"), tmp_path, n=32)
    # the recipe's own mode: the RGB file has no negative channel and no albedo above 1 where mapped (the checks
    # of tests/compose/test_outputs.py, whose every-recipe sweep forces RGB mode)
    a0_min, alb_min, alb_max = _file_checks(res.paths["bsdf"])
    assert a0_min >= 0 and alb_min >= 0, (a0_min, alb_min)
    g = res.report["rgb_file"]
    if g is not None:
        assert alb_max <= 1.0 + 1e-6 and g["max_channel_albedo_after"] <= max(1.0, g["max_channel_albedo_before"]) + 1e-12
    b = open_bsdf(tmp_path / f"{recipe}.bsdf")
    ex = export(tmp_path / f"{recipe}.bsdf", tmp_path / "cpa", method="cpa")
    d = ex["fit"]
    cycles_worst = d.get("cycles", d)["error"]["worst_dE00_E2194"]
    mfit = cpa.CPAFit.from_dict(d.get("materialx", d))
    g = np.asarray(E2194_GEOMETRIES, float)
    de, _ = mr.dE00_against_exact(b, mr.cpa_materialx_rf(mr.table_as_loaded(cpa.materialx_fit(mfit)), g), g)
    print(recipe, "Cycles", round(cycles_worst, 2), "MaterialX", np.round(de, 2))
    assert cycles_worst <= GOAL and de.max() <= GOAL, (cycles_worst, de)
