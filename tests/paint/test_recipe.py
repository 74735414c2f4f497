"""Recipes: schema, semantic checks, error messages, and the CLI's refusal of bad input.

Guards against: unknown keys silently ignored (a typo like ``volume_fracton`` dropping a particle's
loading); errors without the field path, the value, the allowed range or a hint; impossible paints
(R + T > 1, packing limits, unknown species, two binder indices, a primer that is not last) reaching
the solver; a failed compose leaving output files or directories behind; example recipes in
catalog/recipes that the schema does not accept; the auto resolution heuristic drifting.
"""

import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.paint import mapping
from flakedb.solve import resolution
from flakedb.paint.mapping import build_paint, solve_paint
from flakedb.solve.resolution import auto_resolution
from flakedb.paint.recipe import CatalogParticle, CustomFlake, CustomMedium, RecipeError, load_recipe, parse_recipe
from flakedb.rt.adding.stack import InnerSmooth
from tests.cases import basecoat_recipe

RECIPES = sorted((Path(__file__).resolve().parents[2] / "flakedb" / "catalog" / "recipes").glob("*.yaml"))

BASE = basecoat_recipe("test-paint", ["{species: pearlescent, volume_fraction: 0.04, diameter_um: 15, orientation_alpha: 0.2}",
                                      "{species: titanium-white, volume_fraction: 0.02}"], primer="{color: white}")


def doc():
    return yaml.safe_load(BASE)


def problems_of(d):
    with pytest.raises(RecipeError) as ei:
        parse_recipe(yaml.safe_dump(d, sort_keys=False), source="t.yaml")
    return ei.value.problems


def test_example_recipes_all_valid():
    names = {p.stem for p in RECIPES}
    # one paint per catalogue particle, tri-coat, metallic silver, Fig. 5 (2 x 3), Fig. 7 (8)
    for sp in ("metallic", "pearlescent", "gray-mirror", "cadmium-yellow", "titanium-white", "iron-black"):
        assert f"particle-{sp}" in names
    assert {"tri-coat-pearl-white", "metallic-silver"} <= names
    assert sum(n.startswith("fig5-") for n in names) == 6
    assert [n for n in sorted(names) if n.startswith("fig7-")] == [
        f"fig7-pearlescent-tio2-{t:03d}nm" for t in range(70, 141, 10)]
    for p in RECIPES:
        r = load_recipe(p)
        assert r.name == p.stem, f"{p.name}: name {r.name!r} should match the file name"


def test_typed_structure():
    r = parse_recipe(BASE)
    assert r.mode == "spectral" and r.n == 16
    np.testing.assert_array_equal(r.wavelength_nm, np.arange(400, 701, 20))
    assert r.clearcoat.ior == 1.5 and r.clearcoat.roughness == 0 and r.clearcoat.absorption_per_um is None
    (b,) = r.basecoats
    fl, pig = b.particles
    assert isinstance(fl, CatalogParticle) and fl.is_flake and fl.orientation_alpha == 0.2
    assert fl.path == "layers[1].basecoat.particles[0]"
    assert isinstance(pig, CatalogParticle) and pig.kind == "pigment" and pig.volume_fraction == 0.02
    assert r.primer.albedo == 0.9 and r.primer.label == "white"
    d = doc()
    d["resolution"] = "auto"
    del d["spectral"]
    r = parse_recipe(yaml.safe_dump(d))
    assert r.n is None and r.wavelength_nm[0] == 380 and r.wavelength_nm[-1] == 780 and r.wavelength_nm.size == 41


def test_custom_species_parse():
    r = load_recipe(Path(__file__).resolve().parents[2] / "flakedb" / "catalog" / "recipes" / "research-custom-flake.yaml")
    fl, med = r.basecoats[0].particles
    assert isinstance(fl, CustomFlake) and fl.optical_depth == 2.0 and fl.T.value.tolist() == [0.3, 0.3]
    assert isinstance(med, CustomMedium) and med.phase[0] == "table" and med.albedo == 0.9
    assert r.mode == "mono" and r.wavelength_nm is None


def test_unknown_keys_refused_with_path_and_suggestion():
    d = doc()
    d["colour"] = "red"
    d["layers"][1]["basecoat"]["particles"][0]["volume_fracton"] = 0.1
    probs = problems_of(d)
    joined = "\n".join(probs)
    assert "(top level): unknown key 'colour'" in joined
    assert "layers[1].basecoat.particles[0]: unknown key 'volume_fracton' (did you mean 'volume_fraction'?)" in joined
    d = doc()
    d["layers"][1] = {"basecat": d["layers"][1]["basecoat"]}
    assert any("layers[1]: unknown key 'basecat' (did you mean 'basecoat'?)" in p for p in problems_of(d))


