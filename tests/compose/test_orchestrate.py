"""Compose: recipe → physics mapping → solver → files → colour report.

Guards against: a wrong physics mapping (flake loading aρ = φ/t, optical-depth loadings, pigment
number density, phase tables that do not integrate to 1 or are too coarse, flake R/T grids that miss
thin-film fringes); energy leaks through compose's wiring (white furnace, R + T = 1 of a
non-absorbing index-matched slab, absorbing coat against the closed form 2 E_3); the solver's blocks
put in the wrong place of the file's node set (reflection vs transmission, sign of μ_o, the |μ_o|
factor); the spectral → RGB conversion of the .bsdf; wrong geometry of the multi-angle report
(specular vs illuminator side, φ_d = 0 vs π); a wrong CIELAB/flop computation (white primer:
L* = 116·0.9^(1/3) − 16 exactly); metadata missing from the files (delta term, store, recipe text);
half-written outputs when writing fails.
"""

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from scipy.special import expn

from flakedb.bsdf import open_bsdf
from flakedb.cli.main import cli
from flakedb.compose.orchestrate import compose
from flakedb.appearance.report import eval_table, flop_index, multiangle_geometry
from flakedb.paint.mapping import build_paint
from flakedb.paint.components import phase_cos_grid
from flakedb.paint.recipe import parse_recipe
from tests import tolerances as tol


def recipe(layers, mode="mono", n=16, name="t", extra=""):
    spectral = {"mono": "{mode: mono}", "spectral": "{mode: spectral, range_nm: [400, 700], step_nm: 20}",
                "rgb": "{mode: rgb, range_nm: [380, 780], step_nm: 10}"}[mode]
    text = f"flakedb: 1\nname: {name}\nspectral: {spectral}\nresolution: {n}\nlayers:\n" + textwrap.indent(
        yaml.safe_dump(layers, sort_keys=False, default_flow_style=None), "  ") + extra
    return parse_recipe(text)


HG = {"custom": {"kind": "medium", "albedo": 1.0, "phase": {"hg": 0.6}}, "optical_depth": 1.5}
WHITE_FLAKE = {"custom": {"kind": "flake", "R": {"c": [0, 1], "value": [0.9, 0.5]},
                          "T": {"c": [0, 1], "value": [0.1, 0.5]}, "orientation_alpha": 0.3},
               "optical_depth": 1.0}


def test_index_matched_hg_slab_conserves_energy_through_compose(tmp_path):
    r = recipe([{"basecoat": {"thickness_um": 5, "ior": 1.0, "particles": [HG]}}], n=16)
    res = compose(r, tmp_path)
    s = res.stack
    total = s.albedo() + s.transmittance()
    assert np.abs(total - 1.0).max() < 1e-6
    assert s.delta_F is None and res.paint.top is None
    # the file table holds reflection and transmission: 2π Σ_o w_o a_0 over both hemispheres = 1
    t = res.table
    w_full = np.concatenate([s.w[::-1], s.w])
    flux = 2 * np.pi * np.einsum("cio,o->ci", t.coeffs[..., 0], w_full)
    np.testing.assert_allclose(flux, 1.0, atol=1e-6)
    h = s.x.size
    refl = 2 * np.pi * np.einsum("cio,o->ci", t.coeffs[:, h:, :h, 0], s.w[::-1])
    np.testing.assert_allclose(refl, s.albedo(), rtol=1e-12)          # reflection sits in μ_o < 0
    # the optical depth loading: σ_t d = τ
    assert res.paint.slabs[0].medium.sigma_t(np.array([0.5]))[0, 0] * 5 == pytest.approx(1.5)


def test_white_furnace_smooth_coat_conservative_scatterers_white_primer(tmp_path):
    r = recipe([{"clearcoat": {"thickness_um": 20, "ior": 1.5, "roughness": 0}},
                {"basecoat": {"thickness_um": 8, "ior": 1.5, "particles": [HG, WHITE_FLAKE]}},
                {"primer": {"albedo": 1.0}}], n=16)
    res = compose(r, tmp_path)
    assert res.paint.slabs and len(res.paint.slabs) == 1   # a clear non-absorbing coat adds no slab
    np.testing.assert_allclose(res.stack.albedo(), 1.0, atol=1e-6)
    rep = res.report
    for a in rep["albedo"]:
        assert a["albedo_Y"] == pytest.approx(1.0, abs=1e-6)   # spline of the nodal total


