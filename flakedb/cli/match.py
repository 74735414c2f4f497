"""`flakedb match BASE.yaml --target T.csv --out DIR`: fit a recipe's {fit: [min, max]} fields to a target.

Thin: the fit is :func:`flakedb.colour.match.match` (docs/colour-matching.md).  Writes DIR/NAME-fitted.yaml
(the fitted recipe; never over BASE), composes it into DIR/NAME.{bsdf,h5,json} like `flakedb compose`, and writes
DIR/NAME-prediction.csv (target layout) and DIR/NAME-match.json (the fit record), all six together
or none (:class:`flakedb.outputs.OutputPlan`, planned for every target before any work).  Progress lines go
to stderr, one per iteration.  The last line says whether the target's tolerance was reached; exit
status 1 when it was not, after advice (:mod:`flakedb.match.advice`): the colour direction no free parameter
moves, at which geometries, and the catalogue colourants that move it.  Several targets (repeated --target, or a folder): one fit per target into
DIR/<target file name>/, then a summary table; exit status 1 when any target is not reached.

A target with texture columns (sparkle_area_<deg>, sparkle_intensity_<deg>, glints_per_mm2_<deg>,
graininess: :mod:`flakedb.match.texture`) is fitted on colour and texture together, so a flake's
``diameter_um: {fit: [min, max]}`` (which the colour does not depend on) is determined by the sparkle;
"reached" then also needs every index within ``--texture-tolerance`` (docs/colour-matching.md, "Texture").

A target row at the specular geometry is refused before any fit, naming the file and the row:

>>> import tempfile
>>> from pathlib import Path
>>> from click.testing import CliRunner
>>> from flakedb.cli.main import cli
>>> from flakedb.resources import RECIPES_DIR
>>> where = Path(tempfile.mkdtemp())
>>> _ = (where / "t.csv").write_text('''illumination_deg,aspecular_deg,L*,a*,b*
... 45,0,50,0,0
... ''')
>>> result = CliRunner().invoke(cli, ["match", str(RECIPES_DIR / "research-hg-slab.yaml"), "--target", str(where / "t.csv"),
...                                   "--out", str(where / "fit")])
>>> result.exit_code, result.output.splitlines()
(2, ["Error: .../t.csv row 1: aspecular 0° is the specular direction (the smooth coat's mirror delta): not a colour geometry"])
"""

import json
import math
from pathlib import Path

import click
import numpy as np
import yaml

from flakedb.cli.compare import formula, open_store, parse_limits
from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan, remove_created_dirs
from flakedb.cli.options import check_node_count, prediction_options
from flakedb.colour.geometry import key as geometry_key
from flakedb.colour.settings import DEFAULT_MAX_DE00, resolve
from flakedb.colour.tolerance import PerAngleLimits
from flakedb.compose.orchestrate import OUTPUT_SUFFIXES, output_plan
from flakedb.compose.orchestrate import compose as compose_recipe
from flakedb.match import batch
from flakedb.match import fit as cm
from flakedb.match.advice import advise
from flakedb.match.cxf import load_target
from flakedb.match.targets import TargetError, write_target
from flakedb.match.texture import DEFAULT_TEXTURE_TOLERANCE
from flakedb.outputs import OutputError, check_file_name
from flakedb.paint.catalog import CatalogError, load_catalog
from flakedb.paint.recipe import RecipeError, read_recipe_file
from flakedb.store.versions import StoreError

#: The fitted recipe is written as NAME-fitted.yaml, never over the base recipe (issue 25).
FITTED_SUFFIX = "-fitted.yaml"


@click.command()
@click.argument("base", type=click.Path(dir_okay=False))
@click.option("--target", "target_paths", required=True, multiple=True, type=click.Path(),
              help="Target CSV, or a CxF3 file (*.cxf) with multi-angle values (docs/colour-matching.md), or a "
                   "folder of them; repeatable: one fit per target, each into OUT/<target name>/, one summary table.")
@click.option("--cxf-object", "cxf_object", default=None,
              help="With a .cxf target: the object (Name or Id) to match, when the file has several.")
@click.option("--out", "out_dir", default="out", show_default=True, type=click.Path(),
              help="Output directory for the fitted recipe, its BSDF files and the fit record.")
@click.option("--observer", default=None, help="2 or 10 (default: the target's).")
@click.option("--illuminant", default=None, help="D65, A, F11, ... (default: the target's).")
@click.option("--weight", "weights", multiple=True,
              help="Weight of a geometry in the fit, ASPECULAR=W or ILLUM/ASPECULAR=W (default 1); repeatable.")
@click.option("--formula", "formula_text", default="de00", show_default=True,
              help="Colour-difference formula of the tolerance and of the fit's residual: de00 (de00:kL:kC:kH), "
                   "de94 (de94:textiles), cmc (= cmc:2:1; cmc:l:c), din99 (din99:textiles) or deab.")
@click.option("--max-de", "max_de", default=DEFAULT_MAX_DE00, show_default=True, type=float,
              help="The target's tolerance: ΔE (in --formula) limit at every geometry (a policy; exit status 1 when the fit "
                   "does not get within it).")
