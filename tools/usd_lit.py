"""A lit render of ``flakedb export-openpbr``'s ``.usda`` through a real USD consumer: Blender 5.0.1's
USD importer, rendered in Cycles (:func:`flakedb.export.usd_render.render_cycles_usd`), and what it
shows (docs/renderers.md, the ``.usda`` row).

For each ``.usda``: the file and a copy with UsdPreviewSurface's ``clearcoat`` set to 0
(:func:`flakedb.export.usd_render.with_clearcoat`), each rendered twice (32 px at pixel centres over
[-1.05, 1.05]², CPU, no denoising, adaptive sampling off):

* *sun*: a sun of irradiance 1 and 2° radius at 35° from the view axis, black world, 64 spp;
* *furnace*: a uniform world of radiance 1, no sun, 256 spp.

Reported at the 7 off-highlight pixels of ``test_cycles_matches_preview`` (3 x 3 means):

* what Blender imported (the Principled BSDF's inputs and distribution, the mesh);
* the coat under the sun: coated / coat-off (channel sums at the 63 pixels) against what Cycles'
  layering gives, ``1 - A_coat(μ_v)`` (= 1 - F(μ_v; 1.5) for a smooth coat;
  :func:`coat_weight`);
* the coat in the furnace: the coat's own reflection of the uniform sky,
  ``F̂ = (L_coated - L_off) / (1 - L_off)`` (the coated pixel is ``F + (1 - F) L_off`` when the
  coat's reflection is F and it passes 1 - F), per ring of μ_v over the whole sphere, against the
  ring's mean F(μ_v; 1.5), with the standard error of the mean of F̂ - F(μ_v) over the ring's pixels
  (reported where the coat-off sphere absorbs ≥ 20 % of the sky: :data:`MIN_DARK`);
* Cycles against what flakedb predicts it renders of the imported inputs
  (:func:`flakedb.export.blender.principled_sun_image`, ``distribution="MULTI_GGX"``), and in ΔE00
  against flakedb's preview of the exact ``.bsdf`` (``--bsdf DIR`` holding NAME.bsdf), against the
  fitted model itself, and against the Blender-script route (the same fit as
  :func:`~flakedb.export.blender.principled_inputs`, rendered by
  :func:`~flakedb.export.blender.render_cycles_sphere`), with the USD route's loss split into the
  file's (no lobe tint, no film: :func:`flakedb.export.usd_render.usd_route_fit`, with single-scatter
  GGX) and the importer's (Multiscatter GGX).

Needs bpy 5.0.1 in a Python 3.11 environment (``make blender-venv``)::

    python tools/usd_lit.py OUTDIR PAINT.usda [PAINT.usda ...] [--bsdf DIR] [--blender-python PATH]

Writes OUTDIR/NAME.{sun,sun-nocoat,furnace,furnace-nocoat}.f32 (32 x 32 x 3 float32, row 0 at the
top) and OUTDIR/summary.json, and prints the summary.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from flakedb.bsdf import open_bsdf
from flakedb.colour.tolerance import delta_E_2000
from flakedb.export.blender import (
    model_sun_image,
    principled_sun_image,
    render_cycles_sphere,
    sphere_normals,
    sun_direction,
)
from flakedb.export.openpbr import OpenPBRFit
from flakedb.export.usd_render import (
    imported_fit,
    read_usda_fit,
    render_cycles_usd,
    sphere_material,
    usd_route_fit,
    with_clearcoat,
)
from flakedb.match.fit import channels_to_Lab
from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.render.preview import Environment, Sun, render_sphere

SIZE, EXTENT, SUN_DEG = 32, 1.05, 35.0
SUN_SPP, FURNACE_SPP, PREVIEW_SPP = 64, 256, 64
#: Pixels (row, column) compared, 3 x 3 means (tests/export/test_renderers.py::PIXELS)
PIXELS = [(16, 16), (22, 16), (16, 8), (16, 24), (12, 12), (20, 20), (24, 10)]
#: Rings of μ_v of the furnace's coat check; F̂ is reported where the coat-off sphere absorbs at
#: least MIN_DARK of the sky (1 - L_off): a near-white paint reflects the sky whether coated or not
#: (tri-coat pearl white: 1 - L_off ≈ 0.01), and F̂'s noise grows as 1 / (1 - L_off)
RINGS = ((0.9, 1.0), (0.75, 0.9), (0.5, 0.75))
MIN_DARK = 0.2
WL = np.arange(380.0, 781.0, 10.0)
KINDS = ("sun", "sun-nocoat", "furnace", "furnace-nocoat")
REPORTED_INPUTS = ("Base Color", "Metallic", "Roughness", "IOR", "Specular IOR Level", "Specular Tint", "Coat Weight",
                   "Coat Roughness", "Coat IOR", "Thin Film Thickness")


def means(img) -> np.ndarray:
    """(7, 3) 3 x 3-pixel means at :data:`PIXELS`."""
    img = np.asarray(img, float)
    return np.array([img[r - 1:r + 2, c - 1:c + 2].reshape(-1, 3).mean(0) for r, c in PIXELS])


def pixels63() -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of the 63 pixels of the 3 x 3 windows."""
    pix = [(r + i, c + j) for r, c in PIXELS for i in (-1, 0, 1) for j in (-1, 0, 1)]
    return tuple(np.array(pix).T)


