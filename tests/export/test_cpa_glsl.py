"""The ``cpa`` route's MaterialX graph rendered by MaterialX's own GLSL renderer (``materialx`` 1.39,
``GlslRenderer`` on Mesa llvmpipe under Xvfb), at the colour geometries: :mod:`flakedb.export.materialx_render`.

Guards against: a render harness whose light, camera or colour convention is not what it says (a Lambertian of
known albedo must give π f = its albedo at every geometry: the closed form); a ``.cpa.mtlx`` that MaterialX reads
otherwise than flakedb states (the table's rows or columns swapped, the N·V index wrong, the lobes' roughness
mapping, MaterialX's energy compensation or its 8-bit read of the PNG unaccounted for:
:func:`flakedb.export.materialx_render.cpa_materialx_rf`); and, on catalogue paints, a MaterialX route further
from the exact prediction at the E2194 geometries than docs/renderers.md states.

Runs where MaterialX's GLSL renderer imports and a display or ``xvfb-run`` is present (``.ci/run`` installs
Xvfb and Mesa on Debian); skipped, saying which is missing, otherwise.
"""

from pathlib import Path

import numpy as np
import pytest

import flakedb
from flakedb.bsdf import open_bsdf
from flakedb.compose.orchestrate import compose
from flakedb.export import cpa
from flakedb.export import materialx_render as mr
from flakedb.export.materialx import cpa_mtlx_text
from flakedb.export.registry import export
from flakedb.match.targets import E2194_GEOMETRIES, E2539_EXTRA
from flakedb.paint.recipe import load_recipe
from tests.export.test_cpa import truth_fit, truth_fit_retro

TOOL, WHY = mr.glsl_renderer()
RECIPES = Path(flakedb.__file__).parent / "catalog" / "recipes"
GEOMS = np.asarray(list(E2194_GEOMETRIES) + list(E2539_EXTRA) + [(30.0, 31.0), (30.0, 35.0), (60.0, 70.0)], float)

#: π f of a Lambertian against its albedo: the float32 shading and framebuffer (6e-8 relative per operation,
#: a few dozen operations): 1e-5 (measured 3.3e-7).
RTOL_LAMBERT = 1e-5
#: MaterialX against cpa_materialx_rf at a geometry: the graph reads the table's texels at their centres (exact:
#: 8-bit planes, 16 bits recombined) and interpolates in the shader's float32 arithmetic (a few dozen operations of
#: 6e-8 each, the texel-centre coordinate's rounding times the table's slope): 1e-4 (measured 3.8e-6; it was 0.54 %
#: when llvmpipe's bilinear filter, whose weights are fixed point, interpolated the texels).
RTOL_PRED = 1e-4
RTOL_TEXEL_CENTRE = 1e-5


def _lambert(path, colour):
    path.write_text(mr.lambert_mtlx_text(colour))
    return path


def _write_cpa(d, fit, name="m"):
    px, scale = cpa.table_image(fit)
    (d / f"{name}.cpa.png").write_bytes(cpa.table_png_bytes(px))
    p = d / f"{name}.cpa.mtlx"
    p.write_text(cpa_mtlx_text(f"{name}.cpa.png", scale, fit.alphas, fit.coat_ior, fit.n_table, name,
                               retro_alphas=fit.retro_alphas, tilted=fit.tilted))
    return p


def truth_fit_tilted():
    """truth_fit_retro with two tilted lobes (α 0.06 away from the view, k 0.45; α 0.28 towards it, k −0.3)
    coloured by two more rows."""
    t = truth_fit_retro()
    mu = np.linspace(0.0, 1.0, t.n_table)[:, None]
    rows = [(0.2, 0.1, 0.05) * (0.5 + mu), (0.02, 0.06, 0.04) * (1.5 - mu)]
    return cpa.CPAFit(np.concatenate([t.table, rows]), t.alphas, t.coat_ior, retro_alphas=t.retro_alphas,
                      tilted=((0.06, 0.45), (0.28, -0.3)))


@pytest.fixture(scope="module")
def gl_context():
    """Skip, saying why, where MaterialX's GlslRenderer cannot make a GL context (no xvfb-run, or Mesa missing)."""
    if TOOL is None:
        pytest.skip(f"MaterialX GLSL render unavailable: {WHY}")
    ok, why = mr.glsl_probe(TOOL)
    if not ok:
        pytest.skip(f"MaterialX GLSL render unavailable: {why}")
    return why


