"""`flakedb calibrate LADDER.yaml --out-catalog USER.yaml`: fit a species to measured panels.

Thin: the fit is :func:`flakedb.match.calibrate.calibrate` (docs/calibration.md).  Reads the ladder
manifest (recipes and their measured targets, CSV or CxF3), prints one progress line per iteration
on stderr, then the panels' ΔE00 before and after and the fitted parameters with their standard
errors, and writes USER.yaml: the base catalogue plus the calibrated species (atomically; nothing
is written when the fit fails).  Recipes use it with ``--catalog USER.yaml``.

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
from pathlib import Path

import click
import numpy as np

from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan
from flakedb.cli.options import check_node_count
from flakedb.match import calibrate as cal
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
def calibrate(ladder, out_catalog, catalog_path, degree, n, max_nfev, report_path):
    """Calibrate a catalogue species from a masstone / let-down ladder (LADDER: a manifest YAML)."""
    check_node_count(n)
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
