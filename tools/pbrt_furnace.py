"""Furnace check of the pbrt-v3 routes (docs/renderers.md, "pbrt-v3"): render a unit sphere under a uniform
white environment (L = 1) with pbrt-v3's path tracer, once with the ``fourier`` material alone and once with
the coated material of :func:`flakedb.render.mitsuba.coated.pbrt_coated_scene`, and compare each
view-angle ring with what the file says: the table's directional albedo (flakedb's reader) and, for the
coated route, + F(μ, η) of the coat's mirror.  Needs a pbrt-v3 binary (build notes in docs/renderers.md);
not part of ``make test``.

    python tools/pbrt_furnace.py PBRT_BINARY PAINT.bsdf WORKDIR [--spp 64]
"""

import argparse
import subprocess
from pathlib import Path

import numpy as np

from flakedb.bsdf.dispatch import open_bsdf
from flakedb.optics.fresnel import fresnel_dielectric_real
from flakedb.render.mitsuba.coated import pbrt_coated_scene

FOV_DEG, DIST, RES = 26.0, 5.0, 96
RINGS = ((0.97, 1.0), (0.85, 0.88), (0.70, 0.73), (0.49, 0.52), (0.25, 0.28))
SCENE = """LookAt 0 0 {dist}  0 0 0  0 1 0
Camera "perspective" "float fov" [{fov}]
Sampler "halton" "integer pixelsamples" [{spp}]
Integrator "path" "integer maxdepth" [5]
Film "image" "integer xresolution" [{res}] "integer yresolution" [{res}] "string filename" "{out}"
WorldBegin
LightSource "infinite" "rgb L" [1 1 1]
AttributeBegin
{material}
Shape "sphere" "float radius" 1
AttributeEnd
WorldEnd
"""


def read_pfm(path):
    with open(path, "rb") as f:
        kind = f.readline().strip()
        w, h = map(int, f.readline().split())
        scale = float(f.readline())
        d = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4").reshape(h, w, 3 if kind == b"PF" else 1)
    return d[::-1]


def view_cosines(h, w):
    """μ = cos(view, normal) of each pixel's primary ray on the unit sphere (NaN off the sphere)."""
    t = np.tan(np.radians(FOV_DEG) / 2)
    ys, xs = np.mgrid[0:h, 0:w]
    d = np.stack([(2 * (xs + 0.5) / w - 1) * t, (1 - 2 * (ys + 0.5) / h) * t, -np.ones((h, w))], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.array([0.0, 0.0, DIST])
    b = d @ o
    disc = b * b - (o @ o - 1)
    hit = disc > 0
    p = o + (-b - np.sqrt(np.where(hit, disc, 0)))[..., None] * d
    return np.where(hit, -(p * d).sum(-1), np.nan)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("pbrt")
    ap.add_argument("bsdf")
    ap.add_argument("workdir")
    ap.add_argument("--spp", type=int, default=64)
    a = ap.parse_args()
    work = Path(a.workdir)
    work.mkdir(parents=True, exist_ok=True)
    src = Path(a.bsdf).resolve()
    b = open_bsdf(str(src))
    coated = pbrt_coated_scene(str(src), str(work / "paint.x2.bsdf"))
    eta = None if b.delta is None else float(b.delta["eta"])
    routes = {"fourier": (f'Material "fourier" "string bsdffile" "{src}"', None),
              "coated": (f'Include "{Path(coated["pbrt"]).name}"\nNamedMaterial "{coated["material"]}"', eta)}
    for name, (material, coat_eta) in routes.items():
        (work / f"{name}.pbrt").write_text(SCENE.format(dist=DIST, fov=FOV_DEG, spp=a.spp, res=RES,
                                                         out=f"{name}.pfm", material=material))
        subprocess.run([a.pbrt, "--quiet", f"{name}.pbrt"], cwd=work, check=True)
        img = read_pfm(work / f"{name}.pfm")
        mu = view_cosines(*img.shape[:2])
        for lo, hi in RINGS:
            m = (mu >= lo) & (mu < hi)
            expect = np.array([b.albedo(np.array([x])).ravel() for x in mu[m]])
            if coat_eta is not None:
                expect = expect + fresnel_dielectric_real(mu[m], coat_eta)[:, None]
            got, e = img[m].mean(0), expect.mean(0)
            print(f"{name:8s} {np.degrees(np.arccos(0.5 * (lo + hi))):5.1f} deg  pbrt {np.round(got, 4)}  "
                  f"file {np.round(e, 4)}  rel {np.round(100 * (got / e - 1), 2)} %")


if __name__ == "__main__":
    main()
