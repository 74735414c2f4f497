"""`flakedb compose RECIPE --out DIR`: a paint recipe → DIR/NAME.bsdf, DIR/NAME.h5, DIR/NAME.json.

A node count the solver cannot use is refused before any work, in one line, exit status 2:

>>> import tempfile
>>> from click.testing import CliRunner
>>> from flakedb.cli.main import cli
>>> from flakedb.resources import RECIPES_DIR
>>> out = tempfile.mkdtemp()
>>> result = CliRunner().invoke(cli, ["compose", str(RECIPES_DIR / "research-hg-slab.yaml"), "--n", "33", "--out", out])
>>> result.exit_code, result.output.splitlines()
(2, ['Error: --n 33: the node count must be even, 8 ≤ n ≤ 512 (n/2 nodes per hemisphere), e.g. 64'])
"""

import click

from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan, probe_writable, remove_created_dirs
from flakedb.cli.options import RAW_HELP, check_node_count
from flakedb.cli.progress import StageProgress
from flakedb.colour.gamut import RGB_SPACES
from flakedb.colour.settings import (
    DEFAULT_GEOMETRY_SET,
    DEFAULT_ILLUMINANT,
    DEFAULT_OBSERVER,
    GEOMETRY_SETS,
    resolve,
)
from flakedb.colour.tolerance import illuminant_name
from flakedb.compose.orchestrate import output_plan
from flakedb.solve.pipeline import UnphysicalResultError
from flakedb.compose.orchestrate import compose as compose_recipe
from flakedb.appearance.report import format_report
from flakedb.outputs import OutputError
from flakedb.paint.catalog import CatalogError, load_catalog
from flakedb.paint.mapping import catalog_species
from flakedb.paint.recipe import RecipeError, load_recipe
from flakedb.pipelines.build import build as run_build
from flakedb.pipelines.build import request_for_recipe
from flakedb.process import request_fast_exit
from flakedb.store.versions import StoreError, StoreIntegrityError


@click.command()
@click.argument("recipe", type=click.Path(dir_okay=False))
@click.option("--out", "out_dir", default="out", show_default=True, type=click.Path(),
              help="Output directory for NAME.bsdf, NAME.h5 and NAME.json.")
@click.option("--n", "n", default=None, type=int,
              help="Node count (even, >= 8; n/2 per hemisphere); overrides the recipe's resolution.")
@click.option("--store", "store", default=None, envvar="FLAKEDB_STORE",
              help="Precomputed species store of `flakedb build` (path or fsspec URL; default $FLAKEDB_STORE): "
                   "catalogue species' reflectance functions come from its latest version, checksums verified. "
                   "Without it, species optics are computed directly.")
@click.option("--raw", is_flag=True, help=RAW_HELP)
@click.option("--catalog", "catalog_path", default=None, type=click.Path(dir_okay=False, exists=True),
              help="Particle catalogue YAML (default: catalog/particles.yaml or $FLAKEDB_CATALOG).")
@click.option("--rgb-space", "rgb_space", default="srgb", show_default=True, type=click.Choice(list(RGB_SPACES)),
              help="Working space of the RGB .bsdf: linear sRGB (what .bsdf readers assume), or the wide-gamut "
                   "linear Rec.2020 / ACEScg (tell the renderer; docs/renderers.md).  Recorded in the metadata.")
@click.option("--observer", default=None,
              help=f"Colour report observer, 2 or 10 (default {DEFAULT_OBSERVER}; an RGB-mode recipe has 2 only).")
@click.option("--illuminant", default=None,
              help=f"Colour report illuminant, D65, A, F11, ... (default {DEFAULT_ILLUMINANT}).")
@click.option("--geometries", "geometry_set", default=DEFAULT_GEOMETRY_SET, show_default=True,
              type=click.Choice(list(GEOMETRY_SETS)),
              help="Colour report geometries: e2194 (45° illumination), e2539 (adds 15° illumination) or xrite19 (adds "
                   "eight out-of-plane geometries, e.g. 45as25az90).")