def lab(m) -> np.ndarray:
    """CIELAB (D65 / 2°) of linear sRGB radiances under a sun of irradiance 1 (reflectance factor π L)."""
    return channels_to_Lab(np.maximum(np.asarray(m) * np.pi, 1e-6), "rgb", WL)


def dE(a, b) -> list:
    return [round(float(x), 3) for x in delta_E_2000(lab(means(a)), lab(means(b)))]


def without_coat(fit: OpenPBRFit) -> OpenPBRFit:
    return replace(fit, coat_ior=1.0, coat_roughness=0.0)


def coat_weight(imported: OpenPBRFit, direction) -> np.ndarray:
    """(SIZE, SIZE) what Cycles' coat passes to the layers under it at each pixel, the ratio of the
    coated to the coat-off prediction (a smooth coat: 1 - F(μ_v; η_c)); 1 where either is 0."""
    c = principled_sun_image(imported, SIZE, direction, distribution="MULTI_GGX").sum(-1)
    u = principled_sun_image(without_coat(imported), SIZE, direction, distribution="MULTI_GGX").sum(-1)
    return np.where(u > 0, c / np.where(u > 0, u, 1.0), 1.0)


def render_all(usda, out: Path, python: str | None) -> dict:
    """The four renders of the module docstring (and the coat-off copy of the file in ``out``)."""
    usda = Path(usda)
    bare = with_clearcoat(usda, out / f"{usda.stem}.nocoat.usda", 0.0)
    sun = dict(direction=sun_direction(SUN_DEG), samples=SUN_SPP, python=python)
    furnace = dict(irradiance=0.0, world_radiance=1.0, samples=FURNACE_SPP, python=python)
    r = {"sun": render_cycles_usd(usda, **sun), "sun-nocoat": render_cycles_usd(bare, **sun),
         "furnace": render_cycles_usd(usda, **furnace), "furnace-nocoat": render_cycles_usd(bare, **furnace)}
    return r


def coat_checks(imported: OpenPBRFit, sun, sun_bare, furnace, furnace_bare) -> dict:
    """The coat numbers of the module docstring (images SIZE px)."""
    d = sun_direction(SUN_DEG)
    rr, cc = pixels63()
    ratio = np.asarray(sun)[rr, cc].sum(-1) / np.maximum(np.asarray(sun_bare)[rr, cc].sum(-1), 1e-30)
    w = coat_weight(imported, d)[rr, cc]
    N, on = sphere_normals(SIZE, EXTENT)
    mu = N[..., 2]
    L_c, L_u = np.asarray(furnace).mean(-1), np.asarray(furnace_bare).mean(-1)      # the coat is untinted
    F_hat = (L_c - L_u) / np.maximum(1.0 - L_u, 1e-6)
    rings = []
    for lo, hi in RINGS:
        m = on & (mu > lo) & (mu <= hi)
        k = int(m.sum())
        dark = float((1.0 - L_u[m]).mean())
        F = fresnel_dielectric(mu[m], 1.5).R
        ring = {"mu": [lo, hi], "pixels": k, "one_minus_L_off": dark, "F_exact": float(F.mean())}
        if dark >= MIN_DARK:          # the standard error of the mean of F̂ - F(μ_v) over the ring's pixels
            ring.update(F_hat=float(F_hat[m].mean()), standard_error=float((F_hat[m] - F).std(ddof=1) / np.sqrt(k)))
        rings.append(ring)
    return {"sun_ratio_range": [float(ratio.min()), float(ratio.max())],
            "sun_ratio_minus_predicted_max": float(np.abs(ratio - w).max()),
            "predicted_ratio_range": [float(w.min()), float(w.max())],
            "furnace_rings": rings}


