"""A lit render of the coated Mitsuba route (flakedb.render.mitsuba.coated): the coat's mirror
highlight is there.

Guards against: a coated route whose smooth coat no longer reflects the light source (the
``measured`` table alone, what ``--no-coat`` writes, is ``F(θ) L_sun`` darker in the highlight);
a coated route that adds the mirror where the source is not mirrored (off the highlight it must
equal the table alone); a route that disagrees with flakedb's own preview of the exact BSDF (the
table + the exact delta, :func:`flakedb.render.preview.render_sphere`) under the same light.

Scene: the unit sphere seen orthographically along -z; a disk light of angular radius
:data:`SUN_DEG` behind the camera (on the view axis, so the image is radially symmetric and the
two renderers' image orientations cannot differ); no environment.  The coat mirrors the light
where the normal is within SUN_DEG / 2 of the axis: image radius < sin(SUN_DEG / 2).  Pixels whose
farthest corner is inside sin(SUN_DEG / 2 − 2°) (2° ≫ the coat lobe's GGX α = 0.01 rad) are fully in
the highlight; those whose nearest corner is outside sin(SUN_DEG / 2 + 2°) are fully out of it.
"""

import math

import numpy as np
import pytest

from flakedb.bsdf import open_bsdf, write_bsdf
from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.render import mitsuba as fm
from flakedb.render.preview import Sun, constant_environment, render_sphere
from tests.render.test_mitsuba import synthetic_table

SUN_DEG = 30.0          # the light's angular radius
SUN_RADIANCE = 4.0
EXTENT = 0.5            # the image spans [-EXTENT, EXTENT]² of the sphere
SIZE = 16
SPP = 256
RUNS = 4                # independent renders per route: their spread gives the standard error


def mitsuba_image(mi, bsdf: dict, seed: int) -> np.ndarray:
    T = mi.ScalarTransform4f
    dist = 1000.0
    r = dist * math.tan(math.radians(SUN_DEG))
    cam = T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]) @ T().scale([EXTENT, EXTENT, 1.0])
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 2},
        "sensor": {"type": "orthographic", "to_world": cam, "near_clip": 0.1, "far_clip": 10.0,
                   "film": {"type": "hdrfilm", "width": SIZE, "height": SIZE, "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "seed": seed}},
        # a disk facing the sphere (-z) at distance 1000: angular radius SUN_DEG within 0.1 %
        "sun": {"type": "disk", "to_world": T().translate([0, 0, dist]) @ T().rotate([1, 0, 0], 180) @ T().scale([r, r, 1]),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": SUN_RADIANCE}}},
        "sphere": {"type": "sphere", "radius": 1.0, "bsdf": bsdf},
    })
    return np.asarray(mi.render(scene, spp=SPP, seed=seed), dtype=float)


def pixel_masks():
    """(inside, outside) boolean (SIZE, SIZE): pixels wholly in / wholly out of the highlight."""
    e = np.linspace(-EXTENT, EXTENT, SIZE + 1)
    lo, hi = np.minimum(np.abs(e[:-1]), np.abs(e[1:])), np.maximum(np.abs(e[:-1]), np.abs(e[1:]))
    lo = np.where(e[:-1] * e[1:] < 0, 0.0, lo)                     # the pixel straddles the axis
    far = np.hypot(hi[:, None], hi[None, :])
    near = np.hypot(lo[:, None], lo[None, :])
    inside = far < math.sin(math.radians(SUN_DEG / 2 - 2))
    outside = (near > math.sin(math.radians(SUN_DEG / 2 + 2))) & (far < 0.95)
    return inside, outside


@pytest.fixture(scope="module")
def mi():
    mitsuba = pytest.importorskip("mitsuba")
    mitsuba.set_variant("scalar_rgb")
    return mitsuba


def test_coated_route_shows_the_coat_highlight(mi, tmp_path):
    src = tmp_path / "paint.bsdf"
    write_bsdf(src, synthetic_table())
    b = open_bsdf(src)
    coated = fm.export_coated(src, tmp_path / "coated.tensor", res=48, n_theta=16)["bsdf"]
    coated = dict(coated, body=dict(coated["body"], filename=str(tmp_path / "coated.tensor")))
    fm.export_measured(src, tmp_path / "bare.tensor", res=48, n_theta=16)
    bare = {"type": "measured", "filename": str(tmp_path / "bare.tensor")}
    inside, outside = pixel_masks()
    assert inside.sum() >= 4 and outside.sum() >= 20

    def stats(images, mask):
        """Mean over the runs of the mask's pixel mean, and its standard error (from the runs' spread)."""
        v = np.array([im[mask].mean(0) for im in images])               # (RUNS, 3)
        return v.mean(0), v.std(0, ddof=1) / math.sqrt(len(v))

    runs = {name: [mitsuba_image(mi, d, seed) for seed in range(RUNS)] for name, d in (("coated", coated), ("bare", bare))}
    sun = Sun((0.0, 0.0, 1.0), (SUN_RADIANCE,) * 3, SUN_DEG)
    env = constant_environment(0.0)
    prev = [render_sphere(b, env, sun, size=SIZE, spp=SPP, seed=s, extent=EXTENT, threads=1).image.astype(float)
            for s in range(RUNS)]
    F = fresnel_dielectric(1.0, b.delta["eta"]).R      # the highlight pixels see the coat within 7° of normal
    F_hi = fresnel_dielectric(math.cos(math.radians(SUN_DEG / 2)), b.delta["eta"]).R
    for mask, name in ((inside, "in"), (outside, "out")):
        c, sc = stats(runs["coated"], mask)
        m, sm = stats(runs["bare"], mask)
        p, sp = stats(prev, mask)
        # 5 standard errors of the difference, plus the measured grid's resampling error (docs/renderers.md:
        # ≤ 1 % of the table's value at 48² x 16, the furnace test's bound)
        tol_cp = 5 * np.hypot(sc, sp) + 0.01 * m
        tol_cm = 5 * np.hypot(sc, sm) + 0.01 * m
        assert np.all(np.abs(c - p) <= tol_cp), (name, c, p, tol_cp)            # the coated route = the exact paint
        if name == "in":                                                       # the coat's mirror: F L_sun more
            lo, hi = F * SUN_RADIANCE, F_hi * SUN_RADIANCE
            assert np.all(c - m >= lo - tol_cm) and np.all(c - m <= hi + tol_cm), (c - m, lo, hi, tol_cm)
            assert np.all(lo - tol_cm > 0.5 * lo)                                # the check resolves F L_sun
        else:                                                                  # no mirror of the sun here
            assert np.all(np.abs(c - m) <= tol_cm), (c - m, tol_cm)
