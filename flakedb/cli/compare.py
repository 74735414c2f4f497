"""`flakedb compare RECIPE --target T.csv`: a recipe's predicted multi-angle colour against a target.

Several recipes and/or targets (files or folders, or ``--pairs LIST.csv``) make a batch: each recipe
composed once, compared with every target (:mod:`flakedb.match.batch`), one summary table;
``--table`` writes the per-geometry table, ``--plot DIR`` a figure per comparison
(:func:`flakedb.render.plots.plot_multiangle`).

Thin: prediction in :mod:`flakedb.match.fit`, differences and tolerances in
:mod:`flakedb.colour.tolerance`, the CSV layout in :mod:`flakedb.match.targets`
(docs/colour-matching.md).  Exit status 1 when a geometry fails its limit.

A target with texture columns (sparkle_area_<deg>, sparkle_intensity_<deg>, glints_per_mm2_<deg>,
graininess: :mod:`flakedb.match.texture`, docs/texture.md §9) is also compared on them: one line per
index with the predicted and target values, their difference and tolerance (``--texture-tolerance``);
an index outside it fails the comparison like a geometry.  ``--write-csv P.csv --with-texture`` writes
the predicted texture columns into the prediction, so it can serve as such a target.
"""

import math
from pathlib import Path

import click
import numpy as np

from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan, remove_created_dirs
from flakedb.cli.options import check_node_count, prediction_options
from flakedb.colour.geometry import cells as geometry_cells
from flakedb.colour.geometry import compact
from flakedb.colour.geometry import key as geometry_key
from flakedb.colour.settings import (
    DEFAULT_GEOMETRY_SET,
    DEFAULT_ILLUMINANT,
    DEFAULT_MAX_DE00,
    DEFAULT_OBSERVER,
    GEOMETRY_SETS,
    for_target,
)
from flakedb.colour.tolerance import PerAngleLimits, lab_differences, lch, metamerism_index, parse_formula, shade_words
from flakedb.solve.resolution import resolve_node_count
from flakedb.solve.store_context import StoreContext
from flakedb.match import batch
from flakedb.match.cxf import load_target
from flakedb.match.cxf_write import format_cxf
from flakedb.match.fit import compare_texture, predict
from flakedb.match.targets import TargetError, format_target
from flakedb.match.texture import (
    DEFAULT_TEXTURE_OBSERVER,
    DEFAULT_TEXTURE_TOLERANCE,
    format_texture_rows,
    predict_texture,
)
from flakedb.outputs import OutputPlan
from flakedb.paint.catalog import CatalogError, default_catalog_path, load_catalog
from flakedb.paint.mapping import catalog_species
from flakedb.paint.recipe import RecipeError, load_recipe
from flakedb.render.plots import plot_multiangle
from flakedb.store.versions import StoreError


def parse_limits(items, option="--limit"):
    """``ILLUM/ASPEC=VALUE``, ``ASPEC=VALUE`` (illumination 45°) or ``ILLUM/ASPEC/AZIMUTH=VALUE`` (out of plane)
    → {geometry key: value} (:func:`flakedb.colour.geometry.key`).

    >>> parse_limits(["45/15=1.5", "110=2", "45/25/90=3"])
    {(45.0, 15.0): 1.5, (45.0, 110.0): 2.0, (45.0, 25.0, 90.0): 3.0}
    """
    out = {}
    for it in items:
        try:
            geo, val = it.split("=")
            parts = [float(x) for x in geo.split("/")]
            if len(parts) > 3:
                raise ValueError(it)
            g = (45.0, parts[0]) if len(parts) == 1 else tuple(parts)
            value = float(val)
            if not all(math.isfinite(x) for x in g + (value,)) or value < 0:
                raise ValueError(it)
            out[geometry_key(g)] = value
        except ValueError:
            raise FlakedbError(f"{option} {it}: write ASPECULAR=V (45° illumination), ILLUM/ASPECULAR=V or, out of "
                               f"plane, ILLUM/ASPECULAR/AZIMUTH=V with finite angles and V ≥ 0, e.g. {option} 15=1.2 "
                               f"{option} 15/-15=2 {option} 45/25/90=2") from None
    return out