def colour_checks(fit: OpenPBRFit, imported: OpenPBRFit, usd_sun, preview=None, script_sun=None) -> dict:
    """The colour numbers of the module docstring (images SIZE px; ``preview``/``script_sun`` optional)."""
    d = sun_direction(SUN_DEG)
    pred = principled_sun_image(imported, SIZE, d, distribution="MULTI_GGX")
    script_pred = principled_sun_image(fit, SIZE, d)                 # the Blender-script route (GGX)
    file_only = principled_sun_image(usd_route_fit(fit), SIZE, d)    # the file's losses, single-scatter GGX
    model = model_sun_image(fit, SIZE, d)
    out = {"usd_vs_prediction_rel_max": float(np.abs(means(usd_sun) / means(pred) - 1).max()),
           "dE00_usd_vs_model": dE(usd_sun, model),
           "dE00_usd_prediction_vs_script_prediction": dE(pred, script_pred),
           "dE00_file_losses_only_vs_script_prediction": dE(file_only, script_pred),
           "dE00_multiscatter_only": dE(pred, file_only)}
    if preview is not None:
        out["dE00_usd_vs_preview"] = dE(usd_sun, preview)
        out["dE00_usd_prediction_vs_preview"] = dE(pred, preview)
        out["dE00_script_prediction_vs_preview"] = dE(script_pred, preview)
        out["dE00_model_vs_preview"] = dE(model, preview)
    if script_sun is not None:
        out["dE00_usd_vs_script_cycles"] = dE(usd_sun, script_sun)
        out["dE00_script_cycles_vs_preview"] = dE(script_sun, preview) if preview is not None else None
        rel = np.abs(means(script_sun) / means(script_pred) - 1)
        out["script_cycles_vs_script_prediction_rel_max"] = float(rel.max())
    return out


def preview_image(bsdf_path, spp: int = PREVIEW_SPP) -> np.ndarray:
    """flakedb's preview of the exact BSDF under the same sun, at pixel centres."""
    d = sun_direction(SUN_DEG)
    return render_sphere(open_bsdf(bsdf_path), Environment(kind="constant", radiance=(0, 0, 0)),
                         Sun.from_irradiance(d, (1, 1, 1), 2.0), size=SIZE, spp=spp, jitter=False).image.astype(float)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("usda", nargs="+", type=Path)
    ap.add_argument("--bsdf", type=Path, default=None, help="folder holding NAME.bsdf for the exact preview")
    ap.add_argument("--blender-python", default=None, help="the interpreter that has bpy (default: this one)")
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    summary = {"size": SIZE, "extent": EXTENT, "sun_deg": SUN_DEG, "spp": {"sun": SUN_SPP, "furnace": FURNACE_SPP},
               "paints": {}}
    for usda in a.usda:
        t0 = time.perf_counter()
        fit = read_usda_fit(usda)
        r = render_all(usda, a.out, a.blender_python)
        for kind in KINDS:
            r[kind]["image"].astype(np.float32).tofile(a.out / f"{usda.stem}.{kind}.f32")
        mat = sphere_material(r["sun"])
        imp = imported_fit(mat)
        d = sun_direction(SUN_DEG)
        script = render_cycles_sphere(fit, size=SIZE, samples=SUN_SPP, direction=d, python=a.blender_python)["image"]
        pv = preview_image(a.bsdf / f"{usda.stem}.bsdf") if a.bsdf else None
        summary["blender"] = r["sun"]["blender"]
        summary["paints"][usda.stem] = {
            "objects": r["sun"]["objects"], "distribution": mat["distribution"],
            "imported": {k: mat["inputs"][k] for k in REPORTED_INPUTS},
            "coat_off_imported_coat_weight": sphere_material(r["sun-nocoat"])["inputs"]["Coat Weight"],
            "coat": coat_checks(imp, *(r[k]["image"] for k in KINDS)),
            "colours": colour_checks(fit, imp, r["sun"]["image"], pv, script),
            "seconds": round(time.perf_counter() - t0, 1)}
    (a.out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
