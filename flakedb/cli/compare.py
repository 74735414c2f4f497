"""`flakedb compare RECIPE --target T.csv`: a recipe's predicted multi-angle colour against a target.

Thin: prediction in :mod:`flakedb.match.fit`, differences and tolerances in
:mod:`flakedb.colour.tolerance`, the CSV layout in :mod:`flakedb.match.targets`
(docs/colour-matching.md).  Exit status 1 when a geometry fails its limit.
"""

import math

import click
import numpy as np

from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan
from flakedb.cli.options import check_node_count, prediction_options
from flakedb.colour.tolerance import PerAngleLimits, lab_differences, metamerism_index
from flakedb.compose.store_context import StoreContext
from flakedb.match.cxf import load_target
from flakedb.match.fit import predict, resolution
from flakedb.match.targets import GEOMETRY_SETS, TargetError, write_target
from flakedb.outputs import OutputPlan
from flakedb.paint.catalog import CatalogError, load_catalog
from flakedb.paint.mapping import catalog_species
from flakedb.paint.recipe import RecipeError, load_recipe
from flakedb.store.versions import StoreError


def parse_limits(items, option="--limit"):
    """``ILLUM/ASPEC=VALUE`` or ``ASPEC=VALUE`` (illumination 45°) → {(illum, aspec): value}."""
    out = {}
    for it in items:
        try:
            geo, val = it.split("=")
            parts = geo.split("/")
            illum, asp = (45.0, float(parts[0])) if len(parts) == 1 else (float(parts[0]), float(parts[1]))
            value = float(val)
            if not all(math.isfinite(x) for x in (illum, asp, value)) or value < 0 or len(parts) > 2:
                raise ValueError(it)
            out[(illum, asp)] = value
        except ValueError:
            raise FlakedbError(f"{option} {it}: write ASPECULAR=V (45° illumination) or ILLUM/ASPECULAR=V with finite "
                               f"angles and V ≥ 0, e.g. {option} 15=1.2 {option} 15/-15=2") from None
    return out


def open_store(store, recipe, n=None, raw=False, verify=True):
    """The store version serving ``recipe`` at its node count (``n`` or the recipe's own) when ``store``
    is given and the recipe has catalogue species, else None: the newest complete version that serves
    it (``StoreContext.open_for_recipe``, as compose), with the files the recipe reads verified (V's
    order chunks as they are read)."""
    if store is None or not catalog_species(recipe):
        return None
    ctx = StoreContext.open_for_recipe(str(store), recipe, resolution(recipe, n), raw)
    if verify:
        ctx.version.verify(ctx.prefixes(recipe))
    return ctx.version


@click.command()
@click.argument("recipe", type=click.Path(dir_okay=False))
@click.option("--target", "target_path", default=None, type=click.Path(dir_okay=False),
              help="Target CSV (docs/colour-matching.md): illumination_deg,aspecular_deg, then L*,a*,b* or R_<nm>; "
                   "or a CxF3 file (*.cxf) with multi-angle values.")
@click.option("--cxf-object", "cxf_object", default=None,
              help="With a .cxf target: the object (Name or Id) to compare with, when the file has several.")
@click.option("--observer", default=None, help="2 or 10 (default: the target's, else 2).")
@click.option("--illuminant", default=None, help="D65, A, F11, ... (default: the target's, else D65).")
@click.option("--metamerism", "mi_illuminant", default=None,
              help="Also report the metamerism index (CIEDE2000) for a change from --illuminant to this one "
                   "(needs a spectral target and a spectral recipe).")
@click.option("--max-de", "max_de", default=1.0, show_default=True, type=float,
              help="dE00 limit at every geometry (a policy you choose; not a standard's number).")
@click.option("--limit", "limits", multiple=True,
              help="Per-geometry dE00 limit, ASPECULAR=V (45° illumination) or ILLUM/ASPECULAR=V; repeatable.")
@click.option("--geometries", "geometry_set", default="e2539", show_default=True,
              type=click.Choice(["e2194", "e2539"]),
              help="Without --target: the geometries to predict (E2194: 45° illumination; E2539 adds 15°).")
@click.option("--write-csv", "csv_out", default=None, type=click.Path(dir_okay=False),
              help="Write the prediction in the target CSV layout (so it can serve as a target).")
