"""The angle-indexed colour-table material (flakedb.export.cpa) and its routes: MaterialX graph, Blender
node group, PNG table.

Guards against: a fit that cannot recover a table made by its own model (the design, the NNLS, the
view/light convention); a model image on the sphere whose frame or φ_d convention differs from the
file's coordinates; a 16-bit PNG that does not read back as written (row order, byte order); a
MaterialX graph that MaterialX refuses or cannot generate GLSL for; a Cycles node group that is
not the model (wrong image row, wrong index x, wrong roughness mapping, a backscatter lobe not about
the view); a backscatter lobe whose cosine is carried to the wrong normal; an export command that does
not print the route's E2194 ΔE00; and, on catalogue paints rendered in Cycles, an angle-indexed route
that is not better than the single-lobe Principled route or misses the issue's E2194 target (worst
ΔE00 ≤ 2).
"""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import flakedb
from flakedb.bsdf import BSDFTable, open_bsdf, write_bsdf
from flakedb.cli.main import cli
from flakedb.colour.tolerance import delta_E_2000
from flakedb.compose.orchestrate import compose
from flakedb.export import cpa
from flakedb.export import openpbr as op
from flakedb.export.blender import (
    bpy_available,
    cpa_inputs,
    ggx_lobe_height_correlated as op_ggx,
    principled_inputs,
    render_cycles_cpa_sphere,
    render_cycles_geometries,
    render_cycles_sphere,
    sun_direction,
)
from flakedb.export.materialx import PLANE_WEIGHTS
from flakedb.export.registry import EXPORT_METHODS
from flakedb.match.fit import channels_to_Lab, geometry_directions
from flakedb.match.targets import E2194_GEOMETRIES
from flakedb.paint.recipe import load_recipe
from flakedb.rt.basis.quadrature import radau_hemisphere
from tests.blender_python import blender_python
from tests.mtlx_glsl import validated_glsl

ETA = 1.5
WL = np.arange(380.0, 781.0, 10.0)
RECIPES = Path(flakedb.__file__).parent / "catalog" / "recipes"


def truth_fit(n_table=cpa.N_TABLE):
    """A known model: smooth rows (linear in μ_v, so the smoothness penalty costs nothing), lobes on the grid."""
    mu = np.linspace(0.0, 1.0, n_table)[:, None]
    table = np.stack([(0.30, 0.20, 0.10) * (0.5 + 0.5 * mu), (0.05, 0.10, 0.20) * (1.0 + mu),
                      (0.20, 0.15, 0.02) * (1.5 - mu), (0.10, 0.10, 0.10) + 0 * mu])
    return cpa.CPAFit(table, (0.11, 0.28, 0.65), ETA)


def truth_fit_retro(n_table=cpa.N_TABLE):
    """truth_fit with a backscatter lobe (α 0.42) coloured by a fifth row."""
    mu = np.linspace(0.0, 1.0, n_table)[:, None]
    t = truth_fit(n_table)
    return cpa.CPAFit(np.concatenate([t.table, [(0.02, 0.05, 0.10) * (0.5 + mu)]]), t.alphas, ETA, retro_alphas=(0.42,))


def cpa_table(fit, h=20, L=48, M=192):
    """A reflection-only RGB Fourier table of the (non-reciprocal) model, light = the file's μ_i, view =
    μ_o, projected on cos(k φ_d) by FFT (the layout of tests/export/test_renderers.py::model_table)."""
    x = radau_hemisphere(h).x
    mu = np.concatenate([-x[::-1], x])
    phi = 2 * np.pi * np.arange(M) / M
    MI, MO, PH = np.meshgrid(x, x, phi, indexing="ij")
    f = cpa.evaluate_cpa(fit, MI, -MO, PH)
    v = np.moveaxis(f * MO[..., None], -1, 0)
    F = np.fft.rfft(v, axis=-1).real / M
    a = np.concatenate([F[..., :1], 2 * F[..., 1:L]], axis=-1)
    coeffs = np.zeros((3, 2 * h, 2 * h, L))
    coeffs[:, h:, :h] = a[:, :, ::-1]
    return BSDFTable(mu=mu, coeffs=coeffs, eta=1.0, alpha=(0.0, 0.0), delta={"kind": "fresnel", "eta": fit.coat_ior})


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("cpa") / "model.bsdf"
    write_bsdf(p, cpa_table(truth_fit()), truncation=0.0)
    return p


def test_table_file_is_the_model(model_file):
    """The helper's file holds the model in the file's convention (light μ_i, view μ_o): at random
    directions the file's value is the model's, and not the model's with light and view swapped
    (which would make the recovery test below blind to a swap in fit_cpa)."""
    b, fit = open_bsdf(model_file), truth_fit()
    rng = np.random.default_rng(3)
    mi, mo, ph = rng.uniform(0.3, 0.95, 60), -rng.uniform(0.3, 0.95, 60), rng.uniform(0, np.pi, 60)
    ex, mod, swapped = op.exact_rgb(b, mi, mo, ph), cpa.evaluate_cpa(fit, mi, mo, ph), cpa.evaluate_cpa(fit, -mo, -mi, ph)
    assert np.median(np.abs(ex / mod - 1)) < 0.01               # the file's μ interpolation between 20 nodes
    assert np.median(np.abs(ex / swapped - 1)) > 0.05


def test_fit_recovers_its_own_model(model_file, tmp_path):
    """fit_cpa on a file made by the model: the lobes found, the coat's index read from the delta, and
    every E2194 / E2539 colour within 0.5 ΔE00 (what is left is the file's own interpolation); with a
    backscatter lobe in the model, its α is found too."""
    fit = cpa.fit_cpa(open_bsdf(model_file), minimax_passes=2, alpha_grid=(0.05, 0.11, 0.28, 0.65))
    assert fit.alphas == truth_fit().alphas and fit.coat_ior == ETA
    assert fit.error["worst_dE00_E2539"] < 0.5, fit.error["dE00_E2539"]
    assert fit.error["dE00_hemisphere_70deg"]["median"] < 0.5
    write_bsdf(tmp_path / "retro.bsdf", cpa_table(truth_fit_retro()), truncation=0.0)
    fit = cpa.fit_cpa(open_bsdf(tmp_path / "retro.bsdf"), minimax_passes=2, alpha_grid=(0.05, 0.11, 0.28, 0.65),
                      retro_grid=(0.18, 0.42, 1.0))
    assert (fit.alphas, fit.retro_alphas) == (truth_fit().alphas, (0.42,))
    assert fit.error["worst_dE00_E2539"] < 0.5, fit.error["dE00_E2539"]


