"""Sparkle in the angle-indexed material (flakedb.export.sparkle): the glint layer of the Blender node group and
the MaterialX graph.

Guards against: cell normals that do not follow the lobe they realise; a cell weight that does not keep the
smooth lobe's mean off the normal view; a glint width that is not the flake's diffraction; a layer whose count
of glints above the texture model's fixed threshold strays from the model's away from its reference geometry;
a MaterialX graph that MaterialX refuses; and, in Cycles, a node group that is not the layer (wrong frame,
weight, occupancy or cell size: world units), a glint count off the model's, or a mean off the smooth render's.
"""

import json
import math
from pathlib import Path

import numpy as np
import pytest

import flakedb
from flakedb.bsdf import open_bsdf
from flakedb.compose.orchestrate import compose
from flakedb.export import cpa
from flakedb.export import sparkle as sp
from flakedb.export.blender import bpy_available, cpa_inputs, ggx_lobe_height_correlated, render_cycles_patch, sun_disk
from flakedb.export.materialx import cpa_mtlx_text
from flakedb.paint.recipe import load_recipe
from flakedb.paint.texture_inputs import texture_stack
from flakedb.texture.instruments import Observer
from flakedb.texture.model import directional_geometry, sparkle_indices
from tests.blender_python import blender_python
from tests.mtlx_glsl import validated_glsl

RECIPES = Path(flakedb.__file__).parent / "catalog" / "recipes"
SILVER = load_recipe(RECIPES / "metallic-silver.yaml")
#: A layer of metallic silver's numbers (design_from_recipe on its n = 32 cpa fit: lobe 2, α 0.28; 16 µm flakes).
LAYER = sp.SparkleLayer(2, 1.0, 15.0, 0.28, sp.glint_alpha(16.0), 0.4674, {})
V0 = np.array([0.0, 0.0, 1.0])


def _dirs(view_deg, light_deg):
    tv, tl = math.radians(view_deg), math.radians(light_deg)
    return np.array([-math.sin(tv), 0.0, math.cos(tv)]), np.array([math.sin(tl), 0.0, math.cos(tl)])


def test_cell_normals_follow_the_lobe():
    """The cells' normals (sample_normals of uniform u₁, u₂) have GGX's projected-area law: the fraction with
    tan θ ≤ t is t² / (α² + t²) (closed form of ∫ D cos θ dω), and their azimuths are uniform."""
    u = (np.arange(200_000) + 0.5) / 200_000
    rng = np.random.default_rng(3)
    m = sp.sample_normals(u, rng.random(u.size), 0.28)
    tan = np.hypot(m[:, 0], m[:, 1]) / m[:, 2]
    for t in (0.05, 0.2, 0.5, 1.5):
        assert np.mean(tan <= t) == pytest.approx(t * t / (0.28 ** 2 + t * t), abs=2e-5)
    np.testing.assert_allclose(np.linalg.norm(m, axis=-1), 1.0, atol=1e-12)
    assert abs(np.mean(np.arctan2(m[:, 1], m[:, 0]) > 0) - 0.5) < 5e-3


