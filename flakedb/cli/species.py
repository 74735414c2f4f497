"""`flakedb species list | show NAME`: the particle catalogue and one species' optics.

>>> from click.testing import CliRunner
>>> from flakedb.cli.main import cli
>>> listing = CliRunner().invoke(cli, ["species", "list"]).output
>>> [line.split()[:2] for line in listing.splitlines() if line.startswith("gray-mirror")]
[['gray-mirror', 'mirror_flake']]
>>> result = CliRunner().invoke(cli, ["species", "show", "grey-mirror"])
>>> result.exit_code, result.output.splitlines()[-1]
(2, "Error: unknown species 'grey-mirror'; known species: metallic, pearlescent, gray-mirror, ...")
"""

import json

import click

from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan
from flakedb.paint.catalog import CatalogError, expand_sweeps, load_catalog
from flakedb.outputs import OutputPlan
from flakedb.paint.species import optics_table, species_record
from flakedb.render.plots import plot_optics


@click.group()
def species():
    """The particle catalogue (catalog/particles.yaml) and each species' optics."""


@species.command("list")
@click.option("--catalog", "catalog_path", default=None, type=click.Path(dir_okay=False, exists=True),
              help="Catalogue YAML (default: catalog/particles.yaml or $FLAKEDB_CATALOG).")
@click.option("--json", "as_json", is_flag=True,
              help="Print a JSON list: name, kind, description, colour_index, density_g_cm3, density_source, "
                   "source (and a pigment's material, size and grade).")
def list_(catalog_path, as_json):
    """List the species: catalogue particles and sweep members."""
    try:
        allsp = expand_sweeps(load_catalog(catalog_path))
    except CatalogError as exc:
        raise FlakedbError(str(exc)) from exc
    if as_json:
        click.echo(json.dumps([species_record(name, e) for name, e in allsp.items()], indent=2, ensure_ascii=False))
        return
    for name, e in allsp.items():
        ci = e.get("colour_index") or "-"
        click.echo(f"{name:28s} {e['kind']:20s} {ci:8s} {e['description']}")


@species.command("show")
@click.argument("name")
@click.option("--out", "out_dir", default="out", show_default=True, type=click.Path(file_okay=False),
              help="Directory for NAME-optics.png.")
@click.option("--catalog", "catalog_path", default=None, type=click.Path(dir_okay=False, exists=True),
              help="Catalogue YAML (default: catalog/particles.yaml or $FLAKEDB_CATALOG).")
def show(name, out_dir, catalog_path):
    """Print a species' optics (flake R/T at 0°, 30°, 60°, 80° in the binder, or a pigment's
    C_ext, C_sca, albedo, g) and write its plot to OUT/NAME-optics.png."""
    try:
        catalog = load_catalog(catalog_path)
    except CatalogError as exc:
        raise FlakedbError(str(exc)) from exc
    known = list(expand_sweeps(catalog))
    if name not in known:
        raise FlakedbError(f"unknown species {name!r}; known species: {', '.join(known)} (a species of your own "
                           f"catalogue: --catalog FILE.yaml or $FLAKEDB_CATALOG)")
    plan = OutputPlan()
    plan.add_dir(out_dir)
    plan.add_input(catalog_path, "--catalog")
    plan.in_dir(out_dir, f"{name}-optics.png", "plot", option="NAME")
    check_plan(plan)   # before any work: a writable --out, the plot's name not taken by a directory
    click.echo(optics_table(name, catalog))
    path = plot_optics(name, out_dir, catalog)
    click.echo(f"plot: {path}")
