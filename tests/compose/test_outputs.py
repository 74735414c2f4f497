"""Outputs a renderer and a person can trust (issue 15): gamut-safe RGB files, the flop index's
standard value, progress and convergence warnings of compose.

Guards against: negative channels in an RGB `.bsdf` (renderers clamp them, so they render a colour
flakedb did not compute); a gamut mapping whose ΔE00 is not recorded or not what it costs; a
wide-gamut option that is not recorded; a negative flop index reported as the standard value; a
compose that is silent while it works or hides convergence problems.
"""

import re
from pathlib import Path

import numpy as np
import pytest

from flakedb.bsdf import open_bsdf
from flakedb.colour import gamut
from flakedb.compose.orchestrate import compose, gamut_safe_file_channels
from flakedb.solve.pipeline import solver_warnings
from flakedb.appearance.report import flop_index, flop_index_standard
from flakedb.paint.recipe import parse_recipe
from flakedb.paint.species import load_catalog

RECIPES = sorted((Path(__file__).resolve().parents[2] / "flakedb" / "catalog" / "recipes").glob("*.yaml"))


@pytest.fixture(scope="module")
def catalog():
    return load_catalog()


def _recipe(path, catalog, mode=None):
    text = Path(path).read_text()
    if mode == "rgb":
        text = re.sub(r"mode: spectral", "mode: rgb", text)
    return parse_recipe(text, catalog=catalog)


def _file_checks(bsdf_path):
    t = open_bsdf(bsdf_path).to_table()
    h = t.n // 2
    return float(t.coeffs[:, h:, :h, 0].min()), float(t.albedo()[:, h:].min()), float(t.albedo()[:, h:].max())


def test_saturated_yellow_is_mapped_into_gamut_and_its_cost_recorded(catalog, tmp_path):
    r = _recipe(RECIPES[[p.stem for p in RECIPES].index("particle-cadmium-yellow")], catalog)
    res = compose(r, tmp_path / "srgb", n=16, catalog=catalog)
    g = res.report["rgb_file"]
    a0_min, alb_min, alb_max = _file_checks(res.paths["bsdf"])
    assert a0_min >= 0 and alb_min >= 0 and alb_max <= 1
    assert g["min_channel_albedo_before"] < -0.03                # the blue albedo was ≈ −0.04 unmapped
    assert g["pairs_mapped"] > 0 and 1.0 < g["max_dE00"] < 15
    # the recorded ΔE00 is what it costs: recompute at the report's geometries from the files
    b = open_bsdf(res.paths["bsdf"])
    assert b.metadata["gamut_max_dE00"] == pytest.approx(g["max_dE00"], abs=1e-4)
    assert b.metadata["rgb_space"].startswith("linear sRGB")
    ft, info = gamut_safe_file_channels(res.table, "spectral", res.paint.wavelength_nm)
    assert info["max_dE00"] == pytest.approx(g["max_dE00"])
    from flakedb.colour.colorimetry import (
        XYZ_to_Lab,
        delta_E_2000,
        reflectance_to_XYZ,
        white_XYZ,
    )
    from flakedb.appearance.report import eval_table, multiangle_geometry
    wl = res.paint.wavelength_nm
    mi, mo, ph, _ = multiangle_geometry(45.0)
    true_lab = XYZ_to_Lab(reflectance_to_XYZ(np.pi * eval_table(res.table, mi, mo, ph) / abs(mo), wl),
                          white=white_XYZ(wl))
    file_rgb = np.pi * eval_table(ft, mi, mo, ph) / abs(mo)
    file_lab = XYZ_to_Lab(file_rgb @ gamut.space_to_XYZ_matrix(wl, "srgb"), white=white_XYZ(wl))
    assert float(delta_E_2000(true_lab, file_lab)) == pytest.approx(g["dE00_geometries"]["45"], abs=1e-6)
    # Rec.2020 holds the yellow with a far smaller mapping
    res2 = compose(r, tmp_path / "rec2020", n=16, catalog=catalog, rgb_space="rec2020")
    g2 = res2.report["rgb_file"]
    assert g2["max_dE00"] < 0.2 * g["max_dE00"]
    assert open_bsdf(res2.paths["bsdf"]).metadata["rgb_space"].startswith("linear Rec.2020")
    assert _file_checks(res2.paths["bsdf"])[0] >= 0


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["rgb"])   # each recipe in its own mode: tests/export/test_cpa_every_paint.py (n = 32)
def test_every_catalogue_recipe_gives_an_rgb_file_without_negative_channels(catalog, tmp_path, mode):
    for p in RECIPES:
        r = _recipe(p, catalog, mode)
        res = compose(r, tmp_path / p.stem, n=16, catalog=catalog)
        a0_min, alb_min, alb_max = _file_checks(res.paths["bsdf"])
        assert a0_min >= 0, (p.stem, a0_min)
        assert alb_min >= 0, (p.stem, alb_min)
        g = res.report["rgb_file"]
        if g is not None:   # mono recipes are not mapped (a transmissive one exceeds 1 by the known spike
            # integral of the module docstring of flakedb.compose.orchestrate, mapping or not)
            assert alb_max <= 1.0 + 1e-6, (p.stem, alb_max)
            assert g["max_channel_albedo_after"] <= max(1.0, g["max_channel_albedo_before"]) + 1e-12


