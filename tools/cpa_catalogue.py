"""The ``cpa`` route over the catalogue in Cycles: every recipe of ``flakedb/catalog/recipes`` composed at
n = 32, fitted as ``export-cpa`` fits the node group (:func:`flakedb.export.cpa.fit_cpa_cycles`: GGX lobes, or
Beckmann lobes where the GGX fit misses the target and they are closer) and rendered by it at the six
ASTM E2194 geometries (:func:`flakedb.export.blender.render_cycles_geometries`: a plane under a 0.5° sun,
8 px x 256 spp), the ΔE00 (D65 / 2°) against the exact paint per geometry; beside it the route before the
backscatter lobe (``n_retro=0``, 4 minimax passes, the first lobe subset), as its fit's own ΔE00 (the
node group renders the model to ≤ 3e-4: docs/renderers.md), and both fits' E2539 worst.

With ``--renderer glsl`` the recipe is exported by ``export-cpa`` (:func:`flakedb.export.registry.export`,
method ``cpa``) and its ``.cpa.mtlx`` rendered by MaterialX's own GLSL renderer at the six E2194 geometries
(:func:`flakedb.export.materialx_render.check_cpa_glsl`, as ``tests/export/test_cpa_glsl.py``): the ΔE00 per
geometry against the exact paint (needs ``materialx`` and Xvfb or a display).

With ``--fits DIR`` the GGX fits are read from ``DIR/RECIPE.cpa.json`` (``export-cpa``'s, of the same files: the
fit is deterministic) instead of fitted again, the ``before`` fit is skipped, and both renderers are measured: the
node group of :func:`flakedb.export.cpa.fit_cpa_cycles` in Cycles, and the MaterialX files that ``export-cpa``
writes for the fit (:func:`flakedb.export.cpa.fit_cpa_materialx`: a tilted lobe added where the GGX fit misses), all rendered in one MaterialX process, with the render's largest difference from flakedb's
prediction of it (:func:`flakedb.export.materialx_render.cpa_materialx_rf`) per recipe.

Needs bpy 5.0.1 in a Python 3.11 environment (``make blender-venv``)::

    python tools/cpa_catalogue.py OUTDIR [RECIPE ...] [--blender-python PATH] [--renderer cycles|glsl] [--fits DIR]

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
    fit = cpa.fit_cpa_cycles(b, cpa.fit_cpa(b))             # what export-cpa writes into the node group
    cy = render_cycles_geometries(g, cpa=cpa_inputs(fit.table, fit.alphas, fit.coat_ior, retro_alphas=fit.retro_alphas,
                                                    distribution=fit.distribution), python=python)
    de_before = delta_E_2000(lab(np.pi * cpa.evaluate_cpa(before, gi, go, gp)), exact)
    de = delta_E_2000(lab(cy), exact)
    return {"recipe": recipe, "before_fit_worst": round(float(de_before.max()), 2),
            "cycles_dE00": [round(float(x), 2) for x in de], "cycles_worst": round(float(de.max()), 2),
            "alphas": list(fit.alphas), "retro_alphas": list(fit.retro_alphas), "distribution": fit.distribution,
            "E2539_worst_before": round(before.error["worst_dE00_E2539"], 2),
            "E2539_worst": round(fit.error["worst_dE00_E2539"], 2), "seconds": round(time.time() - t, 1)}


def measure_glsl(recipe: str, out: Path) -> dict:
    """One recipe's row in MaterialX GLSL: the exported graph's rendered ΔE00 per E2194 geometry, its worst."""
    from flakedb.export import materialx_render as mr
    from flakedb.export.registry import export

    t = time.time()
    if not (out / f"{recipe}.bsdf").exists():
        compose(load_recipe(RECIPES / f"{recipe}.yaml"), out, n=32)
    b = open_bsdf(out / f"{recipe}.bsdf")
    ex = export(out / f"{recipe}.bsdf", out / "glsl", method="cpa")
    r = mr.check_cpa_glsl(b, ex["files"]["materialx"])
    de = [g["dE00"] for g in r["geometries"]]
    mx = ex["fit"].get("materialx", ex["fit"])           # the graph's fit (a tilted lobe where GGX misses)
    return {"recipe": recipe, "glsl_dE00": [round(float(x), 2) for x in de], "glsl_worst": round(float(max(de)), 2),
            "alphas": list(mx["alphas"]), "retro_alphas": list(mx.get("retro_alphas", [])),
            "tilted": list(mx.get("tilted", [])), "fit_worst": round(mx["error"]["worst_dE00_E2194"], 2),
            "E2539_worst": round(mx["error"]["worst_dE00_E2539"], 2),
            "renderer": r["renderer"], "seconds": round(time.time() - t, 1)}


def measure_from_fits(recipes, out: Path, fits: Path, python: str | None) -> list[dict]:
    """Rows of both renderers from saved GGX fits (module docstring, ``--fits``)."""
    from flakedb.export import materialx_render as mr
    from flakedb.export.materialx import cpa_mtlx_text

    g = np.asarray(E2194_GEOMETRIES, float)
    gi, go, gp = geometry_directions(g)
    mx_dir = out / "glsl-fits"
    mx_dir.mkdir(parents=True, exist_ok=True)
    rows, files, fitted = [], [], []
    for recipe in recipes:
        t = time.time()
        if not (out / f"{recipe}.bsdf").exists():
            compose(load_recipe(RECIPES / f"{recipe}.yaml"), out, n=32)
        b = open_bsdf(out / f"{recipe}.bsdf")
        wl = op.colour_grid(b)
        exact = channels_to_Lab(np.maximum(np.pi * op.exact_rgb(b, gi, go, gp), 1e-6), "rgb", wl)
        fit = cpa.CPAFit.from_dict(json.loads((fits / f"{recipe}.cpa.json").read_text()))
        cy_fit = cpa.fit_cpa_cycles(b, fit)
        cy = render_cycles_geometries(g, cpa=cpa_inputs(cy_fit.table, cy_fit.alphas, cy_fit.coat_ior,
                                                        retro_alphas=cy_fit.retro_alphas,
                                                        distribution=cy_fit.distribution), python=python)
        de = delta_E_2000(channels_to_Lab(np.maximum(cy, 1e-6), "rgb", wl), exact)
        mx_fit = cpa.fit_cpa_materialx(b, fit)                          # what export-cpa writes for MaterialX
        px, scale = cpa.table_image(cpa.materialx_fit(mx_fit))
        (mx_dir / f"{recipe}.cpa.png").write_bytes(cpa.table_png_bytes(px))
        m = mx_dir / f"{recipe}.cpa.mtlx"
        m.write_text(cpa_mtlx_text(f"{recipe}.cpa.png", scale, mx_fit.alphas, mx_fit.coat_ior, mx_fit.n_table, recipe,
                                   retro_alphas=mx_fit.retro_alphas, tilted=mx_fit.tilted), encoding="utf-8")
        files.append(m)
        fitted.append((b, mx_fit, exact, wl))
        rows.append({"recipe": recipe, "cycles_dE00": [round(float(x), 2) for x in de], "cycles_worst": round(float(de.max()), 2),
                     "distribution": cy_fit.distribution, "alphas": list(fit.alphas), "cycles_alphas": list(cy_fit.alphas),
                     "retro_alphas": list(fit.retro_alphas), "fit_worst": round(fit.error["worst_dE00_E2194"], 2),
                     "materialx_tilted": [list(t) for t in mx_fit.tilted],
                     "materialx_fit_worst": round(mx_fit.error["worst_dE00_E2194"], 2),
                     "cycles_seconds": round(time.time() - t, 1)})
    t = time.time()
    r = mr.render_geometries(files, g)
    for row, rf, (b, fit, exact, wl) in zip(rows, r["rf"], fitted):
        de = delta_E_2000(channels_to_Lab(np.maximum(rf, 1e-6), "rgb", wl), exact)
        pred = mr.cpa_materialx_rf(mr.table_as_loaded(cpa.materialx_fit(fit)), g)
        row.update({"glsl_dE00": [round(float(x), 2) for x in de], "glsl_worst": round(float(de.max()), 2),
                    "glsl_minus_prediction": float((np.abs(rf - pred).max(axis=1) / pred.max(axis=1)).max()),
                    "glsl_minus_prediction_abs": float(np.abs(rf - pred).max()),
                    "renderer": f"MaterialX {r['materialx']} on {r['gl'].get('renderer', '?')}"})
    for row in rows:
        row["glsl_seconds_all"] = round(time.time() - t, 1)
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("recipes", nargs="*", help="recipe names [default: every catalogue recipe]")
    ap.add_argument("--blender-python", default=None, help="a Python with bpy 5.0.1 [default: .venv-blender's]")
    ap.add_argument("--renderer", choices=("cycles", "glsl"), default="cycles",
                    help="Cycles (bpy) or MaterialX's GLSL renderer [default: cycles]")
    ap.add_argument("--fits", type=Path, default=None,
                    help="read the GGX fits from DIR/RECIPE.cpa.json and measure both renderers (module docstring)")
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    if a.fits is not None:
        for row in measure_from_fits(a.recipes or sorted(p.stem for p in RECIPES.glob("*.yaml")), a.out, a.fits,
                                     a.blender_python):
            print(json.dumps(row), flush=True)
        return
    for r in a.recipes or sorted(p.stem for p in RECIPES.glob("*.yaml")):
        row = measure_glsl(r, a.out) if a.renderer == "glsl" else measure(r, a.out, a.blender_python)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
