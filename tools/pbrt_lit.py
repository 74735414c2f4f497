"""Lit-render check of the pbrt-v3 routes (docs/renderers.md, "pbrt-v3"; issue 23): the coated route of
:func:`flakedb.render.mitsuba.coated.pbrt_coated_scene` shows the coat's mirror highlight and equals
flakedb's preview of the exact BSDF; ``Material "fourier"`` alone lacks exactly that mirror.  The pbrt-v3
counterpart of ``tests/export/test_mitsuba_lit.py``; needs a pbrt-v3 binary (build notes in
docs/renderers.md), run by ``tests/export/test_pbrt_lit.py`` when ``FLAKEDB_PBRT`` names one.

    python tools/pbrt_lit.py PBRT_BINARY PAINT.bsdf [PAINT.bsdf ...] --workdir DIR [--size 16] [--spp-side 64]
                             [--preview-spp 4096] [--json RESULTS.json]

Scene (the Mitsuba test's): the unit sphere seen orthographically along −z over ``[−EXTENT, EXTENT]²``,
a box pixel filter, no environment, and a light of angular radius ``SUN_DEG`` and radiance
``SUN_RADIANCE`` on the view axis behind the camera (the image is symmetric under the square's 8
rotations and reflections, so the renderers' image orientations cannot differ).  In pbrt-v3 the light
is ``Shape "disk"`` of radius ``DISK_DIST · tan SUN_DEG`` at distance ``DISK_DIST`` facing the sphere,
with ``AreaLightSource "diffuse"``; in flakedb's preview (:func:`flakedb.render.preview.render_sphere`:
the table + the exact delta ``F(μ; η)``) it is a :class:`~flakedb.render.preview.Sun` at infinity.
The path tracer runs to depth 1: the sphere is convex and alone, so one bounce holds the light's
direct reflection (light sample + BSDF sample, MIS) and the coat's specular bounce onto the disk.

The coat mirrors the light where the normal is within ``SUN_DEG / 2`` of the axis: image radius
``< sin(SUN_DEG / 2)``.  Pixels whose farthest corner is inside ``sin(SUN_DEG / 2 − MARGIN_DEG)`` are
wholly in the highlight, those whose nearest corner is outside ``sin(SUN_DEG / 2 + MARGIN_DEG)``
wholly out of it (both routes' mirrors are exact deltas, so the margin only has to exceed the disk's
finite-distance error below, ``1.5 / DISK_DIST`` rad).  Checked per mask and channel:

* coated vs preview: ``|c − p| ≤ NSIGMA · hypot(se_c, se_p) + geometry + clamp + |(P − I) p| + FLOAT32_REL · p``;
* coated − fourier alone vs the coat's mirror term ``m``: inside, ``m`` is the pixel-area mean of
  ``F(μ(x, y); η) · SUN_RADIANCE`` (:func:`coat_term`; ``F`` of :func:`flakedb.optics.fresnel.fresnel_dielectric`);
  outside, ``m = 0``: ``|c − f − m| ≤ NSIGMA · se_(c−f) + |(P − I) m| + FLOAT32_REL · c``; inside, the bound must also
  resolve ``m`` (tolerance < m / 2).

Tolerances.  *Noise*: pbrt-v3 has no seed option (its samplers are seeded by the tile index), so
repeated runs are the same image; the standard error of a mask mean comes from the scene's symmetry
instead (:func:`symmetric_mean_se`): pixels that one of the square's 8 symmetries maps onto each other
have the same expectation and independent estimates (each pixel draws its own samples), so their
spread estimates each pixel's variance.  The difference c − f gets its own error from the spread of
the difference image (the two routes draw the same random numbers per pixel, so their noise is
correlated).  *Geometry*: from a point ``p`` on the unit sphere the disk's centre is off the axis by
``≤ 1 / DISK_DIST`` rad and its angular radius differs from ``SUN_DEG`` by ``≤ sin α cos α / DISK_DIST``,
so the two cones differ by at most ``2π sin α · 1.5 / DISK_DIST`` sr (their boundary's length times
its displacement); the reflected radiance by at most ``SUN_RADIANCE · max(f|μ_o|)`` times that
(:func:`geometry_bound`, the maximum over a grid of the file's directions).  *Film*: pbrt-v3's film
accumulates XYZ and writes RGB (``src/core/film.cpp``) with the 6-digit sRGB matrices of
``src/core/spectrum.h`` (:data:`PBRT_RGB_TO_XYZ`, :data:`PBRT_XYZ_TO_RGB`), whose product is the
identity only to ~1e-6: an image value ``v`` comes back as ``P v``, ``P = XYZ_TO_RGB · RGB_TO_XYZ``;
negligible except on a channel ~1e-4 of the others (cadmium yellow's blue: −0.28 %), so the bound adds
``|(P − I) v|`` (:func:`film_roundtrip_error`).  *Arithmetic*: pbrt-v3 evaluates the series in float32
(a few dozen roundings of 2⁻²⁴ per value: ``FLOAT32_REL``).  *Clamp*: pbrt-v3 clamps each channel of
the evaluated series to ≥ 0 (``FourierBSDF::f``), the preview does not; the compose ``.bsdf``\\ s hold
no negative channel at a node pair (docs/renderers.md), but the series can dip below 0 between nodes
(cadmium yellow's blue by ~1e-6 /sr), so the bound adds the light's reflection of the negative part,
``SUN_RADIANCE ∫_cone max(0, −f|μ_o|) dω`` at the masks' pixel centres (:func:`clamp_bound`).
pbrt-v3 also clamps the luminance Y before it rebuilds G; that is not bounded here (Y, a positive
combination of R, G and B, is below 0 only where some channel is).
"""