def formula(text):
    """The --formula's :class:`flakedb.colour.tolerance.Formula`; a FlakedbError naming the forms otherwise."""
    try:
        return parse_formula(text)
    except ValueError as exc:
        raise FlakedbError(f"--formula: {exc}") from None


def open_store(store, recipe, n=None, raw=False, verify=True):
    """The store version serving ``recipe`` at its node count (``n`` or the recipe's own) when ``store``
    is given and the recipe has catalogue species, else None: the newest complete version that serves
    it (``StoreContext.open_for_recipe``, as compose), with the files the recipe reads verified (V's
    order chunks as they are read)."""
    if store is None or not catalog_species(recipe):
        return None
    ctx = StoreContext.open_for_recipe(str(store), recipe, resolve_node_count(recipe, n)[0], raw)
    if verify:
        ctx.version.verify(ctx.prefixes(recipe))
    return ctx.version


@click.command()
@click.argument("recipes", nargs=-1, type=click.Path())
@click.option("--target", "target_paths", multiple=True, type=click.Path(),
              help="Target CSV (docs/colour-matching.md): illumination_deg,aspecular_deg, then L*,a*,b* or R_<nm>; "
                   "or a CxF3 file (*.cxf) with multi-angle values; or a folder of them.  Repeatable: several "
                   "recipes and/or targets make a batch (every recipe against every target, one table).")
@click.option("--pairs", "pairs_path", default=None, type=click.Path(dir_okay=False),
              help="Batch from a CSV list with header recipe,target[,cxf_object]: only the listed pairs.")
@click.option("--cxf-object", "cxf_object", default=None,
              help="With a .cxf target: the object (Name or Id) to compare with, when the file has several.")
@click.option("--observer", default=None, help=f"2 or 10 (default: the target's, else {DEFAULT_OBSERVER}).")
@click.option("--illuminant", default=None, help=f"D65, A, F11, ... (default: the target's, else {DEFAULT_ILLUMINANT}).")
@click.option("--metamerism", "mi_illuminant", default=None,
              help="Also report the metamerism index (CIEDE2000) for a change from --illuminant to this one "
                   "(needs a spectral target and a spectral recipe).")
@click.option("--formula", "formula_text", default="de00", show_default=True,
              help="Colour-difference formula of --max-de / --limit: de00 (de00:kL:kC:kH, e.g. de00:2:1:1), de94 "
                   "(de94:textiles), cmc (= cmc:2:1; cmc:l:c), din99 (din99:textiles) or deab "
                   "(docs/colour-tolerances.md).")
@click.option("--max-de", "max_de", default=DEFAULT_MAX_DE00, show_default=True, type=float,
              help="ΔE limit (in --formula) at every geometry (a policy you choose; not a standard's number).")
@click.option("--limit", "limits", multiple=True,
              help="Per-geometry ΔE limit (in --formula), ASPECULAR=V (45° illumination), ILLUM/ASPECULAR=V or ILLUM/ASPECULAR/AZIMUTH=V (out of plane); "
                   "repeatable.")
@click.option("--geometries", "geometry_set", default=DEFAULT_GEOMETRY_SET, show_default=True,
              type=click.Choice(list(GEOMETRY_SETS)),
              help="Without --target: the geometries to predict (E2194: 45° illumination; E2539 adds 15°; xrite19 "
                   "adds eight out of plane).")
@click.option("--write-cxf", "cxf_out", default=None, type=click.Path(dir_okay=False),
              help="Write the prediction (multi-angle spectra and CIELAB under the comparison's conditions) as a "
                   "CxF3 file that flakedb and QC software read as a target; one recipe.")
