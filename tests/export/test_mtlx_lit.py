"""The exported .mtlx rendered by MaterialX's own GLSL renderer (``materialx`` 1.39,
``PyMaterialXRenderGlsl.GlslRenderer``; headless: Xvfb + Mesa llvmpipe), driven by tools/mtlx_lit.py.

Guards against: a .mtlx whose coat MaterialX does not render (``coat_weight`` 0 or the coat inputs
misnamed: the furnace's coat reflection is then 0 where F(μ_v; 1.5) ≥ 0.04, and the sun's coated /
uncoated ratio 1 where it is t_c ≤ 0.96); a base colour, metalness, roughness, specular colour or
``specular_ior`` that MaterialX's ``open_pbr_surface`` reads otherwise than flakedb states it does
(:func:`flakedb.export.materialx_glsl.materialx_sun_image`; e.g. ``specular_ior`` written relative
to the coat, n_s instead of n_s η_c); a wrong light, camera or colour convention (a white Lambertian
sphere must give E cos θ / π, to MaterialX's 1e-3 lobe throughput); a fitted material further from
flakedb's preview of the exact BSDF than MaterialX's closures make it.

Runs where MaterialX's GLSL renderer imports and a display or ``xvfb-run`` is present
(``apt-get install -y xvfb libgl1-mesa-dri libglx-mesa0``); skipped, saying which is missing,
otherwise.  The render itself (shader compilation on llvmpipe) takes ~1.5 s per image.
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from flakedb.bsdf import open_bsdf, write_bsdf
from flakedb.colour.tolerance import delta_E_2000
from flakedb.export import openpbr as op
from flakedb.export.blender import model_sun_image, sun_direction
from flakedb.export.materialx import write_mtlx
from flakedb.export.materialx_glsl import materialx_sun_image
from flakedb.render.preview import Environment, Sun, render_sphere
from tests.export.test_renderers import model_table

spec = importlib.util.spec_from_file_location("mtlx_lit", Path(__file__).resolve().parents[2] / "tools" / "mtlx_lit.py")
ml = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ml)

TOOL, WHY = ml.tools()
pytestmark = [pytest.mark.slow, pytest.mark.skipif(TOOL is None, reason=f"MaterialX GLSL render unavailable: {WHY}")]

#: |MaterialX / prediction - 1| per channel of a 3 x 3 mean: float32 shading (1e-6), the view vector
#: within 1e-4 rad of the axis (EYE_Z; the lobes' slope in μ_v: ≤ 1e-4 relative), the sphere's 96 x 192
#: facets (normals interpolated linearly between vertices 1.9° apart, renormalised: ≤ 1.4e-4 rad; the
#: lobe's relative slope ≤ 5 per rad: 7e-4); measured 4.6e-4 (bpy-free, llvmpipe): 2e-3.
RTOL_PRED = 2e-3
#: the coat's reflection of the uniform sky against MaterialX's FIS estimate: float32 sums of 64
#: samples (1e-6) and the same facet normals (dF/dμ ≤ 0.2 at μ ≥ 0.5 × 1.4e-4 rad: 3e-5); 1e-4.
ATOL_COAT = 1e-4
#: the coat's sun ratio (coated / uncoated) against t_c: float32 and facets, as above
ATOL_RATIO = 1e-4


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    d = tmp_path_factory.mktemp("mtlx-lit")
    truth = op.OpenPBRFit((0.70, 0.45, 0.20), 0.3, 0.4, 1.5, 0.0, specular_color=(0.3, 0.5, 0.8),
                          specular_ior_relative=3.0)
    write_bsdf(d / "model.bsdf", model_table(truth), truncation=0.0)
    b = open_bsdf(d / "model.bsdf")
    fit = op.fit_openpbr(b)
    white = write_mtlx(d / "white.mtlx", op.OpenPBRFit((1.0, 1.0, 1.0), 0.0, 1.0, 1.0, 0.0), "white")
    g = write_mtlx(d / "fit.mtlx", fit, "fit")
    bare = ml.without_coat(g, d / "fit.nocoat.mtlx")
    # the bites: the file with its coat switched off, and specular_ior written relative to the coat
    off = ml.with_inputs(g, d / "fit.coat-off.mtlx", coat_weight=0.0)
    wrong = ml.with_inputs(g, d / "fit.ior-relative.mtlx", specular_ior=fit.specular_ior_relative)
    head = [{"mtlx": str(white), "sun": {"direction": [0.0, 0.0, 1.0], "irradiance": 1.0}, "environment": None}]
    bites = ml.renders_for(off, bare) + ml.renders_for(wrong, bare)[:1]
    imgs, info = ml.render(head + ml.renders_for(g, bare) + bites, TOOL)
    return {"white": imgs[0], "four": imgs[1:5], "off": imgs[5:9], "wrong_sun": imgs[9], "fit": fit, "b": b,
            "info": info}


def test_light_convention(rendered):
    """A white Lambertian sphere under a directional light of intensity 1 on the view axis:
    cos θ / π times MaterialX's lobe throughput at F0 = 0 (0.999: materialx_sun_image's doctest)."""
    img = ml.grid32(rendered["white"])
    pred = materialx_sun_image(op.OpenPBRFit((1.0, 1.0, 1.0), 0.0, 1.0, 1.0, 0.0), 32)
    assert img[16, 16] == pytest.approx(pred[16, 16], rel=RTOL_PRED)
    assert img[16, 16, 0] == pytest.approx(float(np.sqrt(1 - 2 * (1.05 / 32) ** 2)) / np.pi, rel=2e-3)
    assert rendered["info"]["materialx"].startswith("1.39")


def test_coat_is_rendered(rendered):
    """The coat: under the sun, coated / uncoated = t_c(μ_v) (0.956–0.960 here: 1 - A(μ_v; F0 = 0.04),
    MaterialX's albedo fit, not 1 - F); in the uniform sky (L = 1) coated - t_c uncoated = the
    coat's FIS reflection = F(μ_v; 1.5) comp, 0.040 at the centre (the exact F(0°; 1.5))."""
    r = ml.analyse(rendered["fit"], *rendered["four"])
    assert r["coat_sun_ratio_minus_t_c_max"] < ATOL_RATIO, r
    assert r["coat_furnace_minus_fis_max"] < ATOL_COAT, r
    assert r["coat_furnace_minus_F_exact_max"] < 2 * ATOL_COAT, r
    assert r["coat_furnace_centre"] == pytest.approx([0.04] * 3, abs=ATOL_COAT)


def test_coat_switched_off_fails(rendered):
    """The bite: the same file with ``coat_weight`` 0 fails both coat checks by over 100 times their
    tolerances (its sun ratio is far from t_c; its furnace 'coat reflection' far from F: with
    ``coat_weight`` 0 alone MaterialX also reads ``specular_ior`` as the base's index in air, η_s =
    n_s η_c instead of n_s, so the base changes too)."""
    r = ml.analyse(rendered["fit"], *rendered["off"])
    assert r["coat_furnace_minus_fis_max"] > 100 * ATOL_COAT, r
    assert r["coat_sun_ratio_minus_t_c_max"] > 100 * ATOL_RATIO, r
    print("coat switched off:", {k: r[k] for k in ("coat_sun_ratio_minus_t_c_max", "coat_furnace_minus_fis_max",
                                                    "coat_furnace_centre")})


def test_colours_match_prediction(rendered):
    """Off the highlight MaterialX renders what flakedb says it does (materialx_sun_image) to
    RTOL_PRED; a file with ``specular_ior`` written relative to the coat (n_s, not n_s η_c) does
    not; MaterialX is no further from flakedb's preview of the exact BSDF than the prediction is
    (to the ΔE00 of RTOL_PRED), and the model's own image agrees with that preview."""
    d = sun_direction(ml.SUN_DEG)
    fit = rendered["fit"]
    sun = ml.grid32(rendered["four"][0])
    pred = materialx_sun_image(fit, 32, d)
    np.testing.assert_allclose(ml.means(sun), ml.means(pred), rtol=RTOL_PRED)
    wrong = ml.means(ml.grid32(rendered["wrong_sun"]))
    assert np.abs(wrong / ml.means(pred) - 1).max() > 10 * RTOL_PRED
    print("specular_ior relative: |MaterialX / prediction - 1| max", np.abs(wrong / ml.means(pred) - 1).max())
    pv = render_sphere(rendered["b"], Environment(kind="constant", radiance=(0, 0, 0)),
                       Sun.from_irradiance(d, (1, 1, 1), 2.0), size=32, spp=16, jitter=False).image.astype(float)
    de = delta_E_2000(ml.lab(ml.means(sun)), ml.lab(ml.means(pv)))
    de_pred = delta_E_2000(ml.lab(ml.means(pred)), ml.lab(ml.means(pv)))
    assert np.all(de <= de_pred + 116 / 3 * RTOL_PRED), (de, de_pred)
    print("dE00 MaterialX vs preview", de, "prediction vs preview", de_pred)
    assert delta_E_2000(ml.lab(ml.means(model_sun_image(fit, 32, d))), ml.lab(ml.means(pv))).max() < 1.0


@pytest.fixture(scope="module")
def usd_rendered(tmp_path_factory):
    """A metal fit whose base lobe index is 1 (as metallic silver's and pearl white's), its .usda read back
    with usd-core into MaterialX's own UsdPreviewSurface node (tools/mtlx_lit.py --usd), with and
    without clearcoat, and the same file with ``ior`` the base's index as flakedb wrote it before."""
    pytest.importorskip("pxr", reason="usd-core (pxr) is not installed")
    from flakedb.export.usd import write_usda

    d = tmp_path_factory.mktemp("usd-mtlx")
    fit = op.OpenPBRFit((0.6, 0.6, 0.62), 1.0, 0.5, 1.5, 0.0, specular_ior_relative=1.0)
    u = write_usda(d / "silver.usda", fit, "silver")
    jobs = ml.renders_for(ml.usd_preview_mtlx(u, d / "a.mtlx"), ml.usd_preview_mtlx(u, d / "b.mtlx", clearcoat=0.0))
    jobs += ml.renders_for(ml.usd_preview_mtlx(u, d / "c.mtlx", ior=1.0),
                           ml.usd_preview_mtlx(u, d / "e.mtlx", ior=1.0, clearcoat=0.0))[:2]
    imgs, _ = ml.render(jobs, TOOL)
    return imgs


def test_usd_route_keeps_the_coat(usd_rendered):
    """UsdPreviewSurface takes the clear coat's index from ``ior`` (its specification; MaterialX's node does):
    flakedb.export.usd writes the coat's 1.5 there, so MaterialX draws the coat: coated / clearcoat-0 under
    the sun = 1 - F(μ_v; 1.5) within MaterialX's albedo fit of the coat (0.956–0.960 for 0.944–0.960, as the
    .mtlx route's t_c) and the uniform sky's coat reflection at the centre, coated − t_c · clearcoat-0 (t_c the
    sun's ratio at that pixel: what the coat passes of the base), F(0°; 1.5) = 0.040.  The bite: ``ior`` = the
    base lobe's 1, as written before, gives no coat (ratio 1)."""
    sun, sun_b, sky, sky_b, sun_old, sun_old_b = usd_rendered
    r = ml.analyse_usd(sun, sun_b, sky, sky_b)
    lo, hi = r["coat_sun_ratio_range"]
    assert 0.950 <= lo and hi <= 0.961, r
    t_c = ml.grid32(sun)[16, 16] / ml.grid32(sun_b)[16, 16]
    coat = ml.grid32(sky)[16, 16] - t_c * ml.grid32(sky_b)[16, 16]
    print("USD route in MaterialX: sun ratio", r["coat_sun_ratio_range"], "coat reflection at the centre", coat)
    np.testing.assert_allclose(coat, 0.04, atol=2e-3)
    old = ml.analyse_usd(sun_old, sun_old_b, sky, sky_b)
    assert old["coat_sun_ratio_range"][0] > 0.99, old