import argparse
import importlib.util
import json
import math
import subprocess
import time
from pathlib import Path

import numpy as np

from flakedb.bsdf.dispatch import open_bsdf
from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.render.mitsuba.coated import pbrt_coated_scene

# the PFM reader of the furnace tool beside this one (tools/ is not a package; the test loads this file by path)
_furnace_spec = importlib.util.spec_from_file_location("pbrt_furnace", Path(__file__).with_name("pbrt_furnace.py"))
_furnace = importlib.util.module_from_spec(_furnace_spec)
_furnace_spec.loader.exec_module(_furnace)
read_pfm = _furnace.read_pfm
from flakedb.render.preview import (
    Sun,
    constant_environment,
    orthonormal_basis,
    render_sphere,
)

SUN_DEG = 30.0           # the light's angular radius
SUN_RADIANCE = 4.0
EXTENT = 0.5             # the image spans [-EXTENT, EXTENT]² of the sphere
MARGIN_DEG = 0.5         # normal-angle margin of the in/out masks (>> 1.5 / DISK_DIST rad = 9e-5 deg)
DISK_DIST = 1.0e6        # the disk's distance; its radius is DISK_DIST tan(SUN_DEG)
NSIGMA = 5.0
FLOAT32_REL = 64 * 2.0 ** -24
#: pbrt-v3's film matrices (src/core/spectrum.h, RGBToXYZ and XYZToRGB), linear sRGB <-> CIE XYZ
PBRT_RGB_TO_XYZ = np.array([[0.412453, 0.357580, 0.180423],
                            [0.212671, 0.715160, 0.072169],
                            [0.019334, 0.119193, 0.950227]])
PBRT_XYZ_TO_RGB = np.array([[3.240479, -1.537150, -0.498535],
                            [-0.969256, 1.875991, 0.041556],
                            [0.055648, -0.204043, 1.057311]])
