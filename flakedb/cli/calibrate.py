"""`flakedb calibrate LADDER.yaml --out-catalog USER.yaml`: fit a species to measured panels.

Thin: the fit is :func:`flakedb.match.calibrate.calibrate` (docs/calibration.md).  Reads the ladder
manifest (recipes and their measured targets, CSV or CxF3), prints one progress line per iteration
on stderr, then the panels' ΔE00 before and after and the fitted parameters with their standard
errors, and writes USER.yaml: the base catalogue plus the calibrated species (atomically; nothing
is written when the fit fails).  Recipes use it with ``--catalog USER.yaml``.

``--tinter``: LADDER is a tinter ladder (``tinter: NAME``, optional Kubelka–Munk ``seed``, panels whose
recipes name NAME) and a new colourant is created instead (:func:`flakedb.match.tinter.fit_tinter`;
docs/calibration.md, "Tinters from drawdowns").

A ladder that names no panels is refused before any work, with one line and exit status 2:

>>> import tempfile
>>> from pathlib import Path
>>> from click.testing import CliRunner
>>> from flakedb.cli.main import cli
>>> where = Path(tempfile.mkdtemp())
>>> _ = (where / "ladder.yaml").write_text("species: cadmium-yellow\\nname: my-yellow\\npanels: []\\n")
>>> r = CliRunner().invoke(cli, ["calibrate", str(where / "ladder.yaml"), "--out-catalog", str(where / "u.yaml")])
>>> r.exit_code, r.output.startswith("Error: "), (where / "u.yaml").exists()
(2, True, False)
"""

import json
import re
from pathlib import Path

import click
import numpy as np

from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan
from flakedb.cli.options import check_node_count
from flakedb.match import calibrate as cal
from flakedb.match import tinter as tn
from flakedb.outputs import OutputPlan
from flakedb.paint.catalog import CatalogError, default_catalog_path, load_catalog
from flakedb.paint.recipe import RecipeError


@click.command()
@click.argument("ladder", type=click.Path(dir_okay=False))
@click.option("--out-catalog", "out_catalog", required=True, type=click.Path(dir_okay=False),
              help="User catalogue to write: the base catalogue plus the calibrated species.")
@click.option("--catalog", "catalog_path", default=None, type=click.Path(dir_okay=False, exists=True),
              help="Base particle catalogue (default: catalog/particles.yaml or $FLAKEDB_CATALOG).")
@click.option("--degree", default=cal.ABSORPTION_DEGREE, show_default=True, type=click.IntRange(0, 6),
              help="Pigments: degree of the Legendre series of ln(k factor).")
@click.option("--n", "n", default=None, type=int, help="Node count of the predictions (default: each recipe's).")
@click.option("--max-evaluations", "max_nfev", default=40, show_default=True, type=click.IntRange(1, 1000),
              help="Most residual evaluations of the least-squares solver.")
@click.option("--report", "report_path", default=None, type=click.Path(dir_okay=False),
              help="Also write the fit record as JSON.")
@click.option("--tinter", "tinter", is_flag=True, default=False,
              help="Create a new colourant (a tinter) from LADDER, a tinter ladder (docs/calibration.md, "
                   "'Tinters from drawdowns'), instead of adjusting a catalogue species.")
@click.option("--tinter-degree", "tinter_degree", default=None, type=click.IntRange(0, 12),
              help="Tinters: degree of the Legendre series of ln(sigma_a/phi) and ln(sigma_s'/phi) "
                   "[default: 6].")
