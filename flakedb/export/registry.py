"""Every export route in one registry, in the style of colour-science's ``method=`` dispatch:
``export(src, out, method="openpbr")``.  :data:`EXPORT_METHODS` maps a method to its function and
what the route keeps; ``flakedb export-*`` commands, docs/renderers.md and ``flakedb info`` name
routes by these keys.  A new route is one function and one entry here."""

from __future__ import annotations

from pathlib import Path

from flakedb.bsdf import open_bsdf
import json
import math

from flakedb.export.blender import cpa_material_script, write_material_script
from flakedb.export.cpa import (E2194_TARGET, fit_cpa, fit_cpa_cycles, fit_cpa_materialx, materialx_fit, table_image,
                                table_png_bytes)
from flakedb.export.gltf import write_gltf
from flakedb.export.materialx import cpa_mtlx_text, write_mtlx
from flakedb.export.sparkle import design_from_recipe
from flakedb.export.sparkle import node_inputs as sparkle_node_inputs
from flakedb.paint.recipe import load_recipe
from flakedb.export.openpbr import fit_openpbr
from flakedb.export.usd import write_usda
from flakedb.outputs import OutputPlan, check_file_name, sweep_stale
from flakedb.render.mitsuba import export_coated, export_measured
from flakedb.render.mitsuba.coated import pbrt_coated_scene


def export_openpbr(src, out_dir, name: str | None = None, progress=None) -> dict:
    """Fit the analytic material to ``src`` (:func:`flakedb.export.openpbr.fit_openpbr`) and write it
    as ``NAME.mtlx`` (MaterialX OpenPBR), ``NAME.usda`` (USD, UsdPreviewSurface), ``NAME.gltf`` and
    ``NAME.glb`` (glTF 2.0 sphere) and ``NAME.blender.py`` (Principled BSDF script) in ``out_dir``.
    Returns {"fit": fit dict, "files": {kind: path}}."""
    out_dir = Path(out_dir)
    option = "--name" if name is not None else "FILE's name (before its first '.'; choose one with --name)"
    name = Path(src).name.split(".")[0] if name is None else str(name)
    routes = (("materialx", write_mtlx, ".mtlx"), ("usd", write_usda, ".usda"), ("gltf", write_gltf, ".gltf"),
              ("glb", write_gltf, ".glb"), ("blender", write_material_script, ".blender.py"))
    # the output plan before any work (flakedb.outputs): no output is the input (a BSDF named NAME.glb, say)
    plan = OutputPlan()
    plan.add_input(src, "FILE")
    check_file_name(name, option)   # NAME is a plain file name in --out: never ../escaped or /anywhere
    finals = {kind: plan.in_dir(out_dir, f"{name}{suffix}", kind) for kind, _, suffix in routes}
    plan.check()
    for p in sweep_stale(out_dir):   # what a killed export left (flakedb.outputs.sweep_stale)
        if progress:
            progress(f"note: removed {p}, a temporary entry left by an interrupted flakedb run")
    b = open_bsdf(src)
    if progress:
        progress("fitting OpenPBR parameters (hemisphere + E2194/E2539 geometries)")
    fit = fit_openpbr(b, source=str(src))
    out_dir.mkdir(parents=True, exist_ok=True)
    with plan.staged() as stage:  # the five files land together or not at all
        for kind, fn, _ in routes:
            fn(stage.path(finals[kind]), fit, name)
    return {"fit": fit.to_dict(), "files": {kind: str(p) for kind, p in finals.items()}}