SCENE = """LookAt 0 0 4  0 0 0  0 1 0
Camera "orthographic" "float screenwindow" [{sw} {sw2} {sw} {sw2}]
Sampler "stratified" "integer xsamples" [{nx}] "integer ysamples" [{nx}] "bool jitter" "true" "integer dimensions" [8]
Integrator "path" "integer maxdepth" [1]
PixelFilter "box"
Film "image" "integer xresolution" [{size}] "integer yresolution" [{size}] "string filename" "{out}"
WorldBegin
AttributeBegin
  Material "matte" "rgb Kd" [0 0 0]
  Translate 0 0 {dist}
  Rotate 180 1 0 0
  AreaLightSource "diffuse" "rgb L" [{L} {L} {L}]
  Shape "disk" "float radius" {radius}
AttributeEnd
AttributeBegin
{material}
Shape "sphere" "float radius" 1
AttributeEnd
WorldEnd
"""


def scene_text(material: str, size: int, spp_side: int, out: str) -> str:
    """The pbrt-v3 scene of the module docstring with ``material`` on the sphere, ``spp_side²`` samples per pixel."""
    radius = DISK_DIST * math.tan(math.radians(SUN_DEG))
    return SCENE.format(sw=-EXTENT, sw2=EXTENT, nx=spp_side, size=size, out=out, dist=f"{DISK_DIST:.9g}",
                        L=f"{SUN_RADIANCE:g}", radius=f"{radius:.9g}", material=material)


def film_roundtrip_error(v) -> np.ndarray:
    """``|(P − I) v|`` (..., 3): how far pbrt-v3's film moves linear-sRGB values ``v`` by storing them as
    XYZ and writing them as RGB, ``P = PBRT_XYZ_TO_RGB · PBRT_RGB_TO_XYZ`` (module docstring)."""
    v = np.asarray(v, dtype=float)
    return np.abs(v @ (PBRT_XYZ_TO_RGB @ PBRT_RGB_TO_XYZ - np.eye(3)).T)


def pixel_masks(size: int, extent: float = EXTENT, margin_deg: float = MARGIN_DEG):
    """(inside, outside) boolean (size, size): pixels wholly in / wholly out of the coat's highlight
    (image radius sin(SUN_DEG / 2) ∓ the margin, by the pixel's farthest / nearest corner)."""
    e = np.linspace(-extent, extent, size + 1)
    lo, hi = np.minimum(np.abs(e[:-1]), np.abs(e[1:])), np.maximum(np.abs(e[:-1]), np.abs(e[1:]))
    lo = np.where(e[:-1] * e[1:] < 0, 0.0, lo)                      # the pixel straddles the axis
    far = np.hypot(hi[:, None], hi[None, :])
    near = np.hypot(lo[:, None], lo[None, :])
    inside = far < math.sin(math.radians(SUN_DEG / 2 - margin_deg))
    outside = (near > math.sin(math.radians(SUN_DEG / 2 + margin_deg))) & (far < 0.95)
    return inside, outside


def symmetric_mean_se(image: np.ndarray, mask: np.ndarray):
    """Mean over ``mask``'s pixels of ``image`` (size, size, C) and its standard error (C,), C each.

    The pixels of one orbit of the square's symmetry group (the 8 rotations and reflections that map
    the pixel grid onto itself; label (max, min) of the pixel's |offsets| from the centre) have one
    expectation; their estimates are independent, so the orbit's sample variance s_o² (n_o − 1 dof)
    estimates each one's variance and Var(mean) = Σ_o n_o s_o² / N² (N the mask's pixels), without
    assuming equal variances across orbits.  ``mask`` must be symmetric and every orbit in it ≥ 2 pixels."""
    if not (np.array_equal(mask, mask[::-1]) and np.array_equal(mask, mask[:, ::-1]) and np.array_equal(mask, mask.T)):
        raise ValueError("the mask must be symmetric under the square's rotations and reflections")
    n = mask.shape[0]
    a = np.abs(np.arange(n) - (n - 1) / 2)
    A, B = np.meshgrid(a, a, indexing="ij")
    key = (np.maximum(A, B) * 2 * n + np.minimum(A, B))[mask]
    vals = np.asarray(image, dtype=float)[mask]
    var_sum = np.zeros(vals.shape[1:])
    for k in np.unique(key):
        x = vals[key == k]
        if len(x) < 2:
            raise ValueError("an orbit of one pixel has no spread: use an even image size")
        var_sum += len(x) * x.var(axis=0, ddof=1)
    return vals.mean(axis=0), np.sqrt(var_sum) / len(vals)


