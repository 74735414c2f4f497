"""`flakedb texture RECIPE`: predicted sparkle and graininess of a paint (docs/texture.md).

One number per paint: the contrasts and the graininess are relative to the paint's mean luminance
factor, which only the composed BSDF knows, so the command composes the paint (`flakedb compose`'s own
function, into a temporary directory, with the same ``--n`` and ``--store``) and prints the ``texture``
section of compose's report, identical to the one in NAME.json.  Custom observers are grounded on the
same composed BSDF.  ``--flakes-only`` skips the solve: contrasts and graininess are then relative to the
flakes' own mean (labelled ``ground: flakes``; not bounds: that mean can exceed the paint's).
"""

import json
import tempfile
from pathlib import Path

import click

from flakedb.bsdf.dispatch import FILE_KINDS, file_kind
from flakedb.bsdf.table import BSDFFileError
from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan, remove_created_dirs
from flakedb.cli.options import check_node_count
from flakedb.solve.pipeline import UnphysicalResultError
from flakedb.compose.orchestrate import compose as compose_recipe
from flakedb.appearance.report import texture_ground
from flakedb.outputs import OutputPlan
from flakedb.paint.catalog import CatalogError, load_catalog
from flakedb.paint.recipe import RecipeError, load_recipe
from flakedb.paint.texture_inputs import texture_report, texture_report_grounded, texture_stack
from flakedb.render.imageio import write_exr
from flakedb.render.mitsuba_sparkle import FILES, material_xml, mitsuba_route
from flakedb.store.versions import StoreError
from flakedb.texture.instruments import PRESETS, Observer

#: The Mitsuba route's texture: texels (µm; the observer's spot when smaller) and texels per side.
MITSUBA_TEXEL_UM, MITSUBA_SIZE = 5.0, 512


def format_texture(rep) -> str:
    """The table ``flakedb texture`` prints (numbers from :func:`flakedb.paint.texture_inputs.texture_report`).

    The catalogue's metallic silver seen by the BYK-mac-like preset: its flakes, and fewer glints as the
    light moves from 15° to 75° (fewer flakes tilted far enough to mirror it):

    >>> from flakedb.resources import RECIPES_DIR
    >>> rep = texture_report(load_recipe(RECIPES_DIR / "metallic-silver.yaml"), [PRESETS["byk-mac-like"]])
    >>> lines = format_texture(rep).splitlines()
    >>> lines[0], lines[1].split(",")[0].strip()
    ('texture metallic-silver (model: docs/texture.md)', 'metallic: median diameter 16 µm')
    >>> glints = [float(ln.split()[2]) for ln in lines[3:6]]
    >>> [ln.split()[1] for ln in lines[3:6]], glints[0] > glints[1] > glints[2] > 0
    (['15°', '45°', '75°'], True)
    """
    lines = [f"texture {rep['recipe']} (model: docs/texture.md)"]
    for n in rep["notes"]:
        lines.append(f"  note: {n}")
    if not rep["sparkle"]:
        lines.append(f"  {rep['summary']}")
        return "\n".join(lines)
    for f in rep["flakes"]:
        lines.append(f"  {f['species']}: median diameter {f['diameter_median_um']:g} µm, σg {f['diameter_gsd']:g}, "
                     f"α {f['orientation_alpha']:g}, {f['flakes_per_mm2']:.0f} flakes/mm² at depth "
                     f"{f['depth_um'][0]:g}–{f['depth_um'][1]:g} µm")
    head = (f"  {'observer':<14} {'light':>6} {'glints/mm²':>11} {'above β_t':>10} {'per spot':>9} {'area frac':>10} "
            f"{'intensity':>10} {'contrast':>9} {'peak β':>8} {'β_t':>7}")
    lines.append(head)
    for o in rep["observers"]:
        for r in o["directional"]:
            if not r["sparkle"]:
                why = r.get("no_sparkle_reason") or f"peak luminance factor {r['peak_luminance_factor']:.3g}"
                lines.append(f"  {o['observer']:<14} {r['light_deg']:>5g}° no sparkle ({why})")
                continue
            lines.append(f"  {o['observer']:<14} {r['light_deg']:>5g}° {r['glints_per_mm2']:>11.3g} "
                         f"{r['glints_per_mm2_above_threshold']:>10.3g} "
                         f"{r['glints_per_spot']:>9.3g} {r['sparkle_area_fraction']:>10.3g} "
                         f"{r['sparkle_intensity']:>10.3g} {r['sparkle_contrast']:>9.3g} "
                         f"{r['peak_luminance_factor']:>8.3g} {r['glint_threshold_luminance_factor']:>7.3g}")
        d = o["diffuse"]
        if d["graininess"] is None:
            lines.append(f"  {o['observer']:<14} {'sky':>6} {d['note']}")
            continue
        ground = "paint's (BSDF)" if d["ground"] == "bsdf" else "flakes' own"
        lines.append(f"  {o['observer']:<14} {'sky':>6} graininess {d['graininess']:.3g} "
                     f"(spot {o['spot_um']:.3g} µm; relative to the {ground} mean)")
    lines.append("  glints/mm²: flakes at least half as bright as an aligned surface flake of their own size; above β_t: "
                 "flakes brighter than the fixed luminance factor β_t (half an aligned R = 1 surface flake of 16 µm: what "
                 "a person or a camera counts); per spot: in one resolved spot; area frac: spots holding a glint; "
                 "intensity: the brightest spot's excess luminance factor (the share of the spot a glint fills); contrast: "
                 "intensity / the mean (the flakes' own with --flakes-only); peak β: an aligned surface "
                 "flake.")
    return "\n".join(lines)


