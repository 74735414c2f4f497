"""`flakedb export-cpa FILE --out DIR`: the angle-indexed colour-table material (MaterialX graph, Blender
node group, PNG table).  Thin: the work is in :func:`flakedb.export.registry.export_cpa`.

A file that is not a Fourier BSDF is refused in one line, exit status 2, nothing written:

>>> import os, tempfile
>>> from pathlib import Path
>>> from click.testing import CliRunner
>>> from flakedb.cli.main import cli
>>> where = Path(tempfile.mkdtemp())
>>> _ = (where / "notes.bsdf").write_bytes(b"hello")
>>> r = CliRunner().invoke(cli, ["export-cpa", str(where / "notes.bsdf"), "--out", str(where)])
>>> r.exit_code, sorted(os.listdir(where))
(2, ['notes.bsdf'])
"""

import json

import click

from flakedb.bsdf import open_bsdf
from flakedb.cli.errors import FlakedbError
from flakedb.cli.exporting import run_export
from flakedb.export.cpa import E2194_TARGET, GGX_MIN_RATIO_75_15, ggx_route_floor
from flakedb.export.materialx_render import check_cpa_glsl, glsl_renderer


@click.command("export-cpa")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--out", "out", default=None, type=click.Path(file_okay=False),
              help="Output directory [default: FILE's directory].")
@click.option("--name", default=None, help="Base name of the files [default: FILE's stem].")
@click.option("--sparkle", "sparkle", default=None, type=click.Path(dir_okay=False),
              help="The paint's recipe (.yaml): add the glint layer (flakes as perturbed normals in cells of the "
                   "UV map), parameterised from its flakes by the texture model (docs/renderers.md, 'Sparkle').")
@click.option("--uv-metres", "uv_metres", default=1.0, show_default=True, type=float,
              help="With --sparkle: metres per UV unit of the geometry's UV map (0.001 for UVs in mm).")
@click.option("--check", "check", type=click.Choice(["glsl"]), default=None,
              help="After writing, render NAME.cpa.mtlx in MaterialX's own GLSL renderer (Xvfb + Mesa when there is no "
                   "display) under a directional light at the ASTM E2194 geometries and print the ΔE00 against FILE's "
                   "exact prediction per geometry: what the renderer produces, not the fit's own number.")