def coat_term(size: int, eta: float, extent: float = EXTENT, radiance: float = SUN_RADIANCE, sub: int = 32) -> np.ndarray:
    """(size, size) pixel-area mean of the coat's mirror ``F(μ; η) · radiance`` where it reflects the
    light (normal within SUN_DEG / 2 of the axis: μ = cos θ_n, the mirror direction at 2 θ_n); a
    ``sub × sub`` midpoint rule per pixel (F varies by < 1e-3 of itself across a highlight pixel)."""
    t = -extent + (np.arange(size * sub) + 0.5) * (2 * extent / (size * sub))
    X, Y = np.meshgrid(t, t, indexing="ij")
    r2 = X * X + Y * Y
    mu = np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
    lit = (r2 < 1.0) & (mu >= math.cos(math.radians(SUN_DEG / 2)))
    F = np.where(lit, fresnel_dielectric(mu, eta).R, 0.0) * radiance
    return F.reshape(size, sub, size, sub).mean(axis=(1, 3))


def geometry_bound(b, n: int = 48) -> tuple:
    """(bound, fmin): the disk-at-distance vs sun-at-infinity bound of the module docstring (C,), and
    the most negative f|μ_o| of the file on the same grid (C,): view cosines over the image's normals,
    light cosines and azimuths over the whole hemisphere, n per axis."""
    mu_i = np.linspace(math.sqrt(1 - 2 * EXTENT ** 2), 1.0, n)
    mu_o = -np.linspace(1e-3, 1.0, n)
    phi = np.linspace(0.0, np.pi, n)
    Mi, Mo, P = np.meshgrid(mu_i, mu_o, phi, indexing="ij")
    v = np.asarray(b.eval(Mi, Mo, P, clamp="none")).reshape(-1, b.eval(0.5, -0.5, 0.0).shape[-1])
    s = math.sin(math.radians(SUN_DEG))
    return SUN_RADIANCE * v.max(axis=0) * 2 * math.pi * s * 1.5 / DISK_DIST, v.min(axis=0)


def clamp_bound(b, mask: np.ndarray, extent: float = EXTENT, n_cos: int = 32, n_phi: int = 64) -> np.ndarray:
    """(C,) mask mean of ``SUN_RADIANCE ∫_cone max(0, −f|μ_o|) dω`` at the pixel centres: what pbrt-v3's
    clamp of negative series values adds over the preview (module docstring).  The cone integral is the
    midpoint rule in ``(1 − cos, φ)`` about the light's axis, ``n_cos × n_phi`` directions of equal solid
    angle (:meth:`Sun.sample` at the cell centres), on the preview's mapping (:mod:`flakedb.render.preview`)."""
    size = mask.shape[0]
    c = -extent + (np.arange(size) + 0.5) * (2 * extent / size)
    X, Y = np.meshgrid(c, c, indexing="ij")
    x, y = X[mask], Y[mask]
    n = np.stack([x, y, np.sqrt(1.0 - x * x - y * y)], axis=-1)                 # (P, 3)
    sun = Sun((0.0, 0.0, 1.0), (SUN_RADIANCE,) * 3, SUN_DEG)
    u1, u2 = np.meshgrid((np.arange(n_cos) + 0.5) / n_cos, (np.arange(n_phi) + 0.5) / n_phi, indexing="ij")
    d = sun.sample(u1.ravel(), u2.ravel())                                    # (D, 3)
    s, t = orthonormal_basis(n)
    mu_i = n[:, 2]
    phi_i = np.arctan2(t[:, 2], s[:, 2])
    cos_o = n @ d.T                                                           # (P, D)
    phi_o = np.arctan2(t @ d.T, s @ d.T)
    phi_d = np.mod(np.pi - (phi_o - phi_i[:, None]), 2 * np.pi)
    f = np.asarray(b.eval(np.broadcast_to(mu_i[:, None], cos_o.shape), -cos_o, phi_d, clamp="none"))
    neg = np.where((cos_o > 0)[..., None], np.maximum(-f, 0.0), 0.0)          # (P, D, C)
    return SUN_RADIANCE * sun.solid_angle * neg.mean(axis=1).mean(axis=0)