def composed_texture(rec, obs, n=None, store=None, catalog=None) -> tuple[dict, dict]:
    """(texture report, {observer name: ground}) of ``rec`` seen by observers ``obs``, grounded on the paint's
    composed BSDF: :func:`flakedb.compose.orchestrate.compose` (the one orchestration, into a temporary
    directory) makes the solve and its report's ``texture`` section; that section's entries are returned
    as they are (one number per paint), and observers it does not hold (custom ones) are computed here and
    grounded on the same BSDF (:func:`flakedb.appearance.report.texture_ground`, as compose grounds its own)."""
    with tempfile.TemporaryDirectory(prefix="flakedb-texture-") as d:
        res = compose_recipe(rec, Path(d) / "out", n=n, store=store, catalog=catalog)
    paint, stack = res.paint, res.stack
    ground = texture_ground(res.table, paint.mode, paint.wavelength_nm, stack.x, stack.albedo(include_delta=False),
                            paint.eta if paint.delta else None)
    section = res.report["texture"]
    held = {e["observer"]: e for e in section.get("observers") or []}
    if not section["sparkle"] or all(o.name in held and PRESETS.get(o.name) == o for o in obs):
        rep = dict(section, observers=[held[o.name] for o in obs] if section["sparkle"] else section["observers"])
    else:
        rep = texture_report_grounded(texture_report(rec, obs), obs, ground)
    return rep, {o.name: ground(o) for o in obs}


def _write_mitsuba(rec, obs, out_dir, ground=None):
    """The Mitsuba 3 sparkle route's files (docs/texture.md §7), planned and written together
    (:class:`flakedb.outputs.OutputPlan`): the parameter set, the glint layer's three textures and the
    material XML.  Texels of min(5 µm, the observer's spot); ``ground``: the paint's luminance factor
    at the observer's first light angle (sets the blend weight)."""
    plan = OutputPlan()
    plan.add_dir(out_dir, "--mitsuba")
    paths = {k: plan.in_dir(out_dir, v.format(name=rec.name), f"--mitsuba {k}") for k, v in FILES.items()}
    check_plan(plan)
    st, _ = texture_stack(rec)
    texel = min(MITSUBA_TEXEL_UM, float(obs.spot_um))
    r = mitsuba_route(st, obs, MITSUBA_SIZE, texel, ground_luminance_factor=ground)
    with remove_created_dirs(Path(out_dir).absolute()), plan.staged() as stage:
        for k in ("normals", "alpha", "gain"):
            write_exr(stage.path(paths[k]), r[k])
        stage.path(paths["params"]).write_text(json.dumps(r["params"], indent=1))
        stage.path(paths["xml"]).write_text(material_xml(rec.name, texel, MITSUBA_SIZE, r["weight"]))
    m = r["params"]["mitsuba"]
    click.echo(f"wrote {', '.join(str(p) for p in paths.values())}: include {paths['xml'].name} in a Mitsuba 3 "
               f"scene (bsdf id flakedb_sparkle, -D measured=FILE; uv period {m['period_um']:g} µm); blend weight "
               f"{m['blend_weight']:.4g} ({m['weight_basis']})", err=True)


def _refuse_bsdf(path):
    """A FlakedbError when ``path`` is a file flakedb knows by its first bytes (a composed .bsdf / .h5, a
    Mitsuba tensor, a MaterialX document) rather than a recipe: the texture model needs the recipe."""
    try:
        kind = file_kind(path)
    except BSDFFileError:
        return                                   # not a known binary kind: read it as a recipe
    raise FlakedbError(f"{path}: a {FILE_KINDS[kind][1]} file, not a recipe.  flakedb texture predicts sparkle from "
                       f"what is in the paint: give the recipe (YAML) it was composed from, e.g. "
                       f"flakedb/catalog/recipes/metallic-silver.yaml (`flakedb info {path}` names the recipe)")


