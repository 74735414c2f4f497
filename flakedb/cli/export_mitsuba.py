"""`flakedb export-mitsuba FILE --out PATH`: a Fourier file as a Mitsuba 3 ``measured`` BSDF file.

Thin: the route is :data:`flakedb.export.registry.EXPORT_METHODS`'s ``mitsuba-coated`` / ``mitsuba-measured``.

A file that is not a Fourier BSDF is refused in one line, exit status 2, nothing written:

>>> import os, tempfile
>>> from pathlib import Path
>>> from click.testing import CliRunner
>>> from flakedb.cli.main import cli
>>> where = Path(tempfile.mkdtemp())
>>> _ = (where / "notes.bsdf").write_bytes(b"hello")
>>> result = CliRunner().invoke(cli, ["export-mitsuba", str(where / "notes.bsdf"), "--out", str(where / "paint.bsdf")])
>>> result.exit_code, result.output.splitlines()
(2, ["Error: .../notes.bsdf: neither a Fourier .bsdf (SCATFUN) nor an HDF5 file (first bytes b'hello')"])
>>> sorted(os.listdir(where))
['notes.bsdf']
"""

import json
from pathlib import Path

import click

from flakedb.bsdf import BSDFFileError
from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan, probe_writable, remove_created_dirs
from flakedb.export.registry import export
from flakedb.outputs import OutputPlan
from flakedb.render import mitsuba as fm

#: The export's own extension: the content is an RGL tensor file, not a Fourier .bsdf (Mitsuba's
#: `measured` plugin reads it by content, whatever the name).
MEASURED_SUFFIX = ".measured.tensor"


@click.command("export-mitsuba")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--out", "out", default=None, type=click.Path(dir_okay=False),
              help=f"Output tensor file for Mitsuba 3's `measured` plugin [default: FILE's stem + {MEASURED_SUFFIX}, "
                   f"next to FILE].")
@click.option("--variant", type=click.Choice(["rgb", "spectral"]), default="rgb", show_default=True,
              help="rgb: an `rgb` field (RGB variants); spectral: `spectra` + `wavelengths` from a "
                   "spectral flakedb .h5 (spectral variants).")
@click.option("--res", type=int, default=None,
              help="Half-vector grid vertices per axis [default: 96].")
@click.option("--n-theta", type=int, default=None,
              help="Incident elevations tabulated [default: 24].")
@click.option("--coat/--no-coat", default=True, show_default=True,
              help="Keep the smooth coat's mirror: the table at x2 blended half-and-half with Mitsuba's "
                   "conductor (k = 0: the dielectric Fresnel), the BSDF written next to OUT as .json and .xml. "
                   "--no-coat: the bare `measured` table (the mirror term dropped).")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def export_mitsuba(file, out, variant, res, n_theta, coat, as_json):
    """Export a Fourier .bsdf / flakedb .h5 FILE to Mitsuba 3's `measured` format (front-side
    reflection only).  With --coat (the default) the smooth coat's mirror term is kept by a
    `blendbsdf` of the table and a `conductor` coat (OUT.json / OUT.xml: use that BSDF); with
    --no-coat it is dropped and the summary lists the albedo it loses (docs/renderers.md)."""
    res = fm.RES_DEFAULT if res is None else res
    n_theta = fm.N_THETA_DEFAULT if n_theta is None else n_theta
    if out is None:
        out = str(Path(file).with_name(Path(file).stem + MEASURED_SUFFIX))
    try:
        fm.check_export_size(res, n_theta)
    except fm.MeasuredExportError as e:
        raise FlakedbError(str(e).replace("n_theta = ", "--n-theta ").replace("res = ", "--res ")) from None
    plan = OutputPlan()
    plan.add_input(file, "FILE")
    plan.add_output(out, "--out")
    check_plan(plan)  # before any work: not onto FILE, not onto a directory, a writable place
    probe_writable(Path(out).absolute().parent, "--out directory")
    try:
        with remove_created_dirs(Path(out).absolute().parent):
            s = export(file, out, method="mitsuba-coated" if coat else "mitsuba-measured", variant=variant, res=res,
                       n_theta=n_theta)
    except (BSDFFileError, fm.MeasuredExportError) as e:
        raise FlakedbError(str(e)) from None
    if as_json:
        click.echo(json.dumps(s, indent=2))
        return
    shape = " x ".join(str(x) for x in s["shape"])
    click.echo(f"wrote {s['out']} ({s['size']} bytes): Mitsuba 3 `measured`, {variant}, "
               f"res {s['res']}, {s['n_theta']} theta_i, data {shape}")
    d = s["dropped"]
    th = d["theta_i_deg"]
    refl = ", ".join(f"{t:g}°: {sum(a) / len(a):.4f}" for t, a in zip(th, s["reflected_albedo"]))
    click.echo(f"reflected albedo (channel mean) kept: {refl}")
    if s.get("kept"):
        kept = ", ".join(f"{t:g}°: {a:.4f}" for t, a in zip(th, s["kept"]["delta_albedo"]))
        click.echo(f"kept: the smooth coat's mirror reflection {s['kept']['delta']} (albedo {kept}) as a conductor "
                   f"k=0 lobe in a blendbsdf; the table is stored at x2")
    if "delta_albedo" in d:
        lost = ", ".join(f"{t:g}°: {a:.4f}" for t, a in zip(th, d["delta_albedo"]))
        click.echo(f"DROPPED: the smooth coat's mirror reflection {d['delta']} (albedo {lost}); "
                   f"add a dielectric coat in the renderer or use the `flakedb` plugin", err=True)
    if "transmitted_albedo" in d:
        lost = ", ".join(f"{t:g}°: {sum(a) / len(a):.4f}" for t, a in zip(th, d["transmitted_albedo"]))
        click.echo(f"DROPPED: transmission (albedo {lost}); `measured` holds reflection only", err=True)
    if "json" in s:
        click.echo(f"use: the BSDF in {s['json']} (mi.load_dict) or {s['xml']} (scene XML)")
    else:
        click.echo(f'use: {{"type": "measured", "filename": "{s["out"]}"}}')