def render_pbrt(pbrt: str, bsdf: str, workdir, size: int, spp_side: int, threads: int | None = None) -> dict:
    """Render the two pbrt-v3 routes of ``bsdf``: {"fourier": image, "coated": image} (size, size, 3)."""
    work = Path(workdir)
    work.mkdir(parents=True, exist_ok=True)
    src = Path(bsdf).resolve()
    coated = pbrt_coated_scene(str(src), str(work / "paint.x2.bsdf"))
    routes = {"fourier": f'Material "fourier" "string bsdffile" "{src}"',
              "coated": f'Include "{Path(coated["pbrt"]).name}"\nNamedMaterial "{coated["material"]}"'}
    images = {}
    for name, material in routes.items():
        (work / f"{name}.pbrt").write_text(scene_text(material, size, spp_side, f"{name}.pfm"))
        cmd = [pbrt, "--quiet"] + ([] if threads is None else ["--nthreads", str(threads)]) + [f"{name}.pbrt"]
        subprocess.run(cmd, cwd=work, check=True)
        images[name] = read_pfm(work / f"{name}.pfm").astype(float)
    return images


def lit_check(pbrt: str, bsdf: str, workdir, size: int = 16, spp_side: int = 64, preview_spp: int = 4096,
              threads: int | None = None) -> dict:
    """Render both pbrt-v3 routes and flakedb's preview of ``bsdf`` and compare (module docstring).

    Returns a dict: the settings, seconds per renderer, and per mask ("in", "out") the means and standard
    errors (``coated``, ``fourier``, ``preview``, ``diff`` = coated − fourier), ``mirror`` (the coat
    term m), the tolerances and ``failures`` (a list of sentences; empty when every check holds)."""
    b = open_bsdf(str(bsdf))
    if b.delta is None or b.delta.get("kind") != "fresnel":
        raise ValueError(f"{bsdf}: no smooth coat (delta=fresnel) to check; the lit check needs one")
    eta = float(b.delta["eta"])
    t0 = time.perf_counter()
    img = render_pbrt(pbrt, bsdf, Path(workdir), size, spp_side, threads)
    t_pbrt = time.perf_counter() - t0
    sun = Sun((0.0, 0.0, 1.0), (SUN_RADIANCE,) * 3, SUN_DEG)
    prev = render_sphere(b, constant_environment(0.0), sun, size=size, spp=preview_spp, seed=0, extent=EXTENT,
                         threads=threads)
    t_prev = prev.seconds
    pimg = prev.image.astype(float)
    inside, outside = pixel_masks(size)
    geom, fmin = geometry_bound(b)
    mirror_map = coat_term(size, eta)
    res = {"file": str(bsdf), "size": size, "pbrt_spp": spp_side ** 2, "preview_spp": preview_spp,
           "eta": eta, "pixels_in": int(inside.sum()), "pixels_out": int(outside.sum()),
           "seconds_pbrt": t_pbrt, "seconds_preview": t_prev, "geometry_bound": geom.tolist(),
           "fmin": fmin.tolist(), "failures": []}
    for mask, name in ((inside, "in"), (outside, "out")):
        c, sc = symmetric_mean_se(img["coated"], mask)
        f, sf = symmetric_mean_se(img["fourier"], mask)
        p, sp = symmetric_mean_se(pimg, mask)
        d, sd = symmetric_mean_se(img["coated"] - img["fourier"], mask)
        m = np.full(3, mirror_map[mask].mean())
        clamp = clamp_bound(b, mask)
        tol_cp = NSIGMA * np.hypot(sc, sp) + geom + clamp + film_roundtrip_error(p) + FLOAT32_REL * np.abs(p)
        tol_d = NSIGMA * sd + film_roundtrip_error(m) + FLOAT32_REL * np.abs(c)
        values = {"coated": c, "se_coated": sc, "fourier": f, "se_fourier": sf, "preview": p, "se_preview": sp,
                  "diff": d, "se_diff": sd, "mirror": m, "clamp": clamp, "tol_cp": tol_cp, "tol_diff": tol_d}
        res[name] = {k: v.tolist() for k, v in values.items()}
        if not np.all(np.abs(c - p) <= tol_cp):
            res["failures"].append(f"{name}: coated {c} vs preview {p}: |difference| {np.abs(c - p)} > {tol_cp}")
        if not np.all(np.abs(d - m) <= tol_d):
            res["failures"].append(f"{name}: coated - fourier {d} vs the coat's mirror {m}: beyond {tol_d}")
        if name == "in" and not np.all(tol_d < 0.5 * m):
            res["failures"].append(f"in: the check does not resolve the mirror {m} (tolerance {tol_d}): more samples")
    return res