@click.command()
@click.argument("recipe", type=click.Path(dir_okay=False))
@click.option("--observer", "observers", multiple=True, type=click.Choice(sorted(PRESETS)),
              help="Observation preset (repeatable; default: all): " + ", ".join(
                  f"{k}: {v.description}" for k, v in PRESETS.items()))
@click.option("--spot-um", type=float, default=None,
              help="A custom observer instead: side of the resolved spot on the panel, µm.")
@click.option("--aperture-deg", type=float, default=0.5, show_default=True,
              help="Custom observer: angular radius of the collecting aperture seen from the panel, degrees.")
@click.option("--source-deg", type=float, default=0.2665, show_default=True,
              help="Custom observer: angular radius of the source, degrees (the sun: 0.2665).")
@click.option("--light-deg", type=float, multiple=True, default=(15.0, 45.0, 75.0), show_default=True,
              help="Custom observer: light polar angles, degrees (repeatable).")
@click.option("--view-deg", type=float, default=0.0, show_default=True,
              help="Custom observer: view polar angle, degrees (opposite side of the normal).")
@click.option("--catalog", "catalog_path", default=None, type=click.Path(dir_okay=False, exists=True),
              help="Particle catalogue YAML (default: catalog/particles.yaml or $FLAKEDB_CATALOG).")
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON instead of the table.")
@click.option("--n", "n", default=None, type=int,
              help="Node count of the BSDF solve that grounds the indices (as `flakedb compose --n`).")
@click.option("--store", "store", default=None, envvar="FLAKEDB_STORE",
              help="Precomputed species store, as `flakedb compose --store` (default $FLAKEDB_STORE).")
@click.option("--flakes-only", is_flag=True,
              help="Skip the BSDF solve: contrasts and graininess relative to the flakes' own mean "
                   "('ground: flakes'), not the paint's, so not bounds on compose's; fast.")
@click.option("--mitsuba", "mitsuba_dir", default=None, type=click.Path(file_okay=False),
              help="Also write the Mitsuba 3 sparkle route for the first observer and light angle into DIR: "
                   "NAME.sparkle.xml (a blendbsdf of the `measured` export and a glint layer), its textures "
                   "NAME.flakes.exr, NAME.glint_alpha.exr, NAME.glint_gain.exr (512², 5 µm texels) and "
                   "NAME.sparkle.json (the shader parameter set) (docs/texture.md §7).")
@click.option("--mitsuba-ground", type=float, default=None,
              help="With --mitsuba: the paint's luminance factor π f_r at the first light angle (from `flakedb "
                   "compose`'s report); the blend weight is then the flakes' share, which keeps the mean.")
def texture(recipe, observers, spot_um, aperture_deg, source_deg, light_deg, view_deg, catalog_path, as_json,
            n=None, store=None, flakes_only=False, mitsuba_dir=None, mitsuba_ground=None):
    """Predicted sparkle (glints per mm², area fraction, intensity, contrast) and graininess of RECIPE,
    relative to the composed paint (compose's report section, identical), or with --flakes-only to the flakes."""
    import numpy as np  # lazy: CLI start-up

    check_node_count(n)
    if mitsuba_ground is not None and not (0.0 < mitsuba_ground < 1e3):
        raise FlakedbError(f"--mitsuba-ground {mitsuba_ground}: give the paint's luminance factor π f_r, a number in "
                           f"(0, 1000)")
    _refuse_bsdf(recipe)
    try:
        catalog = load_catalog(catalog_path)
        rec = load_recipe(recipe, catalog)
    except (RecipeError, CatalogError) as exc:
        raise FlakedbError(str(exc)) from exc
    if spot_um is not None:
        try:
            obs = [Observer("custom", float(spot_um), float(np.radians(aperture_deg)), float(source_deg),
                            tuple(float(a) for a in light_deg), float(view_deg), "custom observer")]
        except ValueError as exc:
            raise FlakedbError(f"custom observer (--spot-um, --aperture-deg, --source-deg, --light-deg, --view-deg): {exc}") from exc
    else:
        obs = [PRESETS[o] for o in (observers or PRESETS)]
    if flakes_only:
        rep = texture_report(rec, obs)
    else:
        try:
            rep, grounds = composed_texture(rec, obs, n=n, store=store, catalog=catalog)
        except (StoreError, UnphysicalResultError, RecipeError) as exc:
            raise FlakedbError(f"composing the paint's BSDF (the ground of the indices; --flakes-only skips it): "
                               f"{exc}") from exc
        if mitsuba_ground is None and obs[0].light_deg:  # the blend weight from the same BSDF
            mitsuba_ground = grounds[obs[0].name]["directional"][float(obs[0].light_deg[0])]
    if mitsuba_dir is not None and rep["sparkle"]:
        _write_mitsuba(rec, obs[0], mitsuba_dir, mitsuba_ground)
    if as_json:
        click.echo(json.dumps(rep, indent=1))
    else:
        click.echo(format_texture(rep))