@click.option("--quiet", is_flag=True, help="No progress lines on stderr (warnings are still printed).")
@click.option("--build-missing", is_flag=True,
              help="When the store cannot serve the recipe (a species, α, n or band range it lacks), build "
                   "exactly what the recipe needs into it as a new version first (as `flakedb build --recipe`), "
                   "then compose from it; later composes find that version.")
@click.option("--allow-unphysical", is_flag=True,
              help="Write the result even when the self-check finds an albedo above 1 + 1e-3, a negative BSDF "
                   "value or unconverged Fourier orders (printed as loud warnings); without it that is an error.")
def compose(recipe, out_dir, n, store, raw, catalog_path, rgb_space, observer, illuminant, geometry_set, quiet,
            build_missing, allow_unphysical):
    """Compose the paint of RECIPE (YAML, schemas/recipe.schema.json) into a BSDF and a colour report."""
    check_node_count(n)

    try:
        catalog = load_catalog(catalog_path)
        rec = load_recipe(recipe, catalog)
        colour = resolve(observer, illuminant, geometry_set, rec.mode)
        if illuminant is not None:
            illuminant_name(illuminant)
    except (RecipeError, CatalogError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    inputs = [(recipe, "RECIPE")] + ([(catalog_path, "--catalog")] if catalog_path else [])
    check_plan(output_plan(out_dir, rec.name, inputs))
    probe_writable(out_dir)
    if colour.note:
        click.echo(f"note: {colour.note}", err=True)
    for w in rec.warnings:
        click.echo(f"warning: {w}", err=True)

    if store is None:
        click.echo(f"compose {rec.name}: store: none; species optics computed directly from the catalogue")
    elif not catalog_species(rec):
        click.echo(f"compose {rec.name}: store: none needed (no catalogue species); optics computed directly")
    else:
        click.echo(f"compose {rec.name}: store: {store} ({'raw samples' if raw else 'compressed factors'})")
    def attempt():
        bar = StageProgress()
        progress = bar if not quiet else (lambda stage, d: bar(stage, d) if stage == "warning" else None)
        try:
            with remove_created_dirs(out_dir):
                return compose_recipe(rec, out_dir, n=n, raw=raw, catalog=catalog,
                                      log=lambda s: click.echo(f"  {s}"), store=store, rgb_space=rgb_space,
                                      progress=progress, allow_unphysical=allow_unphysical,
                                      colour_settings=colour, inputs=inputs)
        finally:
            bar.close()

    built = False
    try:
        try:
            res = attempt()
        except StoreError as exc:
            if not build_missing or isinstance(exc, StoreIntegrityError) or store is None:
                raise
            lines = str(exc).splitlines()
            reason = lines[1].strip() if len(lines) > 1 else lines[0]
            click.echo(f"compose {rec.name}: the store cannot serve the recipe yet ({reason}); --build-missing: "
                       f"building what it needs into {store} as a new version", err=True)
            b = run_build(request_for_recipe(rec, n=n, store_raw=raw), store, scheduler="threads",
                          progress=not quiet)
            built = True
            click.echo(f"compose {rec.name}: {b['status']} version {b['version'][:12]} ({b['tasks_run']} of "
                       f"{b['tasks_total']} tasks run, {b['seconds']:.1f} s)", err=True)
            res = attempt()
    except (StoreError, UnphysicalResultError, RecipeError, OutputError) as exc:
        raise FlakedbError(str(exc)) from exc
    for w in res.warnings:
        if w.startswith("UNPHYSICAL"):
            click.echo(f"WARNING: {w}", err=True)

    click.echo(format_report(res.report))
    s = res.bsdf_summary
    click.echo(f"wrote {res.paths['bsdf']} ({s['n_channels']} channel(s), {s['n_nodes']} nodes, max order "
               f"{s['max_order']}, {s['size'] / 1e6:.2f} MB)")
    click.echo(f"wrote {res.paths['h5']} (full precision) and {res.paths['json']} (colour report)")
    click.echo(f"time: {sum(res.timings_s.values()):.1f} s (" +
               ", ".join(f"{k} {v:.2f} s" for k, v in res.timings_s.items()) + ")")
    if not built:  # every output written and closed, no build's scheduler left: no teardown needed (flakedb.process)
        request_fast_exit()