@click.option("--limit", "limits", multiple=True,
              help="Per-geometry ΔE limit (in --formula), ASPECULAR=V (45° illumination), ILLUM/ASPECULAR=V or ILLUM/ASPECULAR/AZIMUTH=V (out of plane); repeatable.")
@click.option("--max-evaluations", "max_nfev", default=50, show_default=True, type=click.IntRange(1, 10_000),
              help="Most residual evaluations of the least-squares solver.")
@click.option("--texture-tolerance", "texture_tol", default=DEFAULT_TEXTURE_TOLERANCE, show_default=True, type=float,
              help="Relative tolerance of a target's texture columns, with a floor per index (docs/texture.md §9); "
                   "an index at it weighs in the fit as one geometry at the --max-de limit.")
@prediction_options
def match(base, target_paths, cxf_object, out_dir, observer, illuminant, weights, formula_text, max_de, limits, max_nfev,
          texture_tol, n, store, raw, catalog_path):
    """Fit the {fit: [min, max]} fields of BASE (a recipe YAML) so its colour matches the target.

    Exit status 0 when every geometry ends within the tolerance (--max-de / --limit), 1 when not (the
    best fit is still written, and the reason is printed: the failing geometries and any parameter at a
    bound), 2 for an error."""
    check_node_count(n)
    if not (math.isfinite(max_de) and max_de > 0):
        raise FlakedbError(f"--max-de {max_de}: a ΔE tolerance is a finite number > 0 (e.g. --max-de 1)")
    if not (math.isfinite(texture_tol) and texture_tol > 0):
        raise FlakedbError(f"--texture-tolerance {texture_tol}: a relative tolerance is a finite number > 0 "
                           f"(e.g. 0.1 for 10 %)")
    scheme = PerAngleLimits(default=max_de, limits=parse_limits(limits), formula=formula(formula_text))
    weight_items = parse_limits(weights, "--weight")

    try:
        catalog = load_catalog(catalog_path)
        _, doc = read_recipe_file(base)  # the recipe's strict loader (duplicate keys, alias bombs refused)
        if not isinstance(doc, dict):
            raise RecipeError(base, ["a recipe is a YAML mapping"])
        files = batch.expand_paths(target_paths, (".csv", ".cxf"))
        targets = [load_target(t, observer, illuminant, cxf_object if str(t).lower().endswith(".cxf") else None)
                   for t in files]
        params = cm.find_fit_parameters(doc, base)
        if not params:   # before any target's work (the fit itself says so only after the first target's outputs)
            raise RecipeError(base, ["no field to fit: write one or more numeric fields as {fit: [min, max]}"])
        rec0 = cm.recipe_from_doc(cm.substitute(doc, params, [p.start for p in params]), base, catalog)
    except (RecipeError, CatalogError, TargetError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    for t in targets:   # every target's --weight geometries before the first fit (not after target 1's outputs)
        for k in weight_items:
            if not any(geometry_key(g) == k for g in t.geometries):
                raise FlakedbError(f"--weight {'/'.join(f'{x:g}' for x in k)}: the target {_short(t.source)} has no "
                                   f"such geometry")
    stems = [Path(str(f)).stem for f in files]
    if len(targets) > 1:
        for f, stem in zip(files, stems):   # OUT/<stem>/ must be a folder in OUT ('..' of '...csv' is OUT's parent)
            try:
                check_file_name(stem, f"--target {_short(f)}: its file name's stem", "--out")
            except OutputError as exc:
                raise FlakedbError(str(exc).replace("(hint: give e.g.", "(hint: rename the target file; e.g.")) from None
        seen = {}
        for f, stem in zip(files, stems):
            if stem in seen:
                raise FlakedbError(f"--target {_short(seen[stem])} and {_short(f)} have the same file name stem "
                                   f"{_short(stem)!s}: each fit goes to OUT/<target file name stem>/, so one would "
                                   f"overwrite the other (hint: rename one)")
            seen[stem] = f
    outs = [Path(out_dir)] if len(targets) == 1 else [Path(out_dir) / stem for stem in stems]
    inputs = ([(base, "BASE")] + [(str(f), "--target") for f in files]
              + ([(catalog_path, "--catalog")] if catalog_path else []))
    plans = [_output_plan(out, rec0.name, inputs) for out in outs]  # before any work: never over BASE or a target
    try:
        version = open_store(store, rec0, n, raw)
    except StoreError as exc:
        raise FlakedbError(str(exc)) from exc
    if len(targets) == 1:
        res = _fit_one(doc, base, params, targets[0], outs[0], plans[0], observer, illuminant, weight_items, scheme,
                       max_nfev, n, catalog, version, raw, store, texture_tol)
        if not res.reached:
            raise SystemExit(1)
        return
    results = []
    for k, (t, out, plan) in enumerate(zip(targets, outs, plans), 1):
        click.echo(f"--- target {k}/{len(targets)}: {t.source}")
        results.append(_fit_one(doc, base, params, t, out, plan, observer, illuminant, weight_items, scheme,
                                max_nfev, n, catalog, version, raw, store, texture_tol))
    click.echo(f"{'target':<32} {'max dE00 start':>14} {'max dE00 fit':>13}  reached  at a bound")
    for t, r in zip(targets, results):
        click.echo(f"{str(t.source)[-32:]:<32} {r.de_start.max():>14.3f} {r.de_fit.max():>13.3f}  "
                   f"{'yes' if r.reached else 'NO ':<7}  {', '.join(n_ for n_, _, _ in r.at_bound) or '-'}")
    n_bad = sum(not r.reached for r in results)
    click.echo(f"{len(results) - n_bad} of {len(results)} target(s) reached")
    if n_bad:
        raise SystemExit(1)


def _short(text, limit=100) -> str:
    t = str(text)
    return t if len(t) <= limit else t[:limit - 3] + "..."


def _output_plan(out_dir, name, inputs):
    """The checked plan of one fit's six outputs in ``out_dir``: ``(plan, paths)`` (:class:`flakedb.outputs.OutputPlan`)."""
    plan = output_plan(out_dir, name, inputs)   # NAME.bsdf/.h5/.json, then the fit's own files
    paths = {k: plan.in_dir(out_dir, f"{name}{suffix}", f"output NAME{suffix}")
             for k, suffix in (("yaml", FITTED_SUFFIX), ("csv", "-prediction.csv"), ("json", "-match.json"))}
    check_plan(plan)
    return plan, paths


def _fit_one(doc, base, params, target, out, planned, observer, illuminant, weight_items, scheme, max_nfev, n, catalog,
             version, raw, store, texture_tol=DEFAULT_TEXTURE_TOLERANCE):
    """One fit and its files, all together or none (module docstring); returns the MatchResult."""
    plan, paths = planned
    w = np.ones(len(target.geometries))
    for k, v in weight_items.items():
        hit = [i for i, g in enumerate(target.geometries) if geometry_key(g) == k]
        if not hit:
            raise FlakedbError(f"--weight {'/'.join(f'{x:g}' for x in k)}: the target has no such geometry")
        w[hit] = v
    click.echo(f"match {doc.get('name')}: {len(params)} parameter(s), {len(target.geometries)} geometries"
               + (f" and {len(target.texture)} texture indices" if target.texture else "") + f" from "
               f"{target.source}; store: {store if version is not None else 'none (optics computed directly)'}")
    try:
        res = cm.match(doc, target, observer=observer, illuminant=illuminant, weights=w, n=n, catalog=catalog,
                       store=version, raw=raw, log=lambda s: click.echo(f"  {s}", err=True), max_nfev=max_nfev,
                       source=base, tolerance=scheme, texture_tolerance=texture_tol)
    except (RecipeError, StoreError, TargetError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    click.echo(cm.format_match(res))
    record = cm.match_report(res)
    if not res.reached and res.tolerance is not None:   # which direction no free parameter moves, and who moves it
        try:
            adv = advise(res, catalog, version, raw, log=lambda s: click.echo(f"  {s}", err=True))
        except StoreError as exc:
            raise FlakedbError(str(exc)) from exc
        for line in adv.lines():
            click.echo(line)
        record["advice"] = adv.record()
    name = res.fitted_doc["name"]
    text = (f"# fitted by flakedb match to {target.source} ({res.observer}° / {res.illuminant}); "
            f"max dE00 {res.de_fit.max():.3f}\n" + yaml.safe_dump(res.fitted_doc, sort_keys=False, allow_unicode=True))
    rec = cm.recipe_from_doc(res.fitted_doc, str(paths["yaml"]), catalog)
    p = res.prediction
    spectral = p.mode == "spectral"
    with remove_created_dirs(out), plan.staged() as stage:   # every output or none
        stage_dir = stage.dir_for(out)
        try:
            compose_recipe(rec, stage_dir, n=res.n, raw=raw, catalog=catalog, store=version,
                           colour_settings=resolve(res.observer, res.illuminant, mode=rec.mode))
        except StoreError as exc:
            raise FlakedbError(str(exc)) from exc
        Path(stage.path(paths["yaml"])).write_text(text, encoding="utf-8")
        write_target(stage.path(paths["csv"]), p.geometries, lab=None if spectral else res.lab_fit,
                     reflectance=p.rf if spectral else None, wavelength_nm=p.wavelength_nm if spectral else None,
                     observer=res.observer, illuminant=res.illuminant, name=name,
                     notes={"generator": f"flakedb match, n = {res.n}, mode {p.mode}"},
                     texture={r["index"]: r["predicted"] for r in res.texture_fit} or None,
                     texture_observer=target.texture_observer)
        stage.path(paths["json"]).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    final = [out / f"{name}{suffix}" for suffix in OUTPUT_SUFFIXES]
    click.echo(f"wrote {paths['yaml']} (fitted recipe), {final[0]}, {final[1]}, {final[2]}, {paths['csv']} and "
               f"{paths['json']}")
    click.echo(res.outcome)
    return res