def _layer_mean_ratio(layer, view_deg, light_deg, half_angle_deg=2.0, weight=True, reach=0.7, n_r=240, n_psi=48):
    """Mean over cells (∫ p(m) f β_cell(m) dΩ_m on a polar grid about the mirror normal, log-spaced radii
    from 1e-4 to ``reach`` in the tangent plane: the glint's core and its GGX tail) over the smooth lobe's
    luminance factor under the same sun."""
    v, ld = _dirs(view_deg, light_deg)
    h0 = (ld + v) / np.linalg.norm(ld + v)
    e1, e2 = sp._frame(h0)
    edges = np.exp(np.linspace(math.log(1e-4), math.log(reach), n_r + 1))
    r = np.sqrt(edges[:-1] * edges[1:])
    psi = (np.arange(n_psi) + 0.5) * 2 * math.pi / n_psi
    R, P = np.meshgrid(r, psi, indexing="ij")
    A, B = R * np.cos(P), R * np.sin(P)
    q = h0 + A[..., None] * e1 + B[..., None] * e2
    m = q / np.linalg.norm(q, axis=-1, keepdims=True)
    dA = (0.5 * (edges[1:] ** 2 - edges[:-1] ** 2))[:, None] * (2 * math.pi / n_psi) / (1 + R * R) ** 1.5
    beta = sp.layer_luminance_factor(m, v, ld, half_angle_deg, layer, 1.0)
    if not weight:
        w = sp.cell_weight(m, v, layer.lobe_alpha, layer.glint_alpha)
        beta = beta / np.where(w > 0, w, 1.0)
    cells = layer.occupancy * np.sum(sp.ggx_D(m[..., 2], layer.lobe_alpha) * m[..., 2] * dA * beta)
    cells += layer.occupancy * math.pi * 1e-8 * float(sp.ggx_D(h0[2], layer.lobe_alpha) * h0[2]) * float(
        sp.layer_luminance_factor(h0, v, ld, half_angle_deg, layer, 1.0))            # the disc r < 1e-4
    dirs, wts = sun_disk(ld, half_angle_deg, sp.SUN_RINGS, sp.SUN_AZIMUTHS)
    hh = (dirs + v) / np.linalg.norm(dirs + v, axis=-1, keepdims=True)
    smooth = np.pi * np.sum(wts * ggx_lobe_height_correlated(v[2], dirs[:, 2], hh[:, 2], layer.lobe_alpha) * dirs[:, 2]) / ld[2]
    return cells / smooth


#: |cells' mean / smooth lobe − 1|: the narrow lobe's own width (GGX tails: O((α_g/α_k)² ln(α_k/α_g)) ≈ 0.5 %
#: for 0.011 on 0.28; the polar grid agrees with a 1201² Cartesian one to 1e-3); measured ≤ 1.1 %.
MEAN_RTOL = 0.015


@pytest.mark.parametrize("view_deg, light_deg", [(0, 20), (0, 45), (40, 10), (40, 50)])
def test_cells_keep_the_lobe_mean(view_deg, light_deg):
    """Averaged over cells, the glint layer is the smooth lobe it replaces (module docstring of
    flakedb.export.sparkle), also off the normal view; without the weight W it is 17 % off at a 40° view."""
    assert _layer_mean_ratio(LAYER, view_deg, light_deg) == pytest.approx(1.0, abs=MEAN_RTOL)
    if view_deg:
        assert abs(_layer_mean_ratio(LAYER, view_deg, light_deg, weight=False) - 1.0) > 0.1


def _flake_Y(stack, light_deg, src):
    g = directional_geometry(stack.eta, light_deg, 0.0, src, 1e-4)
    f = stack.flakes[0]
    return float(stack.y_weights @ f.reflectance(np.array([g.c]))[:, 0]) * g.t_in * g.t_out


def test_glint_width_is_the_flakes_diffraction():
    """α_g = λ / (π D): under a source far smaller than the diffraction (0.05°) an aligned cell as bright as
    the flake (R T_in T_out) peaks at the texture model's Airy peak of the median flake (peak_luminance_factor)
    within 1 % at 10° (measured 0.5 %; 15 % high at 30°, where the paraxial slope map η s is off); with D in
    mm instead of µm it would be 10⁶ off."""
    stack, _ = texture_stack(SILVER)
    L, src = 10.0, 0.05
    row = sparkle_indices(stack, Observer("pinhole", 10.0, 1e-4, src, light_deg=(L,)), L)
    lay = sp.SparkleLayer(2, 1.0, 15.0, 0.28, sp.glint_alpha(stack.flakes[0].diameter_median_um), 1.0, {})
    h = sp._mirror_normal(L)
    peak = sp.layer_luminance_factor(h, V0, sp._light(L), src, lay, _flake_Y(stack, L, src))
    peak = float(peak / sp.cell_weight(h, V0, lay.lobe_alpha, lay.glint_alpha))
    assert peak == pytest.approx(row["peak_luminance_factor"], rel=0.01)


