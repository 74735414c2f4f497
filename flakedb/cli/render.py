"""`flakedb render FILE…`: preview images of composed BSDF files on a sphere (OpenEXR + PNG), and a
side-by-side sheet of several paints or of one paint under several lights."""

import math
import sys
from pathlib import Path

import click
import numpy as np

from flakedb.bsdf import BSDFFileError, open_bsdf, table_evaluator
from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import check_plan, probe_writable, remove_created_dirs
from flakedb.compose.orchestrate import gamut_safe_file_channels
from flakedb.outputs import OutputError, OutputPlan
from flakedb.render import look, preview, quadrature
from flakedb.render.envmap import LatLongEnvironment, rasterise_latlong
from flakedb.render.imageio import read_exr, write_exr, write_png
from flakedb.render.mitsuba import channel_wavelengths
from flakedb.render.sparkle import sparkle_image
from flakedb.paint.recipe import RecipeError, load_recipe
from flakedb.paint.texture_inputs import texture_stack

ENV_CONSTANT_RADIANCE = 0.5  # the furnace of renderers.md
ENVS = ("softbox", "studio", "constant")
#: Largest |--exposure| [stops].
MAX_EXPOSURE_STOPS = 40.0
#: Width of the lat-long EXR of --write-environment [pixels] (0.35° per pixel: the 2° sun is 11 across).
ENV_EXR_WIDTH = 1024
METHODS = ("quadrature", "montecarlo")
#: Largest --environment file read [bytes] (an 8192 x 4096 half-float RGB EXR is ~200 MiB uncompressed).
ENV_MAX_BYTES = 512 << 20


def renderable(path):
    """The FourierBSDF to render for ``path``: the file itself, or for a spectral flakedb ``.h5`` its
    gamut-safe white-normalised linear sRGB (CIE 1931 2° / D65, :func:`flakedb.compose.orchestrate.
    gamut_safe_file_channels`, what compose writes into the ``.bsdf``), evaluated in memory.

    What is not a BSDF file is refused before any rendering:

    >>> import tempfile
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "notes.bsdf"
    >>> _ = path.write_bytes(b"hello")
    >>> renderable(path)
    Traceback (most recent call last):
    ...
    flakedb.bsdf.table.BSDFFileError: .../notes.bsdf: neither a Fourier .bsdf (SCATFUN) nor an HDF5 file (first bytes b'hello')
    """
    b = open_bsdf(path)
    wl = channel_wavelengths(b) if b.kind == "h5" and b.n_channels not in (1, 3) else None
    if wl is None:
        preview.check_renderable(b)
        return b
    order = np.argsort(wl)
    t = b.to_table()
    t.coeffs = t.coeffs[order]
    ft, _ = gamut_safe_file_channels(t, "spectral", wl[order], "srgb")
    rb = table_evaluator(ft, path=b.path)
    preview.check_renderable(rb)
    return rb


def _sparkle_stacks(recipes, n_files, sun):
    """One (recipe name, TextureStack) or None per file (``--sparkle``)."""
    if not recipes:
        return [None] * n_files
    if sun is False:
        raise FlakedbError("--sparkle draws the sun's glints: it cannot be combined with --no-sun")
    if len(recipes) not in (1, n_files):
        raise FlakedbError(f"--sparkle given {len(recipes)} times for {n_files} files: give it once (for all) or "
                           f"once per file, in order")
    out = []
    for path in (recipes * n_files if len(recipes) == 1 else recipes):
        try:
            rec = load_recipe(path)
        except RecipeError as exc:
            raise FlakedbError(str(exc)) from None
        st, _ = texture_stack(rec)
        if not st.flakes and len(recipes) == 1:   # one recipe for every file: nothing at all to draw
            raise FlakedbError(f"--sparkle {path}: the recipe has no flakes the texture model can use: no sparkle to draw")
        out.append((rec.name, st))               # in a sheet a flake-free paint is drawn smooth (no glints)
    return out


def add_sparkle(result, stack, sun, seed, sphere_mm, reference=None):
    """The render with the sun's glints, energy-consistent (:func:`flakedb.render.sparkle.sparkle_image`;
    ``reference``: the deterministic render that bounds what the glints take, for a Monte Carlo one)."""
    img, info = sparkle_image(result.image, stack, sun, result.settings["extent"], sphere_diameter_mm=sphere_mm,
                              seed=seed, reference=reference)
    result.image = img.astype(np.float32)
    result.settings["sparkle"] = info
    return result, info