@pytest.mark.parametrize("where, value, expect", [
    (("layers", 1, "basecoat", "particles", 0, "volume_fraction"), 1.5,
     "layers[1].basecoat.particles[0].volume_fraction: value 1.5 is outside the allowed range 0 < value < 1"),
    (("layers", 0, "clearcoat", "ior"), 0.5, "layers[0].clearcoat.ior: value 0.5 is outside the allowed range 1 ≤ value ≤ 3"),
    (("layers", 0, "clearcoat", "roughness"), -0.1, "layers[0].clearcoat.roughness: value -0.1 is outside"),
    (("layers", 2, "primer", "color"), "blue", "layers[2].primer.color: value \"blue\" is not one of black, gray, white"),
    (("resolution",), 33, "resolution: value 33"),
    (("flakedb",), 2, "flakedb: recipe format version 2 is not supported"),
    (("layers", 1, "basecoat", "thickness_um"), "thick", "layers[1].basecoat.thickness_um: value \"thick\" has the wrong type"),
])
def test_bad_values_name_path_value_range_and_hint(where, value, expect):
    d = doc()
    node = d
    for k in where[:-1]:
        node = node[k]
    node[where[-1]] = value
    probs = problems_of(d)
    assert any(expect in p for p in probs), probs
    if where[-1] in ("volume_fraction", "ior"):
        assert any("(hint: " in p for p in probs), probs


def test_missing_required_key():
    d = doc()
    del d["layers"][1]["basecoat"]["thickness_um"]
    assert any(p.startswith("layers[1].basecoat: 'thickness_um' is missing") for p in problems_of(d))


def test_unknown_species_suggests():
    d = doc()
    d["layers"][1]["basecoat"]["particles"][0]["species"] = "pearlescnt"
    (p,) = problems_of(d)
    assert p.startswith("layers[1].basecoat.particles[0].species: unknown species 'pearlescnt'")
    assert "did you mean 'pearlescent'" in p and "flakedb species list" in p


def test_semantic_problems_all_reported():
    d = doc()
    d["layers"].append({"clearcoat": {"thickness_um": 10, "ior": 1.5}})   # clear coat not on top
    d["layers"][1]["basecoat"]["particles"][1]["gsd"] = 1.2          # fine (pigment)
    d["layers"][1]["basecoat"]["particles"][0]["gsd"] = 1.2          # pigment-only key on a flake
    probs = problems_of(d)
    j = "\n".join(probs)
    assert "layers[3].clearcoat: a clear coat must be the first (top) layer" in j
    assert "layers[2].primer: the primer must be the last (bottom) layer" in j
    assert "layers[1].basecoat.particles[0].gsd: 'pearlescent' is a interference_flake; gsd applies to pigments only" in j


def test_packing_limits():
    d = doc()
    parts = d["layers"][1]["basecoat"]["particles"]
    parts[1]["volume_fraction"] = 0.5
    parts.append({"species": "iron-black", "volume_fraction": 0.2})
    (p,) = problems_of(d)
    assert p.startswith("layers[1].basecoat.particles: the pigments' volume fractions add up to 0.7")
    assert "0.64" in p
    d = doc()
    parts = d["layers"][1]["basecoat"]["particles"]
    parts[0]["volume_fraction"] = 0.6
    parts.append({"species": "metallic", "volume_fraction": 0.45})
    assert any("add up to 1.07" in p and "below 1" in p for p in problems_of(d))
    d = doc()
    d["layers"][1]["basecoat"]["particles"][0]["volume_fraction"] = 0.35
    r = parse_recipe(yaml.safe_dump(d))
    assert any("independent-scattering" in w for w in r.warnings)


def test_custom_flake_R_plus_T_and_optical_depth():
    d = doc()
    d["spectral"] = {"mode": "mono"}
    d["layers"][1]["basecoat"]["particles"] = [
        {"custom": {"kind": "flake", "R": {"c": [0, 1], "value": [0.8, 0.5]}, "T": 0.3, "orientation_alpha": 0.2},
         "optical_depth": 1.0}]
    (p,) = problems_of(d)
    assert p.startswith("layers[1].basecoat.particles[0].custom: R + T = 1.1 at c = 0 exceeds 1")
    d["layers"][1]["basecoat"]["particles"][0]["custom"]["R"] = 0.0
    d["layers"][1]["basecoat"]["particles"][0]["custom"]["T"] = 1.0
    assert any("optical_depth: value 1 cannot be met" in p for p in problems_of(d))
    del d["layers"][1]["basecoat"]["particles"][0]["optical_depth"]
    assert any("'optical_depth' is missing" in p for p in problems_of(d))


