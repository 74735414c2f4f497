"""The ``cpa`` route's MaterialX graph (``NAME.cpa.mtlx``) on a sphere under the studio, rendered by MaterialX's
own GLSL renderer (``GlslRenderer``, the ``materialx`` wheel 1.39, Mesa llvmpipe under Xvfb), against flakedb's
exact prediction of the same pixels (docs/renderers.md, "The studio in MaterialX").

* **The light.**  The studio (:func:`flakedb.render.preview.studio_environment`, no sun) as the lat-long image
  ``flakedb render --write-environment`` writes (:func:`flakedb.render.envmap.rasterise_latlong`, Mitsuba's
  layout :data:`flakedb.render.envmap.LATLONG`), :data:`ENV_WIDTH` pixels wide, given to MaterialX's
  ``LightHandler`` as its radiance map (sampled by FIS, ``env_samples`` samples per lobe and pixel) and, for
  the Lambert term, the irradiance map ``E(n) / π`` (:func:`irradiance_over_pi`, the cosine integral of the
  same image over its pixels' exact solid angles).  MaterialX reads the image in the same layout as
  :data:`LATLONG` (measured: :func:`orientation_check` renders a white Lambertian whose irradiance map is the
  direction itself, (d + 1)/2, and compares each pixel with that map looked up at the pixel's normal; with
  ``mx_latlong_projection``'s u = atan(x, −z)/2π + 1/2 that means ``GlslProgram``'s environment matrix is a half
  turn about +y).  Every texture unit is read through a ``GL_LINEAR`` sampler without mip levels
  (:meth:`flakedb.export.mtlx_session.Session.bind_linear_samplers`: the table on a curved surface), so the FIS
  lookups read the radiance map's base level and the sample count alone sets the estimate's noise.
* **The scene.**  The unit sphere of ``tools/mtlx_lit.py`` (96 × 192 quads, exact vertex normals) seen by an
  orthographic camera along −z over [−EXTENT, EXTENT]², one sample at each pixel centre: the scene and camera
  of :func:`flakedb.render.quadrature.render_sphere_quadrature` with ``pixel_ss = 1``.
* **The exact prediction.**  :func:`flakedb.render.quadrature.render_sphere_quadrature` of the paint's ``.bsdf``
  under the same image (:class:`flakedb.render.envmap.LatLongEnvironment`): the deterministic preview's
  integrator, the coat's mirror term included.
* **The graph's prediction.**  :func:`graph_image`: what MaterialX's closures give the exported graph
  (:func:`flakedb.export.materialx_render.cpa_materialx_vectors`) summed over the image's pixels, plus the
  coat's mirror F(μ_v; η) L(r): it separates the route's fit error (graph vs exact) from the renderer's FIS
  sampling error (render vs graph).
* **Colour.**  Every image divided by the same white: the studio's irradiance / π at the normal facing the
  camera (a white Lambertian's radiance there), then CIEDE2000 per pixel (D65 / 2°, the file's white-normalised
  linear sRGB: as :func:`flakedb.export.materialx_render.dE00_against_exact`) over pixels whose normal is
  within :data:`MAX_VIEW_DEG` of the view (the silhouette's pixels are partly background in one image, not
  the other).

Usage::

    python tools/mtlx_studio.py OUTDIR PAINT.bsdf [PAINT.bsdf ...]   (NAME.cpa.mtlx beside each)
    python tools/mtlx_studio.py OUTDIR --orientation

Writes OUTDIR/NAME.{render-S,exact,graph}.f32 (SIZE × SIZE × 3 float32, row 0 at the top) and summary.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from flakedb.colour.tolerance import delta_E_2000
from flakedb.export.materialx_render import cpa_materialx_vectors, glsl_renderer
from flakedb.export.openpbr import colour_grid
from flakedb.match.fit import channels_to_Lab
from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.render.envmap import LATLONG, LatLongEnvironment, cell_average, cell_directions, cell_solid_angles, \
    rasterise_latlong
from flakedb.render.preview import studio_environment
from flakedb.render.quadrature import render_sphere_quadrature

SIZE, EXTENT = 64, 1.05
#: the studio's lat-long image width (height ENV_WIDTH / 2)
ENV_WIDTH = 256
#: the graph's prediction sums over the studio rasterised at this width (a quadrature of the same environment:
#: silver's uniform-sky centre pixel moves 0.2 % from 128 to 256)
GRAPH_ENV_WIDTH = 128
#: FIS sample counts rendered (MaterialX's default is 16)
ENV_SAMPLES = (64, 256, 1024)
#: pixels compared: normal within this angle of the view
MAX_VIEW_DEG = 75.0
EYE_Z = 1.0e4


def studio_image(width: int = ENV_WIDTH) -> np.ndarray:
    """The studio (no sun) as a lat-long image (width/2, width, 3): what ``--write-environment`` writes."""
    return rasterise_latlong(studio_environment(), None, width).astype(np.float64)


def irradiance_over_pi(img, width: int = 64) -> np.ndarray:
    """E(n) / π (width/2, width, 3) at the cell centres of a lat-long grid: Σ_pixels max(n·d, 0) Ω L / π over
    ``img``'s pixels (exact solid angles; a constant image L gives L)."""
    h, w = img.shape[:2]
    d = cell_directions(h, w, LATLONG).reshape(-1, 3)
    wL = (np.repeat(cell_solid_angles(h, w), w)[:, None] * img.reshape(-1, 3)) / np.pi
    n = cell_directions(width // 2, width, LATLONG).reshape(-1, 3)
    return (np.maximum(n @ d.T, 0.0) @ wL).reshape(width // 2, width, 3)


def pixel_normals(size: int = SIZE, extent: float = EXTENT):
    """(normals (size, size, 3), on-sphere mask) at the pixel centres, row 0 at the top (+y)."""
    x = -extent + (np.arange(size) + 0.5) * 2 * extent / size
    X, Y = np.meshgrid(x, x[::-1])
    r2 = X * X + Y * Y
    return np.stack([X, Y, np.sqrt(np.clip(1 - r2, 0, 1))], -1), r2 < 1.0


def graph_image(fit, img, eta: float | None, size: int = SIZE, extent: float = EXTENT, chunk: int = 64) -> np.ndarray:
    """What MaterialX's closures give the ``cpa`` graph of ``fit`` on the sphere under the lat-long ``img``
    (module docstring): Σ_cells f_graph(ω_l, ω_v) μ_l Ω L over ``img``'s pixel centres, plus the coat's mirror
    F(μ_v; η) L(r) (η None: no coat).  Background pixels are 0."""
    h, w = img.shape[:2]
    d = cell_directions(h, w, LATLONG).reshape(-1, 3)
    wL = np.repeat(cell_solid_angles(h, w), w)[:, None] * img.reshape(-1, 3)
    N, hit = pixel_normals(size, extent)
    out = np.zeros((size, size, 3))
    n = N[hit]
    res = np.zeros((n.shape[0], 3))
    v = np.array([0.0, 0.0, 1.0])
    env = LatLongEnvironment(img)
    for i0 in range(0, n.shape[0], chunk):
        nn = n[i0:i0 + chunk]
        t = v - nn[:, 2:3] * nn                                      # tangent towards the view (0 at the centre)
        tl = np.linalg.norm(t, axis=1, keepdims=True)
        t = np.where(tl > 1e-9, t / np.maximum(tl, 1e-12), np.array([1.0, 0.0, 0.0]))
        b = np.cross(nn, t)
        wv = np.stack([(v * t).sum(1), (v * b).sum(1), nn[:, 2]], -1)               # (P, 3)
        wl = np.stack([d @ t.T, d @ b.T, d @ nn.T], -1).transpose(1, 0, 2)          # (P, C, 3)
        up = wl[..., 2] > 0
        P, C = up.shape
        rf = np.zeros((P, C, 3))
        wvv = np.broadcast_to(wv[:, None], wl.shape)
        rf[up] = cpa_materialx_vectors(fit, wl[up], wvv[up])
        res[i0:i0 + chunk] = np.einsum("pc,pcj,cj->pj", np.where(up, wl[..., 2], 0.0), rf / np.pi, wL)
    if eta is not None:
        r = 2 * n[:, 2:3] * n - v
        res += fresnel_dielectric(n[:, 2], eta).R[:, None] * env(r)
    out[hit] = res
    return out


def exact_image(bsdf, img, size: int = SIZE, extent: float = EXTENT) -> np.ndarray:
    """flakedb's exact prediction: :func:`render_sphere_quadrature` of ``bsdf`` under ``img``, one sample per pixel."""
    return np.asarray(render_sphere_quadrature(bsdf, LatLongEnvironment(img), None, size=size, extent=extent,
                                               pixel_ss=1).image, float)


def dE00_map(a, b, wl_nm, white: float, mask) -> np.ndarray:
    """CIEDE2000 per masked pixel of RGB radiance images ``a`` against ``b``, both divided by ``white``."""
    la = channels_to_Lab(np.maximum(a[mask] / white, 1e-6), "rgb", wl_nm)
    lb = channels_to_Lab(np.maximum(b[mask] / white, 1e-6), "rgb", wl_nm)
    return delta_E_2000(la, lb)


def stats(de) -> dict:
    return {"median": float(np.median(de)), "p95": float(np.percentile(de, 95)), "max": float(de.max())}


# ---- the render (a subprocess with a display: python mtlx_studio.py --worker JOB.json) ----
def _worker(job_path: str) -> int:
    from flakedb.export.mtlx_session import Session
    _mtlx_lit = _load_mtlx_lit()
    job = json.loads(Path(job_path).read_text())
    t = Path(job_path).parent
    session = Session(int(job["size"]))
    session.load_geometry(_mtlx_lit.sphere_obj(t / "sphere.obj"))
    session.orthographic((0.0, 0.0, EYE_Z), (0, 1, 0), float(job["extent"]), 2.0)
    maps = {}
    for r in job["renders"]:
        key = (r["radiance"], r["irradiance"])
        if key not in maps:
            maps[key] = tuple(np.load(p) for p in key)
        session.program(session.document(r["mtlx"]), env_maps=maps[key], env_samples=int(r["samples"]))
        if job.get("sampler", True):
            session.bind_linear_samplers()
        px = session.render()[::-1]
        np.ascontiguousarray(px, dtype=np.float32).tofile(r["out"])
    print(json.dumps(session.info))
    return 0


def _load_mtlx_lit():
    import importlib.util
    spec = importlib.util.spec_from_file_location("mtlx_lit", Path(__file__).with_name("mtlx_lit.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def render(renders: list[dict], tool: dict, size: int = SIZE, timeout: float = 900.0):
    """Render ``renders`` ({"mtlx", "radiance", "irradiance" (float (H, W, 3) arrays), "samples"}) in a
    subprocess; returns (images (size, size, 3) row 0 at the top, renderer info)."""
    with tempfile.TemporaryDirectory(prefix="flakedb-studio-") as tmp:
        t = Path(tmp)
        job = {"size": size, "extent": EXTENT, "renders": []}
        saved = {}
        for i, r in enumerate(renders):
            paths = []
            for k in ("radiance", "irradiance"):
                a = r[k]
                if id(a) not in saved:
                    saved[id(a)] = str(t / f"map{len(saved)}.npy")
                    np.save(saved[id(a)], np.asarray(a, np.float32))
                paths.append(saved[id(a)])
            job["renders"].append({"mtlx": str(Path(r["mtlx"]).resolve()), "radiance": paths[0],
                                   "irradiance": paths[1], "samples": int(r["samples"]), "out": str(t / f"{i}.f32")})
        (t / "job.json").write_text(json.dumps(job))
        env = dict(os.environ, LP_NUM_THREADS=os.environ.get("LP_NUM_THREADS", "2"),
                   PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")]))
        p = subprocess.run(tool["wrap"] + [tool["python"], str(Path(__file__).resolve()), "--worker", str(t / "job.json")],
                           capture_output=True, text=True, timeout=timeout, check=False, env=env)
        if p.returncode != 0:
            tail = "\n".join((p.stdout + p.stderr).strip().splitlines()[-12:])
            raise RuntimeError(f"the MaterialX GLSL render failed (exit {p.returncode}):\n{tail}")
        info = json.loads(p.stdout.strip().splitlines()[-1])
        imgs = [np.fromfile(t / f"{i}.f32", np.float32).reshape(size, size, 3).astype(float) for i in range(len(renders))]
    return imgs, info


def white_lambert_mtlx(path) -> Path:
    from flakedb.export.materialx_render import lambert_mtlx_text
    Path(path).write_text(lambert_mtlx_text((1.0, 1.0, 1.0)))
    return Path(path)


def orientation_check(tool, out: Path) -> dict:
    """A white Lambertian whose irradiance map is (d + 1)/2 in :data:`LATLONG`'s layout (radiance map 0):
    MaterialX draws (n + 1)/2 at each pixel iff it reads the image in that layout.  Returns the largest
    difference from (n + 1)/2 and from the map looked up at n (bilinear), over pixels within MAX_VIEW_DEG."""
    pattern = cell_average(lambda d: 0.5 * (d + 1.0), 32, 64, LATLONG, 4)
    (img,), info = render([{"mtlx": white_lambert_mtlx(out / "white.mtlx"), "radiance": np.zeros_like(pattern),
                            "irradiance": pattern, "samples": 16}], tool)
    N, hit = pixel_normals()
    m = hit & (N[..., 2] > np.cos(np.radians(MAX_VIEW_DEG)))
    look = LatLongEnvironment(pattern)(N[m])
    return {"max_abs_vs_(n+1)/2": float(np.abs(img[m] - 0.5 * (N[m] + 1)).max()),
            "max_abs_vs_map_lookup": float(np.abs(img[m] - look).max()), "pixels": int(m.sum()), "renderer": info}


def measure(bsdf_paths, tool, samples=ENV_SAMPLES, size: int = SIZE, progress=print):
    """Render each ``.bsdf``'s ``.cpa.mtlx`` (beside it, with its ``.cpa.json``) under the studio at each FIS
    sample count and compare with the exact and the graph's predictions (module docstring): (summary, images
    {stem: {"render-S", "exact", "graph"}})."""
    from flakedb.bsdf import read_bsdf
    from flakedb.export.cpa import CPAFit, materialx_fit
    from flakedb.export.materialx_render import table_as_loaded

    bsdf_paths = [Path(p) for p in bsdf_paths]
    rad = studio_image()
    irr = irradiance_over_pi(rad)
    white = float(LatLongEnvironment(irr)(np.array([0.0, 0.0, 1.0])).mean())
    N, hit = pixel_normals(size)
    mask = hit & (N[..., 2] > np.cos(np.radians(MAX_VIEW_DEG)))
    t0 = time.perf_counter()
    imgs = []
    for p in bsdf_paths:          # one process a paint: a program left a later one's pixels off (docs/renderers.md)
        im, info = render([{"mtlx": p.with_suffix(".cpa.mtlx"), "radiance": rad, "irradiance": irr, "samples": s}
                           for s in samples], tool, size)
        imgs += im
    info["render_s"] = round(time.perf_counter() - t0, 1)
    summary = {"renderer": info, "size": size, "extent": EXTENT, "env_width": ENV_WIDTH,
               "graph_env_width": GRAPH_ENV_WIDTH, "max_view_deg": MAX_VIEW_DEG, "pixels": int(mask.sum()),
               "white": white, "paints": {}}
    images = {}
    for i, p in enumerate(bsdf_paths):
        b = read_bsdf(p)
        wl_nm = colour_grid(b)
        fit = table_as_loaded(materialx_fit(CPAFit.from_dict(json.loads(p.with_suffix(".cpa.json").read_text()))))
        t1 = time.perf_counter()
        ex = exact_image(b, rad, size)
        t_ex = time.perf_counter() - t1
        eta = fit.coat_ior if b.delta is not None else None
        t1 = time.perf_counter()
        gr = graph_image(fit, studio_image(GRAPH_ENV_WIDTH), None if eta is None else float(eta), size)
        t_gr = time.perf_counter() - t1
        row = {"exact_s": round(t_ex, 1), "graph_s": round(t_gr, 1), "eta": eta,
               "graph_vs_exact": stats(dE00_map(gr, ex, wl_nm, white, mask))}
        ims = {"exact": ex, "graph": gr}
        for k, s in enumerate(samples):
            im = imgs[i * len(samples) + k]
            ims[f"render-{s}"] = im
            row[f"render{s}_vs_exact"] = stats(dE00_map(im, ex, wl_nm, white, mask))
            row[f"render{s}_vs_graph"] = stats(dE00_map(im, gr, wl_nm, white, mask))
            row[f"render{s}_vs_graph_rel_max"] = float(np.abs(im[mask] - gr[mask]).max() / gr[mask].max())
        if len(samples) > 1:
            row[f"render{samples[0]}_vs_render{samples[-1]}"] = stats(
                dE00_map(ims[f"render-{samples[0]}"], ims[f"render-{samples[-1]}"], wl_nm, white, mask))
        summary["paints"][p.stem] = row
        images[p.stem] = ims
        if progress is not None:
            progress(p.stem, json.dumps(row), flush=True)
    return summary, images


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("bsdf", nargs="*", type=Path)
    ap.add_argument("--orientation", action="store_true")
    ap.add_argument("--samples", type=int, nargs="+", default=list(ENV_SAMPLES))
    a = ap.parse_args(argv)
    tool, why = glsl_renderer()
    if tool is None:
        print(f"cannot render: {why}", file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    if a.orientation:
        print(json.dumps(orientation_check(tool, a.out), indent=1))
        return 0
    summary, images = measure(a.bsdf, tool, a.samples)
    for stem, ims in images.items():
        for kind, im in ims.items():
            im.astype(np.float32).tofile(a.out / f"{stem}.{kind}.f32")
    (a.out / "summary.json").write_text(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--worker":
        sys.exit(_worker(sys.argv[2]))
    sys.exit(main())