@click.option("--write-csv", "csv_out", default=None, type=click.Path(dir_okay=False),
              help="Write the prediction in the target CSV layout (so it can serve as a target); one recipe.")
@click.option("--table", "table_out", default=None, type=click.Path(dir_okay=False),
              help="Write the per-geometry table (recipe, target, geometry, L*a*b*, dL*, dC*, dH*, dE00, pass, C*, h°, "
                   "the --formula's ΔE, shade words) as CSV.")
@click.option("--plot", "plot_dir", default=None, type=click.Path(file_okay=False),
              help="Write a figure per comparison into this folder: L*, a*, b* vs aspecular angle with the target, "
                   "a*b* travel, reflectance curves.")
@click.option("--plot-format", "plot_format", default="png", show_default=True, type=click.Choice(["png", "pdf", "svg"]))
@click.option("--texture-tolerance", "texture_tol", default=DEFAULT_TEXTURE_TOLERANCE, show_default=True, type=float,
              help="Relative tolerance of a target's texture columns (sparkle_area_<deg>, sparkle_intensity_<deg>, "
                   "glints_per_mm2_<deg>, graininess), with a floor per index (docs/texture.md §9).")
@click.option("--with-texture", "with_texture", is_flag=True,
              help=f"With --write-csv: also write the predicted texture columns ({DEFAULT_TEXTURE_OBSERVER} "
                   f"observer, light at 15/45/75°, and graininess).")