@pytest.fixture(scope="module")
def harness(tmp_path_factory, gl_context):
    """One renderer run: a Lambertian of albedo (0.8, 0.5, 0.2) and the model table's graph at GEOMS."""
    d = tmp_path_factory.mktemp("cpa-glsl")
    files = [_lambert(d / "lambert.mtlx", (0.8, 0.5, 0.2)), _write_cpa(d, truth_fit()),
             _write_cpa(d, truth_fit_tilted(), "tilted")]
    return mr.render_geometries(files, GEOMS, tool=TOOL)


def test_lambertian_closed_form(harness):
    """The harness's own check: a Lambertian of albedo c (MaterialX's ``oren_nayar_diffuse_bsdf`` at roughness 0,
    exactly c/π) under the directional light of intensity 1 renders L = c μ_l / π at every geometry, so the image
    mean read back as π L / μ_l is c: the light's irradiance, its direction's μ_l, the float target with no tone
    map or display encoding, and the linear colour space."""
    np.testing.assert_allclose(harness["rf"][0], np.tile([0.8, 0.5, 0.2], (len(GEOMS), 1)), rtol=RTOL_LAMBERT)
    assert harness["pixel_spread"][0].max() < 1e-6          # every pixel is the same geometry
    assert harness["materialx"].startswith("1.39")


def test_graph_renders_what_flakedb_predicts(harness):
    """The exported graph of a known table (lobes α 0.11 / 0.28 / 0.65, rows linear in μ_v) renders
    cpa_materialx_rf of the table as MaterialX loads it: at every geometry within RTOL_PRED, and where μ_v = 1
    (a texel centre: E2194 45°/45° and E2539 15°/15°) within RTOL_TEXEL_CENTRE, lobes and energy compensation
    included.  The bites: the table read as 8 bits, the table's rows reversed, and the model without MaterialX's
    energy compensation (the Cycles node group's numbers), are each further off than RTOL_PRED."""
    rf = harness["rf"][1]
    fit = truth_fit()
    pred = mr.cpa_materialx_rf(mr.table_as_loaded(fit), GEOMS)
    rel = np.abs(rf / pred - 1)
    print("MaterialX / prediction - 1, max", rel.max())
    assert rel.max() < RTOL_PRED, rel
    centre = np.isclose(GEOMS[:, 0], GEOMS[:, 1])
    assert centre.sum() == 2 and rel[centre].max() < RTOL_TEXEL_CENTRE, rel[centre]
    px, scale = cpa.table_image(fit)                   # the table read as 8 bits (a 16-bit PNG's high byte)
    eight = cpa.CPAFit(np.floor(np.round(px * 65535.0) / 256.0) / 255.0 * scale[:, None, None], fit.alphas, fit.coat_ior)
    assert np.abs(rf / mr.cpa_materialx_rf(eight, GEOMS) - 1).max() > 10 * RTOL_PRED
    reversed_rows = cpa.CPAFit(fit.table[::-1], fit.alphas, fit.coat_ior)
    assert np.abs(rf / mr.cpa_materialx_rf(reversed_rows, GEOMS) - 1).max() > 10 * RTOL_PRED
    from flakedb.match.fit import geometry_directions

    no_comp = np.pi * cpa.evaluate_cpa(fit, *geometry_directions(GEOMS))
    assert np.abs(rf / no_comp - 1).max() > 2 * RTOL_PRED


