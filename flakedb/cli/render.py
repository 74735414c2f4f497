"""`flakedb render FILE`: a preview image of a composed BSDF file on a sphere (OpenEXR + PNG)."""

import sys
from pathlib import Path

import click

from flakedb.bsdf import BSDFFileError, open_bsdf
from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import probe_writable, remove_created_dirs
from flakedb.compose.orchestrate import OutputError, check_output_dir
from flakedb.render import preview
from flakedb.render.imageio import write_exr, write_png

ENV_CONSTANT_RADIANCE = 0.5  # the furnace of renderers.md


@click.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--out", "out_dir", default="out", show_default=True, type=click.Path(file_okay=False),
              help="Directory for FILE-stem.exr (linear RGB float32) and FILE-stem.png (sRGB 8-bit).")
@click.option("--size", default=256, show_default=True, type=click.IntRange(8, 8192),
              help="Image width and height [pixels].")
@click.option("--spp", default=None, type=click.IntRange(1, 1 << 16),
              help="Samples per pixel (default: flakedb.render.preview.DEFAULT_SPP, 32).")
@click.option("--env", "env_kind", default="studio", show_default=True, type=click.Choice(["studio", "constant"]),
              help=f"'studio': bright sky dome over a dim ground (+y up); 'constant': radiance "
                   f"{ENV_CONSTANT_RADIANCE} everywhere (the white-furnace check).")
@click.option("--sun/--no-sun", default=None,
              help="Add the studio key light (a 2° disk, sampled directly). Default: on with "
                   "--env studio, off with --env constant.")
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed.")
@click.option("--exposure", default=0.0, show_default=True, type=float,
              help="PNG exposure [stops]; the EXR is always unscaled linear radiance.")
@click.option("--threads", default=None, type=click.IntRange(1, 1024),
              help="Worker threads (default: the CPUs available).")
def render(file, out_dir, size, spp, env_kind, sun, seed, exposure, threads):
    """Render a unit sphere of the BSDF in FILE (.bsdf or flakedb .h5) under an environment.

    Orthographic camera looking down -z; BSDF importance sampling from the file's CDF combined
    with sun sampling (MIS, power heuristic); the smooth coat's mirror term (the file's delta)
    added exactly.  Writes OUT/<stem>.exr and OUT/<stem>.png atomically."""
    try:
        bsdf = open_bsdf(file)
        preview.check_renderable(bsdf)
    except BSDFFileError as e:
        raise FlakedbError(f"{e}\nflakedb render reads Fourier .bsdf files (SCATFUN) and flakedb HDF5 "
                           "BSDF files.") from None
    except ValueError as e:
        raise FlakedbError(str(e)) from None
    try:
        check_output_dir(out_dir)  # before the work, not after it
        probe_writable(out_dir)
    except OutputError as e:
        raise FlakedbError(str(e)) from None
    if env_kind == "constant":
        env = preview.constant_environment(ENV_CONSTANT_RADIANCE)
    else:
        env = preview.studio_environment()
    if sun is None:
        sun = env_kind == "studio"
    spp = preview.DEFAULT_SPP if spp is None else spp

    with click.progressbar(length=size, label=f"rendering {size}x{size} at {spp} spp",
                           file=sys.stderr) as bar:
        result = preview.render_sphere(bsdf, env, preview.studio_sun() if sun else None, size=size, spp=spp,
                                       seed=seed, threads=threads, progress=bar.update)
    out = Path(out_dir)
    stem = Path(file).stem
    with remove_created_dirs(out):
        out.mkdir(parents=True, exist_ok=True)
        exr = write_exr(out / f"{stem}.exr", result.image)
        try:
            png = write_png(out / f"{stem}.png", result.image, exposure=exposure)
        except BaseException:
            exr.unlink(missing_ok=True)  # both images or none
            raise
    sphere = result.coverage >= 1.0
    mean = result.image[sphere].mean(axis=0) if sphere.any() else [float("nan")] * 3
    click.echo(f"rendered in {result.seconds:.1f} s ({result.settings['threads']} threads); "
               f"sphere mean RGB {mean[0]:.4f} {mean[1]:.4f} {mean[2]:.4f}")
    click.echo(f"wrote {exr}")
    click.echo(f"wrote {png}")