def test_retro_lobe_is_the_ggx_lobe_about_the_view():
    """The backscatter lobe is the GGX lobe about ω_v seen through N: when ω_v = N the two normals coincide
    and it equals the ordinary lobe (the cosine carried from its own normal to N is then 1); it peaks
    at ω_l = ω_v with D(1) G2 / (4 μ_l) = 1 / (4 π α² μ_l); and at E2194's aspecular 15° and 75° (one
    view cosine) it is larger on the light's side, which no GGX lobe about N is."""
    rng = np.random.default_rng(5)
    mu_l = rng.uniform(0.05, 1.0, 50)
    for a in (0.18, 0.42, 1.0):
        np.testing.assert_allclose(cpa.retro_lobe(mu_l, mu_l, a),
                                   op_ggx(1.0, mu_l, np.sqrt(0.5 * (1 + mu_l)), a), rtol=1e-12)
        th = rng.uniform(0.0, 1.4, 20)
        np.testing.assert_allclose(cpa.retro_lobe(np.cos(th), 1.0, a), 1.0 / (4 * np.pi * a * a * np.cos(th)), rtol=1e-12)
    gi, go, gp = geometry_directions(np.array([[45.0, 15.0], [45.0, 75.0]]))
    wl, wv = op.file_directions(gi, go, gp)
    B = cpa.lobe_basis(wv[..., 2], wl[..., 2], cpa._half_cos(wv, wl), (0.42,), (0.42,), np.sum(wv * wl, axis=-1))
    assert B[0, 1] > 6 * B[1, 1] and B[1, 2] > 6 * B[0, 2]          # measured 6.4 and 9.1


def test_sun_image_frame():
    """cpa_sun_image (lobes evaluated from world vectors) equals sun_image of evaluate_cpa (the
    file's coordinates via the per-pixel frame): two paths, one φ_d convention; and a white Lambert
    row under a sun on the view axis gives E μ / π at the centre."""
    fit, d = truth_fit(), sun_direction(35.0)
    a = cpa.cpa_sun_image(fit, 24, d)
    b = cpa.sun_image(lambda mi, mo, ph: cpa.evaluate_cpa(fit, mi, mo, ph), 24, d)
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    white = cpa.CPAFit(np.concatenate([np.ones((1, 8, 3)), np.zeros((1, 8, 3))]), (0.3,), 1.0)
    img = cpa.sun_image(lambda mi, mo, ph: cpa.evaluate_cpa(white, mi, mo, ph), 8, (0, 0, 1), extent=1.0)
    mu = math.sqrt(1 - 2 * 0.125 ** 2)
    np.testing.assert_allclose(img[3:5, 3:5], mu / np.pi, rtol=1e-3)      # the 2° disk: cos θ' average


def test_png_round_trip():
    """16-bit PNG: what is read is what was written, to the 16-bit quantum, row 0 the bottom row; the table's
    PNG (two 8-bit planes) reads back the 16-bit values exactly, and the graph's recombination of the planes
    (PLANE_WEIGHTS) is q / 65535; the quantised fit differs from the fit by at most half a quantum of each
    row's scale."""
    rng = np.random.default_rng(1)
    px = rng.uniform(0, 1, (4, 32, 3))
    back = cpa.read_png16(cpa.png16_bytes(px))
    np.testing.assert_allclose(back, px, atol=0.5 / 65535 + 1e-12)
    fit = truth_fit()
    tab, scale = cpa.table_image(fit)
    png = cpa.table_png_bytes(tab)                       # NAME.cpa.png: 16 bits in two 8-bit planes
    planes, depth = cpa.read_png(png)
    assert depth == 8 and planes.shape == (2 * len(tab), tab.shape[1], 3)
    q16 = np.round(tab * 65535.0)
    np.testing.assert_array_equal(cpa.read_table_png(png) * 65535.0, q16)
    w_hi, w_lo = PLANE_WEIGHTS                           # what the MaterialX graph computes from two texture reads
    r = len(tab)
    np.testing.assert_allclose(w_hi * planes[:r] / 255.0 + w_lo * planes[r:] / 255.0, q16 / 65535.0, rtol=0, atol=1e-15)
    q = cpa.quantised(fit)
    assert np.all(np.abs(q.table - fit.table) <= 0.5 / 65535 * scale[:, None, None] * (1 + 1e-9))