def test_custom_medium_phase_table_checked():
    d = doc()
    d["spectral"] = {"mode": "mono"}
    d["layers"][1]["basecoat"]["particles"] = [
        {"custom": {"kind": "medium", "albedo": 0.5, "phase": {"table": {"cos_theta": [-1, 0.5], "value": [1, 1]}}},
         "optical_depth": 1.0}]
    (p,) = problems_of(d)
    assert "phase.table.cos_theta: must increase strictly from -1 to 1" in p
    d["layers"][1]["basecoat"]["particles"][0]["custom"]["phase"] = {"hg": 1.0}
    assert any("phase" in p and "value 1" in p for p in problems_of(d))


def _vmf_doc(albedo, phase):
    d = doc()
    d["layers"][1]["basecoat"]["particles"] = [
        {"custom": {"kind": "medium", "albedo": albedo, "phase": phase}, "optical_depth": 2.0}]
    return d


SPECTRAL_ALBEDO = {"wavelength_nm": [400, 550, 700], "value": [0.9, 0.5, 0.2]}


def test_custom_medium_spectral_albedo_and_vmf_parse():
    r = parse_recipe(yaml.safe_dump(_vmf_doc(SPECTRAL_ALBEDO, {"vmf": {"kappa": 20}})))
    (_, med), = r.particles()
    assert isinstance(med, CustomMedium) and med.phase == ("vmf", 20.0)
    np.testing.assert_allclose(med.albedo.at([400, 475, 700]), [0.9, 0.7, 0.2])
    # the mean cosine g is converted to κ (g = coth κ − 1/κ; κ = 20 ↔ g = 0.95 to 1e-17)
    r = parse_recipe(yaml.safe_dump(_vmf_doc(0.8, {"vmf": {"g": 0.95}})))
    (_, med), = r.particles()
    assert med.albedo == 0.8 and med.phase[0] == "vmf" and abs(med.phase[1] - 20.0) < 1e-9


def test_custom_medium_bad_albedo_spectrum_and_kappa_refused():
    bad = {"wavelength_nm": [400, 550, 700], "value": [0.9, 1.2, 0.2]}
    (p,) = problems_of(_vmf_doc(bad, {"vmf": {"kappa": 20}}))
    assert p.startswith("layers[1].basecoat.particles[0].custom.albedo.value[1]: value 1.2 is outside the "
                        "allowed range 0 ≤ albedo ≤ 1 (hint:"), p
    short = {"wavelength_nm": [450, 700], "value": [0.9, 0.2]}
    (p,) = problems_of(_vmf_doc(short, "isotropic"))
    assert p.startswith("layers[1].basecoat.particles[0].custom.albedo.wavelength_nm: covers 450-700 nm but the "
                        "recipe's grid is 400-700 nm"), p
    (p,) = problems_of(_vmf_doc(0.5, {"vmf": {"kappa": -1}}))
    assert p.startswith("layers[1].basecoat.particles[0].custom.phase.vmf.kappa: value -1 is outside the allowed "
                        "range 0 ≤ value ≤ 2000"), p
    (p,) = problems_of(_vmf_doc(0.5, {"vmf": {"g": 1.0}}))
    assert "custom.phase.vmf.g: value 1.0 is outside the allowed range 0 ≤ value ≤ 0.9995" in p, p
    (p,) = problems_of(_vmf_doc(0.5, {"vmf": {"g": 0.9, "kappa": 3}}))
    assert "custom.phase.vmf" in p and "exactly one of the keys g, kappa" in p, p
    d = _vmf_doc(SPECTRAL_ALBEDO, "isotropic")
    d["spectral"] = {"mode": "mono"}
    assert any(p.startswith("layers[1].basecoat.particles[0].custom.albedo: a spectrum needs spectral or rgb mode")
               for p in problems_of(d))