@click.option("--json", "as_json", is_flag=True, help="Print the fit and the files as JSON.")
def export_cpa(file, out, name, sparkle, uv_metres, check, as_json):
    """Fit a coat mirror, a Lambert term, three GGX lobes and a backscatter lobe whose colours are a table indexed by the view angle to a Fourier .bsdf / flakedb .h5 FILE, and write NAME.cpa.png (the table), NAME.cpa.mtlx (MaterialX standard nodes), NAME.cpa.blender.py (Cycles / EEVEE node group) and NAME.cpa.json (the fit and its ΔE00)."""
    tool = None
    if check == "glsl":   # before any work: a check that cannot run is refused, nothing written
        tool, why = glsl_renderer()
        if tool is None:
            raise FlakedbError(f"--check glsl: {why}; or leave out --check")
    s = run_export(file, out, "cpa", name, as_json, bad_input=(ValueError, OSError), sparkle_recipe=sparkle,
                   uv_metres=uv_metres)
    rendered = None
    if check == "glsl":
        if not as_json:
            click.echo("rendering NAME.cpa.mtlx in MaterialX's GLSL renderer at the E2194 geometries", err=True)
        try:
            rendered = check_cpa_glsl(open_bsdf(file), s["files"]["materialx"], tool=tool)
        except RuntimeError as e:
            raise FlakedbError(f"--check glsl: the files are written, but the render failed: {e}") from None
    if as_json:
        fit = {k: ({kk: vv for kk, vv in v.items() if kk != "table"} if k in ("cycles", "materialx") else v)
               for k, v in s["fit"].items() if k != "table"}
        click.echo(json.dumps({"fit": fit, "files": s["files"],
                               **({"check_glsl": rendered} if rendered else {})}, indent=2))
        return
    f, e = s["fit"], s["fit"]["error"]
    retro = f.get("retro_alphas", [])
    click.echo(f"fit: lobes GGX α {', '.join(f'{a:.3g}' for a in f['alphas'])}"
               + (f", backscatter GGX α {', '.join(f'{a:.3g}' for a in retro)}" if retro else "")
               + f", colour table {len(f['table'])} x {f['n_table']} (indexed by N.V); coat ior {f['coat_ior']:.4g}")
    cy = f.get("cycles")
    if cy:
        click.echo(f"in Cycles / EEVEE: the GGX fit misses the target, so the node group has Beckmann lobes "
                   f"(α {', '.join(f'{a:.3g}' for a in cy['alphas'])}; MaterialX has GGX only"
                   + (": it gets a tilted GGX lobe, below)" if f.get("materialx") else ")"))
    click.echo(f"in Cycles (the node group renders this model to ≤ 3e-4 at the E2194 geometries, ≤ 0.01 ΔE00; "
               f"docs/renderers.md): worst ΔE00 against FILE {(cy or f)['error']['worst_dE00_E2194']:.2f} at the "
               f"E2194 geometries (target ≤ {E2194_TARGET:g})")
    mx = f.get("materialx")
    if e["worst_dE00_E2194"] > E2194_TARGET:
        floor = ggx_route_floor(open_bsdf(file))
        click.echo(f"in MaterialX (GGX lobes, its only distribution): the GGX fit's worst ΔE00 {e['worst_dE00_E2194']:.2f} "
                   f"misses the target; no mix of GGX lobes about N with view-indexed colours can go below "
                   f"{floor:.2f} at aspecular 15°/75° for this paint (one table column; a GGX lobe's 75°/15° ratio is "
                   f"≥ {GGX_MIN_RATIO_75_15:.3g}; docs/renderers.md)")
        if mx:
            tilt = "; ".join(f"α {a:.3g}, k {k:.3g}" for a, k in mx["tilted"])
            click.echo(f"in MaterialX: the graph adds a GGX lobe about a normal tilted away from the view ({tilt}): the fit's worst ΔE00 {mx['error']['worst_dE00_E2194']:.2f} at the E2194 geometries "
                       f"(E2539's geometries not weighted: worst {mx['error']['worst_dE00_E2539']:.2f})")
    click.echo(f"fit error (the model against FILE): worst ΔE00 {e['worst_dE00_E2539']:.2f} with E2539's geometries; "
               f"over the hemisphere (both within 70°) median {e['dE00_hemisphere_70deg']['median']:.2f}, "
               f"max {e['dE00_hemisphere_70deg']['max']:.2f}")
    if "sparkle" in f:
        g, r = f["sparkle"], f["sparkle"]["reference"]
        click.echo(f"sparkle: lobe {g['lobe']} (GGX α {g['lobe_alpha']:.3g}) split {g['share']:.3g} into glints: cells "
                   f"{g['cell_um']:.3g} µm, {g['occupancy']:.3g} of them a flake, glint α {g['glint_alpha']:.3g} "
                   f"({r['diameter_um']:g} µm flakes); {r['glints_per_mm2_above_threshold']:.3g} glints/mm² above the "
                   f"texture model's {'kind-relative ' if r.get('threshold') == 'relative' else ''}threshold "
                   f"(luminance factor {r['glint_threshold_luminance_factor']:.3g}) at {r['light_deg']:g}° under a {r['source_half_angle_deg']:g}° source "
                   f"(the model's count, Cycles within ±20 %, docs/renderers.md)")
    if rendered:
        per = ", ".join(f"{g['aspecular_deg']:g}°: {g['dE00']:.2f}" for g in rendered["geometries"])
        click.echo(f"MaterialX GLSL render ({rendered['renderer']}; a plane under a directional light) against "
                   f"FILE's exact prediction, ΔE00 per E2194 aspecular angle: {per}; worst {rendered['worst_dE00']:.2f}")
    for k, p in s["files"].items():
        click.echo(f"wrote {p} ({k})")