@pytest.fixture(scope="module")
def silver_layer():
    """The silver's layer as design_from_recipe makes it from a cpa table (lobe 2 of colour 0.378 at μ_v = 1,
    the n = 32 fit's: the table enters only through that lobe's colour)."""
    table = np.zeros((4, 32, 3))
    table[2] = (0.3724, 0.3789, 0.3877)
    table[3] = (0.1793, 0.1834, 0.1924)
    return table, sp.design_from_recipe(table, (0.18, 0.28, 0.42), SILVER)


#: The layer's count against the model's away from the reference (20°, 10° source): measured −11 … +26 %
#: over sources 0.27–10° and lights 10–45° (the sun's 0.27° included); the points below: −8 … +17 %.
PREDICTION_RTOL = 0.3


@pytest.mark.parametrize("src, light", [(0.2665, 20.0), (0.2665, 45.0), (1.0, 10.0), (5.0, 30.0), (10.0, 45.0)])
def test_layer_predicts_the_models_count(silver_layer, src, light):
    """Calibrated once (its cell size, at 20° under a 10° source), the layer's expected count of glints above
    the model's fixed threshold follows the model's elsewhere, from the sun to a 10° softbox: the normals, the
    glint width and the occupancy carry the physics, not the calibration."""
    table, lay = silver_layer
    stack, _ = texture_stack(SILVER)
    row = sparkle_indices(stack, Observer("pinhole", 10.0, 1e-4, src, light_deg=(light,)), light)
    n = sp.layer_glints_per_mm2(lay, float(sp.Y_WEIGHTS @ table[lay.lobe, -1]), light, src,
                                row["glint_threshold_luminance_factor"])
    assert n == pytest.approx(row["glints_per_mm2_above_threshold"], rel=PREDICTION_RTOL)


def test_design_refuses_what_cannot_glint(silver_layer):
    """A paint without flakes, and a layer whose brightest cell stays below the model's threshold (lobe colour
    far below the flake's and occupancy 1), are refused with the numbers."""
    table, _ = silver_layer
    with pytest.raises(ValueError, match="no flakes"):
        sp.design_from_recipe(table, (0.18, 0.28, 0.42), load_recipe(RECIPES / "particle-cadmium-yellow.yaml"))
    stack, _ = texture_stack(SILVER)
    row = sparkle_indices(stack, Observer("pinhole", 10.0, 1e-4, 10.0, light_deg=(20.0,)), 20.0)
    with pytest.raises(ValueError, match="cannot reach"):
        sp.design_layer(table * 0.01, (0.18, 0.28, 0.42), eta=1.5, flake_alpha=0.2, diameter_um=16.0,
                        flake_Y=0.001, model_row=row, light_deg=20.0, half_angle_deg=10.0)


def test_materialx_graph_with_sparkle(silver_layer):
    """The .cpa.mtlx with the glint layer validates against MaterialX's standard library, GLSL is generated,
    and it carries the layer's numbers (cells per UV unit, the lobe's α, the glint's α)."""
    mx = pytest.importorskip("MaterialX", reason="materialx not installed (pip install 'flakedb[materialx]')")

    table, lay = silver_layer
    fit = cpa.CPAFit(table, (0.18, 0.28, 0.42), 1.5)
    _, scale = cpa.table_image(fit)
    nodes = sp.node_inputs(lay)
    doc = mx.createDocument()
    mx.readFromXmlString(doc, cpa_mtlx_text("t.png", scale, fit.alphas, 1.5, 32, "silver", "{}", sparkle=nodes))
    code = validated_glsl(doc, "M_silver", "cpa")
    assert "cellnoise" in code
    assert doc.getNode("glints").getInputValue("roughness")[0] == pytest.approx(lay.glint_alpha, rel=1e-6)
    assert doc.getNode("colour_2_smooth").getInputValue("in2") == pytest.approx(1.0 - lay.share, abs=1e-9)
    cells = [n for n in doc.getNodes() if n.getCategory() == "multiply" and n.getType() == "vector2"]
    assert cells[0].getInputValue("in2") == pytest.approx(nodes["cells_per_uv"], rel=1e-6)
    assert nodes["cells_per_uv"] == pytest.approx(1.0 / (lay.cell_um * 1e-6))