@pytest.mark.parametrize("roughness", [0, 0.1])
def test_falling_binder_index_composes_and_conserves_energy(tmp_path, roughness):
    """A coat 1.6 over basecoats of 1.45 (a fall: a smooth inner interface into the less dense binder,
    docs/model.md §4 "Inner interface") then 1.55 (a rise): the recipe composes to files end to end, the
    conservative stack over a white primer returns all its light, and the fall changes the result."""
    layers = [{"clearcoat": {"thickness_um": 20, "ior": 1.6, "roughness": roughness}},
              {"basecoat": {"thickness_um": 8, "ior": 1.45, "particles": [HG, WHITE_FLAKE]}},
              {"basecoat": {"thickness_um": 4, "ior": 1.55, "particles": [HG]}},
              {"primer": {"albedo": 1.0}}]
    # allow_unphysical: a white furnace (primer albedo 1) at n = 16 under the rough 0.1 coat: the written table's
    # Catmull-Rom albedo, what renderers integrate, is 1.0030 (the solver's 1.0000), which compose now refuses
    # like `flakedb info` does (issue 38); the stack itself is what this test checks
    res = compose(recipe(layers, n=16), tmp_path / "fall", allow_unphysical=bool(roughness))
    kinds = [c["kind"] for c in res.paint.components]
    assert kinds.count("inner interface") == 2
    np.testing.assert_allclose(res.stack.albedo(), 1.0, atol=1e-10)
    assert sorted(p.name for p in (tmp_path / "fall").iterdir())  # files written
    layers[1]["basecoat"]["ior"] = 1.6
    layers[2]["basecoat"]["ior"] = 1.6
    layers[3] = {"primer": {"albedo": 0.5}}
    same = compose(recipe(layers, n=16), tmp_path / "same").stack.albedo()
    layers[1]["basecoat"]["ior"] = 1.45
    layers[2]["basecoat"]["ior"] = 1.55
    fall = compose(recipe(layers, n=16), tmp_path / "fall2").stack.albedo()
    assert np.abs(fall - same).max() > 1e-3


def test_custom_flake_optical_depth_is_normal_incidence_extinction():
    r = recipe([{"basecoat": {"thickness_um": 4, "ior": 1.5, "particles": [WHITE_FLAKE]}},
                {"primer": {"color": "black"}}])
    p = build_paint(r)
    med = p.slabs[0].medium
    assert med.sigma_t(np.array([1.0]))[0, 0] * 4 == pytest.approx(1.0, rel=1e-12)
    assert p.bottom.albedo[0] == 0.04


def test_absorbing_index_matched_coat_closed_form(tmp_path):
    """Coat of optical depth τ over a white Lambertian: albedo(μ) = e^{−τ/μ} · 2 E_3(τ)."""
    tau, d = 0.2, 10.0
    r = recipe([{"clearcoat": {"thickness_um": d, "ior": 1.0, "absorption_per_um": tau / d}},
                {"primer": {"albedo": 1.0}}], n=32)
    res = compose(r, tmp_path)
    x = res.stack.x
    np.testing.assert_allclose(res.stack.albedo()[0], np.exp(-tau / x) * 2 * expn(3, tau), rtol=1e-5,
                               atol=2e-6)  # the direct beam at grazing nodes: diamond start