def test_mode_and_spectrum_checks():
    d = doc()
    d["spectral"] = {"mode": "mono"}
    assert any("mono mode takes wavelength-independent inputs only" in p for p in problems_of(d))
    d = doc()
    d["spectral"]["step_nm"] = 7
    assert any(p.startswith("spectral.step_nm: value 7 does not divide") for p in problems_of(d))
    d = doc()
    d["layers"][2] = {"primer": {"spectrum": {"wavelength_nm": [450, 700], "value": [0.2, 0.3]}}}
    assert any("layers[2].primer.spectrum.wavelength_nm: covers 450-700 nm" in p for p in problems_of(d))
    d["layers"][2] = {"primer": {"spectrum": {"wavelength_nm": [400, 700], "value": [0.2, 1.3]}}}
    assert any("layers[2].primer.spectrum.value[1]: value 1.3 is outside the allowed range" in p for p in problems_of(d))


def test_stack_shape_checks():
    d = doc()
    d["layers"] = d["layers"][:2]  # no primer under an ior 1.5 coat: not representable in one node set
    assert any("no primer" in p and "index-matched" in p for p in problems_of(d))
    d = doc()
    d["layers"][0]["clearcoat"]["ior"] = 1.0
    d["layers"][1]["basecoat"]["ior"] = 1.0
    d["layers"][0]["clearcoat"]["roughness"] = 0.1
    assert any("layers[0].clearcoat.roughness: value 0.1 with ior 1" in p for p in problems_of(d))
    d = doc()
    d["layers"][1]["basecoat"]["thickness_um"] = 0.3  # thinner than the 0.54 µm flake
    assert any("the flake is 0.54 µm thick" in p for p in problems_of(d))
    d = doc()
    d["layers"][0]["clearcoat"]["roughness"] = 0.05  # lossless at every n now: no blanket warning
    assert not any("roughness" in w for w in parse_recipe(yaml.safe_dump(d)).warnings)


def test_metal_base_parses_and_is_checked(monkeypatch):
    """A metal base (issue 12 item 3(b)) in place of the primer: a catalogue material or {n, k}, with a
    Beckmann roughness; each problem names the field, the value, the allowed range or names, a fix."""
    d = doc()
    d["layers"][2] = {"metal": {"material": "Al", "roughness": 0.1}}
    r = parse_recipe(yaml.safe_dump(d))
    assert r.primer is None and r.metal.material == "Al" and r.metal.roughness == 0.1 and r.metal.energy_compensation
    assert r.metal.path == "layers[2].metal"
    d["layers"][2]["metal"] = {"material": {"n": 1.2, "k": 7.0}, "roughness": 0.2, "energy_compensation": False}
    r = parse_recipe(yaml.safe_dump(d))
    assert r.metal.material == 1.2 + 7.0j and not r.metal.energy_compensation
    d["layers"][2]["metal"] = {"material": "Alu", "roughness": 0.1}
    assert any(p.startswith("layers[2].metal.material: unknown material \"Alu\" (did you mean 'Al'?)")
               and "known materials: " in p for p in problems_of(d))
    d["layers"][2]["metal"] = {"material": "Al", "roughness": 0.001}
    assert "layers[2].metal.roughness: value 0.001 is outside the allowed range 0.01 ≤ value ≤ 1" in problems_of(d)[0]
    d["layers"][2]["metal"] = {"material": {"n": 1.2, "k": -1}, "roughness": 0.1}
    assert any("layers[2].metal.material.k: value -1 is outside the allowed range 0 ≤ value ≤ 100" in p
               for p in problems_of(d))
    d["layers"][2] = {"metal": {"material": "Al", "roughness": 0.1}}
    d["layers"].append({"primer": {"color": "white"}})
    probs = problems_of(d)
    assert any(p.startswith("layers[2].metal: the metal base must be the last (bottom) layer") for p in probs)
    assert any(p.startswith("layers: a primer and a metal base") for p in probs)
    d = doc()
    d["layers"] = [{"clearcoat": {"thickness_um": 40, "ior": 1.5}}, {"metal": {"material": "Al", "roughness": 0.1}}]
    d["spectral"] = {"mode": "mono"}
    assert any(p.startswith("layers[1].metal.material: 'Al' has a spectral index; mono mode") for p in problems_of(d))
    d["layers"][1]["metal"]["material"] = "SiO2"
    d["spectral"] = {"mode": "spectral", "range_nm": [400, 700], "step_nm": 10}
    assert any("hardly a metal" in w for w in parse_recipe(yaml.safe_dump(d)).warnings)
    # resolution: auto takes the metal lobe's measured envelope (docs/resolution.md "Metal base")
    d["layers"][1]["metal"]["material"] = "Al"
    n, why = auto_resolution(parse_recipe(yaml.safe_dump(d)))  # the default colour_error 0.1 binds (issue 26)
    assert n == 176 and "colour_error ≤ 0.1" in why
    monkeypatch.setattr(resolution, "AUTO_TARGETS", {k: v for k, v in resolution.AUTO_TARGETS.items() if k != "colour_error"})
    n, why = auto_resolution(parse_recipe(yaml.safe_dump(d)))  # the lobe rule alone
    assert n == 48 and "metal base α = 0.1" in why and "measured 0.048" in why
    d["layers"][1]["metal"]["roughness"] = 0.01
    n, why = auto_resolution(parse_recipe(yaml.safe_dump(d)))
    assert n == 248 and "scaled by 0.05/α" in why
    d["resolution"] = {"lobe_error": 0.001}
    with pytest.raises(RecipeError, match="lobe_error 0.001 for a metal base is not reachable"):
        auto_resolution(parse_recipe(yaml.safe_dump(d)))