@prediction_options
def compare(recipes, target_paths, pairs_path, cxf_object, observer, illuminant, mi_illuminant, formula_text, max_de,
            limits,
            geometry_set, cxf_out, csv_out, table_out, plot_dir, plot_format, texture_tol, with_texture, n, store, raw,
            catalog_path):
    """Predict each RECIPE's colour at the target's geometries and compare: dL*, dC*, dH*, ΔE, pass/fail.

    RECIPES: recipe YAML files or folders of them.  Exit status 1 when a geometry fails its limit."""
    check_node_count(n)
    if not recipes and pairs_path is None:
        raise FlakedbError("give a RECIPE (or a folder of recipes, or --pairs LIST.csv)")
    if not target_paths and csv_out is None and cxf_out is None and pairs_path is None and table_out is None:
        raise FlakedbError("give --target T.csv (compare) and/or --write-csv P.csv / --write-cxf P.cxf / --table T.csv "
                           "(write the prediction)")
    if not (math.isfinite(max_de) and max_de >= 0):
        raise FlakedbError(f"--max-de {max_de}: a ΔE00 limit is a finite number ≥ 0 (e.g. --max-de 1)")
    if not (math.isfinite(texture_tol) and texture_tol > 0):
        raise FlakedbError(f"--texture-tolerance {texture_tol}: a relative tolerance is a finite number > 0 "
                           f"(e.g. 0.1 for 10 %)")
    if with_texture and csv_out is None:
        raise FlakedbError("--with-texture adds texture columns to --write-csv P.csv: give --write-csv")
    scheme = PerAngleLimits(default=max_de, limits=parse_limits(limits), formula=formula(formula_text))  # before work
    try:
        recipe_files = batch.expand_paths(recipes, (".yaml", ".yml"))
        target_files = batch.expand_paths(target_paths, (".csv", ".cxf"))
    except ValueError as exc:
        raise FlakedbError(str(exc)) from exc
    outputs = (recipe_files, target_files, pairs_path, catalog_path, csv_out, table_out, plot_dir)
    _check_outputs(*outputs, cxf_out=cxf_out)   # at once: the figures' names are known when the recipes and targets are read
    if pairs_path is not None or len(recipe_files) > 1 or len(target_files) > 1:
        if csv_out or cxf_out or mi_illuminant:
            raise FlakedbError("--write-csv, --write-cxf and --metamerism take one recipe and one target; a batch "
                               "writes --table")
        return _compare_batch(recipe_files, target_files, pairs_path, cxf_object, observer, illuminant, scheme,
                              geometry_set, table_out, plot_dir, plot_format, n, store, raw, catalog_path,
                              texture_tol, outputs)
    recipe = str(recipe_files[0])
    target_path = str(target_files[0]) if target_files else None

    try:
        catalog = load_catalog(catalog_path)
        rec = load_recipe(recipe, catalog)
        target = load_target(target_path, observer, illuminant, cxf_object) if target_path else None
        version = open_store(store, rec, n, raw)
    except (RecipeError, CatalogError, TargetError, StoreError) as exc:
        raise FlakedbError(str(exc)) from exc
    plan = _check_outputs(*outputs, figures=[(rec.name, None if target is None else _target_label(target))],
                          plot_format=plot_format, cxf_out=cxf_out)   # every output, before any work
    geoms = target.geometries if target is not None else compact(GEOMETRY_SETS[geometry_set])
    try:
        pred = predict(rec, geoms, n, catalog, version, raw)
        cs = for_target(pred.mode, target, observer, illuminant, geometry_set)
        obs, ill = cs.observer, cs.illuminant
        lab = pred.lab(obs, ill)
    except (StoreError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    cxf = None
    if cxf_out is not None:   # formatted before any file is written: what CxF3 cannot hold writes nothing
        sp = pred.mode == "spectral"
        try:
            cxf = (cxf_out, format_cxf(geoms, lab, pred.rf if sp else None, pred.wavelength_nm if sp else None, obs,
                                       ill, rec.name, f"flakedb compare prediction, n = {pred.n}, mode {pred.mode}"),
                   f"prediction as CxF3: {len(geoms)} geometries, " + ("spectra and CIELab" if sp else "CIELab"))
        except ValueError as exc:
            raise FlakedbError(f"--write-cxf {cxf_out}: {exc}") from None
    if cs.note:
        click.echo(f"note: {cs.note}", err=True)
    click.echo(f"compare {rec.name} ({pred.mode}, n = {pred.n}; {obs}° observer, {ill})"
               + (f" with {target.source}" if target else ""))
    if csv_out:
        spectral = pred.mode == "spectral"
        tex = None
        if with_texture:
            names = [f"{k}_{a:g}" for k in ("sparkle_area", "sparkle_intensity", "glints_per_mm2")
                     for a in (15.0, 45.0, 75.0)] + ["graininess"]
            tex = predict_texture(rec, names, DEFAULT_TEXTURE_OBSERVER, pred.ground)[0]
            dropped = [k for k, v in tex.items() if v is None]
            if dropped:  # outside the texture model (flakedb.texture.model.graininess_indices): no number to write
                click.echo(f"note: {', '.join(dropped)} not predicted for {rec.name} (the hiding term cancels the "
                           f"single-flake term, docs/texture.md §4): left out of --write-csv", err=True)
                tex = {k: v for k, v in tex.items() if v is not None}
        csv = (csv_out, format_target(geoms, lab=None if spectral else lab, reflectance=pred.rf if spectral else None,
                                      wavelength_nm=pred.wavelength_nm if spectral else None, observer=obs,
                                      illuminant=ill, name=rec.name,
                                      notes={"generator": f"flakedb compare, n = {pred.n}, mode {pred.mode}"},
                                      texture=tex, texture_observer=DEFAULT_TEXTURE_OBSERVER),
               "prediction in the target layout" + (", with texture columns" if tex else ""))
    else:
        csv = None
    if target is None:
        click.echo(f"{'illum':>6} {'aspec':>6} {'L*':>8} {'a*':>8} {'b*':>8}")
        for g, v in zip(geoms, lab):
            click.echo(f"{geometry_cells(g)} {v[0]:8.2f} {v[1]:8.2f} {v[2]:8.2f}")
        comp = batch.Comparison(rec.name, None, compact(geoms), lab, None, obs, ill, None, None, pred)
        _outputs(plan, [comp], table_out, plot_dir, plot_format, csv, cxf)
        return
    try:
        lab_t = target.lab_under(obs, ill)
    except TargetError as exc:
        raise FlakedbError(str(exc)) from exc
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
    lch_t, lch_s, words = lch(lab_t), lch(lab), shade_words(lab_t, lab)
    click.echo(f"{'illum':>6} {'aspec':>6} | {'target L*  a*  b*  C*  h°':>36} | {'recipe L*  a*  b*  C*  h°':>36} | "
               f"{'dL*':>6} {'dC*':>6} {'dH*':>6} {ev['formula']:>7} {'limit':>6}  ok  shade"
               + (f"  MI({ill}->{mi_illuminant})" if mi is not None else ""))
    for i, g in enumerate(geoms):
        lt, ls = lab_t[i], lab[i]
        click.echo(f"{geometry_cells(g)} | {lt[0]:6.2f} {lt[1]:7.2f} {lt[2]:7.2f} {lch_t[i, 1]:6.2f} {lch_t[i, 2]:6.1f} | "
                   f"{ls[0]:6.2f} {ls[1]:7.2f} {ls[2]:7.2f} {lch_s[i, 1]:6.2f} {lch_s[i, 2]:6.1f} | {d['dL'][i]:+6.2f} "
                   f"{d['dC'][i]:+6.2f} {d['dH'][i]:+6.2f} {ev['value'][i]:7.2f} {ev['limit'][i]:6.2f}  "
                   f"{'yes' if ev['passed'][i] else 'NO '}  {words[i]}" + (f"  {mi[i]:.3f}" if mi is not None else ""))
    n_fail = int(np.sum(~ev["passed"]))
    tex, sparkle = compare_texture(rec, pred, target, texture_tol)
    if tex:
        click.echo(f"texture ({target.texture_observer} observer; tolerance {texture_tol:.0%} of the target or the "
                   f"index's floor, docs/texture.md §9):")
        for line in format_texture_rows(tex, sparkle):
            click.echo(line)
    t_fail = sum(not r["passed"] for r in tex)
    comp = batch.Comparison(rec.name, _target_label(target), np.asarray(geoms, float), lab, lab_t, obs, ill, ev,
                            d, pred, target.reflectance, target.wavelength_nm, tex, sparkle)
    _outputs(plan, [comp], table_out, plot_dir, plot_format, csv, cxf)
    verdict = "pass" if ev["passed_all"] else f"FAIL at {n_fail} geometr" + ("y" if n_fail == 1 else "ies")
    if tex:
        verdict += "; texture " + ("pass" if not t_fail else f"FAIL at {t_fail} of {len(tex)} indices")
    click.echo(f"{ev['scheme']}: {verdict}")
    if not comp.passed:
        raise SystemExit(1)


def _safe(name) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(name))[:80] or "x"


