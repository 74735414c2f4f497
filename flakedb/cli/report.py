"""`flakedb report RECIPE --target T --out DIR`: a one-page QC report (PDF, and a PNG of the same page).

Thin: the prediction is :func:`flakedb.match.fit.predict` at the target's geometries (as ``compare``), the
differences and limits :class:`flakedb.colour.tolerance.PerAngleLimits` in ``--formula``, the tolerance bands
:func:`flakedb.colour.bands.coordinate_bands`, the texture indices :func:`flakedb.match.fit.compare_texture`
(a target with texture columns) or :func:`flakedb.match.texture.predict_texture` (the indices compose's
report gives, for the default observer), the page :mod:`flakedb.render.qc_report`.  Writes
DIR/RECIPE--TARGET-qc.pdf and DIR/RECIPE--TARGET-qc.png together or not at all
(:class:`flakedb.outputs.OutputPlan`, checked before any work).  Exit status 1 when the verdict is FAIL
(the report is still written), 2 for an error.
"""

import math
from pathlib import Path

import click
import numpy as np

from flakedb.cli.compare import formula, open_store, parse_limits
from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan, remove_created_dirs
from flakedb.cli.options import check_node_count, prediction_options
from flakedb.colour.bands import coordinate_bands
from flakedb.colour.settings import DEFAULT_MAX_DE00, for_target
from flakedb.colour.tolerance import PerAngleLimits, shade_words
from flakedb.match.cxf import load_target
from flakedb.match.fit import compare_texture, predict
from flakedb.match.targets import TargetError
from flakedb.match.texture import DEFAULT_TEXTURE_OBSERVER, DEFAULT_TEXTURE_TOLERANCE, predict_texture
from flakedb.outputs import OutputPlan
from flakedb.paint.catalog import CatalogError, default_catalog_path, load_catalog
from flakedb.paint.recipe import RecipeError, load_recipe
from flakedb.render.qc_report import QCPage, write_qc_report
from flakedb.store.versions import StoreError

#: The texture indices reported for a target without texture columns (those ``compare --with-texture`` writes).
REPORT_TEXTURE_COLUMNS = tuple(f"{k}_{a:g}" for k in ("sparkle_area", "sparkle_intensity", "glints_per_mm2")
                               for a in (15.0, 45.0, 75.0)) + ("graininess",)


def report_name(recipe, target) -> str:
    """The stem of the report's files: ``RECIPE--TARGET-qc``, every character outside letters, digits and
    ``-_.`` replaced by ``_``, each part cut to 80 characters (always a plain file name).

    >>> report_name("silver 2", "A-17")
    'silver_2--A-17-qc'
    """
    def safe(text):
        return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(text))[:80].strip(".") or "x"

    return f"{safe(recipe)}--{safe(target)}-qc"


def texture_rows(rec, pred, target, texture_tol):
    """(rows for :class:`flakedb.render.qc_report.QCPage`, note): the target's texture columns compared, or
    the default columns predicted (no target values)."""
    if target.texture:
        rows, sparkle = compare_texture(rec, pred, target, texture_tol)
        note = "" if sparkle else "the recipe has no flakes the texture model can use: zero sparkle predicted"
        return rows, note + (f"; {target.texture_observer} observer" if note else f"{target.texture_observer} observer, "
                             f"tolerance {texture_tol:.0%} or the index's floor")
    values, rep = predict_texture(rec, list(REPORT_TEXTURE_COLUMNS), DEFAULT_TEXTURE_OBSERVER, pred.ground)
    if not rep["sparkle"]:
        return [], rep.get("summary", "no sparkle predicted")
    rows = [{"index": k, "predicted": v, "target": None, "tolerance": None, "passed": None} for k, v in values.items()]
    return rows, f"predicted ({DEFAULT_TEXTURE_OBSERVER} observer); the target has no texture columns"


@click.command()
@click.argument("recipe", type=click.Path(dir_okay=False))
@click.option("--target", "target_path", required=True, type=click.Path(dir_okay=False),
              help="Target CSV (docs/colour-matching.md) or a CxF3 file (*.cxf) with multi-angle values.")
@click.option("--cxf-object", "cxf_object", default=None,
              help="With a .cxf target: the object (Name or Id), when the file has several.")
@click.option("--out", "out_dir", default="out", show_default=True, type=click.Path(file_okay=False),
              help="Output folder of RECIPE--TARGET-qc.pdf and RECIPE--TARGET-qc.png.")