def report(res: dict) -> str:
    """Lines of the comparison: per mask, coated vs preview [%], coated − fourier vs the mirror term."""
    lines = [(f"{res['file']}: {res['size']}² px, pbrt {res['pbrt_spp']} spp (stratified), preview {res['preview_spp']} spp; "
              f"{res['pixels_in']} px in the highlight, {res['pixels_out']} out; pbrt {res['seconds_pbrt']:.1f} s, "
              f"preview {res['seconds_preview']:.1f} s; geometry bound {np.max(res['geometry_bound']):.1e}, "
              f"most negative f|mu_o| {np.min(res['fmin']):.2e}")]
    for name in ("in", "out"):
        r = {k: np.asarray(v) for k, v in res[name].items()}
        rel = 100 * (r["coated"] / r["preview"] - 1)
        rel_se = 100 * np.hypot(r["se_coated"], r["se_preview"]) / r["preview"]
        dark = 100 * (1 - r["fourier"] / r["coated"])
        lines.append(f"  {name:3s} coated {np.round(r['coated'], 4)}  preview {np.round(r['preview'], 4)}  "
                     f"coated/preview - 1 {np.round(rel, 2)} % (se {np.round(rel_se, 2)} %)")
        lines.append(f"      coated - fourier {np.round(r['diff'], 4)} (se {np.round(r['se_diff'], 4)})  "
                     f"mirror F L {np.round(r['mirror'], 4)}  fourier alone darker by {np.round(dark, 1)} %")
    lines.append("  PASS" if not res["failures"] else "  FAIL: " + "; ".join(res["failures"]))
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pbrt")
    ap.add_argument("bsdf", nargs="+")
    ap.add_argument("--workdir", required=True)
    ap.add_argument("--size", type=int, default=16)
    ap.add_argument("--spp-side", type=int, default=64, help="pbrt's stratified sampler: spp = side²")
    ap.add_argument("--preview-spp", type=int, default=4096)
    ap.add_argument("--json", help="write the results (a list, one per file) here")
    a = ap.parse_args()
    out = []
    for k, f in enumerate(a.bsdf):
        res = lit_check(a.pbrt, f, Path(a.workdir) / f"{k}_{Path(f).stem}", a.size, a.spp_side, a.preview_spp)
        print(report(res), flush=True)
        out.append(res)
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    raise SystemExit(1 if any(r["failures"] for r in out) else 0)


if __name__ == "__main__":
    main()