def test_flop_index_standard_value_is_never_negative():
    assert flop_index_standard(100, 50, 20) == pytest.approx(2.69 * 80**1.11 / 50**0.86)
    assert flop_index(20, 50, 100) < 0 and flop_index_standard(20, 50, 100) == 0.0
    assert flop_index_standard(10, 0, 5) is None


def test_compose_reports_stages_and_warnings(tmp_path):
    events = []
    text = ("flakedb: 1\nname: t\nspectral: {mode: mono}\nresolution: 16\nlayers:\n"
            "  - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0}\n"
            "  - basecoat: {thickness_um: 10, ior: 1.5, particles: [{custom: {kind: medium, albedo: 0.9, "
            "phase: {hg: 0.9}}, optical_depth: 2}]}\n  - primer: {color: gray}\n")
    res = compose(parse_recipe(text), tmp_path, progress=lambda st, d: events.append((st, d)))
    stages = [e[0] for e in events]
    assert stages[0] == "optics" and "projection" in stages and "solve" in stages and stages[-1] == "write"
    assert stages.index("projection") < stages.index("solve") < stages.index("write")
    warn = [d["message"] for st, d in events if st == "warning"]
    assert warn == solver_warnings(res.stack.info, 16) and all(w in res.warnings for w in warn)
    assert res.report["warnings"] == res.warnings


def test_solver_warnings_in_words():
    info = {"orders": 11, "order_converged": False, "order_tail": 3e-4, "order_tol": 1e-4, "orders_available": 32,
            "slab0": {"converged": False, "n_phi": 128, "tail": 8e-6, "orders": 32, "renorm_max_dev": 0.024}}
    w = solver_warnings(info, 16)
    assert len(w) == 3 and "2.4%" in w[1] and "stopped at 128 azimuth samples" in w[0] and "3.0e-04" in w[2]
    assert solver_warnings({"orders": 3, "order_converged": True, "slab0": {"converged": True,
                                                                           "renorm_max_dev": 1e-3}}, 64) == []


def test_gamut_mapping_of_a_reflection_only_table_is_that_of_its_dense_copy(catalog, tmp_path):
    """An opaque paint's table is mapped on its reflection quadrant alone (no dense 4× array): the file
    table, the recorded costs and eval_table are those of the same table given densely, bit for bit."""
    from flakedb.bsdf import BSDFTable
    from flakedb.appearance.report import eval_table, multiangle_geometry

    r = _recipe(RECIPES[[p.stem for p in RECIPES].index("particle-cadmium-yellow")], catalog)
    res = compose(r, tmp_path / "q", n=16, catalog=catalog)
    quad = res.table
    assert quad.reflection_only
    dense = BSDFTable(mu=quad.mu, coeffs=quad.coeffs.copy(), eta=quad.eta, alpha=quad.alpha, delta=quad.delta,
                      metadata=quad.metadata, channels=quad.channels)
    quad = dense.replace(reflection=dense.live_quadrant().copy())
    fq, iq = gamut_safe_file_channels(quad, "spectral", res.paint.wavelength_nm)
    fd, idd = gamut_safe_file_channels(dense, "spectral", res.paint.wavelength_nm)
    assert iq["pairs_mapped"] > 0 and iq == idd
    assert fq.reflection_only
    np.testing.assert_array_equal(fq.coeffs, fd.coeffs)
    mi, mo, ph, _ = multiangle_geometry(45.0)
    pts = (np.array([mi, 0.3, 0.9]), np.array([mo, -0.2, -0.95]), np.array([ph, 1.0, 2.5]))
    np.testing.assert_array_equal(eval_table(quad, *pts), eval_table(dense, *pts))