def test_two_binders_map_to_an_inner_interface():
    """Issue 12 item 3(a): a basecoat denser (or less dense) than the coat above is a smooth inner interface (η_b / η_a),
    equal indices add none; the paint composes and stays passive."""
    d = doc()
    d["layers"][1]["basecoat"]["ior"] = 1.6
    paint = build_paint(parse_recipe(yaml.safe_dump(d)))
    inner = [s for s in paint.slabs if isinstance(s, InnerSmooth)]
    assert len(inner) == 1 and inner[0].eta == pytest.approx(1.6 / 1.5) and paint.eta == 1.5
    assert any(c["kind"] == "inner interface" and c["eta_below"] == 1.6 for c in paint.components)
    assert not any(isinstance(s, InnerSmooth) for s in build_paint(parse_recipe(yaml.safe_dump(doc()))).slabs)
    d["spectral"] = {"mode": "spectral", "range_nm": [400, 700], "step_nm": 20}
    d["layers"][2] = {"primer": {"color": "white"}}
    A = solve_paint(build_paint(parse_recipe(yaml.safe_dump(d))), 16).albedo()
    assert A.max() <= 1.0 and A.min() > 0
    d["layers"][1]["basecoat"]["ior"] = 1.4  # a fall into a less dense binder: also a smooth inner interface
    paint = build_paint(parse_recipe(yaml.safe_dump(d)))
    inner = [s for s in paint.slabs if isinstance(s, InnerSmooth)]
    assert len(inner) == 1 and inner[0].eta == pytest.approx(1.4 / 1.5)
    d["layers"][2] = {"primer": {"albedo": 1.0}}
    d["layers"][1]["basecoat"]["particles"] = [{"custom": {"kind": "medium", "albedo": 1.0, "phase": {"hg": 0.5}},
                                                "optical_depth": 1.0}]
    A = solve_paint(build_paint(parse_recipe(yaml.safe_dump(d))), 16).albedo()
    assert np.abs(A - 1.0).max() < 1e-10
    d["layers"][0]["clearcoat"]["ior"] = 1.0
    d["layers"][1]["basecoat"]["ior"] = 1.5
    assert any("an inner interface needs a binder above it" in p for p in problems_of(d))


def test_yaml_syntax_error_names_line():
    with pytest.raises(RecipeError, match="YAML syntax error at line 2, column 8"):
        parse_recipe("flakedb: 1\nname: a: b\nlayers: []\n")


def test_auto_resolution_from_targets():
    """n from the measured envelopes of flakedb.paint.mapping (docs/resolution.md), and refusals."""
    from flakedb.solve.resolution import auto_resolution

    d = doc()
    d["resolution"] = "auto"
    assert auto_resolution(parse_recipe(yaml.safe_dump(d)))[0] == 48          # α_f 0.2: colour h·α_f ≥ 4.8 → h 24
    d["layers"][1]["basecoat"]["particles"][0]["orientation_alpha"] = 0.05
    assert auto_resolution(parse_recipe(yaml.safe_dump(d)))[0] == 192         # h = 4.8/0.05 = 96 (albedo: 64)
    d["resolution"] = {"albedo_error": 0.01}                                     # h·α_f ≥ 9.6 → h 192
    assert auto_resolution(parse_recipe(yaml.safe_dump(d)))[0] == 384
    d["layers"][1]["basecoat"]["particles"][0]["orientation_alpha"] = 0.01
    d["resolution"] = "auto"
    with pytest.raises(RecipeError, match=r"needs n ≥ 640 .* largest allowed n = 512 \(hint: set resolution: 512"):
        auto_resolution(parse_recipe(yaml.safe_dump(d)))
    d["layers"][1]["basecoat"]["particles"] = [{"species": "titanium-white", "volume_fraction": 0.1}]
    d["layers"][0]["clearcoat"]["roughness"] = 0.1
    n, why = auto_resolution(parse_recipe(yaml.safe_dump(d)))
    assert n == 48 and "rough coat α = 0.1" in why and "measured 0.034" in why   # h·α ≥ 2.4
    d["resolution"] = {"lobe_error": 0.0001}
    with pytest.raises(RecipeError, match="lobe_error 0.0001 .* not reachable: the smallest measured error is 0.0015"):
        auto_resolution(parse_recipe(yaml.safe_dump(d)))
    d["resolution"] = {"lobe_errr": 0.01}
    assert any("resolution" in p for p in problems_of(d))