def figure_name(recipe, target, plot_format) -> str:
    """The --plot file name of a comparison: ``RECIPE--TARGETSTEM.FORMAT`` (``RECIPE.FORMAT`` without a target),
    every character outside letters, digits and ``-_.`` replaced by ``_`` and each part cut to 80 characters: always
    a plain file name (two comparisons that get one name are refused by the output plan, before any work).

    >>> figure_name("good", "panels/a b.csv", "png"), figure_name("x", None, "svg")
    ('good--a_b.png', 'x.svg')
    """
    return _safe(recipe) + ("" if target is None else f"--{_safe(Path(str(target)).stem)}") + f".{plot_format}"


def _target_label(t):
    return t.label


def _check_outputs(recipe_files, target_files, pairs_path, catalog_path, csv_out, table_out, plot_dir=None,
                   figures=(), plot_format="png", cxf_out=None):
    """The output plan of compare, checked before any work (:class:`flakedb.outputs.OutputPlan`): --write-csv,
    --table, the table's texture companion and every --plot figure (``figures``: (recipe name, target label or
    None) per comparison) are never a recipe, a target, the --pairs list or a file it names, the catalogue (given
    or default) or one another, and --plot is a folder that can be written.  Returns the plan (None: no output)."""
    if csv_out is None and table_out is None and plot_dir is None and cxf_out is None:
        return None
    plan = OutputPlan()
    for path in recipe_files:
        plan.add_input(path, "RECIPE")
    for path in target_files:
        plan.add_input(path, "--target")
    plan.add_input(pairs_path, "--pairs")
    plan.add_input(catalog_path if catalog_path is not None else default_catalog_path(), "--catalog")
    if pairs_path is not None:
        try:
            for r, t, _ in batch.read_pair_list(pairs_path):
                plan.add_input(r, "RECIPE (--pairs)")
                plan.add_input(t, "--target (--pairs)")
        except ValueError as exc:
            raise FlakedbError(str(exc)) from exc
    if csv_out is not None:
        plan.add_output(csv_out, "--write-csv")
    if cxf_out is not None:
        plan.add_output(cxf_out, "--write-cxf")
    if table_out is not None:
        plan.add_output(table_out, "--table")
        plan.add_output(batch.texture_table_path(table_out), "--table (texture rows)")
    if plot_dir is not None:
        plan.add_dir(plot_dir, "--plot")
        for rec, tgt in figures:
            plan.in_dir(plot_dir, figure_name(rec, tgt, plot_format),
                        f"--plot figure of {_short(rec)}" + ("" if tgt is None else f" vs {_short(tgt)}"))
    return check_plan(plan)