# --------------------------------------------------------------------------------------------
# Cycles
# --------------------------------------------------------------------------------------------
BLENDER_PYTHON, BLENDER_NOTE = blender_python()
BPY_OK, BPY_WHY = bpy_available(BLENDER_PYTHON)
needs_bpy = pytest.mark.skipif(not BPY_OK, reason=f"Blender's bpy is not available: {BPY_WHY}{BLENDER_NOTE}")


@pytest.fixture(scope="module")
def silver_cpa(tmp_path_factory):
    """The catalogue's metallic silver composed at n = 32, its cpa fit and its layer (design_from_recipe)."""
    d = tmp_path_factory.mktemp("silver")
    compose(SILVER, d, n=32)
    fit = cpa.fit_cpa(open_bsdf(d / "metallic-silver.bsdf"))
    return fit, sp.design_from_recipe(fit.table, fit.alphas, SILVER)


def _count(img, cells, light_deg, threshold):
    """Cells whose mean luminance factor π Y / cos θ_l over their pixel centres is ≥ threshold, and cells seen."""
    beta = np.pi * (img @ sp.Y_WEIGHTS) / math.cos(math.radians(light_deg))
    key = (cells[..., 0] * 1_000_003 + cells[..., 1]).ravel()
    _, inv = np.unique(key, return_inverse=True)
    cb = np.bincount(inv, beta.ravel()) / np.bincount(inv)
    return int(np.sum(cb >= threshold)), int(cb.size), beta


#: Glint count in Cycles against the texture model's (the issue's ±20 %).  At the reference the expectation
#: is the model's by construction of the cell size, so the test is of the node group in Cycles (frame, weight,
#: occupancy, world units); its Poisson spread at ~640 glints is 4 %.  At 30° it is a prediction (layer −11 %).
COUNT_RTOL = 0.2
#: Σ Cycles / Σ layer over the lit pixel centres: 16 spp of the 10° sun across a flat-topped glint (< 1 %)
#: plus the layer's 6 × 16-point sun quadrature at the glints' edges (measured 0.3 %): 3 %.
CELLS_RTOL = 0.03


@pytest.mark.slow
@needs_bpy
@pytest.mark.parametrize("light_deg", [20.0, 30.0])
def test_cycles_glint_count_matches_the_model(silver_cpa, light_deg):
    """A lit patch of metallic silver in Cycles (2.56 mm, 256 px at every pixel's centre: 10 µm pixels on 15 µm
    cells, 16 spp, a 10° sun): every cell of the patch is seen, the lit pixels are the layer's prediction from
    each cell's own random numbers, and the count of cells above the texture model's fixed threshold is the
    model's within ±20 %."""
    fit, lay = silver_cpa
    src = sp.REFERENCE_SOURCE_DEG
    stack, _ = texture_stack(SILVER)
    row = sparkle_indices(stack, Observer("pinhole", 10.0, 1e-4, src, light_deg=(light_deg,)), light_deg)
    side = 256 * 10e-6
    r = render_cycles_patch(cpa_inputs(fit.table, fit.alphas, fit.coat_ior, sp.node_inputs(lay), fit.retro_alphas), side_m=side, size=256,
                            light_deg=light_deg, half_angle_deg=src, samples=16, cells=True, python=BLENDER_PYTHON)
    n, seen, beta = _count(r["image"], r["cells"], light_deg, row["glint_threshold_luminance_factor"])
    assert seen == pytest.approx((side * 1e6 / lay.cell_um) ** 2, rel=0.02)   # + a partial row and column
    u = r["random"]
    m = sp.sample_normals(u[..., 0], u[..., 1], lay.lobe_alpha)
    pred = np.where(u[..., 2] < lay.occupancy, sp.layer_luminance_factor(
        m, V0, sp._light(light_deg), src, lay, float(sp.Y_WEIGHTS @ fit.table[lay.lobe, -1])), 0.0)
    lit = pred > 1.0
    assert beta[lit].sum() / pred[lit].sum() == pytest.approx(1.0, abs=CELLS_RTOL)
    expected = row["glints_per_mm2_above_threshold"] * (side * 1e3) ** 2
    assert n == pytest.approx(expected, rel=COUNT_RTOL), (n, expected)


