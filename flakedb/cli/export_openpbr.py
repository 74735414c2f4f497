"""`flakedb export-openpbr FILE --out DIR`: the fitted analytic material (OpenPBR / MaterialX, USD,
glTF, Blender Principled).  Thin: the work is in :func:`flakedb.export.registry.export_openpbr`.

A FILE that is not a BSDF is refused with exit status 2 and one line, and nothing is created:

>>> import tempfile
>>> from pathlib import Path
>>> from click.testing import CliRunner
>>> from flakedb.cli.main import cli
>>> d = Path(tempfile.mkdtemp())
>>> _ = (d / "paint.bsdf").write_bytes(b"not a bsdf file")
>>> r = CliRunner().invoke(cli, ["export-openpbr", str(d / "paint.bsdf"), "--out", str(d / "out")])
>>> r.exit_code, r.output.replace(str(d), "D").splitlines()[0]
(2, "Error: D/paint.bsdf: neither a Fourier .bsdf (SCATFUN) nor an HDF5 file (first bytes b'not a bs')")
>>> sorted(p.name for p in d.iterdir())
['paint.bsdf']
"""

import json

import click

from flakedb.cli.exporting import run_export


@click.command("export-openpbr")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--out", "out", default=None, type=click.Path(file_okay=False),
              help="Output directory [default: FILE's directory].")
@click.option("--name", default=None, help="Base name of the files [default: FILE's stem].")
@click.option("--json", "as_json", is_flag=True, help="Print the fit and the files as JSON.")
def export_openpbr(file, out, name, as_json):
    """Fit an OpenPBR Surface (coat, base colour, metalness, roughness) to a Fourier .bsdf / flakedb
    .h5 FILE by weighted least squares, and write NAME.mtlx (MaterialX), NAME.usda (USD),
    NAME.gltf / NAME.glb (glTF sphere) and NAME.blender.py (Principled BSDF).  The fit's error
    (ΔE00 at the ASTM E2194 / E2539 geometries, cosine-weighted BSDF difference) is printed and
    stored in each file (`flakedb info NAME.mtlx` shows it)."""
    s = run_export(file, out, "openpbr", name, as_json)
    if as_json:
        click.echo(json.dumps(s, indent=2))
        return
    f = s["fit"]
    e = f["error"]
    c = ", ".join(f"{x:.4f}" for x in f["base_color"])
    click.echo(f"fit: base_color ({c}) linear sRGB, metalness {f['base_metalness']:.3f}, roughness "
               f"{f['specular_roughness']:.3f}; coat ior {f['coat_ior']:.4g}, roughness {f['coat_roughness']:.3f}")
    click.echo(f"error: worst ΔE00 {e['worst_dE00_E2194']:.2f} at the E2194 geometries, {e['worst_dE00_E2539']:.2f} "
               f"with E2539's; cosine-weighted BSDF difference {100 * e['cosine_weighted_difference']:.1f} %")
    click.echo("  " + "  ".join(f"{g['illumination_deg']:g}as{g['aspecular_deg']:g}: {g['dE00']:.2f}"
                                for g in e["dE00_E2539"]))
    for k, p in s["files"].items():
        click.echo(f"wrote {p} ({k})")