# --- the command line refuses bad input before computing and leaves nothing behind --------------


def _run(args):
    return CliRunner().invoke(cli, args)


def test_cli_bad_recipe_exits_nonzero_without_outputs(tmp_path):
    d = doc()
    d["layers"][1]["basecoat"]["particles"][0]["volume_fraction"] = 1.5
    rp = tmp_path / "bad.yaml"
    rp.write_text(yaml.safe_dump(d))
    out = tmp_path / "out"
    r = _run(["compose", str(rp), "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert "layers[1].basecoat.particles[0].volume_fraction: value 1.5" in r.output
    assert not out.exists()


def test_cli_empty_store_and_bad_n(tmp_path):
    rp = tmp_path / "ok.yaml"
    rp.write_text(BASE)
    r = _run(["compose", str(rp), "--out", str(tmp_path / "o"), "--store", str(tmp_path / "store.zarr")])
    assert r.exit_code == 2 and "flakedb build --store" in r.output  # names the command that fills it
    r = _run(["compose", str(rp), "--out", str(tmp_path / "o"), "--n", "33"])
    assert r.exit_code == 2 and "--n 33" in r.output and "even" in r.output
    assert not (tmp_path / "o").exists()
    r = _run(["compose", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "no such file" in r.output


def test_cli_unwritable_output_refused_before_computing(tmp_path):
    rp = tmp_path / "ok.yaml"
    rp.write_text(BASE)
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    r = _run(["compose", str(rp), "--out", str(blocker)])
    assert r.exit_code == 2 and "exists and is not a directory" in r.output
    r = _run(["compose", str(rp), "--out", str(blocker / "sub")])
    assert r.exit_code == 2 and "is not a directory" in r.output
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        r = _run(["compose", str(rp), "--out", str(ro)])
        assert r.exit_code == 2 and "not writable" in r.output
    assert "optics:" not in r.output  # nothing was computed


def test_cli_composes_spectral_albedo_vmf_medium_and_refuses_bad_ones(tmp_path):
    """A recipe using a per-band albedo and a vMF phase composes end to end; an albedo spectrum
    value of 1.2 and κ < 0 are refused with exit 2, one line naming the field, nothing written."""
    d = _vmf_doc(SPECTRAL_ALBEDO, {"vmf": {"g": 0.9}})
    rp = tmp_path / "vmf.yaml"
    rp.write_text(yaml.safe_dump(d))
    r = _run(["compose", str(rp), "--out", str(tmp_path / "ok"), "--n", "32"])
    assert r.exit_code == 0, r.output
    assert {p.suffix for p in (tmp_path / "ok").iterdir()} == {".bsdf", ".h5", ".json"}
    for bad, field in ((_vmf_doc({"wavelength_nm": [400, 700], "value": [0.5, 1.2]}, "isotropic"),
                        "layers[1].basecoat.particles[0].custom.albedo.value[1]: value 1.2 is outside"),
                       (_vmf_doc(0.5, {"vmf": {"kappa": -2}}),
                        "layers[1].basecoat.particles[0].custom.phase.vmf.kappa: value -2 is outside")):
        rp.write_text(yaml.safe_dump(bad))
        out = tmp_path / "bad"
        r = _run(["compose", str(rp), "--out", str(out)])
        assert r.exit_code == 2, r.output
        lines = [ln for ln in r.output.splitlines() if ln.strip()]
        assert lines[0].startswith("Error:") and "(1 problem)" in lines[0] and len(lines) == 2, r.output
        assert lines[1].strip().startswith(field) and "hint" in lines[1], r.output
        assert "Traceback" not in r.output and not out.exists()