@click.option("--observer", default=None, help="2 or 10 (default: the target's).")
@click.option("--illuminant", default=None, help="D65, A, F11, ... (default: the target's).")
@click.option("--formula", "formula_text", default="de00", show_default=True,
              help="Colour-difference formula of the limits: de00 (de00:kL:kC:kH), de94 (de94:textiles), cmc "
                   "(cmc:l:c), din99 (din99:textiles) or deab (docs/colour-tolerances.md).")
@click.option("--max-de", "max_de", default=DEFAULT_MAX_DE00, show_default=True, type=float,
              help="ΔE limit (in --formula) at every geometry (a policy you choose).")
@click.option("--limit", "limits", multiple=True,
              help="Per-geometry ΔE limit, ASPECULAR=V (45° illumination), ILLUM/ASPECULAR=V or ILLUM/ASPECULAR/AZIMUTH=V (out of plane); repeatable.")
@click.option("--texture-tolerance", "texture_tol", default=DEFAULT_TEXTURE_TOLERANCE, show_default=True, type=float,
              help="Relative tolerance of the target's texture columns, with a floor per index (docs/texture.md §9).")
@prediction_options
def report(recipe, target_path, cxf_object, out_dir, observer, illuminant, formula_text, max_de, limits, texture_tol,
           n, store, raw, catalog_path):
    """Write a one-page QC report of RECIPE against the target: a PDF and a PNG of the same page.

    L*, a*, b* against the aspecular angle with the target and the tolerance band, ΔE per geometry
    against its limit, the a*b* travel, the spectra per geometry, the texture indices and the verdict.
    Exit status 1 when the verdict is FAIL (the report is written)."""
    check_node_count(n)
    if not (math.isfinite(max_de) and max_de >= 0):
        raise FlakedbError(f"--max-de {max_de}: a ΔE limit is a finite number ≥ 0 (e.g. --max-de 1)")
    if not (math.isfinite(texture_tol) and texture_tol > 0):
        raise FlakedbError(f"--texture-tolerance {texture_tol}: a relative tolerance is a finite number > 0 "
                           f"(e.g. 0.1 for 10 %)")
    scheme = PerAngleLimits(default=max_de, limits=parse_limits(limits), formula=formula(formula_text))
    try:
        catalog = load_catalog(catalog_path)
        rec = load_recipe(recipe, catalog)
        target = load_target(target_path, observer, illuminant, cxf_object)
    except (RecipeError, CatalogError, TargetError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    plan = OutputPlan()
    plan.add_input(recipe, "RECIPE")
    plan.add_input(target_path, "--target")
    plan.add_input(catalog_path if catalog_path is not None else default_catalog_path(), "--catalog")
    plan.add_dir(out_dir, "--out")
    stem = report_name(rec.name, target.label)
    pdf = plan.in_dir(out_dir, f"{stem}.pdf", "report PDF")
    png = plan.in_dir(out_dir, f"{stem}.png", "report PNG")
    check_plan(plan)   # every output, before any work
    try:
        version = open_store(store, rec, n, raw)
        pred = predict(rec, target.geometries, n, catalog, version, raw)
        cs = for_target(pred.mode, target, observer, illuminant)
        lab = pred.lab(cs.observer, cs.illuminant)
        lab_t = target.lab_under(cs.observer, cs.illuminant)
        tex, tex_note = texture_rows(rec, pred, target, texture_tol)
    except (StoreError, TargetError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    if cs.note:
        click.echo(f"note: {cs.note}", err=True)
    geoms = np.asarray(target.geometries, float)
    ev = scheme.evaluate(geoms, lab_t, lab)
    spectral = pred.mode == "spectral"
    page = QCPage(recipe=rec.name, target=target.label, geometries=geoms, lab=lab, lab_target=lab_t,
                  formula=ev["formula"], de=ev["value"], limit=ev["limit"], passed=ev["passed"],
                  band=coordinate_bands(scheme.formula, lab_t, ev["limit"]), shade=shade_words(lab_t, lab),
                  conditions=f"{cs.illuminant}/{cs.observer}°, n = {pred.n}, {pred.mode}",
                  wavelength_nm=pred.wavelength_nm if spectral else None, reflectance=pred.rf if spectral else None,
                  target_wavelength_nm=target.wavelength_nm if target.spectral else None,
                  target_reflectance=target.reflectance if target.spectral else None, texture=tex,
                  texture_note=tex_note)
    with remove_created_dirs(out_dir), plan.staged() as stage:   # both files or neither
        write_qc_report(page, stage.path(pdf), stage.path(png))
    click.echo(f"report {rec.name} vs {target.label} ({cs.observer}° / {cs.illuminant}, {ev['formula']})")
    click.echo(page.summary())
    click.echo(f"wrote {pdf} and {png}")
    if page.verdict != "PASS":
        raise SystemExit(1)