@pytest.mark.parametrize("mode, space", [("rgb", "srgb"), ("rgb", "rec2020"), ("spectral", "srgb"), ("spectral", "acescg")])
def test_grey_table_is_mapped_once_as_its_materialised_copy(mode, space):
    """A grey stack solved once gives a table whose channels are one array (stride 0): gamut_safe_file_channels maps
    that one channel (no C-channel copy, nothing to desaturate) and gives the file table and the recorded costs of
    the same table with its channels written out (the general path: the C × 3 map, then desaturation, then mono),
    to the rounding of the map's column sums (exactly for RGB mode in sRGB, whose map is the identity)."""
    from flakedb.bsdf.convert import stack_to_table
    from flakedb.colour.colorimetry import spectral_grid
    from flakedb.rt.scattering.media import PhaseMedium
    from flakedb.rt.adding.stack import Lambertian, Rough, Slab, SolverSettings, solve_stack

    wl = spectral_grid()  # RGB mode: the grid its white is integrated on
    C = wl.size if mode == "spectral" else 3
    slab = Slab(1.0, PhaseMedium(sigma_t_per_um=[1.0] * C, albedo=[0.9] * C, phase=("hg", 0.7)))
    st = solve_stack(Rough(1.5, 0.2), [slab], Lambertian([0.5] * C), SolverSettings.product(16))
    grey = stack_to_table(st)
    assert grey.stored.shape[0] == C and grey.stored.strides[0] == 0
    written = grey.replace(stored=np.array(grey.stored))
    fg, ig = gamut_safe_file_channels(grey, mode, wl, space)
    fw, iw = gamut_safe_file_channels(written, mode, wl, space)
    assert fg.channels == fw.channels == ("mono",) and ig["pairs_mapped"] == iw["pairs_mapped"] == 0
    exact = mode == "rgb" and space == "srgb"
    if exact:
        assert np.shares_memory(fg.stored, grey.stored)  # the solver's one channel, not a mapped copy
        np.testing.assert_array_equal(fg.stored, fw.stored)
        assert ig == iw
    else:
        np.testing.assert_allclose(fg.stored, fw.stored, rtol=1e-14, atol=1e-14 * np.abs(fw.stored).max())
        assert ig.keys() == iw.keys()
        for k, v in iw.items():
            if isinstance(v, float):
                assert ig[k] == pytest.approx(v, rel=1e-13, abs=1e-12), k
            elif k != "dE00_geometries":
                assert ig[k] == v, k


def test_an_rgb_mode_table_in_srgb_is_written_as_it_is():
    """RGB mode's channels are white-normalised linear sRGB: the sRGB file holds the same values (the identity map,
    applied as c + 0.0), an in-gamut table nothing desaturated, and the recorded costs zero."""
    from flakedb.bsdf.convert import stack_to_table
    from flakedb.colour.colorimetry import spectral_grid
    from flakedb.rt.scattering.media import PhaseMedium
    from flakedb.rt.adding.stack import Lambertian, Rough, Slab, SolverSettings, solve_stack

    slab = Slab(1.0, PhaseMedium(sigma_t_per_um=[1.0] * 3, albedo=[0.95, 0.8, 0.6], phase=("hg", 0.7)))
    table = stack_to_table(solve_stack(Rough(1.5, 0.2), [slab], Lambertian([0.5, 0.4, 0.3]), SolverSettings.product(16)))
    ft, info = gamut_safe_file_channels(table, "rgb", spectral_grid(), "srgb")
    assert ft.channels == ("R", "G", "B") and info["pairs_mapped"] == 0 and info["max_dE00"] == 0.0
    np.testing.assert_array_equal(ft.stored, table.stored)
    # the general map (an einsum over the channels) makes -0.0 +0.0: so does the identity, bit for bit
    c = np.array(table.stored)
    c[1, 2, 3, -3:] = -0.0
    ft2, _ = gamut_safe_file_channels(table.replace(stored=c), "rgb", spectral_grid(), "srgb")
    want = np.einsum("jk,j...->k...", np.eye(3), c)
    assert not np.signbit(ft2.stored[1, 2, 3, -3:]).any()
    np.testing.assert_array_equal(ft2.stored.view(np.int64), want.view(np.int64))