def _short(text, limit=60) -> str:
    t = str(text)
    return t if len(t) <= limit else t[:limit - 3] + "..."


def _outputs(plan, comparisons, table_out, plot_dir, plot_format, csv=None, cxf=None):
    """Write the --write-csv prediction (``csv``: (path, text, what)), the --write-cxf one (``cxf``: (path, bytes,
    what)), the --table CSV and the --plot figures of some
    comparisons, all together or none (``plan``: :func:`_check_outputs`'s, with every figure in it)."""
    if plan is None:
        return
    wrote = []
    with remove_created_dirs(plot_dir or "."), plan.staged() as stage:
        if csv is not None:
            stage.path(csv[0]).write_text(csv[1], encoding="utf-8")
            wrote.append(f"wrote {csv[0]} ({csv[2]})")
        if cxf is not None:
            stage.path(cxf[0]).write_bytes(cxf[1])
            wrote.append(f"wrote {cxf[0]} ({cxf[2]})")
        if table_out:
            batch.write_table(stage.path(table_out), comparisons)
            wrote.append(f"wrote {table_out} ({sum(len(c.geometries) for c in comparisons)} rows)")
            n_tex = len(batch.texture_rows(comparisons))
            if n_tex:
                wrote.append(f"wrote {batch.texture_table_path(table_out)} ({n_tex} texture rows)")
        if plot_dir:
            for c in comparisons:
                final = Path(plot_dir) / figure_name(c.recipe, c.target, plot_format)
                p = c.prediction
                spectral = p.mode == "spectral"
                tr = c.target_reflectance if spectral else None
                plot_multiangle(stage.path(final), c.geometries, c.lab_pred, c.lab_target,
                                p.wavelength_nm if spectral else None, p.rf if spectral else None, tr,
                                c.target_wavelength_nm if tr is not None else None,
                                title=_short(c.recipe) + ("" if c.target is None else f" vs {_short(c.target)}"),
                                conditions=f"{c.illuminant}/{c.observer}°", target_name=_short(c.target or "target"))
                wrote.append(f"wrote {final}")
    for line in wrote:
        click.echo(line)


