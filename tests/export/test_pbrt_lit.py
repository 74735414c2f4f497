"""A lit render of the pbrt-v3 routes (tools/pbrt_lit.py): the coated route (``pbrt_coated_scene``: ``mix``
0.5 of ``glass`` Kr 2 Kt 0 and the table ×2) shows the coat's mirror highlight, ``Material "fourier"``
alone lacks exactly that, and the coated route equals flakedb's preview of the exact BSDF.

Guards against: a coated pbrt scene whose smooth coat no longer reflects the light (a ``mix`` amount or
Kr that halves or drops the mirror: coated − fourier is then not ``F(θ) L`` in the highlight); a coated
scene that adds light where the source is not mirrored (off the highlight it must equal the table
alone); a pbrt-v3 reading of the file (direction mapping, channel rebuild, the ×2 table) that differs
from flakedb's own evaluation under the same light.  The scene, the masks and the tolerances are in the
docstring of tools/pbrt_lit.py.  pbrt-v3 is on neither PyPI nor Debian: the render test runs when
``FLAKEDB_PBRT`` names a pbrt-v3 binary (built as docs/renderers.md says) and is skipped otherwise; the
tool's own arithmetic (error estimate, masks, mirror term) is tested always.
"""

import importlib.util
import math
import os
from pathlib import Path

import numpy as np
import pytest

from flakedb.bsdf import write_bsdf
from flakedb.optics.fresnel import fresnel_dielectric
from tests.render.test_mitsuba import ETA, synthetic_table

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("pbrt_lit", ROOT / "tools" / "pbrt_lit.py")
pbrt_lit = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(pbrt_lit)

SIZE = 16
SPP_SIDE = 32           # pbrt: 32² = 1024 stratified samples per pixel
PREVIEW_SPP = 1024


@pytest.fixture(scope="module")
def pbrt():
    exe = os.environ.get("FLAKEDB_PBRT")
    if not exe:
        pytest.skip("FLAKEDB_PBRT is not set: set it to a pbrt-v3 binary (built from source as docs/renderers.md "
                    "says; pbrt-v3 is on neither PyPI nor Debian) to run the pbrt-v3 lit render")
    if not (Path(exe).is_file() and os.access(exe, os.X_OK)):
        pytest.fail(f"FLAKEDB_PBRT={exe!r} is not an executable file: point it at pbrt-v3's build/pbrt")
    return exe


def test_pbrt_coated_route_shows_the_coat_highlight(pbrt, tmp_path):
    src = tmp_path / "paint.bsdf"
    write_bsdf(src, synthetic_table())
    res = pbrt_lit.lit_check(pbrt, src, tmp_path / "work", size=SIZE, spp_side=SPP_SIDE, preview_spp=PREVIEW_SPP,
                             threads=1)
    assert res["pixels_in"] >= 4 and res["pixels_out"] >= 20
    assert not res["failures"], pbrt_lit.report(res)
    # the highlight pixels see the coat within 15° of normal: the mirror is F(0°) L to 1 % (F(15°) / F(0°) = 1.004)
    F0 = fresnel_dielectric(1.0, ETA).R * pbrt_lit.SUN_RADIANCE
    assert np.allclose(res["in"]["mirror"], F0, rtol=0.01)


def test_symmetric_standard_error_matches_the_noise():
    """Pixels of a symmetric expected image plus independent noise of known σ: the orbit-spread error of
    the mask mean is σ / √N within its own sampling error (one image: ~150 dof, ±6 % at 1 sd; the mean of
    40 images ±1 %, and E[s] < σ by < 1 % at this dof: 5 % is over 5 sd).  Orbits mixing pixels of different
    expectation (the image varies by more than 100 σ across the mask) would inflate it many times."""
    rng = np.random.default_rng(7)
    size = 16
    a = np.abs(np.arange(size) - (size - 1) / 2)
    expected = np.cos(np.hypot(a[:, None], a[None, :]) / 4)[..., None] * np.array([1.0, 2.0, 3.0])
    _, outside = pbrt_lit.pixel_masks(size)
    sigma = np.array([0.01, 0.02, 0.05])
    est = []
    for _ in range(40):
        img = expected + sigma * rng.standard_normal(expected.shape)
        mean, se = pbrt_lit.symmetric_mean_se(img, outside)
        est.append(se)
        assert np.all(np.abs(mean - expected[outside].mean(0)) < 5 * sigma / math.sqrt(outside.sum()))
    ratio = np.mean(est, axis=0) / (sigma / math.sqrt(outside.sum()))
    assert np.all(np.abs(ratio - 1) < 0.05), ratio
    with pytest.raises(ValueError, match="symmetric"):
        pbrt_lit.symmetric_mean_se(expected, np.triu(np.ones((size, size), bool)))


def test_masks_and_mirror_term():
    """The masks are the highlight's pixels and none else: every inside pixel's mirror term is F L over
    its whole area, every outside pixel's is 0; both masks hold pixels."""
    inside, outside = pbrt_lit.pixel_masks(SIZE)
    m = pbrt_lit.coat_term(SIZE, ETA)
    F0 = fresnel_dielectric(1.0, ETA).R * pbrt_lit.SUN_RADIANCE
    F_edge = fresnel_dielectric(math.cos(math.radians(pbrt_lit.SUN_DEG / 2)), ETA).R * pbrt_lit.SUN_RADIANCE
    assert inside.sum() >= 4 and outside.sum() >= 20 and not np.any(inside & outside)
    assert np.all((m[inside] >= F0 * (1 - 1e-12)) & (m[inside] <= F_edge))
    assert np.all(m[outside] == 0)


def test_film_matrices_are_inverse_pairs():
    """pbrt-v3's RGB -> XYZ -> RGB film round trip is the identity to its constants' 6 digits (a mistyped
    constant would move it by > 1e-4), and what it does to a near-zero channel is what the bound adds."""
    P = pbrt_lit.PBRT_XYZ_TO_RGB @ pbrt_lit.PBRT_RGB_TO_XYZ
    assert np.max(np.abs(P - np.eye(3))) < 1e-6
    v = np.array([0.5, 0.3, 4e-5])                                   # cadmium yellow off the highlight
    assert np.allclose(pbrt_lit.film_roundtrip_error(v), np.abs(P @ v - v), rtol=0, atol=1e-15)  # P v - v cancels: float64 to 1e-16