def load_environment(path):
    """The :class:`LatLongEnvironment` of a lat-long RGB OpenEXR file (Mitsuba 3 ``envmap`` layout,
    docs/previews.md), or a FlakedbError naming the file and what is wrong."""
    size = Path(path).stat().st_size
    if size > ENV_MAX_BYTES:
        raise FlakedbError(f"--environment {path}: {size / 2**20:.0f} MiB, more than the {ENV_MAX_BYTES >> 20} MiB a "
                           f"preview light needs (the preview samples it on 1.4° cells): downsample it, e.g. to "
                           f"2048 x 1024")
    try:
        image = read_exr(path)
    except Exception as exc:   # OpenEXR raises plain exceptions for what is not an EXR
        raise FlakedbError(f"--environment {path}: not a readable RGB OpenEXR image ({exc}); give a lat-long "
                           "(equirectangular) .exr, e.g. one written by `flakedb render --write-environment`") from None
    try:
        return LatLongEnvironment(image, source=str(path))
    except ValueError as exc:
        raise FlakedbError(f"--environment {path}: {exc}") from None


def _uses_sun(kind, sun):
    """Whether the key light is on for the light ``kind`` (default: with --env studio only; an
    --environment file carries its own sun)."""
    return (kind == "studio") if sun is None else bool(sun)


def environment(kind):
    if kind == "constant":
        return preview.constant_environment(ENV_CONSTANT_RADIANCE)
    if kind == "studio":
        return preview.studio_environment()
    return look.softbox_studio()


@click.command()
@click.argument("files", nargs=-1, type=click.Path(dir_okay=False))
@click.option("--out", "out_dir", default="out", show_default=True, type=click.Path(file_okay=False),
              help="Directory for <stem>.exr (linear RGB float32) and <stem>.png (tone-mapped sRGB 8-bit).")
@click.option("--size", default=256, show_default=True, type=click.IntRange(8, 8192),
              help="Image width and height [pixels].")
@click.option("--method", default=None, type=click.Choice(METHODS),
              help="'quadrature' (default): deterministic, no noise, the same image for every seed "
                   "(flakedb.render.quadrature); 'montecarlo': the sampled renderer (BSDF and sun sampling, MIS).")
@click.option("--spp", default=None, type=click.IntRange(1, 1 << 16),
              help="Samples per pixel of --method montecarlo (giving it selects that method; default "
                   "flakedb.render.preview.DEFAULT_SPP, 32).")
@click.option("--environment", "env_file", default=None, type=click.Path(dir_okay=False, exists=True),
              help="Light the spheres with this lat-long (equirectangular) RGB OpenEXR environment, Mitsuba 3 "
                   "envmap layout (+y up; e.g. one written by --write-environment) instead of --env.")
@click.option("--write-environment", is_flag=True, default=False,
              help="Also write each light used (--env kind, with the sun where it is on) as a lat-long HDR "
                   "OpenEXR, OUT/environment-<kind>.exr (1024 x 512, radiance), for an A/B in another "
                   "renderer under the same light.  FILES may then be omitted.")
@click.option("--env", "env_kinds", multiple=True, type=click.Choice(ENVS),
              help="'softbox' (default): a studio with soft boxes over a gradient and a dark ground, no hard "
                   "horizon; 'studio': the older sky dome with a key light; 'constant': radiance "
                   f"{ENV_CONSTANT_RADIANCE} everywhere (the white-furnace check).  Repeat for a sheet of one "
                   "paint under several lights.")
