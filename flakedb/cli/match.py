"""`flakedb match BASE.yaml --target T.csv --out DIR`: fit a recipe's {fit: [min, max]} fields to a target.

Thin: the fit is :func:`flakedb.colour.match.match` (docs/colour-matching.md).  Writes DIR/NAME-fitted.yaml
(the fitted recipe; never over BASE), composes it into DIR/NAME.{bsdf,h5,json} like `flakedb compose`, and writes
DIR/NAME-prediction.csv (target layout) and DIR/NAME-match.json (the fit record), all six together
or none (:class:`flakedb.outputs.OutputPlan`).  Progress lines go
to stderr, one per iteration.
"""

import json
from pathlib import Path

import click
import numpy as np
import yaml

from flakedb.cli.compare import open_store, parse_limits
from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan, remove_created_dirs
from flakedb.cli.options import check_node_count, prediction_options
from flakedb.compose.orchestrate import OUTPUT_SUFFIXES, output_plan
from flakedb.compose.orchestrate import compose as compose_recipe
from flakedb.match import fit as cm
from flakedb.match.cxf import load_target
from flakedb.match.targets import TargetError, write_target
from flakedb.paint.catalog import CatalogError, load_catalog
from flakedb.paint.recipe import RecipeError, read_recipe_file
from flakedb.store.versions import StoreError


#: The fitted recipe is written as NAME-fitted.yaml, never over the base recipe (issue 25).
FITTED_SUFFIX = "-fitted.yaml"


@click.command()
@click.argument("base", type=click.Path(dir_okay=False))
@click.option("--target", "target_path", required=True, type=click.Path(dir_okay=False),
              help="Target CSV, or a CxF3 file (*.cxf) with multi-angle values (docs/colour-matching.md).")
@click.option("--cxf-object", "cxf_object", default=None,
              help="With a .cxf target: the object (Name or Id) to match, when the file has several.")
@click.option("--out", "out_dir", default="out", show_default=True, type=click.Path(),
              help="Output directory for the fitted recipe, its BSDF files and the fit record.")
@click.option("--observer", default=None, help="2 or 10 (default: the target's).")
@click.option("--illuminant", default=None, help="D65, A, F11, ... (default: the target's).")
@click.option("--weight", "weights", multiple=True,
              help="Weight of a geometry in the fit, ASPECULAR=W or ILLUM/ASPECULAR=W (default 1); repeatable.")
@click.option("--max-evaluations", "max_nfev", default=50, show_default=True, type=click.IntRange(1, 10_000),
              help="Most residual evaluations of the least-squares solver.")
@prediction_options
def match(base, target_path, cxf_object, out_dir, observer, illuminant, weights, max_nfev, n, store, raw, catalog_path):
    """Fit the {fit: [min, max]} fields of BASE (a recipe YAML) so its colour matches the target."""
    check_node_count(n)

    try:
        catalog = load_catalog(catalog_path)
        _, doc = read_recipe_file(base)  # the recipe's strict loader (duplicate keys, alias bombs refused)
        if not isinstance(doc, dict):
            raise RecipeError(base, ["a recipe is a YAML mapping"])
        target = load_target(target_path, observer, illuminant, cxf_object)
        params = cm.find_fit_parameters(doc, base)
        rec0 = cm.recipe_from_doc(cm.substitute(doc, params, [p.start for p in params]), base, catalog)
    except (RecipeError, CatalogError, TargetError) as exc:
        raise FlakedbError(str(exc)) from exc
    name = rec0.name
    inputs = [(base, "BASE"), (target_path, "--target")] + ([(catalog_path, "--catalog")] if catalog_path else [])
    plan = output_plan(out_dir, name, inputs)   # NAME.bsdf/.h5/.json, then the fit's own files
    paths = {k: plan.in_dir(out_dir, f"{name}{suffix}", f"output NAME{suffix}")
             for k, suffix in (("yaml", FITTED_SUFFIX), ("csv", "-prediction.csv"), ("json", "-match.json"))}
    check_plan(plan)   # before any work: never over BASE or the target, no name taken by a directory
    try:
        version = open_store(store, rec0, n, raw)
    except StoreError as exc:
        raise FlakedbError(str(exc)) from exc
    w = np.ones(len(target.geometries))
    for (il, asp), v in parse_limits(weights, "--weight").items():
        hit = [i for i, g in enumerate(target.geometries) if g[0] == il and g[1] == asp]
        if not hit:
            raise FlakedbError(f"--weight {il:g}/{asp:g}: the target has no such geometry")
        w[hit] = v
    click.echo(f"match {doc.get('name')}: {len(params)} parameter(s), {len(target.geometries)} geometries from "
               f"{target.source}; store: {store if version is not None else 'none (optics computed directly)'}")
    try:
        res = cm.match(doc, target, observer=observer, illuminant=illuminant, weights=w, n=n, catalog=catalog,
                       store=version, raw=raw, log=lambda s: click.echo(f"  {s}", err=True), max_nfev=max_nfev,
                       source=base)
    except (RecipeError, StoreError, TargetError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    click.echo(cm.format_match(res))
    text = (f"# fitted by flakedb match to {target.source} ({res.observer}° / {res.illuminant}); "
            f"max dE00 {res.de_fit.max():.3f}\n" + yaml.safe_dump(res.fitted_doc, sort_keys=False, allow_unicode=True))
    rec = cm.recipe_from_doc(res.fitted_doc, str(paths["yaml"]), catalog)
    p = res.prediction
    spectral = p.mode == "spectral"
    out = Path(out_dir)
    with remove_created_dirs(out), plan.staged() as stage:   # every output or none
        stage_dir = stage.dir_for(out)
        try:
            compose_recipe(rec, stage_dir, n=res.n, raw=raw, catalog=catalog, store=version)
        except StoreError as exc:
            raise FlakedbError(str(exc)) from exc
        Path(stage.path(paths["yaml"])).write_text(text, encoding="utf-8")
        write_target(stage.path(paths["csv"]), p.geometries, lab=None if spectral else res.lab_fit,
                     reflectance=p.rf if spectral else None, wavelength_nm=p.wavelength_nm if spectral else None,
                     observer=res.observer, illuminant=res.illuminant, name=name,
                     notes={"generator": f"flakedb match, n = {res.n}, mode {p.mode}"})
        stage.path(paths["json"]).write_text(json.dumps(cm.match_report(res), indent=1) + "\n", encoding="utf-8")
    final = [out / f"{name}{suffix}" for suffix in OUTPUT_SUFFIXES]
    click.echo(f"wrote {paths['yaml']} (fitted recipe), {final[0]}, {final[1]}, {final[2]}, {paths['csv']} and "
               f"{paths['json']}")