def _compare_batch(recipe_files, target_files, pairs_path, cxf_object, observer, illuminant, scheme,
                   geometry_set, table_out, plot_dir, plot_format, n, store, raw, catalog_path,
                   texture_tol=DEFAULT_TEXTURE_TOLERANCE, outputs=None):
    """Every recipe against every target (or the --pairs list): one summary table; exit 1 when any fails."""
    try:
        catalog = load_catalog(catalog_path)
        if pairs_path is not None:
            listed = batch.read_pair_list(pairs_path)
            r_paths = list(dict.fromkeys([str(r) for r, _, _ in listed] + [str(r) for r in recipe_files]))
            t_keys = list(dict.fromkeys([(str(t), o) for _, t, o in listed]))
            pairs = [(r_paths.index(str(r)), t_keys.index((str(t), o))) for r, t, o in listed]
        else:
            r_paths = [str(r) for r in recipe_files]
            t_keys = [(str(t), cxf_object if str(t).lower().endswith(".cxf") else None) for t in target_files]
            pairs = None
        recs = [load_recipe(r, catalog) for r in r_paths]
        targets = [load_target(t, observer, illuminant, o) for t, o in t_keys]
        names = [r.name for r in recs]
        if len(set(names)) != len(names):
            dup = sorted({x for x in names if names.count(x) > 1})
            raise FlakedbError(f"recipes share a name ({', '.join(_short(x) for x in dup)}): give each recipe its own "
                               f"name: field")
        pair_list = pairs if pairs is not None else (
            [(i, j) for i in range(len(recs)) for j in range(len(targets))] if targets else
            [(i, None) for i in range(len(recs))])
        plan = None if outputs is None else _check_outputs(
            *outputs, plot_format=plot_format,
            figures=[(recs[i].name, None if j is None else _target_label(targets[j])) for i, j in pair_list])
        click.echo(f"compare: {len(recs)} recipe(s), {len(targets)} target(s)"
                   + (f", {len(pairs)} listed pair(s)" if pairs is not None else ""))
        comps = batch.compare_batch(recs, targets, pairs, observer, illuminant, scheme, geometry_set, n, catalog,
                                    store_for=(lambda r: open_store(store, r, n, raw)) if store else None, raw=raw,
                                    log=lambda s: click.echo(f"  {s}", err=True), texture_tolerance=texture_tol)
    except (RecipeError, CatalogError, TargetError, StoreError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    if not targets:
        rows = batch.long_rows(comps)
        click.echo(f"{'recipe':<28} {'illum':>6} {'aspec':>6} {'L*':>8} {'a*':>8} {'b*':>8}")
        for r in rows:
            click.echo(f"{r['recipe'][:28]:<28} {r['illumination_deg']:5g}° {r['aspecular_deg']:5g}° {r['L']:8.2f} "
                       f"{r['a']:8.2f} {r['b']:8.2f}")
        _outputs(plan, comps, table_out, plot_dir, plot_format)
        return
    summary = batch.summary_rows(comps)
    click.echo(f"{'recipe':<28} {'target':<28} {'max dE00':>9} {'max ' + scheme.formula.label:>14} {'worst':>10} "
               f"{'failed':>7} {'texture':>8}  ok")
    for r, c in zip(summary, [c for c in comps if c.differences is not None]):
        tx = "-" if r["texture_failed"] is None else f"{r['texture_failed']}/{len(c.texture)} NO" if r["texture_failed"] \
            else f"{len(c.texture)} ok"
        click.echo(f"{r['recipe'][:28]:<28} {str(r['target'])[:28]:<28} {r['max_dE00']:9.2f} {r['max_dE']:14.2f} "
                   f"{r['worst_geometry']:>10} "
                   f"{r['failed']:>4}/{r['geometries']:<2} {tx:>8}  {'yes' if r['passed'] else 'NO'}")
    _outputs(plan, comps, table_out, plot_dir, plot_format)
    n_fail = sum(1 for r in summary if not r["passed"])
    click.echo(f"{scheme.name}: {len(summary) - n_fail} of {len(summary)} pair(s) pass")
    if n_fail:
        raise SystemExit(1)