@click.option("--sun/--no-sun", default=None,
              help="Add the key light (a 2° disk). Default: on with --env studio only.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0, 2 ** 63 - 1), help="Random seed (≥ 0).")
@click.option("--exposure", default=None, type=float,
              help="PNG exposure [stops] relative to the automatic one (default: automatic, Reinhard 2002 key "
                   "0.18; with --tone clip: stops on the raw radiance).  The EXR is always unscaled radiance.")
@click.option("--tone", default="filmic", show_default=True, type=click.Choice(["filmic", "clip"]),
              help="PNG tone curve: 'filmic' (ACES fit, Narkowicz 2016, with automatic exposure) or 'clip' "
                   "(exposure, clip at 1: the raw radiance).")
@click.option("--sheet", "sheet_name", default=None,
              help="File name of the side-by-side PNG in --out (default: sheet.png when there are several "
                   "images).")
@click.option("--threads", default=None, type=click.IntRange(1, 1024),
              help="Worker threads of --method montecarlo (default: the CPUs available); the quadrature runs on one.")
@click.option("--sparkle", "sparkle_recipes", multiple=True, type=click.Path(dir_okay=False, exists=True),
              help="Draw the sun's glints from this recipe's flake statistics (docs/texture.md §6); one for all "
                   "FILES or one per file, in order (the same .bsdf twice with two recipes: two flake sizes side "
                   "by side).  Turns the sun on.  Deterministic for --seed, independent of --spp.")
@click.option("--sphere-mm", default=100.0, show_default=True, type=click.FloatRange(1.0, 1e5),
              help="With --sparkle: the sphere's diameter in mm (sets each pixel's footprint on the paint).")
def render(files, out_dir, size, method, spp, env_file, write_environment, env_kinds, sun, seed, exposure, tone,
           sheet_name, threads, sparkle_recipes=(), sphere_mm=100.0):
    """Render unit spheres of the BSDFs in FILES (.bsdf, or a flakedb .h5 — a spectral one is converted
    to linear sRGB by the colour module) under a studio.

    Orthographic camera looking down -z.  By default deterministic: the lights on a grid, the file's
    Fourier series evaluated towards every grid cell, sub-pixel positions fixed (no noise); with
    --method montecarlo / --spp, BSDF importance sampling combined with sun sampling (MIS).  The smooth
    coat's mirror term (the file's delta) is added exactly either way.  Writes OUT/<stem>[-<env>].exr and
    .png atomically, and a sheet for several."""
    if not files and not write_environment:
        raise FlakedbError("give the BSDF files to render (FILES), or --write-environment to write the lights only")
    if method == "quadrature" and spp is not None:
        raise FlakedbError(f"--spp {spp} is the sample count of --method montecarlo; --method quadrature has no "
                           "samples (drop --spp, or use --method montecarlo)")
    method = method or ("montecarlo" if spp is not None else "quadrature")
    if env_file is not None and env_kinds:
        raise FlakedbError(f"--environment {env_file} and --env {env_kinds[0]} both set the light: give one")
    if env_file is not None and sparkle_recipes and sun is not True:
        raise FlakedbError(f"--sparkle draws the glints of flakedb's key light, which --environment {env_file} does not "
                           f"have (the file's own sun is not known to the texture model): add --sun to light the "
                           f"spheres with the file plus the key light, or drop --environment")
    env_kinds = env_kinds or ("softbox",)
    lights = {}
    if env_file is not None:
        label = Path(env_file).stem
        label = label if label not in ENVS else f"{label}-file"   # the file's own light, never the studio's sun
        lights[label] = load_environment(env_file)
        env_kinds = (label,)
    else:
        lights = {k: environment(k) for k in env_kinds}
    if exposure is not None and not (math.isfinite(exposure) and abs(exposure) <= MAX_EXPOSURE_STOPS):
        raise FlakedbError(f"--exposure {exposure}: give a finite number of stops in ±{MAX_EXPOSURE_STOPS:g} (each stop "
                           f"doubles the brightness; ±{MAX_EXPOSURE_STOPS:g} already spans a factor of 10^12)")
    # the output plan first (issue 25): two files of one paint (a.bsdf, a.h5) would write a.exr twice;
    # --sheet is a file name in --out, not a path; no output may replace an input
    stacks = _sparkle_stacks(sparkle_recipes, len(files), sun)   # their names are part of the image names
    plan = OutputPlan()
    plan.add_dir(out_dir)
    out = Path(out_dir)
    names = []
    if env_file is not None:
        plan.add_input(env_file, "--environment")
    env_names = []
    if write_environment:
        for kind in env_kinds:
            env_names.append((kind, plan.in_dir(out, f"environment-{kind}.exr", f"--write-environment {kind}")))
    for path in sparkle_recipes:
        plan.add_input(path, "--sparkle")
    for f, st in zip(files, stacks):
        plan.add_input(f, "FILE")
        for kind in env_kinds:
            stem = Path(f).stem + (f"-{st[0]}" if st is not None else "") + (f"-{kind}" if len(env_kinds) > 1 else "")
            names.append((plan.in_dir(out, f"{stem}.exr", f"image of {f}"), plan.in_dir(out, f"{stem}.png", f"image of {f}")))
    sheet_path = None
    if len(files) * len(env_kinds) > 1 or sheet_name:
        try:
            sheet_path = plan.in_dir(out, sheet_name or "sheet.png", "--sheet", option="--sheet" if sheet_name else None)
        except OutputError as e:
            raise FlakedbError(str(e)) from None
    check_plan(plan)
    bsdfs = []
    for f in files:
        try:
            bsdfs.append((f, renderable(f)))
        except BSDFFileError as e:
            raise FlakedbError(f"{e}\nflakedb render reads Fourier .bsdf files (SCATFUN) and flakedb HDF5 "
                               "BSDF files.") from None
        except ValueError as e:
            raise FlakedbError(str(e)) from None
    probe_writable(out_dir)
    spp = preview.DEFAULT_SPP if spp is None else spp
    jobs = [(f, b, k, st) for (f, b), st in zip(bsdfs, stacks) for k in env_kinds]
    results = []
    for f, b, kind, st in jobs:
        use_sun = _uses_sun(kind, sun) or st is not None
        how = f"at {spp} spp" if method == "montecarlo" else "by quadrature"
        label = f"rendering {Path(f).name} ({kind}) {size}x{size} {how}"
        with click.progressbar(length=size, label=label, file=sys.stderr) as bar:
            sun_light = preview.studio_sun() if use_sun else None
            if method == "montecarlo":
                r = preview.render_sphere(b, lights[kind], sun_light, size=size, spp=spp, seed=seed, threads=threads,
                                          progress=bar.update)
            else:
                r = quadrature.render_sphere_quadrature(b, lights[kind], sun_light, size=size, progress=bar.update)
        if st is not None and not st[1].flakes:
            click.echo(f"{Path(f).name}: sparkle of {st[0]}: the recipe has no flakes: no glints (drawn smooth)")
            f = str(Path(f).with_name(Path(f).stem + f"-{st[0]}" + Path(f).suffix))
        elif st is not None:
            ref = (None if method == "quadrature" else quadrature.render_sphere_quadrature(
                b, lights[kind], sun_light, size=size, extent=r.settings["extent"]).image)
            r, info = add_sparkle(r, st[1], preview.studio_sun(), seed, sphere_mm, ref)
            click.echo(f"{Path(f).name}: sparkle of {st[0]}: {info['glints']} glints drawn (expected "
                       f"{info['sum_lambda']:.0f}), pixel {info['pixel_mm']:.3g} mm on a {sphere_mm:g} mm sphere")
            f = str(Path(f).with_name(Path(f).stem + f"-{st[0]}" + Path(f).suffix))
        results.append((f, kind, r))
    sphere = [r.coverage >= 1.0 for _, _, r in results]
    if tone == "filmic":
        # one exposure for every image of the run, so a sheet compares like with like
        stack = np.concatenate([r.image[m] for (_, _, r), m in zip(results, sphere)] or [np.zeros((1, 3))])
        scale = look.auto_exposure(stack) * 2.0 ** float(exposure or 0.0)
    else:
        scale = 2.0 ** float(exposure or 0.0)
    shown, written = [], []
    env_images = [(kind, path, rasterise_latlong(lights[kind], preview.studio_sun() if _uses_sun(kind, sun) else None,
                                                 ENV_EXR_WIDTH)) for kind, path in env_names]
    with remove_created_dirs(out), plan.staged() as stage:   # every image or none
        for kind, path, image in env_images:
            write_exr(stage.path(path), image)
            written.append(path)
        for (f, kind, r), m, (exr_path, png_path) in zip(results, sphere, names):
            disp = look.tone_map(r.image, scale) if tone == "filmic" else np.clip(r.image * scale, 0.0, 1.0)
            write_exr(stage.path(exr_path), r.image)
            written.append(exr_path)
            write_png(stage.path(png_path), disp)
            written.append(png_path)
            shown.append(disp)
            mean = r.image[m].mean(axis=0) if m.any() else [float("nan")] * 3
            how = (f"{r.settings['threads']} threads, {r.settings['spp']} spp" if r.settings.get("method") != "quadrature"
                   else "quadrature, deterministic")
            click.echo(f"{Path(f).name} ({kind}): rendered in {r.seconds:.1f} s ({how}); "
                       f"sphere mean RGB {mean[0]:.4f} {mean[1]:.4f} {mean[2]:.4f}; "
                       f"{100 * look.clipped_fraction(disp, m):.2f}% of sphere pixels clip")
        if sheet_path is not None:
            write_png(stage.path(sheet_path), look.contact_sheet(shown))
            written.append(sheet_path)
    for w in written:
        click.echo(f"wrote {w}" + (f" ({len(shown)} images side by side, one exposure)" if w == sheet_path else ""))
    if tone == "filmic":
        click.echo(f"exposure: automatic x{scale:.3g} ({np.log2(scale):+.2f} stops), ACES filmic curve")