@prediction_options
def compare(recipe, target_path, cxf_object, observer, illuminant, mi_illuminant, max_de, limits, geometry_set, csv_out, n,
            store, raw, catalog_path):
    """Predict RECIPE's colour at the target's geometries and compare: dL*, dC*, dH*, dE00, pass/fail."""
    check_node_count(n)
    if not (math.isfinite(max_de) and max_de >= 0):
        raise FlakedbError(f"--max-de {max_de}: a ΔE00 limit is a finite number ≥ 0 (e.g. --max-de 1)")
    if target_path is None and csv_out is None:
        raise FlakedbError("give --target T.csv (compare) and/or --write-csv P.csv (write the prediction)")
    if csv_out is not None:  # the output plan, before any work: never onto the target, the recipe, the catalogue
        plan = OutputPlan()
        for path, label in ((recipe, "RECIPE"), (target_path, "--target"), (catalog_path, "--catalog")):
            plan.add_input(path, label)
        plan.add_output(csv_out, "--write-csv")
        check_plan(plan)

    try:
        catalog = load_catalog(catalog_path)
        rec = load_recipe(recipe, catalog)
        target = load_target(target_path, observer, illuminant, cxf_object) if target_path else None
        version = open_store(store, rec, n, raw)
    except (RecipeError, CatalogError, TargetError, StoreError) as exc:
        raise FlakedbError(str(exc)) from exc
    obs = observer or (target.observer if target else "2")
    ill = illuminant or (target.illuminant if target else "D65")
    geoms = target.geometries if target is not None else np.asarray(GEOMETRY_SETS[geometry_set])
    try:
        pred = predict(rec, geoms, n, catalog, version, raw)
        lab = pred.lab(obs, ill)
    except (StoreError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    click.echo(f"compare {rec.name} ({pred.mode}, n = {pred.n}; {obs}° observer, {ill})"
               + (f" with {target.source}" if target else ""))
    if csv_out:
        spectral = pred.mode == "spectral"
        write_target(csv_out, geoms, lab=None if spectral else lab, reflectance=pred.rf if spectral else None,
                     wavelength_nm=pred.wavelength_nm if spectral else None, observer=obs, illuminant=ill,
                     name=rec.name, notes={"generator": f"flakedb compare, n = {pred.n}, mode {pred.mode}"})
        click.echo(f"wrote {csv_out} (prediction in the target layout)")
    if target is None:
        click.echo(f"{'illum':>6} {'aspec':>6} {'L*':>8} {'a*':>8} {'b*':>8}")
        for g, v in zip(geoms, lab):
            click.echo(f"{g[0]:5g}° {g[1]:5g}° {v[0]:8.2f} {v[1]:8.2f} {v[2]:8.2f}")
        return
    try:
        lab_t = target.lab_under(obs, ill)
    except TargetError as exc:
        raise FlakedbError(str(exc)) from exc
    scheme = PerAngleLimits(default=max_de, limits=parse_limits(limits))
    d = lab_differences(lab_t, lab)
    ev = scheme.evaluate(geoms, lab_t, lab)
    mi = None
    if mi_illuminant:
        if not target.spectral or pred.mode != "spectral":
            raise FlakedbError("--metamerism needs spectral reflectance factors on both sides (R_ columns in the "
                               "target, a spectral-mode recipe)")
        R_pred = np.stack([np.interp(target.wavelength_nm, pred.wavelength_nm, r) for r in pred.rf])
        if target.wavelength_nm[0] < pred.wavelength_nm[0] or target.wavelength_nm[-1] > pred.wavelength_nm[-1]:
            raise FlakedbError(f"--metamerism: the recipe's bands {pred.wavelength_nm[0]:g}-{pred.wavelength_nm[-1]:g} nm "
                               f"do not cover the target's grid {target.wavelength_nm[0]:g}-"
                               f"{target.wavelength_nm[-1]:g} nm")
        mi = metamerism_index(target.reflectance, R_pred, target.wavelength_nm, obs, ill, mi_illuminant)
    click.echo(f"{'illum':>6} {'aspec':>6} | {'target L*  a*  b*':>22} | {'recipe L*  a*  b*':>22} | {'dL*':>6} "
               f"{'dC*':>6} {'dH*':>6} {'dE00':>6} {'limit':>6}  ok" + (f"  MI({ill}->{mi_illuminant})" if mi is not None else ""))
    for i, g in enumerate(geoms):
        lt, ls = lab_t[i], lab[i]
        click.echo(f"{g[0]:5g}° {g[1]:5g}° | {lt[0]:6.2f} {lt[1]:7.2f} {lt[2]:7.2f} | {ls[0]:6.2f} {ls[1]:7.2f} "
                   f"{ls[2]:7.2f} | {d['dL'][i]:+6.2f} {d['dC'][i]:+6.2f} {d['dH'][i]:+6.2f} {ev['value'][i]:6.2f} "
                   f"{ev['limit'][i]:6.2f}  {'yes' if ev['passed'][i] else 'NO'}"
                   + (f"  {mi[i]:.3f}" if mi is not None else ""))
    n_fail = int(np.sum(~ev["passed"]))
    click.echo(f"{ev['scheme']}: {'pass' if ev['passed_all'] else f'FAIL at {n_fail} geometr' + ('y' if n_fail == 1 else 'ies')}")
    if not ev["passed_all"]:
        raise SystemExit(1)