def test_tilted_graph_renders_what_flakedb_predicts(harness):
    """The graph's tilted lobes (``generalized_schlick_bsdf`` whose ``normal`` is normalize(N (1 + k μ_v²) +
    k μ_v ``viewdirection``), :func:`flakedb.export.cpa.tilted_lobe`) and the backscatter lobe render
    cpa_materialx_rf of the table within RTOL_PRED at every geometry, MaterialX's energy compensation taken at the
    tilted normal's N'·V.  The bites: the same lobes untilted (k = 0), or with E_ss taken at μ_v, are further off."""
    from dataclasses import replace

    from flakedb.export import materialx_glsl as mg

    rf = harness["rf"][2]
    fit = mr.table_as_loaded(truth_fit_tilted())
    pred = mr.cpa_materialx_rf(fit, GEOMS)
    rel = np.abs(rf - pred).max(axis=1) / pred.max(axis=1)
    print("tilted lobes: |MaterialX - prediction| / largest channel, max", rel.max())
    assert rel.max() < RTOL_PRED, rel
    untilted = replace(fit, tilted=tuple((a, 0.0) for a, _ in fit.tilted))
    assert (np.abs(rf - mr.cpa_materialx_rf(untilted, GEOMS)).max(axis=1) / pred.max(axis=1)).max() > 10 * RTOL_PRED
    wl, wv = mr.geometry_vectors(GEOMS)      # E_ss at μ_v instead of N'·V: only the tilted lobes' compensation changes
    cos_h = (wl + wv)[:, 2] / np.linalg.norm(wl + wv, axis=1)
    cos_vl = np.einsum("gi,gi->g", wl, wv)
    C = np.einsum("gj,kjc->gkc", cpa.hat_weights(wv[:, 2], fit.n_table), fit.table)
    wrong = pred.copy()
    for k, (a, t) in enumerate(fit.tilted, start=1 + len(fit.alphas) + len(fit.retro_alphas)):
        e_t = mg.ggx_dir_albedo_analytic(cpa.tilted_cosines(wv[:, 2], wl[:, 2], cos_h, cos_vl, t)[0], a, 1.0, 1.0)[:, None]
        e_n = mg.ggx_dir_albedo_analytic(wv[:, 2], a, 1.0, 1.0)[:, None]
        lobe = cpa.tilted_lobe(wv[:, 2], wl[:, 2], cos_h, cos_vl, a, t)[:, None]
        wrong += np.pi * C[:, k] ** 2 * ((1.0 - e_n) / e_n - (1.0 - e_t) / e_t) * lobe
    assert (np.abs(rf - wrong).max(axis=1) / pred.max(axis=1)).max() > 2 * RTOL_PRED


@pytest.mark.slow
def test_coated_aluminium_tilted_lobe_in_materialx(tmp_path, gl_context):
    """coated-aluminium, a bare Beckmann aluminium panel under the coat, out of the reach of GGX lobes about N
    (test_cpa.py::test_coated_aluminium_out_of_reach: ≥ 5.56; rendered 7.74 with them), in MaterialX with the
    tilted lobe of :func:`flakedb.export.cpa.fit_cpa_materialx` (the files export-cpa writes for it: the fit's first
    lobe subset, where the full search stops): worst ΔE00 at the six E2194 geometries ≤ GOAL (measured 1.88), and the
    render is flakedb's prediction of the graph within RTOL_PRED (so the number is the route's)."""
    compose(load_recipe(RECIPES / "coated-aluminium.yaml"), tmp_path, n=32)
    b = open_bsdf(tmp_path / "coated-aluminium.bsdf")
    fit = cpa.fit_cpa_materialx(b, cpa.fit_cpa(b, max_subsets=1, minimax_passes=2), max_subsets=1)
    assert fit.tilted
    m = _write_cpa(tmp_path, cpa.materialx_fit(fit), "coated-aluminium")
    r = mr.check_cpa_glsl(b, m, tool=TOOL)
    de = np.array([g["dE00"] for g in r["geometries"]])
    rf = np.array([g["rendered_rf"] for g in r["geometries"]])
    pred = mr.cpa_materialx_rf(mr.table_as_loaded(cpa.materialx_fit(fit)), E2194_GEOMETRIES)
    off = np.abs(rf - pred).max(axis=1) / pred.max(axis=1)
    print("coated-aluminium, tilted lobe", fit.tilted, "dE00 per E2194 geometry", np.round(de, 2), "off", off.max())
    assert off.max() < RTOL_PRED, off
    assert de.max() <= GOAL, de


#: The issue's goal, worst ΔE00 at the E2194 geometries in MaterialX GLSL ≤ 2, and per paint what is reached
#: (docs/renderers.md, "Rendered in MaterialX's GLSL renderer"): the bound asserted where the goal is missed.
#: fig7-pearlescent-tio2-110nm rendered 2.37 while the table was read as 8 bits and interpolated by llvmpipe's
#: fixed-point filter; with the 16 bits in two planes interpolated in the graph it renders its prediction, 1.99.
#: All 35 catalogue recipes (tools/cpa_catalogue.py --renderer glsl) meet the goal; coated-aluminium (7.74 with GGX
#: lobes about N, out of their reach: test_cpa.py::test_coated_aluminium_out_of_reach) only with the tilted lobe
#: (1.88), test_coated_aluminium_tilted_lobe_in_materialx (export-cpa's full GGX search takes ~30-110 s there).
GOAL = 2.0
MEASURED_BOUND = {"metallic-silver": 2.0, "particle-cadmium-yellow": 2.0, "particle-pearlescent": 2.0,
                  "tri-coat-pearl-white": 2.0, "red-metallic": 2.0, "fig7-pearlescent-tio2-110nm": 2.0}