#: |sparkle / smooth − 1| of the patch mean per channel (the issue's 2 %).  The cells' mean is the lobe's to
#: ≤ 1.1 % (test_cells_keep_the_lobe_mean); 128² px × 64 spp sample ~10⁶ of the patch's 7·10⁶ cells, of
#: which ~2 % are lit under the 10° sun: ≤ 0.5 % spread (three seeds: 0.998–1.001 at 20°, 1.002–1.008 at 45°).
PATCH_MEAN_RTOL = 0.02


@pytest.mark.slow
@needs_bpy
@pytest.mark.parametrize("light_deg, view_deg", [(20.0, 0.0), (45.0, 0.0), (20.0, 40.0)])
def test_cycles_mean_is_the_smooth_render(silver_cpa, light_deg, view_deg):
    """A 40 mm patch (128 px, Blackman–Harris 1.5 px, 64 spp: each sample a different cell) under a 10° sun,
    seen along its normal and at 40° from it (where the cells' weight W matters: test_cells_keep_the_lobe_mean):
    the mean with the glint layer is the smooth material's (no sparkle) within 2 % per channel."""
    fit, lay = silver_cpa
    kw = dict(side_m=0.04, size=128, light_deg=light_deg, view_deg=view_deg, half_angle_deg=sp.REFERENCE_SOURCE_DEG, samples=64,
              filter_width_px=1.5, python=BLENDER_PYTHON)
    a = render_cycles_patch(cpa_inputs(fit.table, fit.alphas, fit.coat_ior, sp.node_inputs(lay), fit.retro_alphas), **kw)["image"]
    b = render_cycles_patch(cpa_inputs(fit.table, fit.alphas, fit.coat_ior, retro_alphas=fit.retro_alphas), **kw)["image"]
    np.testing.assert_allclose(a.mean(axis=(0, 1)) / b.mean(axis=(0, 1)), 1.0, atol=PATCH_MEAN_RTOL)


def test_export_cpa_carries_the_layer(tmp_path):
    """``export(..., method="cpa", sparkle_recipe=...)`` writes the layer of design_from_recipe on its own fit
    into the JSON, the MaterialX graph (node ``glints``) and the Blender script (its node inputs, cells per UV
    unit scaled by ``uv_metres``); a non-positive ``uv_metres`` is refused before anything is written."""
    from flakedb.bsdf import write_bsdf
    from flakedb.export.registry import export
    from tests.export.test_cpa import cpa_table, truth_fit

    src = tmp_path / "model.bsdf"
    write_bsdf(src, cpa_table(truth_fit()), truncation=0.0)
    recipe = RECIPES / "metallic-silver.yaml"
    out = export(src, tmp_path / "out", method="cpa", sparkle_recipe=recipe, uv_metres=1e-3)
    d = json.loads(Path(out["files"]["fit"]).read_text())
    lay = sp.design_from_recipe(np.asarray(d["table"]), d["alphas"], SILVER)
    got = sp.SparkleLayer.from_dict(d["sparkle"])                # the JSON's table is rounded to 1e-7
    assert (got.lobe, got.reference["light_deg"]) == (lay.lobe, lay.reference["light_deg"])
    for k in ("share", "cell_um", "occupancy", "lobe_alpha", "glint_alpha"):
        assert getattr(got, k) == pytest.approx(getattr(lay, k), rel=1e-5)
    assert d["sparkle"]["node_inputs"] == sp.node_inputs(got, 1e-3)
    assert d["sparkle"]["node_inputs"]["cells_per_uv"] == pytest.approx(1e-3 / (got.cell_um * 1e-6))
    assert 'name="glints"' in Path(out["files"]["materialx"]).read_text()
    assert repr(d["sparkle"]["node_inputs"]) in Path(out["files"]["blender"]).read_text()
    with pytest.raises(ValueError, match="uv-metres"):
        export(src, tmp_path / "bad", method="cpa", sparkle_recipe=recipe, uv_metres=0.0)
    assert not (tmp_path / "bad").exists()