def calibrate(ladder, out_catalog, catalog_path, degree, n, max_nfev, report_path, tinter, tinter_degree):
    """Calibrate a catalogue species from a masstone / let-down ladder (LADDER: a manifest YAML)."""
    check_node_count(n)
    if tinter:
        return _calibrate_tinter(ladder, out_catalog, catalog_path, tinter_degree, n, max_nfev, report_path)
    try:
        catalog = load_catalog(catalog_path)
        species, name, free, panels = cal.read_ladder(ladder)
        if not Path(out_catalog).parent.is_dir():
            raise ValueError(f"--out-catalog {out_catalog}: the folder {Path(out_catalog).parent} does not exist")
        plan = OutputPlan()  # before any work: the outputs are never an input (the base catalogue above all)
        plan.add_input(ladder, "LADDER")
        plan.add_input(catalog_path if catalog_path is not None else default_catalog_path(), "--catalog")
        for pn in panels:
            for q in pn.paths:
                plan.add_input(q, f"panel {pn.name}")
        plan.add_output(out_catalog, "--out-catalog")
        if report_path:
            plan.add_output(report_path, "--report")
        check_plan(plan)
        if name in catalog["particles"]:
            raise ValueError(f"{ladder}: name {name!r} is already a species of the base catalogue; choose another name")
        if species not in catalog["particles"]:
            raise ValueError(f"{ladder}: species {species!r} is not in the base catalogue "
                             f"({', '.join(catalog['particles'])})")
        if catalog["particles"][species]["kind"] == "tinter":
            raise ValueError(f"{ladder}: species {species!r} is a tinter: refit it from its drawdowns with "
                             f"`flakedb calibrate --tinter` (docs/calibration.md, 'Tinters from drawdowns')")
        click.echo(f"calibrate {species} -> {name}: {len(panels)} panel(s) from {ladder}")
        res = cal.calibrate(species, panels, catalog, free=free, degree=degree, n=n, max_nfev=max_nfev,
                            log=lambda s: click.echo(f"  {s}", err=True))
        cat_text = cal.format_user_catalog(out_catalog, catalog, name, res.entry,
                                           note=f"{name}: {species} calibrated from {ladder}")
    except (RecipeError, CatalogError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    path = out_catalog
    click.echo(f"{'panel':<24} {'geometries':>10} {'max dE00 catalogue':>19} {'max dE00 calibrated':>20}")
    for p, d0, d1 in zip(res.panels, res.de_start, res.de_fit):
        click.echo(f"{p.name:<24} {len(d0):>10} {d0.max():>19.3f} {d1.max():>20.3f}")
    click.echo(f"{'parameter':<16} {'fitted':>9} {'std. error':>10}  meaning")
    for p, z, se in zip(res.params, res.z, res.stderr):
        click.echo(f"{p.name:<16} {z:>+9.4f} {se:>10.4f}  {p.description}")
    click.echo(f"rms residual {res.rms_residual:.4g} ({res.n_compose} compose calls; {res.message.strip()})")
    rec = None
    if report_path:
        rec = {"species": species, "name": name, "parameters": [
            {"name": p.name, "fitted": float(z), "stderr": float(se) if np.isfinite(se) else None,
             "bounds": [p.lo, p.hi], "meaning": p.description}
            for p, z, se in zip(res.params, res.z, res.stderr)],
            "panels": [{"name": p.name, "dE00_catalogue": d0.tolist(), "dE00_calibrated": d1.tolist()}
                       for p, d0, d1 in zip(res.panels, res.de_start, res.de_fit)],
            "rms_residual": res.rms_residual, "compose_calls": res.n_compose, "entry": res.entry}
    with plan.staged() as stage:   # the catalogue and the report together, or neither
        stage.path(out_catalog).write_text(cat_text, encoding="utf-8")
        if rec is not None:
            stage.path(report_path).write_text(json.dumps(rec, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    if report_path:
        click.echo(f"wrote {report_path} (the fit record)")
    click.echo(f"wrote {path} (species {name}; use it with --catalog {path})")
    if not np.all(np.isfinite(res.stderr)):
        click.echo("warning: the parameters are not all determined by these panels (singular Jacobian): add "
                   "let-downs (docs/calibration.md, Experimental design)", err=True)


def _calibrate_tinter(ladder, out_catalog, catalog_path, degree, n, max_nfev, report_path):
    """``--tinter``: fit a new tinter to the ladder's panels (:func:`flakedb.match.tinter.fit_tinter`), or write
    its Kubelka–Munk seed as it is when the ladder has no panels; the user catalogue written atomically."""
    degree = tn.TINTER_DEGREE if degree is None else degree
    try:
        catalog = load_catalog(catalog_path)
        name, meta, seed, panels = tn.read_tinter_ladder(ladder)
        if not re.fullmatch(r"[a-z0-9][a-z0-9-]*", name):
            raise ValueError(f"{ladder}: tinter: {name!r} is not a species name (lower-case letters, digits and '-', "
                             f"e.g. my-blue)")
        if name in catalog["particles"]:
            raise ValueError(f"{ladder}: tinter: {name!r} is already a species of the base catalogue; choose another name")
        if not Path(out_catalog).parent.is_dir():
            raise ValueError(f"--out-catalog {out_catalog}: the folder {Path(out_catalog).parent} does not exist")
        plan = OutputPlan()  # before any work: the outputs are never an input
        plan.add_input(ladder, "LADDER")
        plan.add_input(catalog_path if catalog_path is not None else default_catalog_path(), "--catalog")
        for pn in panels:
            for q in pn.paths:
                plan.add_input(q, f"panel {pn.name}")
        plan.add_output(out_catalog, "--out-catalog")
        if report_path:
            plan.add_output(report_path, "--report")
        check_plan(plan)
        res = None
        if not panels:
            click.echo(f"tinter {name}: from its Kubelka-Munk seed alone (no panels)")
            entry = tn.seed_entry(seed, meta.get("description") or f"tinter {name} (from Kubelka-Munk data)",
                                  f"Kubelka-Munk seed of {ladder}", meta)
        else:
            click.echo(f"tinter {name}: {len(panels)} panel(s) from {ladder}, Legendre degree {degree}")
            res = tn.fit_tinter(name, panels, catalog, meta=meta, seed=seed, degree=degree, n=n, max_nfev=max_nfev,
                                log=lambda s: click.echo(f"  {s}", err=True))
            entry = res.entry
        cat_text = cal.format_user_catalog(out_catalog, catalog, name, entry, note=f"{name}: tinter from {ladder}")
        path = str(out_catalog)
    except (RecipeError, CatalogError, ValueError) as exc:
        raise FlakedbError(str(exc)) from exc
    rec = None
    if res is not None:
        click.echo(f"{'panel':<24} {'geometries':>10} {'max dE00':>9}")
        for p, d1 in zip(res.panels, res.de_fit):
            click.echo(f"{p.name:<24} {len(d1):>10} {d1.max():>9.3f}")
        se = res.ln_sigma_stderr
        click.echo(f"g = {res.params.g:.4f} ± {res.stderr[-1]:.4f}; std. error of ln sigma_a/phi "
                   f"{np.nanmax(se['ln_sigma_a']):.3g} and of ln sigma_s'/phi {np.nanmax(se['ln_sigma_s_reduced']):.3g} "
                   f"at worst over {se['wavelength_nm'][0]:g}-{se['wavelength_nm'][-1]:g} nm")
        click.echo(f"rms residual {res.rms_residual:.4g} % reflectance ({res.n_solves} solves; {res.message.strip()})")
        if report_path:
            rec = {"tinter": name, "degree": res.params.degree, "span_nm": list(res.span_nm),
                   "a": res.params.a.tolist(), "b": res.params.b.tolist(), "g": res.params.g,
                   "stderr": [float(v) if np.isfinite(v) else None for v in res.stderr],
                   "ln_sigma_stderr": {k: [float(x) if np.isfinite(x) else None for x in v]
                                       for k, v in res.ln_sigma_stderr.items()},
                   "panels": [{"name": p.name, "dE00": d1.tolist()} for p, d1 in zip(res.panels, res.de_fit)],
                   "rms_residual_percent": res.rms_residual, "solves": res.n_solves, "entry": entry}
    elif report_path:
        rec = {"tinter": name, "from": "Kubelka-Munk seed", "entry": entry}
    with plan.staged() as stage:   # the catalogue and the report together, or neither
        stage.path(out_catalog).write_text(cat_text, encoding="utf-8")
        if rec is not None:
            stage.path(report_path).write_text(json.dumps(rec, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    click.echo(f"wrote {path} (tinter {name}; use it with --catalog {path})")