def test_materialx_graph(tmp_path):
    """`flakedb export-cpa`: the exported .cpa.mtlx validates against MaterialX's standard library, GLSL is generated for
    it, its image rows and scales are the fit's table, and its backscatter lobe's normal is the view
    direction reversed (MaterialX's ``viewdirection`` points at the surface); the command prints the
    worst E2194 ΔE00 of the route as rendered."""
    mx = pytest.importorskip("MaterialX", reason="materialx not installed (pip install 'flakedb[materialx]')")

    src = tmp_path / "model.bsdf"
    write_bsdf(src, cpa_table(truth_fit_retro()), truncation=0.0)
    r = CliRunner().invoke(cli, ["export-cpa", str(src), "--out", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(tmp_path / "out" / "model.cpa.mtlx"))
    assert len(validated_glsl(doc, "M_model", "cpa")) > 1000
    fit = cpa.CPAFit.from_dict(json.loads((tmp_path / "out" / "model.cpa.json").read_text()))
    px = cpa.read_table_png((tmp_path / "out" / "model.cpa.png").read_bytes())
    # the command prints the route's ΔE00 at the E2194 geometries, what Cycles renders (the model, to ≤ 3e-4)
    assert "in Cycles" in r.output and f"worst ΔE00 against FILE {fit.error['worst_dE00_E2194']:.2f} at the E2194" in r.output
    scales = [doc.getNode(f"colour_{k}").getInputValue("in2") for k in range(len(px))]
    table = cpa.materialx_fit(fit).table         # the lobes' colours with MaterialX's energy compensation undone
    np.testing.assert_allclose(px * np.asarray(scales)[:, None, None], table, atol=1e-4 * table.max())
    assert np.all(table[1:] < fit.table[1:] + 1e-12) and np.array_equal(table[0], fit.table[0])
    assert doc.getNode("lobe_1").getInputValue("roughness")[0] == pytest.approx(fit.alphas[0], rel=1e-6)
    retro = doc.getNode(f"lobe_{1 + len(fit.alphas)}")                 # the backscatter lobe: about -viewdirection
    assert fit.retro_alphas == (0.42,) and retro.getInputValue("roughness")[0] == pytest.approx(0.42, rel=1e-6)
    assert retro.getInput("normal").getNodeName() == "V_back"
    assert doc.getNode("V_back").getInput("in1").getNodeName() == "V_world"
    assert "cpa" in EXPORT_METHODS
    # `flakedb info` reads the .cpa.mtlx flakedb wrote (it refused it: "without flakedb's fit")
    r = CliRunner().invoke(cli, ["info", str(tmp_path / "out" / "model.cpa.mtlx")])
    assert r.exit_code == 0, r.output
    assert f"worst ΔE00 {fit.error['worst_dE00_E2194']:.2f} (E2194 geometries)" in r.output
    assert "backscatter α 0.42" in r.output and "tilted" not in r.output


def test_export_cpa_writes_the_tilted_graph_where_ggx_misses(tmp_path, monkeypatch):
    """`flakedb export-cpa` where the GGX fit misses the E2194 target (made to miss here: the GGX fit of the model
    file, its first subset, with its worst set to 3; one tilted (α, k) and one pass, to keep it short; coated-aluminium's real one is test_coated_aluminium_tilted_lobe_fit) writes the
    MaterialX graph of fit_cpa_materialx: the JSON carries it under ``materialx`` with its tilted lobe, the PNG's rows
    are its table with MaterialX's compensation undone, the last lobe's ``normal`` is the tilted normal node built from
    N_world and V_world with k (the document validates and GLSL is generated), and the command says so."""
    mx = pytest.importorskip("MaterialX", reason="materialx not installed (pip install 'flakedb[materialx]')")
    import flakedb.export.registry as reg

    src = tmp_path / "model.bsdf"
    write_bsdf(src, cpa_table(truth_fit_retro()), truncation=0.0)
    real_fit = cpa.fit_cpa

    def missing(b, **kw):
        fit = real_fit(b, max_subsets=1, minimax_passes=1, **kw)
        fit.error["worst_dE00_E2194"] = 3.0
        return fit

    real_mx = cpa.fit_cpa_materialx
    monkeypatch.setattr(reg, "fit_cpa", missing)
    monkeypatch.setattr(reg, "fit_cpa_cycles", lambda b, fit, **kw: fit)
    monkeypatch.setattr(reg, "fit_cpa_materialx", lambda b, fit, **kw: real_mx(b, fit, max_subsets=1, minimax_passes=1,
                                                                                tilt_grid=((0.06, 0.45),), **kw))
    r = CliRunner().invoke(cli, ["export-cpa", str(src), "--out", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    d = json.loads((tmp_path / "out" / "model.cpa.json").read_text())
    assert "materialx" in d and "cycles" not in d
    mfit = cpa.CPAFit.from_dict(d["materialx"])
    assert len(mfit.tilted) == 1 and mfit.error["worst_dE00_E2194"] < 3.0
    assert "a GGX lobe about a normal tilted away from the view" in r.output
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(tmp_path / "out" / "model.cpa.mtlx"))
    assert len(validated_glsl(doc, "M_model", "cpa")) > 1000
    px = cpa.read_table_png((tmp_path / "out" / "model.cpa.png").read_bytes())
    assert len(px) == 1 + len(mfit.alphas) + len(mfit.retro_alphas) + 1
    scales = [doc.getNode(f"colour_{k}").getInputValue("in2") for k in range(len(px))]
    table = cpa.materialx_fit(mfit).table
    np.testing.assert_allclose(px * np.asarray(scales)[:, None, None], table, atol=1e-4 * table.max())
    lobe = doc.getNode(f"lobe_{len(px) - 1}")
    assert lobe.getInput("normal").getNodeName() == "N_tilt_0"
    assert lobe.getInputValue("roughness")[0] == pytest.approx(mfit.tilted[0][0], rel=1e-6)
    assert doc.getNode("tilt_b_0").getInputValue("in2") == pytest.approx(mfit.tilted[0][1], rel=1e-7)   # float32
    assert doc.getNode("tilt_nV_0").getInput("in1").getNodeName() == "V_world"
    r = CliRunner().invoke(cli, ["info", str(tmp_path / "out" / "model.cpa.mtlx")])      # the graph's own fit
    assert r.exit_code == 0 and "1 tilted lobe(s)" in r.output and "MaterialX route's own fit" in r.output, r.output
    assert f"worst ΔE00 {mfit.error['worst_dE00_E2194']:.2f} (E2194" in r.output


# --------------------------------------------------------------------------------------------
# Cycles
# --------------------------------------------------------------------------------------------
BLENDER_PYTHON, BLENDER_NOTE = blender_python()
BPY_OK, BPY_WHY = bpy_available(BLENDER_PYTHON)
SIZE = 32


def compared_pixels(d, size=SIZE, extent=1.05):
    """Pixels of the sphere compared: view and sun within 80° of the normal, and the normal more than
    6° from the half vector (off the coat mirror's image of the 2° sun, which only Cycles draws)."""
    from flakedb.export.blender import sphere_normals

    N, on = sphere_normals(size, extent)
    h = np.asarray(d) + (0.0, 0.0, 1.0)
    h = h / np.linalg.norm(h)
    c80 = math.cos(math.radians(80))
    return on & (N[..., 2] > c80) & (N @ np.asarray(d) > c80) & (N @ h < math.cos(math.radians(6)))


def _lab(img, mask):
    return channels_to_Lab(np.maximum(img[mask] * np.pi, 1e-6), "rgb", WL)


#: |Cycles / model - 1| allowed for the sum over the compared pixels, per channel: 64 spp x ~600
#: pixels of a per-sample spread below 20 % (the 2° disk across a lobe of α ≥ 0.1) is < 0.1 %,
#: plus the 128 x 64 facets' normals (a few 1e-3 near the limb): 1 %.
CYCLES_SUM_RTOL = 0.01
#: What the angle-indexed route reaches in Cycles (median ΔE00 over the compared pixels against the
#: exact paint; docs/renderers.md): metallic silver 3.0 (single lobe 5.6), particle pearlescent 7.5 (8.2), measured at n = 32.
CPA_MEDIAN_BOUND = {"metallic-silver": 3.5, "particle-pearlescent": 8.0}


#: |Cycles / model - 1| at a geometry (the plane's mean): 64 px x 256 spp of a per-sample spread below
#: 5 % (the 0.5° sun across lobes of α ≥ 0.11) is 4e-4 at 4 σ, plus float32 film: 1e-3 (measured ≤ 3e-4).
CYCLES_GEOMETRY_RTOL = 1e-3


@pytest.mark.skipif(not BPY_OK, reason=f"Blender's bpy is not available: {BPY_WHY}{BLENDER_NOTE}")
def test_cycles_node_group_is_the_model():
    """The node group in Cycles at the six E2194 geometries (a plane under a 0.5° sun, every pixel one
    geometry: :func:`flakedb.export.blender.render_cycles_geometries`) renders the numpy model
    (:func:`flakedb.export.cpa.evaluate_cpa`, with a backscatter lobe) within CYCLES_GEOMETRY_RTOL per
    channel: the image row per lobe, the N·V index, the roughness mapping and the backscatter lobe's
    normal (the view) are the model's.  With the table's rows reversed (a wrong row index), or the
    backscatter lobe drawn about N (its Normal input left unlinked), the model is far off."""
    fit = truth_fit_retro()
    g = np.asarray(E2194_GEOMETRIES, float)
    gi, go, gp = geometry_directions(g)
    model = np.pi * cpa.evaluate_cpa(fit, gi, go, gp)
    cy = render_cycles_geometries(g, cpa=cpa_inputs(fit.table, fit.alphas, fit.coat_ior, retro_alphas=fit.retro_alphas),
                                  python=BLENDER_PYTHON)
    np.testing.assert_allclose(cy, model, rtol=CYCLES_GEOMETRY_RTOL)
    wrong = cpa.CPAFit(fit.table[::-1], fit.alphas, fit.coat_ior, retro_alphas=fit.retro_alphas)
    assert np.max(np.abs(np.pi * cpa.evaluate_cpa(wrong, gi, go, gp) / model - 1)) > 0.1
    about_n = cpa.CPAFit(fit.table, fit.alphas + fit.retro_alphas, fit.coat_ior)
    assert np.max(np.abs(np.pi * cpa.evaluate_cpa(about_n, gi, go, gp) / model - 1)) > 0.1


#: The catalogue paints of docs/renderers.md (issue 23's four), composed at n = 32, and red metallic, whose
#: first lobe subset misses the target (3.17) so that the fit's search for a subset that meets it is run.
#: The one catalogue recipe that GGX lobes cannot bring to the target, the clear-coated bare aluminium panel
#: (7.71; test_coated_aluminium_out_of_reach), is test_coated_aluminium_beckmann_in_cycles.
PAINTS = ["metallic-silver", "particle-cadmium-yellow", "particle-pearlescent", "tri-coat-pearl-white", "red-metallic"]
#: The issue's target at the E2194 geometries in Cycles: worst ΔE00 ≤ 2 against the exact paint, every paint.
E2194_BOUND = 2.0


@pytest.fixture(scope="module")
def catalogue(tmp_path_factory):
    """paint -> (its exact file at n = 32, its cpa fit), composed and fitted once per module."""
    cache = {}

    def get(paint):
        if paint not in cache:
            d = tmp_path_factory.mktemp(paint)
            compose(load_recipe(RECIPES / f"{paint}.yaml"), d, n=32)
            b = open_bsdf(d / f"{paint}.bsdf")
            cache[paint] = (b, cpa.fit_cpa(b))
        return cache[paint]
    return get


def _e2194_lab_exact(b):
    g = np.asarray(E2194_GEOMETRIES, float)
    return g, channels_to_Lab(np.pi * op.exact_rgb(b, *geometry_directions(g)), "rgb", WL)


@pytest.mark.slow
@pytest.mark.skipif(not BPY_OK, reason=f"Blender's bpy is not available: {BPY_WHY}{BLENDER_NOTE}")
@pytest.mark.parametrize("paint", PAINTS)
def test_cycles_e2194_worst_within_2(paint, catalogue):
    """The issue's target, in the renderer: the catalogue paint (n = 32) fitted by ``fit_cpa`` and rendered
    by the node group in Cycles at the six E2194 geometries (:func:`render_cycles_geometries`: a plane
    under a 0.5° sun, 256 spp) has its worst ΔE00 against the exact paint ≤ E2194_BOUND.  Measured
    (docs/renderers.md): 0.87 (silver), 0.40 (cadmium yellow), 1.69 (pearlescent: 3.68 without the
    backscatter lobe, whose one view cosine at aspecular 15° and 75° no lobe about N can tell apart),
    0.36 (pearl white), 1.90 (red metallic: 3.17 with its first lobe subset)."""
    b, fit = catalogue(paint)
    g, lab_exact = _e2194_lab_exact(b)
    rf = render_cycles_geometries(g, cpa=cpa_inputs(fit.table, fit.alphas, fit.coat_ior, retro_alphas=fit.retro_alphas),
                                  python=BLENDER_PYTHON)
    de = delta_E_2000(channels_to_Lab(np.maximum(rf, 1e-6), "rgb", WL), lab_exact)
    assert de.max() <= E2194_BOUND, dict(zip(g[:, 1].tolist(), np.round(de, 2).tolist()))


@pytest.mark.slow
@pytest.mark.skipif(not BPY_OK, reason=f"Blender's bpy is not available: {BPY_WHY}{BLENDER_NOTE}")
@pytest.mark.parametrize("paint", ["metallic-silver", "particle-pearlescent"])
def test_cycles_cpa_beats_single_lobe(paint, catalogue):
    """The catalogue paint (n = 32) under a 2° sun at 35° from the view axis (32 px, 64 spp, black
    world): the node group in Cycles renders the model (the sum over the compared pixels within
    CYCLES_SUM_RTOL per channel), and against the exact paint (:func:`flakedb.export.cpa.sun_image`
    of the file, deterministic) its median ΔE00 is below the single-lobe Principled route's and
    within CPA_MEDIAN_BOUND; at the six E2194 geometries its worst ΔE00 is below the single lobe's."""
    b, fit = catalogue(paint)
    d = sun_direction(35.0)
    mask = compared_pixels(d)
    exact = cpa.sun_image(lambda mi, mo, ph: op.exact_rgb(b, mi, mo, ph), SIZE, d)
    cy = render_cycles_cpa_sphere(fit.table, fit.alphas, fit.coat_ior, retro_alphas=fit.retro_alphas, size=SIZE,
                                  samples=64, direction=d, python=BLENDER_PYTHON)["image"]
    model = cpa.cpa_sun_image(fit, SIZE, d)
    np.testing.assert_allclose(cy[mask].sum(0), model[mask].sum(0), rtol=CYCLES_SUM_RTOL)
    pbr = op.fit_openpbr(b)
    single = render_cycles_sphere(pbr, size=SIZE, samples=64, direction=d, python=BLENDER_PYTHON)["image"]
    de_cpa = np.median(delta_E_2000(_lab(cy, mask), _lab(exact, mask)))
    de_single = np.median(delta_E_2000(_lab(single, mask), _lab(exact, mask)))
    assert de_cpa < de_single and de_cpa <= CPA_MEDIAN_BOUND[paint], (de_cpa, de_single)
    # at the six E2194 geometries, rendered (a plane under a sun; test_cycles_node_group_is_the_model)
    g, lab_exact = _e2194_lab_exact(b)
    worst = {}
    for route, kw in (("cpa", {"cpa": cpa_inputs(fit.table, fit.alphas, fit.coat_ior, retro_alphas=fit.retro_alphas)}),
                      ("single", {"inputs": principled_inputs(pbr)})):
        rf = render_cycles_geometries(g, python=BLENDER_PYTHON, **kw)
        worst[route] = float(delta_E_2000(channels_to_Lab(np.maximum(rf, 1e-6), "rgb", WL), lab_exact).max())
    assert worst["cpa"] < worst["single"], worst


#: Half-vector polar angles (about N) of E2194's aspecular 15° and 75° (45° illumination): both are seen at
#: μ_v = cos 30°, on either side of the normal, so every table colour C_k(μ_v) is shared between them and only
#: the lobes' shapes can tell them apart.
THETA_H_15, THETA_H_75 = math.radians(7.5), math.radians(37.5)


def ggx_tail_ratio(alpha):
    """D(θ_75; α) / D(θ_15; α) of GGX, D = α² / (π (α² cos²θ + sin²θ)²): the closed form of what a GGX lobe
    about N gives aspecular 75° relative to 15° at E2194 (G2 and 1 / (4 μ_v μ_l) are the same at both).  Its
    derivative in α² has the sign of cos²θ_15 sin²θ_75 − cos²θ_75 sin²θ_15 > 0, so it increases with α and its
    infimum is the α → 0 limit (sin θ_15 / sin θ_75)⁴ = 2.11e-3."""
    a2 = np.asarray(alpha, float) ** 2
    return ((a2 * math.cos(THETA_H_15) ** 2 + math.sin(THETA_H_15) ** 2)
            / (a2 * math.cos(THETA_H_75) ** 2 + math.sin(THETA_H_75) ** 2)) ** 2


def test_ggx_tail_ratio_at_e2194_15_75():
    """The model's lobes at E2194 aspecular 75° against 15° (one view cosine): a GGX lobe about N (what Cycles'
    Glossy BSDF and MaterialX's generalized_schlick_bsdf draw) gives the closed form :func:`ggx_tail_ratio`,
    which grows with α from (sin 7.5° / sin 37.5°)⁴ = 2.11e-3; the Lambert term gives 1 and the backscatter lobe
    more than 1.  So no non-negative mix of them, whatever its colours, makes 75° darker than 2.11e-3 of 15°
    (test_coated_aluminium_out_of_reach)."""
    g = np.asarray(E2194_GEOMETRIES, float)
    _, mu_v, _ = geometry_directions(g)
    assert np.allclose(g[[1, 4], 1], [15.0, 75.0]) and np.isclose(abs(mu_v[1]), abs(mu_v[4]))
    from flakedb.export.materialx_render import geometry_vectors

    wl, wv = geometry_vectors(g[[1, 4]])
    h = (wl + wv) / np.linalg.norm(wl + wv, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.arccos(h[:, 2]), [THETA_H_15, THETA_H_75], rtol=1e-12)
    alphas = np.geomspace(1e-3, 1.0, 41)            # Cycles' and the model's least α is 1e-3
    lobe = np.array([op_ggx(wv[:, 2], wl[:, 2], h[:, 2], a) for a in alphas])        # (A, 2)
    np.testing.assert_allclose(lobe[:, 1] / lobe[:, 0], ggx_tail_ratio(alphas), rtol=1e-10)
    assert np.all(np.diff(lobe[:, 1] / lobe[:, 0]) > 0)
    limit = (math.sin(THETA_H_15) / math.sin(THETA_H_75)) ** 4
    assert limit == pytest.approx(2.1135e-3, rel=1e-4)
    assert limit < lobe[0, 1] / lobe[0, 0] < limit * (1 + 2e-4)        # 2 α² (cot²θ_15 − cot²θ_75) = 1.1e-4 above
    cos_vl = np.einsum("gi,gi->g", wl, wv)
    for a in cpa.RETRO_ALPHA_GRID:
        r = cpa.retro_lobe(wl[:, 2], cos_vl, a)
        assert r[1] > r[0]


#: The least worst ΔE00 over aspecular 15° and 75° that any non-negative mix of the model's lobes can reach
#: on coated-aluminium (a lower bound for the route in Cycles and in MaterialX: MaterialX's energy compensation
#: is a factor of μ_v, the same at both): measured 5.56.
COATED_ALUMINIUM_FLOOR = 5.0


@pytest.mark.slow
def test_coated_aluminium_out_of_reach(tmp_path):
    """Why coated-aluminium misses the E2194 target in the ``cpa`` route with GGX lobes (MaterialX's only
    distribution; Cycles takes Beckmann lobes there: test_coated_aluminium_beckmann_in_cycles): its exact
    aspecular 75° is 7e-6 of its 15° (a Beckmann α 0.1 conductor under the coat), and the route's 75° is at least
    (sin 7.5° / sin 37.5°)⁴ = 2.11e-3 of its 15° (test_ggx_tail_ratio_at_e2194_15_75).  The best any RGB colour m
    at 15° (with 2.11e-3 m at 75°, the most favourable the lobes allow) does is max(ΔE00) 5.56 > 2
    (:func:`flakedb.export.cpa.ggx_route_floor`, the number ``export-cpa`` prints for MaterialX); the bite: with
    the ratio of the exact paint the same search reaches 0."""
    compose(load_recipe(RECIPES / "coated-aluminium.yaml"), tmp_path, n=32)
    b = open_bsdf(tmp_path / "coated-aluminium.bsdf")
    g, _ = _e2194_lab_exact(b)
    exact = np.pi * op.exact_rgb(b, *geometry_directions(g))
    assert cpa.GGX_MIN_RATIO_75_15 == pytest.approx(float(ggx_tail_ratio(0.0)), rel=1e-12)
    lowest = cpa.ggx_route_floor(b)
    print("coated-aluminium: exact 75/15", exact[4] / exact[1], "least worst dE00 at 15/75", lowest)
    assert lowest > COATED_ALUMINIUM_FLOOR > E2194_BOUND
    assert cpa.ggx_route_floor(b, ratio=float(exact[4].mean() / exact[1].mean())) < 0.05


# --------------------------------------------------------------------------------------------
# Beckmann lobes (the Cycles node group's option)
# --------------------------------------------------------------------------------------------
def beckmann_lambda_exact(alpha, mu):
    """Beckmann's Smith Λ in closed form (Heitz 2014, eq. 69 / Walter et al. 2007, eq. 25):
    Λ = (erf(a) − 1) / 2 + exp(−a²) / (2 a √π), a = 1 / (α tan θ)."""
    from scipy.special import erf

    a = mu / (alpha * np.sqrt(1.0 - mu * mu))
    return 0.5 * (erf(a) - 1.0) + np.exp(-a * a) / (2.0 * a * np.sqrt(np.pi))


#: Walter et al.'s rational Λ against the closed form, relative in G1: the approximation's own error, 0.35 % in
#: their paper (measured here on α 0.05…1, θ 1…89°: 0.36 %, at α 0.05 and θ 89°): 0.4 %.
BECKMANN_G1_RTOL = 4e-3


def test_beckmann_lobe_closed_forms():
    """The numpy Beckmann lobe (Cycles' Glossy BSDF, Beckmann): its D is normalised (∫ D cos θ_h dω = 1 by
    quadrature for α 0.05…0.6), its Smith G1 = 1 / (1 + Λ) is the closed form's within BECKMANN_G1_RTOL,
    the lobe is D G2 / (4 μ_v μ_l) with the height-correlated G2 and is reciprocal; the bite: it is not the GGX
    lobe of the same α (its tail falls as exp(−tan²θ_h / α²): at E2194 aspecular 75° vs 15°, 3e-25 of GGX's
    2.1e-3 ratio at α 0.1)."""
    from flakedb.export.blender import beckmann_lambda, beckmann_lobe_height_correlated

    x, w = np.polynomial.legendre.leggauss(400)
    c = 0.5 * (x + 1.0)                                              # cos θ_h on (0, 1)
    for alpha in (0.05, 0.11, 0.28, 0.6):
        a2 = alpha * alpha
        D = np.exp(-(1 - c * c) / (c * c * a2)) / (np.pi * a2 * c ** 4)
        assert 2 * np.pi * np.sum(0.5 * w * D * c) == pytest.approx(1.0, rel=1e-6)
    mu = np.cos(np.radians(np.linspace(1.0, 89.0, 177)))
    for alpha in (0.05, 0.1, 0.3, 0.6, 1.0):
        g_approx = 1.0 / (1.0 + beckmann_lambda(alpha * alpha, mu))
        g_exact = 1.0 / (1.0 + beckmann_lambda_exact(alpha, mu))
        assert np.abs(g_approx / g_exact - 1).max() <= BECKMANN_G1_RTOL, (alpha, np.abs(g_approx / g_exact - 1).max())
    rng = np.random.default_rng(3)
    mv, ml, ch = rng.uniform(0.05, 1, 50), rng.uniform(0.05, 1, 50), rng.uniform(0.5, 1, 50)
    a = 0.2
    f = beckmann_lobe_height_correlated(mv, ml, ch, a)
    D = np.exp(-(1 - ch ** 2) / (ch ** 2 * a * a)) / (np.pi * a * a * ch ** 4)
    G2 = 1.0 / (1.0 + beckmann_lambda(a * a, mv) + beckmann_lambda(a * a, ml))
    np.testing.assert_allclose(f, D * G2 / (4 * mv * ml), rtol=1e-12)
    np.testing.assert_allclose(f, beckmann_lobe_height_correlated(ml, mv, ch, a), rtol=1e-12)
    from flakedb.export.materialx_render import geometry_vectors

    wl, wv = geometry_vectors(np.asarray(E2194_GEOMETRIES, float)[[1, 4]])
    h = (wl + wv) / np.linalg.norm(wl + wv, axis=-1, keepdims=True)
    beck = beckmann_lobe_height_correlated(wv[:, 2], wl[:, 2], h[:, 2], 0.1)
    ggx = op_ggx(wv[:, 2], wl[:, 2], h[:, 2], 0.1)
    assert beck[1] / beck[0] < 1e-20 and ggx[1] / ggx[0] > cpa.GGX_MIN_RATIO_75_15


@pytest.mark.skipif(not BPY_OK, reason=f"Blender's bpy is not available: {BPY_WHY}{BLENDER_NOTE}")
def test_cycles_beckmann_node_group_is_the_model():
    """The node group with Beckmann lobes (``cpa_inputs(..., distribution="beckmann")``) renders the numpy model
    with Beckmann lobes (:func:`flakedb.export.cpa.evaluate_cpa` of a fit with ``distribution="beckmann"``) at the
    six E2194 geometries within CYCLES_GEOMETRY_RTOL per channel, the model averaged over the render's 0.5° sun
    disk (the steeper Beckmann lobe makes the disk's average differ from the point value by up to 1.2e-3 on this
    table, GGX's by 3.4e-4); the bite: the same table with GGX lobes (the node's distribution not set) is further
    off than 10 CYCLES_GEOMETRY_RTOL."""
    from flakedb.export.blender import sun_disk
    from flakedb.export.materialx_render import geometry_vectors

    t = truth_fit_retro()
    fit = cpa.CPAFit(t.table, t.alphas, t.coat_ior, retro_alphas=t.retro_alphas, distribution="beckmann")
    g = np.asarray(E2194_GEOMETRIES, float)
    gi, go, gp = geometry_directions(g)
    wl, wv = geometry_vectors(g)
    model = np.zeros((len(g), 3))
    for k in range(len(g)):                             # π f averaged over the 0.5° sun, over μ_l of its centre
        for l, w in zip(*sun_disk(wl[k], 0.5, n_rings=8, n_azimuth=16)):
            model[k] += w * np.pi * cpa.evaluate_cpa(fit, *geometry_directions_of(l, wv[k]))[0] * l[2] / wl[k, 2]
    cy = render_cycles_geometries(g, cpa=cpa_inputs(fit.table, fit.alphas, fit.coat_ior, retro_alphas=fit.retro_alphas,
                                                    distribution="beckmann"), python=BLENDER_PYTHON)
    print("Cycles Beckmann / model - 1, max", np.abs(cy / model - 1).max())
    np.testing.assert_allclose(cy, model, rtol=CYCLES_GEOMETRY_RTOL)
    ggx = np.pi * cpa.evaluate_cpa(t, gi, go, gp)
    assert np.abs(cy / ggx - 1).max() > 10 * CYCLES_GEOMETRY_RTOL


def test_materialx_refuses_beckmann():
    """MaterialX's generalized_schlick_bsdf has GGX only: a Beckmann fit is refused for the graph, saying so."""
    t = truth_fit()
    with pytest.raises(ValueError, match="GGX only"):
        cpa.materialx_fit(cpa.CPAFit(t.table, t.alphas, t.coat_ior, distribution="beckmann"))
    with pytest.raises(ValueError, match="distribution"):
        cpa.fit_cpa(None, distribution="phong")


@pytest.mark.slow
@pytest.mark.skipif(not BPY_OK, reason=f"Blender's bpy is not available: {BPY_WHY}{BLENDER_NOTE}")
def test_coated_aluminium_beckmann_in_cycles(tmp_path):
    """The clear-coated bare aluminium panel (a Beckmann α 0.1 conductor under the coat), out of the GGX route's
    reach (test_coated_aluminium_out_of_reach: ≥ 5.56), reaches the issue's target in Cycles with Beckmann lobes:
    ``fit_cpa_cycles`` of a GGX fit that misses (its first lobe subset only, to keep the test short: the full GGX
    search takes ~110 s and stops at 7.72) chooses the Beckmann fit, and Cycles renders it at the six E2194
    geometries within E2194_BOUND of the exact paint (measured 0.27; the model 0.28).  The bite: the GGX fit's own
    worst is above 5."""
    compose(load_recipe(RECIPES / "coated-aluminium.yaml"), tmp_path, n=32)
    b = open_bsdf(tmp_path / "coated-aluminium.bsdf")
    ggx = cpa.fit_cpa(b, max_subsets=1, minimax_passes=2)
    assert ggx.error["worst_dE00_E2194"] > 5.0
    fit = cpa.fit_cpa_cycles(b, ggx)
    assert fit.distribution == "beckmann" and fit.error["worst_dE00_E2194"] <= E2194_BOUND
    g, lab_exact = _e2194_lab_exact(b)
    rf = render_cycles_geometries(g, cpa=cpa_inputs(fit.table, fit.alphas, fit.coat_ior, retro_alphas=fit.retro_alphas,
                                                    distribution=fit.distribution), python=BLENDER_PYTHON)
    de = delta_E_2000(channels_to_Lab(np.maximum(rf, 1e-6), "rgb", WL), lab_exact)
    print("coated-aluminium, Beckmann lobes in Cycles: dE00 per E2194 geometry", np.round(de, 2))
    assert de.max() <= E2194_BOUND, dict(zip(g[:, 1].tolist(), np.round(de, 2).tolist()))


# --------------------------------------------------------------------------------------------
# Tilted lobes (the MaterialX graph's option where GGX lobes about N miss the target)
# --------------------------------------------------------------------------------------------
def _tilted_lobe_by_vectors(wv, wl, alpha, k):
    """The tilted lobe from explicit vectors, as MaterialX's ``mx_generalized_schlick_bsdf`` computes it
    (pbrlib/genglsl: N' = normalize(N (1 + k μ_v²) − k μ_v ω_v), H = normalize(L + V), D = mx_ggx_NDF,
    G2 = mx_ggx_smith_G2, response D G2 / (4 N'·V)), divided by μ_l: independent of cpa.tilted_cosines."""
    from flakedb.export.materialx_glsl import ggx_ndf, smith_G2

    mu_v = wv[:, 2]
    n = np.array([0.0, 0.0, 1.0]) * (1.0 + k * mu_v * mu_v)[:, None] - k * mu_v[:, None] * wv
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    h = (wv + wl) / np.linalg.norm(wv + wl, axis=1, keepdims=True)
    nv, nl, nh = (np.einsum("pi,pi->p", n, x) for x in (wv, wl, h))
    f = ggx_ndf(nh, alpha) * smith_G2(nl, nv, alpha) / (4.0 * nv * wl[:, 2])
    return np.where((nl > 0) & (wl[:, 2] > 0), f, 0.0), n


#: The tilted lobe from the model's cosines against the vectors' (both in double precision, a few dozen
#: operations, the GGX D's 1 / (…)² amplifying the cosine's rounding by up to 4 / α² at the peak): 1e-9.
RTOL_TILTED = 1e-9


def test_tilted_lobe_is_materialx_closure():
    """cpa.tilted_lobe (from the cosines the model knows) is MaterialX's closure built from explicit vectors with
    the graph's tilted normal, at random directions, for tilts either way; k = 0 is the GGX lobe about N; N'·ω_v > 0
    (MaterialX would flip N' otherwise); k = 0.304 tilts the normal at μ_v = cos 30° by 7.5°, onto the half vector of
    E2194's aspecular 15° (45° light), and then the lobe's 75° / 15° ratio (one table column) is ≤ 4 α⁴ / (1 + α²)²
    (N'·h = cos 45° at 75°; 3e-6 at α 0.03): far below the 2.11e-3 that no GGX lobe about N goes under
    (test_ggx_tail_ratio_at_e2194_15_75), which is why the route floor does not bind it.  The bite: the lobe about
    N (k = 0) at the same geometries gives that floor's ratio."""
    rng = np.random.default_rng(7)

    def hemi(n):
        v = rng.normal(size=(n, 3))
        v[:, 2] = np.abs(v[:, 2]) + 0.05
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    wv, wl = hemi(400), hemi(400)
    cos_h = (wv + wl)[:, 2] / np.linalg.norm(wv + wl, axis=1)
    cos_vl = np.einsum("pi,pi->p", wv, wl)
    for alpha in (0.03, 0.11, 0.42):
        for k in (-0.3, 0.15, 0.45, 0.9):
            ours = cpa.tilted_lobe(wv[:, 2], wl[:, 2], cos_h, cos_vl, alpha, k)
            ref, n = _tilted_lobe_by_vectors(wv, wl, alpha, k)
            np.testing.assert_allclose(ours, ref, rtol=RTOL_TILTED, atol=0.0)
            assert np.all(np.einsum("pi,pi->p", n, wv) > 0)
            nv, nl, nh = cpa.tilted_cosines(wv[:, 2], wl[:, 2], cos_h, cos_vl, k)
            h = (wv + wl) / np.linalg.norm(wv + wl, axis=1, keepdims=True)
            np.testing.assert_allclose(nh, np.einsum("pi,pi->p", n, h), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(cpa.tilted_lobe(wv[:, 2], wl[:, 2], cos_h, cos_vl, alpha, 0.0),
                                   op_ggx(wv[:, 2], wl[:, 2], cos_h, alpha), rtol=1e-12)
    from flakedb.export.materialx_render import geometry_vectors

    wl2, wv2 = geometry_vectors(np.asarray(E2194_GEOMETRIES, float)[[1, 4]])         # aspecular 15°, 75°
    h2 = (wl2 + wv2) / np.linalg.norm(wl2 + wv2, axis=-1, keepdims=True)
    c_vl = np.einsum("gi,gi->g", wl2, wv2)
    _, _, nh = cpa.tilted_cosines(wv2[:, 2], wl2[:, 2], h2[:, 2], c_vl, 0.304)
    assert math.degrees(math.acos(min(nh[0], 1.0))) < 0.01                            # 15°: on the lobe's axis
    assert nh[1] == pytest.approx(math.cos(math.radians(45.0)), abs=2e-4)             # 75°: 45° off it
    for alpha in (0.03, 0.06):
        lobe = cpa.tilted_lobe(wv2[:, 2], wl2[:, 2], h2[:, 2], c_vl, alpha, 0.304)
        assert lobe[1] / lobe[0] <= 1.01 * 4 * alpha ** 4 / (1 + alpha * alpha) ** 2 < 0.03 * cpa.GGX_MIN_RATIO_75_15
        about_n = cpa.tilted_lobe(wv2[:, 2], wl2[:, 2], h2[:, 2], c_vl, alpha, 0.0)
        assert about_n[1] / about_n[0] > cpa.GGX_MIN_RATIO_75_15


def test_tilted_fit_round_trip_and_materialx_colours():
    """A fit with a tilted lobe survives to_dict / from_dict (evaluate_cpa the same), and materialx_fit undoes
    MaterialX's energy compensation at the tilted lobe's own N'·V: at every table node the compensated colour
    F (1 + F (1 − E_ss(N'·V)) / E_ss) is the model's colour.  The bite: taking E_ss at μ_v (N's) instead is off."""
    from flakedb.export.materialx_glsl import ggx_dir_albedo_analytic

    t = truth_fit_retro()
    mu = np.linspace(0.0, 1.0, t.n_table)[:, None]
    fit = cpa.CPAFit(np.concatenate([t.table, [(0.3, 0.2, 0.1) * (0.5 + mu)]]), t.alphas, ETA,
                     retro_alphas=t.retro_alphas, tilted=((0.06, 0.45),))
    back = cpa.CPAFit.from_dict(json.loads(json.dumps(fit.to_dict())))
    assert back.tilted == fit.tilted
    mi, mo, ph = np.array([0.7, 0.4]), np.array([-0.8, -0.5]), np.array([0.3, 2.5])
    np.testing.assert_allclose(cpa.evaluate_cpa(back, mi, mo, ph), cpa.evaluate_cpa(fit, mi, mo, ph), rtol=1e-6)  # 7 digits
    F = cpa.materialx_fit(fit).table[-1]
    m = mu[:, 0]
    nv = cpa.tilted_cosines(m, m, m, m, 0.45)[0]
    np.testing.assert_allclose(nv, (m * (1.0 + 0.45 * m * m) - 0.45 * m) / np.sqrt(1.0 + 0.45 ** 2 * m * m * (1.0 - m * m)),
                               rtol=1e-12, atol=1e-15)
    ess = ggx_dir_albedo_analytic(np.maximum(nv, 1e-8), 0.06, 1.0, 1.0)[:, None]
    # where MaterialX's rational E_ss is ≤ 1 (at α 0.06 it exceeds 1 by ≤ 2e-3 for N'·V > 0.9, where
    # compensated_lobe_colours leaves F = C: docs/renderers.md)
    below = ess[:, 0] <= 1.0
    assert below.sum() > 20
    np.testing.assert_allclose((F * (1 + F * (1 - ess) / ess))[below], fit.table[-1][below], rtol=1e-9)
    ess_n = ggx_dir_albedo_analytic(np.maximum(m, 1e-8), 0.06, 1.0, 1.0)[:, None]
    assert np.abs(F * (1 + F * (1 - ess_n) / ess_n) / fit.table[-1] - 1)[below].max() > 1e-3


@pytest.mark.slow
def test_coated_aluminium_tilted_lobe_fit():
    """coated-aluminium, out of the reach of GGX lobes about N (test_coated_aluminium_out_of_reach: ≥ 5.56),
    reaches the E2194 target with one tilted lobe (fit_cpa_materialx, what export-cpa writes into the MaterialX
    graph; the first lobe subset, as the full search would stop there): the model's worst ΔE00 ≤ E2194_BOUND
    (measured 1.88) where the GGX fit's is above 5 (the bite)."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        compose(load_recipe(RECIPES / "coated-aluminium.yaml"), d, n=32)
        b = open_bsdf(Path(d) / "coated-aluminium.bsdf")
    ggx = cpa.fit_cpa(b, max_subsets=1, minimax_passes=2)
    assert ggx.error["worst_dE00_E2194"] > 5.0 and not ggx.tilted
    fit = cpa.fit_cpa_materialx(b, ggx, max_subsets=1)
    print("coated-aluminium, tilted lobe", fit.tilted, "E2194 per geometry",
          [round(g["dE00"], 2) for g in fit.error["dE00_E2194"]], "E2539 worst", fit.error["worst_dE00_E2539"])
    assert len(fit.tilted) == 1 and fit.distribution == "ggx"
    assert fit.error["worst_dE00_E2194"] <= E2194_BOUND


def geometry_directions_of(wl, wv):
    """(mu_i, mu_o, phi_d) arrays of one (light, view) pair of unit vectors in the surface frame (normal +z), the
    file's coordinates of :func:`flakedb.export.openpbr.file_directions`."""
    tv, tl = wv[:2], wl[:2]
    den = np.linalg.norm(tv) * np.linalg.norm(tl)
    cos_dphi = float(np.dot(tv, tl) / den) if den > 0 else 1.0
    return np.array([wl[2]]), np.array([-wv[2]]), np.array([np.pi - np.arccos(np.clip(cos_dphi, -1.0, 1.0))])


def _brute_albedo(fit, mu_v, n_t=500, n_p=400):
    """The model's directional albedo (coat mirror + table lobes) by a midpoint rule over ω_l (θ, φ): independent
    of cpa.lobe_albedos, fine enough for lobes of α ≥ 0.18 (against a 2× finer grid: ≤ 1e-4)."""
    th = (np.arange(n_t) + 0.5) * (np.pi / 2) / n_t
    ph = (np.arange(n_p) + 0.5) * np.pi / n_p
    T, P = np.meshgrid(th, ph, indexing="ij")
    w = (np.cos(T) * np.sin(T)).ravel() * (np.pi / 2 / n_t) * (2 * np.pi / n_p)     # φ_d in (0, π), f even in φ_d
    out = []
    for m in mu_v:
        f = cpa.evaluate_cpa(fit, np.cos(T).ravel(), np.full(T.size, -m), P.ravel())
        out.append((f * w[:, None]).sum(axis=0))
    from flakedb.optics.fresnel import fresnel_dielectric_real

    mirror = fresnel_dielectric_real(np.asarray(mu_v, float), fit.coat_ior) if fit.coat_ior != 1.0 else 0.0 * np.asarray(mu_v)
    return np.array(out) + mirror[:, None]


def test_lobe_albedos_against_a_brute_force_integral():
    """cpa.lobe_albedos (half-vector quadrature) is each lobe's ∫ B μ_l dω_l: a model with one unit-colour row at a
    time, integrated by brute force over ω_l, within 3e-3 (measured ≤ 2.2e-3, the tilted α 0.18 lobe at μ_v 0.3)
    for GGX, backscatter and tilted lobes; a narrow GGX lobe (α 0.03, F = 1) has an albedo in (0.99, 1] at
    normal view."""
    alphas, retro, tilted = (0.18, 0.42), (0.65,), ((0.18, 0.45),)
    mu = np.array([0.3, 0.6, 0.9])
    A = cpa.lobe_albedos(mu, alphas, retro, "ggx", tilted)
    for r in range(1, 5):
        table = np.zeros((5, cpa.N_TABLE, 3))
        table[r] = 1.0
        brute = _brute_albedo(cpa.CPAFit(table, alphas, 1.0, retro_alphas=retro, tilted=tilted), mu)[:, 0]
        np.testing.assert_allclose(A[r], brute, atol=3e-3, err_msg=f"row {r}")
    a = cpa.lobe_albedos([1.0], (0.03,))[1, 0]
    assert 0.99 < a <= 1.0 + 1e-9


def test_energy_capped_holds_the_albedo_at_most_one():
    """A table whose colours exceed what energy allows (a narrow lobe's colour of several, as the unconstrained
    least squares gave a coated near-mirror: albedo 4.8 at μ_v 0.5) is scaled down until the model's albedo,
    integrated by brute force between and at the nodes, is ≤ 1 (+ the brute force's error); a table within
    energy is returned unchanged; no colour is raised or made negative.  Before energy_capped export-cpa wrote the
    4.8."""
    alphas, retro, tilted = (0.18, 0.42), (0.65,), ((0.18, 0.45),)
    mu = np.linspace(0.0, 1.0, cpa.N_TABLE)[:, None]
    table = np.stack([np.full((cpa.N_TABLE, 3), 0.2), (3.0, 2.0, 0.5) * (0.2 + mu), np.full((cpa.N_TABLE, 3), 0.3),
                      np.full((cpa.N_TABLE, 3), 0.1), np.full((cpa.N_TABLE, 3), 0.4)])
    hot = cpa.CPAFit(table, alphas, ETA, retro_alphas=retro, tilted=tilted)
    views = np.r_[0.05, 0.2, (np.arange(6) + 0.37) / 6.2, 1.0]
    assert _brute_albedo(hot, views).max() > 2.0                                   # the bite: far above 1
    capped = cpa.energy_capped(hot)
    assert np.all(capped.table <= hot.table) and np.all(capped.table >= 0)
    assert _brute_albedo(capped, views).max() <= 1.0 + 2e-3
    assert _brute_albedo(capped, views).max() > 0.95                                # scaled to the limit, not below
    cool = cpa.CPAFit(table * 0.1, alphas, ETA, retro_alphas=retro, tilted=tilted)
    cool = cpa.energy_capped(cool)   # column 0 (grazing view, F_c = 1): no energy left for any colour
    assert np.all(cool.table[:, 0] == 0)
    np.testing.assert_array_equal(cpa.energy_capped(cool).table, cool.table)
    np.testing.assert_allclose(cool.table[:, 2:], 0.1 * table[:, 2:], rtol=0)


@pytest.mark.slow
def test_a_coated_near_mirror_fit_conserves_energy(tmp_path):
    """A coated near-mirror (Beckmann metal α 0.05 under a smooth coat, n = 48): the unconstrained fit's α 0.03
    lobe took a colour of 4.97 (albedo 4.8 at μ_v 0.5); the fit's albedo (lobe_albedos, 8 points per table
    interval) is now ≤ 1 at every view (measured 1.000, 15 s)."""
    from flakedb.optics.fresnel import fresnel_dielectric_real
    from flakedb.paint.recipe import parse_recipe

    rec = parse_recipe("flakedb: 1\nname: coatmirror\nspectral: {mode: spectral, range_nm: [380, 780], step_nm: 20}\n"
                       "layers:\n  - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0}\n"
                       "  - metal: {material: {n: 0.1, k: 8}, roughness: 0.05}\n", source="coatmirror")
    compose(rec, tmp_path, n=48)
    fit = cpa.fit_cpa(open_bsdf(tmp_path / "coatmirror.bsdf"), max_subsets=1, minimax_passes=2)
    mu = np.linspace(0.0, 1.0, 8 * (fit.n_table - 1) + 1)[1:]
    A = cpa.lobe_albedos(mu, fit.alphas, fit.retro_alphas, fit.distribution, fit.tilted)
    C = np.einsum("qj,rjc->qrc", cpa.hat_weights(mu, fit.n_table), fit.table)
    albedo = fresnel_dielectric_real(mu, fit.coat_ior)[:, None] + np.einsum("qrc,rq->qc", C, A)
    assert albedo.max() <= 1.0 + 1e-6, (albedo.max(), mu[albedo.max(axis=1).argmax()])