def export_cpa(src, out_dir, name: str | None = None, progress=None, sparkle_recipe=None,
               uv_metres: float = 1.0) -> dict:
    """Fit the angle-indexed material to ``src`` (:func:`flakedb.export.cpa.fit_cpa`: coat mirror,
    Lambert and GGX lobes whose colours are a table indexed by N·V) and write ``NAME.cpa.png`` (the
    colour table, 16-bit linear RGB in two 8-bit planes, each row scaled to its maximum), ``NAME.cpa.mtlx`` (MaterialX
    graph of standard nodes reading that image by the relative name), ``NAME.cpa.blender.py``
    (Cycles / EEVEE node group; the table in float, packed: no file needed) and ``NAME.cpa.json``
    (the fit: table, roughnesses, error) in ``out_dir``.  With ``sparkle_recipe`` (the paint's recipe file)
    the MaterialX graph and the node group carry the glint layer of :mod:`flakedb.export.sparkle`,
    parameterised from the recipe's flakes by the texture model, for a UV map of ``uv_metres`` metres per unit;
    the layer is in the fit's JSON under ``sparkle``.  The fit has GGX lobes (MaterialX's only distribution); where
    it misses the E2194 target the node group gets the Beckmann fit of :func:`flakedb.export.cpa.fit_cpa_cycles`
    when that is closer (without ``sparkle_recipe``: the glint layer is designed for GGX lobes), in the JSON
    under ``cycles``, and the MaterialX graph the fit with a tilted lobe of
    :func:`flakedb.export.cpa.fit_cpa_materialx` when that is closer (likewise), in the JSON under ``materialx``.
    Returns {"fit": dict, "files": {kind: path}}."""
    out_dir = Path(out_dir)
    option = "--name" if name is not None else "FILE's name (before its first '.'; choose one with --name)"
    name = Path(src).name.split(".")[0] if name is None else str(name)
    plan = OutputPlan()
    plan.add_input(src, "FILE")
    check_file_name(name, option)
    kinds = {"image": ".cpa.png", "materialx": ".cpa.mtlx", "blender": ".cpa.blender.py", "fit": ".cpa.json"}
    finals = {kind: plan.in_dir(out_dir, f"{name}{suffix}", kind) for kind, suffix in kinds.items()}
    plan.check()
    for p in sweep_stale(out_dir):
        if progress:
            progress(f"note: removed {p}, a temporary entry left by an interrupted flakedb run")
    if not (math.isfinite(float(uv_metres)) and float(uv_metres) > 0):
        raise ValueError(f"--uv-metres {uv_metres}: the UV map's metres per UV unit must be a finite number > 0 "
                         f"(1 when the UVs are in metres, 0.001 in millimetres)")
    recipe = load_recipe(sparkle_recipe) if sparkle_recipe is not None else None
    b = open_bsdf(src)
    if progress:
        progress("fitting the angle-indexed colour table (hemisphere + E2194/E2539 geometries)")
    fit = fit_cpa(b, source=str(src))
    d = fit.to_dict()
    cycles = mtlx = fit
    if recipe is None:
        if progress and fit.error["worst_dE00_E2194"] > E2194_TARGET:
            progress("the GGX fit misses the E2194 target: fitting Beckmann lobes for the Cycles node group "
                     "and a tilted GGX lobe for the MaterialX graph")
        cycles = fit_cpa_cycles(b, fit, source=str(src))
        mtlx = fit_cpa_materialx(b, fit, source=str(src))
    if cycles is not fit:
        d["cycles"] = cycles.to_dict()
    if mtlx is not fit:
        d["materialx"] = mtlx.to_dict()
    nodes = None
    if recipe is not None:
        if progress:
            progress(f"designing the glint layer from {sparkle_recipe}'s flakes (texture model)")
        layer = design_from_recipe(fit.table, fit.alphas, recipe)
        nodes = sparkle_node_inputs(layer, uv_metres)
        d["sparkle"] = dict(layer.to_dict(), node_inputs=nodes)
    fit_json = json.dumps(d, separators=(",", ":"))
    px, scale = table_image(materialx_fit(mtlx))    # the graph's colours: MaterialX's energy compensation undone
    texts = {"materialx": cpa_mtlx_text(finals["image"].name, scale, mtlx.alphas, mtlx.coat_ior, mtlx.n_table, name,
                                        json.dumps({k: ({kk: vv for kk, vv in v.items() if kk != "table"}
                                                        if k in ("cycles", "materialx") else v)
                                                    for k, v in d.items() if k != "table"}, separators=(",", ":")),
                                        sparkle=nodes, retro_alphas=mtlx.retro_alphas, tilted=mtlx.tilted),
             "blender": cpa_material_script(cycles.table, cycles.alphas, cycles.coat_ior, name,
                                            fit_json if cycles is fit else json.dumps(d["cycles"], separators=(",", ":")),
                                            sparkle=nodes, retro_alphas=cycles.retro_alphas,
                                            distribution=cycles.distribution),
             "fit": json.dumps(d, indent=1)}
    out_dir.mkdir(parents=True, exist_ok=True)
    with plan.staged() as stage:  # the four files land together or not at all
        stage.path(finals["image"]).write_bytes(table_png_bytes(px))
        for kind, text in texts.items():
            stage.path(finals[kind]).write_text(text, encoding="utf-8")
    return {"fit": d, "files": {kind: str(p) for kind, p in finals.items()}}


def _mitsuba_coated(src, out, **kw):
    return export_coated(src, out, **kw)


def _pbrt_coated(src, out, **kw):
    return pbrt_coated_scene(src, out, **kw)


def _openpbr(src, out, **kw):
    return export_openpbr(src, out, **kw)


#: method -> (function(src, out, **kwargs), what the route keeps, what it loses).
EXPORT_METHODS = {
    "mitsuba-measured": (export_measured, "the table (front-side reflection)", "the smooth coat's mirror term"),
    "mitsuba-coated": (_mitsuba_coated, "the table and the coat's Fresnel mirror (blendbsdf + conductor k=0)",
                       "transmission, back side"),
    "pbrt-v3-coated": (_pbrt_coated, "the table (RGB) and the coat's mirror (mix of glass Kr 2 and fourier x2)",
                       "spectral channels; not run"),
    "openpbr": (_openpbr, "coat (index, roughness), base colour, metalness, one GGX lobe",
                "colour travel, the table's lobe shape beyond one GGX lobe, sparkle"),
    "cpa": (export_cpa, "coat mirror, Lambert + 3 GGX lobes with RGB colours indexed by N.V (MaterialX graph, "
                        "Blender node group, PNG table)",
            "colour changes with the light direction beyond the lobes' shapes, the coat's refraction, sparkle unless "
            "sparkle_recipe is given"),
}


def export(src, out, method: str = "openpbr", **kwargs):
    """Export ``src`` by ``method`` (a key of :data:`EXPORT_METHODS`, case-insensitive).

    An unknown route is refused by name, before anything is read:

    >>> export("paint.bsdf", "out", method="blender")
    Traceback (most recent call last):
    ...
    ValueError: method = 'blender' is not an export route; the routes are: mitsuba-measured, mitsuba-coated, pbrt-v3-coated, openpbr, cpa
    """
    key = str(method).lower()
    if key not in EXPORT_METHODS:
        raise ValueError(f"method = {method!r} is not an export route; the routes are: {', '.join(EXPORT_METHODS)}")
    return EXPORT_METHODS[key][0](src, out, **kwargs)
