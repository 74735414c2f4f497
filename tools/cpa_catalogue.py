"""The ``cpa`` route over the catalogue in Cycles: every recipe of ``flakedb/catalog/recipes`` composed at
n = 32, fitted by :func:`flakedb.export.cpa.fit_cpa` and rendered by its Blender node group at the six
ASTM E2194 geometries (:func:`flakedb.export.blender.render_cycles_geometries`: a plane under a 0.5° sun,
8 px x 256 spp), the ΔE00 (D65 / 2°) against the exact paint per geometry; beside it the route before the
backscatter lobe (``n_retro=0``, 4 minimax passes, the first lobe subset), as its fit's own ΔE00 (the
node group renders the model to ≤ 3e-4: docs/renderers.md), and both fits' E2539 worst.

Needs bpy 5.0.1 in a Python 3.11 environment (``make blender-venv``)::

    python tools/cpa_catalogue.py OUTDIR [RECIPE ...] [--blender-python PATH]

Composes into OUTDIR (a recipe already composed there is reused) and prints one JSON line per recipe
(docs/renderers.md, "Every catalogue recipe").
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import flakedb
from flakedb.bsdf import open_bsdf
from flakedb.colour.tolerance import delta_E_2000
from flakedb.compose.orchestrate import compose
from flakedb.export import cpa
from flakedb.export import openpbr as op
from flakedb.export.blender import cpa_inputs, render_cycles_geometries
from flakedb.match.fit import channels_to_Lab, geometry_directions
from flakedb.match.targets import E2194_GEOMETRIES
from flakedb.paint.recipe import load_recipe

RECIPES = Path(flakedb.__file__).parent / "catalog" / "recipes"


def measure(recipe: str, out: Path, python: str | None) -> dict:
    """One recipe's row: before / after worst ΔE00 at E2194, the rendered per-geometry ΔE00, E2539 worst."""
    t = time.time()
    if not (out / f"{recipe}.bsdf").exists():
        compose(load_recipe(RECIPES / f"{recipe}.yaml"), out, n=32)
    b = open_bsdf(out / f"{recipe}.bsdf")
    g = np.asarray(E2194_GEOMETRIES, float)
    gi, go, gp = geometry_directions(g)
    wl = op.colour_grid(b)

    def lab(x):
        return channels_to_Lab(np.maximum(x, 1e-6), "rgb", wl)

    exact = lab(np.pi * op.exact_rgb(b, gi, go, gp))
    before = cpa.fit_cpa(b, n_retro=0, minimax_passes=4, max_subsets=1)
    fit = cpa.fit_cpa(b)
    cy = render_cycles_geometries(g, cpa=cpa_inputs(fit.table, fit.alphas, fit.coat_ior, retro_alphas=fit.retro_alphas),
                                  python=python)
    de_before = delta_E_2000(lab(np.pi * cpa.evaluate_cpa(before, gi, go, gp)), exact)
    de = delta_E_2000(lab(cy), exact)
    return {"recipe": recipe, "before_fit_worst": round(float(de_before.max()), 2),
            "cycles_dE00": [round(float(x), 2) for x in de], "cycles_worst": round(float(de.max()), 2),
            "alphas": list(fit.alphas), "retro_alphas": list(fit.retro_alphas),
            "E2539_worst_before": round(before.error["worst_dE00_E2539"], 2),
            "E2539_worst": round(fit.error["worst_dE00_E2539"], 2), "seconds": round(time.time() - t, 1)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("recipes", nargs="*", help="recipe names [default: every catalogue recipe]")
    ap.add_argument("--blender-python", default=None, help="a Python with bpy 5.0.1 [default: .venv-blender's]")
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    for r in a.recipes or sorted(p.stem for p in RECIPES.glob("*.yaml")):
        print(json.dumps(measure(r, a.out, a.blender_python)), flush=True)


if __name__ == "__main__":
    main()