def test_catalogue_mapping_flake_and_pigment():
    r = recipe([{"clearcoat": {"thickness_um": 40, "ior": 1.5}},
                {"basecoat": {"thickness_um": 15, "ior": 1.5, "particles": [
                    {"species": "pearlescent", "volume_fraction": 0.04, "orientation_alpha": 0.2},
                    {"species": "titanium-white", "volume_fraction": 0.02}]}},
                {"primer": {"color": "white"}}], mode="spectral")
    p = build_paint(r)
    fl, pig = p.components[0], p.components[1]
    assert fl["a_rho_per_um"] == pytest.approx(0.04 / 0.54)   # φ / flake thickness (docs/model.md §3)
    assert p.info["flake_c_grid"]["layers[1].basecoat.particles[0]"]["max_midpoint_error"] <= 1e-3
    from flakedb.paint.catalog import get_species
    from flakedb.paint.species import pigment_optics

    mu = phase_cos_grid()
    po = pigment_optics(get_species("titanium-white"), r.wavelength_nm, 1.5, mu=mu)
    rho = 0.02 / po.mean_volume_um3
    med = p.slabs[0].medium.components[1]
    np.testing.assert_allclose(med.sigma_t_per_um, rho * po.c_ext_um2, rtol=1e-12)
    np.testing.assert_allclose(med.albedo, po.c_sca_um2 / po.c_ext_um2, rtol=1e-12)
    # the tabulated phase integrates to 1 and its mean cosine is the Mie g (grid fine enough)
    ct, tab = med.phase[1], med.phase[2]
    np.testing.assert_allclose(2 * np.pi * np.trapezoid(tab, ct, axis=-1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(2 * np.pi * np.trapezoid(tab * ct, ct, axis=-1), po.g, atol=2e-4)
    assert p.info["phase_table_norm_error"]["layers[1].basecoat.particles[1]"] < 1e-3
    assert p.delta == {"kind": "fresnel", "eta": 1.5}


def test_flake_grid_resolves_thin_film_fringes():
    """Linear interpolation on the adaptive c grid against a fine grid: ≤ 1e-3 (catalogue pearl)."""
    from flakedb.paint.catalog import get_species
    from flakedb.paint.components import adaptive_flake_optics
    from flakedb.paint.species import flake_reflectance_transmittance

    e = get_species("pearlescent")
    wl = np.arange(380.0, 781.0, 40.0)
    fn = lambda c: flake_reflectance_transmittance(e, wl, c, 1.5)  # noqa: E731
    c, R, T, err = adaptive_flake_optics(fn)
    cf = np.linspace(0.0, 1.0, 6001)
    Rf, Tf = fn(cf)
    Ri = np.array([np.interp(cf, c, v) for v in R])
    assert np.abs(Ri - Rf).max() < 2e-3 and err <= 1e-3
    assert c.size > 48   # a fixed 48-node grid misses the fringes (error 0.15)


def test_rgb_mode_flake_optics_physical_and_flat_input_grey():
    r = recipe([{"clearcoat": {"thickness_um": 40, "ior": 1.5}},
                {"basecoat": {"thickness_um": 15, "ior": 1.5, "particles": [
                    {"species": "pearlescent-tio2-090nm", "volume_fraction": 0.04}]}},
                {"primer": {"color": "gray"}}], mode="rgb")
    p = build_paint(r)
    opt = p.slabs[0].medium.optics
    assert opt.R.shape[0] == 3 and opt.R.min() >= 0 and (opt.R + opt.T).max() <= 1 + 1e-12
    np.testing.assert_allclose(p.bottom.albedo, 0.18, rtol=1e-12)   # a flat spectrum stays grey


def test_files_read_back_and_evaluate_to_solver_values(tmp_path):
    r = recipe([{"clearcoat": {"thickness_um": 40, "ior": 1.5}},
                {"basecoat": {"thickness_um": 10, "ior": 1.5, "particles": [
                    {"species": "metallic", "volume_fraction": 0.03, "orientation_alpha": 0.35}]}},
                {"primer": {"color": "gray"}}], mode="spectral", n=16, name="rt-test")
    res = compose(r, tmp_path, raw=True)
    s = res.stack
    h = s.x.size
    phi = np.array([0.0, 0.7, np.pi])
    f = s.eval_nodes(phi)                                         # (C, h_o, h_i, P) in 1/sr
    fcos = f * s.x[None, :, None, None]
    # full-precision .h5: every band, exact at the nodes
    b5 = open_bsdf(tmp_path / "rt-test.h5")
    assert b5.channels == tuple(f"{w:g}nm" for w in r.wavelength_nm)
    MI, MO, PH = np.meshgrid(s.x, -s.x, phi, indexing="ij")       # (i, o, p)
    v5 = b5.eval(MI, MO, PH, clamp="none")                       # (i, o, p, C)
    np.testing.assert_allclose(v5, np.transpose(fcos, (2, 1, 3, 0)), rtol=1e-10, atol=1e-14)
    # nothing transmitted, nothing from below
    assert np.all(b5.eval(MI, -MO, PH, clamp="none") == 0)
    # .bsdf: float32 RGB = the white-normalised sRGB of the band values
    from flakedb.colour.colorimetry import spectra_to_rgb_mode

    bb = open_bsdf(tmp_path / "rt-test.bsdf")
    assert bb.n_channels == 3
    vb = bb.eval(MI, MO, PH, clamp="none")
    expect = spectra_to_rgb_mode(v5, r.wavelength_nm)
    # float32 storage, and G rebuilt from Y, R, B with the spec's 6-digit coefficients: ~1e-6 relative
    assert np.abs(vb - expect).max() < 3e-6 * np.abs(expect).max()
    # the mirror term and provenance are recorded
    assert bb.delta == {"kind": "fresnel", "eta": 1.5} and b5.delta == {"kind": "fresnel", "eta": 1.5}
    assert bb.metadata["recipe"] == "rt-test" and bb.metadata["store"] == "none: computed directly"
    assert b5.metadata["store_version"] == "none: computed directly" and b5.metadata["raw"] is True
    assert b5.metadata["recipe_text"] == r.text and "flakedb_version" in b5.metadata
    # the report's interpolation is the readers' (off-node points, both sides)
    mi = np.array([0.71, 0.3, 0.95])
    mo = np.array([-0.5, -0.86, -0.2])
    ph = np.array([0.0, np.pi, 1.1])
    np.testing.assert_allclose(eval_table(res.table, mi, mo, ph), b5.eval(mi, mo, ph, clamp="none"),
                               rtol=1e-10, atol=1e-14)
    assert not list(tmp_path.glob(".*"))                         # no temporary leftovers
    # opaque paint: the nodes' reflected flux is the solver's albedo
    np.testing.assert_allclose(res.table.coeffs[:, h:, :h, 0] @ s.w[::-1] * 2 * np.pi,
                               s.albedo(include_delta=False), rtol=1e-12)


def test_white_primer_colour_report_exact(tmp_path):
    r = recipe([{"primer": {"color": "white"}}], mode="spectral", n=16, name="white")
    res = compose(r, tmp_path)
    rep = res.report
    L_expect = 116 * 0.9 ** (1 / 3) - 16
    for g in rep["geometries"]:
        assert g["L"] == pytest.approx(L_expect, abs=1e-9)
        assert abs(g["a"]) < 1e-9 and abs(g["b"]) < 1e-9
        assert g["reflectance_factor"] == pytest.approx([0.9] * len(r.wavelength_nm), abs=1e-12)
    assert abs(rep["flop_index"]) < 1e-9
    assert all(a["albedo_Y"] == pytest.approx(0.9, abs=1e-12) and a["mirror"] == 0 for a in rep["albedo"])
    import json

    assert json.loads((tmp_path / "white.json").read_text())["geometries"][0]["L"] == pytest.approx(L_expect)
    assert open_bsdf(tmp_path / "white.bsdf").n_channels == 1     # grey: one channel


def test_spectral_primer_lab_matches_colorimetry(tmp_path):
    from flakedb.colour.settings import DEFAULT_ILLUMINANT, DEFAULT_OBSERVER
    from flakedb.colour.tolerance import reflectance_to_Lab

    wl = np.arange(400.0, 701.0, 20.0)
    spec = 0.1 + 0.7 * (wl - 400) / 300
    r = recipe([{"primer": {"spectrum": {"wavelength_nm": wl.tolist(), "value": spec.tolist()}}}],
               mode="spectral", n=16)
    rep = compose(r, tmp_path).report
    lab = reflectance_to_Lab(spec, wl, DEFAULT_OBSERVER, DEFAULT_ILLUMINANT)   # the report's default conditions
    assert (rep["observer"], rep["illuminant"]) == (DEFAULT_OBSERVER, DEFAULT_ILLUMINANT)
    for g in rep["geometries"]:
        np.testing.assert_allclose([g["L"], g["a"], g["b"]], lab, atol=1e-9)
    assert lab[1] > 5    # a reddish ramp: the test would notice channels mixed up


def test_rgb_mode_white_is_white(tmp_path):
    r = recipe([{"primer": {"color": "white"}}], mode="rgb", n=16)
    rep = compose(r, tmp_path).report
    g = rep["geometries"][3]
    assert g["L"] == pytest.approx(116 * 0.9 ** (1 / 3) - 16, abs=1e-9) and abs(g["a"]) < 1e-9


def test_multiangle_geometry_and_flop():
    assert multiangle_geometry(15) == pytest.approx((np.cos(np.pi / 4), -np.cos(np.radians(30)), 0.0, 30.0))
    mu_i, mu_o, phi, tv = multiangle_geometry(110)
    assert phi == np.pi and tv == -65 and mu_o == pytest.approx(-np.cos(np.radians(65)))
    assert flop_index(100, 50, 20) == pytest.approx(2.69 * 80**1.11 / 50**0.86)
    assert flop_index(20, 50, 100) == pytest.approx(-2.69 * 80**1.11 / 50**0.86)
    assert flop_index(10, 0, 5) is None


def test_mirror_like_flakes_bright_on_the_specular_side(tmp_path):
    """Nearly aligned mirror flakes over black: the near-specular geometries (φ_d = 0 side) are far
    brighter than those on the illuminator's side, and the flop index is large."""
    flake = {"custom": {"kind": "flake", "R": 1.0, "T": 0.0, "orientation_alpha": 0.15}, "optical_depth": 3.0}
    r = recipe([{"basecoat": {"thickness_um": 5, "ior": 1.0, "particles": [flake]}},
                {"primer": {"color": "black"}}], n=32)
    rep = compose(r, tmp_path).report
    L = {g["aspecular_deg"]: g["L"] for g in rep["geometries"]}
    assert L[15.0] > L[25.0] > L[45.0] > L[75.0] and L[-15.0] > L[75.0] and L[15.0] > 2 * L[110.0]
    assert rep["flop_index"] > 10


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
    import flakedb.bsdf

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(flakedb.bsdf, "write_h5", boom)
    r = recipe([{"primer": {"color": "gray"}}], n=16, name="fail")
    with pytest.raises(OSError, match="disk full"):
        compose(r, tmp_path / "out")
    assert list((tmp_path / "out").iterdir()) == []


def test_cli_compose_end_to_end(tmp_path):
    rp = tmp_path / "r.yaml"
    rp.write_text("flakedb: 1\nname: cli-paint\nspectral: {mode: mono}\nresolution: 16\nlayers:\n"
                  "  - clearcoat: {thickness_um: 30, ior: 1.5}\n  - primer: {color: gray}\n")
    res = CliRunner().invoke(cli, ["compose", str(rp), "--out", str(tmp_path / "o"), "--raw"])
    assert res.exit_code == 0, res.output
    assert "store: none" in res.output and "flop index" in res.output and "aspecular" in res.output
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["cli-paint.bsdf", "cli-paint.h5", "cli-paint.json"]


def test_check_physical_flags_energy_gain_negative_values_and_unconverged_orders():
    """compose's self-check (issue 12): a lossless rough coat over a white primer passes; the same
    stack scaled by 1.01, with a negative coefficient, or flagged unconverged does not."""
    import copy

    from flakedb.solve.pipeline import check_physical
    from flakedb.rt.adding.stack import Lambertian, Rough, SolverSettings, solve_stack

    r = solve_stack(Rough(1.5, 0.1), [], Lambertian(1.0), SolverSettings.product(32))
    assert check_physical(r) == []
    hot = copy.copy(r)
    hot.Rt = r.Rt * 1.01
    assert any("albedo" in p for p in check_physical(hot))
    neg = copy.copy(r)
    neg.Rt = r.Rt.copy()
    neg.Rt[1] -= 0.5 * np.abs(r.Rt[0]).max()  # a cos φ term that drives f negative somewhere
    assert any("negative" in p for p in check_physical(neg))
    unc = copy.copy(r)
    unc.info = dict(r.info, order_converged=False, order_tail=0.01)
    assert any("converge" in p for p in check_physical(unc))


@pytest.mark.parametrize("grey", [True, False])
def test_check_physical_range_is_the_bsdf_evaluated_at_the_nodes(grey):
    """check_physical's negativity range (one product over the orders, the node pair's factor after) is the max and
    min of f μ_i μ_o from StackBSDF.eval_nodes (the coefficient array times cos(l φ), summed), to rounding; a
    grey stack solved once (channels broadcast, stride 0) is read as one channel."""
    from flakedb.solve.pipeline import _bsdf_range
    from flakedb.rt.scattering.media import PhaseMedium
    from flakedb.rt.adding.stack import Lambertian, Rough, Slab, SolverSettings, solve_stack

    albedo, primer = ([0.9] * 3, [0.5] * 3) if grey else ([0.95, 0.6, 0.3], [0.5, 0.2, 0.7])
    slab = Slab(1.0, PhaseMedium(sigma_t_per_um=[1.0] * 3, albedo=albedo, phase=("hg", 0.7)))
    st = solve_stack(Rough(1.5, 0.2), [slab], Lambertian(primer), SolverSettings.product(16))
    assert (st.Rt.strides[1] == 0) == grey
    if not grey:
        st.Rt = st.Rt.copy()
        st.Rt[1] -= 0.3 * np.abs(st.Rt[0]).max()  # negative values somewhere, for the min
    phi = np.linspace(0.0, np.pi, 37)
    g = st.eval_nodes(phi) * (st.x[:, None] * st.x[None, :])[None, :, :, None]
    gmax, gmin = _bsdf_range(st, phi)
    scale = np.abs(g).max()
    assert abs(gmax - g.max()) <= 1e-12 * scale and abs(gmin - g.min()) <= 1e-12 * scale


def test_compose_refuses_an_unphysical_result_unless_allowed(tmp_path, monkeypatch):
    """A result failing the self-check is an error and writes nothing; --allow-unphysical writes it
    with a loud warning."""
    import flakedb.solve.pipeline as orch

    monkeypatch.setattr(orch, "check_physical", lambda stack: ["albedo 1.2 > 1 + 0.001 (injected)"])
    rec = recipe([{"basecoat": {"thickness_um": 5, "ior": 1.0, "particles": [HG]}}], n=16)
    with pytest.raises(orch.UnphysicalResultError, match="unphysical result"):
        compose(rec, tmp_path / "a", n=16)
    assert not (tmp_path / "a").exists() or not any((tmp_path / "a").iterdir())
    res = compose(rec, tmp_path / "b", n=16, allow_unphysical=True)
    assert any(w.startswith("UNPHYSICAL") for w in res.warnings) and Path(res.paths["bsdf"]).exists()


def test_compose_and_its_report_do_not_import_colour_science(tmp_path):
    """Issue 11: the default colorimetry (CIE 1931 2°, D65, integer-nm grid, sRGB) is flakedb's own
    (docs/colorimetry.md), so `flakedb compose` of a spectral recipe that needs gamut mapping (cadmium
    yellow, outside sRGB) and its colour report import neither colour-science nor matplotlib."""
    root = Path(__file__).resolve().parents[2]
    code = textwrap.dedent(f"""
        import sys
        from flakedb.cli.main import cli
        cli(["compose", {str(root / "flakedb" / "catalog" / "recipes" / "particle-cadmium-yellow.yaml")!r}, "--n", "16",
             "--quiet", "--out", {str(tmp_path)!r}], standalone_mode=False)
        heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("colour", "matplotlib"))
        print("HEAVY", len(heavy), heavy[:3])
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root, check=False)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "HEAVY 0 []" in r.stdout, r.stdout.splitlines()[-1]
    assert "colour report" in r.stdout and (tmp_path / "particle-cadmium-yellow.json").exists()


def test_bsdf_range_by_channel_blocks_is_the_whole_arrays():
    """check_physical's BSDF range is taken a few channels at a time (issue 26 item 5: the whole f copy held
    1.15 GB at n = 200, 41 bands): the same max and min as f μ_i μ_o of StackBSDF.eval_nodes over every
    channel, within the rounding of the two evaluation orders, including a negative value placed in the
    last channel block only."""
    import copy

    from flakedb.solve.pipeline import CHECK_CHANNEL_BLOCK, _bsdf_range
    from flakedb.rt.adding.stack import Lambertian, Rough, SolverSettings, solve_stack

    C = 2 * CHECK_CHANNEL_BLOCK + 1
    r = solve_stack(Rough(1.5, 0.2), [], Lambertian(np.linspace(0.1, 0.9, C)), SolverSettings.product(16))
    r = copy.copy(r)
    r.Rt = np.array(np.broadcast_to(r.Rt, (r.Rt.shape[0], C) + r.Rt.shape[2:]))
    r.Rt[1, C - 1] -= 0.5 * np.abs(r.Rt[0]).max()  # negative somewhere in channel C − 1 only
    phi = np.linspace(0.0, np.pi, 37)
    g = r.eval_nodes(phi) * (r.x[:, None] * r.x[None, :])[None, :, :, None]
    gmax, gmin = _bsdf_range(r, phi)
    L = r.Rt.shape[0]
    cos = np.abs(np.cos(np.arange(L)[:, None] * phi[None, :]))
    terms = np.einsum("lcoi,lp->coip", np.abs(r.f_coefficients()), cos) * (r.x[:, None] * r.x[None, :])[None, :, :, None]
    bound = float(tol.sum_tol(L, terms.max(), extra_ops=4))  # L products summed, the scalings before and after
    assert g.min() < 0 and abs(gmin - g.min()) <= bound and abs(gmax - g.max()) <= bound


def test_the_discretisation_solve_runs_first_and_is_freed_before_the_solve(tmp_path, monkeypatch):
    """For a paint above flakedb.solve.pipeline.CONCURRENT_SECOND_BYTES, the report's second solve (n' = 3n/4) is
    made before the solve at n, and nothing of it is alive when the solve at n runs: made after, while n's R^t and
    table were held, it set the peak (cadmium yellow under a rough 0.1 coat, 41 bands, n = 200: 3.95 GB, 2.97 GB
    with it first).  Auto's refinement keeps the order at every n.  (Small paints run it beside the solve:
    tests/solve/test_one_home.py.)"""
    import gc
    import weakref

    import flakedb.solve.pipeline as orch

    solve_paint = orch.solve_paint
    calls, alive = [], []

    def recording(paint, n, **kw):
        alive.append(sum(1 for r in calls if r[1]() is not None))  # solves still referenced when this one starts
        st = solve_paint(paint, n, **kw)
        calls.append((n, weakref.ref(st)))
        return st

    monkeypatch.setattr(orch, "solve_paint", recording)
    monkeypatch.setattr(orch, "CONCURRENT_SECOND_BYTES", 0.0)  # this small paint takes the large paints' path
    gc.disable()  # only reference counting frees them: what the compose itself holds
    try:
        rec = parse_recipe(textwrap.dedent("""\
            flakedb: 1
            name: order-of-solves
            spectral: {mode: rgb}
            resolution: 24
            layers:
              - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0}
              - basecoat: {thickness_um: 10, ior: 1.5, particles: [{species: titanium-white, volume_fraction: 0.05}]}
              - primer: {color: gray}
            """))
        res = compose(rec, tmp_path / "o")
    finally:
        gc.enable()
    assert [n for n, _ in calls] == [18, 24]
    assert alive == [0, 0]
    assert res.report["discretisation"]["n_second"] == 18