@pytest.mark.slow
@pytest.mark.parametrize("paint", sorted(MEASURED_BOUND))
def test_catalogue_paint_e2194(paint, tmp_path, gl_context):
    """The catalogue paint composed at n = 32, exported by ``export-cpa``, its ``.cpa.mtlx`` rendered by MaterialX
    at the six E2194 geometries: the worst ΔE00 against the exact prediction is within the paint's bound, and the
    rendered colours are what flakedb predicts MaterialX draws of the exported table (so the number is the
    route's, not a render fault: the graph carries the lobes' colours with MaterialX's energy compensation undone,
    :func:`flakedb.export.cpa.materialx_fit`).  Where the bound is above the goal of 2 the goal is asserted as a strict xfail
    (meeting it fails until docs/renderers.md says so)."""
    compose(load_recipe(RECIPES / f"{paint}.yaml"), tmp_path, n=32)
    b = open_bsdf(tmp_path / f"{paint}.bsdf")
    out = export(tmp_path / f"{paint}.bsdf", tmp_path / "out", method="cpa")
    r = mr.check_cpa_glsl(b, out["files"]["materialx"], tool=TOOL)
    de = np.array([g["dE00"] for g in r["geometries"]])
    rf = np.array([g["rendered_rf"] for g in r["geometries"]])
    fit = cpa.CPAFit.from_dict(out["fit"])
    pred = mr.cpa_materialx_rf(mr.table_as_loaded(cpa.materialx_fit(fit)), E2194_GEOMETRIES)
    off = np.abs(rf - pred).max(axis=1) / pred.max(axis=1)       # a near-black channel's ratio means nothing
    print(paint, "dE00 per E2194 geometry", np.round(de, 2), "|MaterialX - prediction| / largest channel, max", off.max())
    assert off.max() < RTOL_PRED, off
    assert de.max() <= MEASURED_BOUND[paint], de
    if MEASURED_BOUND[paint] > GOAL:         # strict: meeting the goal fails until the bound and the docs say so
        assert de.max() > GOAL, f"{paint} now meets the goal ({de.max():.2f}): set its MEASURED_BOUND to {GOAL} and update docs"
        pytest.xfail(f"{paint}: worst ΔE00 {de.max():.2f} at the E2194 geometries in MaterialX GLSL, above the "
                     f"goal of {GOAL} (docs/renderers.md)")
    assert de.max() <= GOAL


def _model_bsdf(d):
    from flakedb.bsdf import write_bsdf
    from tests.export.test_cpa import cpa_table

    p = d / "model.bsdf"
    write_bsdf(p, cpa_table(truth_fit()), truncation=0.0)
    return p


def test_cli_check_refused_before_work(tmp_path, monkeypatch):
    """``export-cpa --check glsl`` where no renderer can run: one line naming the option and the fix, exit 2,
    nothing written (checked before the fit)."""
    from click.testing import CliRunner

    import flakedb.cli.export_cpa as cli_mod
    from flakedb.cli.main import cli

    monkeypatch.setattr(cli_mod, "glsl_renderer", lambda: (None, "no DISPLAY and no xvfb-run: apt-get install -y xvfb"))
    src = tmp_path / "notes.bsdf"
    src.write_bytes(b"not read")
    r = CliRunner().invoke(cli, ["export-cpa", str(src), "--out", str(tmp_path / "out"), "--check", "glsl"])
    assert r.exit_code == 2 and "--check glsl" in r.output and "apt-get install" in r.output, r.output
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_cli_check_prints_render(tmp_path, gl_context):
    """``export-cpa FILE --check glsl`` prints MaterialX's ΔE00 per E2194 geometry: what the renderer produces
    of the written graph (the numbers of check_cpa_glsl on it), not the fit's own."""
    import re

    from click.testing import CliRunner

    from flakedb.cli.main import cli

    src = _model_bsdf(tmp_path)
    r = CliRunner().invoke(cli, ["export-cpa", str(src), "--out", str(tmp_path / "out"), "--check", "glsl"])
    assert r.exit_code == 0, r.output
    line = next(x for x in r.output.splitlines() if x.startswith("MaterialX GLSL render"))
    printed = [float(v) for v in re.findall(r"-?\d+°: (\d+\.\d+)", line)]
    again = mr.check_cpa_glsl(open_bsdf(src), tmp_path / "out" / "model.cpa.mtlx", tool=TOOL)
    assert printed == [round(g["dE00"], 2) for g in again["geometries"]], (line, again["worst_dE00"])
    assert f"worst {again['worst_dE00']:.2f}" in line
    assert again["worst_dE00"] < 1.0       # a file made by the model itself: what is left is the file's interpolation
