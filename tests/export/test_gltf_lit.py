"""The exported .glb rendered by a real glTF renderer: three.js r187 (GLTFLoader, MeshPhysicalMaterial)
in headless Chromium (WebGL 2 on SwiftShader), driven by tools/gltf_lit.py.

Guards against: a .glb whose coat a renderer does not see (the clearcoat extension dropped or
misnamed: the furnace's coat reflection is then 0 where F(μ_v) is ≥ 0.04, and the sun's coated /
uncoated ratio 1 where it is 1 - F(μ_v) ≤ 0.96); a base colour, metalness, roughness, ior or
specular colour that three.js reads otherwise than flakedb states it does
(:func:`flakedb.export.gltf.threejs_sun_image`); a wrong light convention (a white Lambertian sphere
must give E cos θ / π).

Runs only with FLAKEDB_GLTF_RENDER=1 and node, Chromium and three + playwright-core present
(tools/gltf_lit.py's docstring says how to install them); it skips, saying which is missing,
otherwise.
"""

import importlib.util
import os
from pathlib import Path

import numpy as np
import pytest

from flakedb.export import openpbr as op
from flakedb.export.gltf import threejs_coat_fresnel, threejs_sun_image, write_gltf

spec = importlib.util.spec_from_file_location("gltf_lit", Path(__file__).resolve().parents[2] / "tools" / "gltf_lit.py")
gl = importlib.util.module_from_spec(spec)
spec.loader.exec_module(gl)

TOOL, WHY = gl.tools()
ENABLED = os.environ.get("FLAKEDB_GLTF_RENDER", "") == "1"
pytestmark = [pytest.mark.slow, pytest.mark.skipif(not ENABLED, reason="set FLAKEDB_GLTF_RENDER=1 to render in three.js"),
              pytest.mark.skipif(ENABLED and TOOL is None, reason=f"three.js render unavailable: {WHY}")]

#: |three.js / prediction - 1| per channel of a 3 x 3 mean: three.js takes E_ss from its 16 x 16
#: half-float DFG table (bilinear), the prediction by quadrature; at r = 0.4 they differ by ≤ 0.4 %
#: of E_ss, × F0 (1/E_ss - 1) ≤ 0.1 of the lobe; float32 shading; the mesh's 48 x 24 facets
#: (interpolated normals ≤ 0.1° off the sphere's) 0.2 %; 1 % in all.
RTOL_PRED = 0.01
#: the coat's reflection of a uniform sky against three.js's Schlick F_c(μ_v): its DFG table
#: interpolated linearly, (1/16)² / 8 × max|d²F/dμ²| ≤ 20 (1 - μ)³ ≤ 2.5 at μ ≥ 0.5 (the pixels),
#: 1.2e-3, + half-float rounding 5e-4 of 1, + PMREM's half-float radiance 5e-4: 3e-3
ATOL_COAT = 3e-3


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    d = tmp_path_factory.mktemp("gltf-lit")
    white = op.OpenPBRFit((1.0, 1.0, 1.0), 0.0, 1.0, 1.0, 0.0)
    fit = op.OpenPBRFit((0.70, 0.45, 0.20), 0.3, 0.4, 1.5, 0.0, specular_color=(0.3, 0.5, 0.8),
                        specular_ior_relative=3.0)
    g_white, g = write_gltf(d / "white.glb", white, "white"), write_gltf(d / "fit.glb", fit, "fit")
    bare = gl.without_clearcoat(g, d / "fit.nocoat.glb")
    head = [{"glb": str(g_white), "sun": {"direction": [0.0, 0.0, 1.0], "irradiance": 1.0}, "environment": None}]
    imgs, info = gl.render(head + gl.renders_for(g, bare), TOOL)
    return {"white": imgs[0], "four": imgs[1:], "fit": fit, "info": info}


def test_light_convention(rendered):
    """A white Lambertian sphere under a sun of irradiance 1 on the view axis: cos θ / π."""
    img = gl.grid32(rendered["white"])
    mu = gl.mu_v_means()[0, 4]                                   # the centre pixel (16, 16)
    assert img[16, 16] == pytest.approx(np.full(3, mu / np.pi), rel=1e-3)
    assert rendered["info"]["webgl2"] and rendered["info"]["three"] == "187"


def test_coat_is_rendered(rendered):
    """The coat: under the sun, coated / uncoated = 1 - F_c(μ_v) (three.js's coat at the view end);
    in the uniform sky (L = 1) coated - (1 - F_c) uncoated = F_c(μ_v), 0.04 at the centre (= the
    exact F(0°; 1.5))."""
    r = gl.analyse(rendered["fit"], *rendered["four"])
    assert r["coat_sun_ratio_minus_1_minus_Fc_max"] < 1e-3, r
    assert r["coat_furnace_minus_Fc_schlick_max"] < ATOL_COAT, r
    assert r["coat_furnace_centre"] == pytest.approx([0.04] * 3, abs=ATOL_COAT)
    assert float(threejs_coat_fresnel(1.0)) == pytest.approx(0.04, abs=2e-4)   # 2^-12.54 of 0.96 at normal


def test_colours_match_prediction(rendered):
    """Off the highlight three.js renders what flakedb says it does (threejs_sun_image) to RTOL_PRED;
    its difference from the fitted model is three.js's material (the prediction's), not the file."""
    sun = gl.grid32(rendered["four"][0])
    pred = threejs_sun_image(rendered["fit"], 32, gl.sun_direction(gl.SUN_DEG), pixel_size=2 * gl.EXTENT / gl.SIZE)
    np.testing.assert_allclose(gl.means(sun), gl.means(pred), rtol=RTOL_PRED)
    r = gl.analyse(rendered["fit"], *rendered["four"])
    assert np.all(np.array(r["dE00_three_vs_model"]) <= np.array(r["dE00_prediction_vs_model"]) + 116 / 3 * RTOL_PRED)
