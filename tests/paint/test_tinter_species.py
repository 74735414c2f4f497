"""The ``tinter`` catalogue kind (optics per unit volume fraction; flakedb.paint.components.tinter_medium).

Guards against: a tinter that does not reach the solver as σ = φ · σ/φ with its HG g (checked against
a custom medium of the same optical depth, albedo and g, which the solver must answer identically); its
tables read at the wrong wavelengths (the medium's σ_t per band against linear interpolation); a mixture
with a catalogue pigment losing either; catalogue and recipe checks that let a malformed tinter, a
pigment-only field or a grid outside its tables through; the store trying to project a tinter;
:func:`with_media` replacing more (or less) than the named particle; `species list/show` failing on one.
"""

import copy
import json

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.match.targets import E2194_GEOMETRIES
from flakedb.paint.catalog import load_catalog, validate_catalog
from flakedb.paint.mapping import build_paint, catalog_species, with_media
from flakedb.paint.components import tinter_medium
from flakedb.paint.recipe import RecipeError
from flakedb.pipelines.build import make_request
from flakedb.rt.scattering.media import Mixture, PhaseMedium

WL = [400.0, 550.0, 700.0]


def tinter(a=(3.0, 0.5, 0.1), s=(1.0, 1.5, 2.0), g=0.4, wl=WL):
    return {"kind": "tinter", "description": "test tinter", "source": "tests",
            "specific_absorption_per_um": {"wavelength_nm": list(wl), "value": list(a), "source": "tests"},
            "specific_scattering_per_um": {"wavelength_nm": list(wl), "value": list(s), "source": "tests"},
            "asymmetry_g": {"value": g, "source": "tests"}}


@pytest.fixture(scope="module")
def catalog():
    cat = copy.deepcopy(load_catalog(None))
    cat["particles"]["t-var"] = tinter()
    cat["particles"]["t-flat"] = tinter(a=(2.0, 2.0, 2.0), s=(6.0, 6.0, 6.0), g=0.3)
    assert validate_catalog(cat) == []
    return cat


def recipe(parts, mode="spectral", step=20, d=20.0):
    return {"flakedb": 1, "name": "t", "spectral": {"mode": mode, "range_nm": [400, 700], "step_nm": step},
            "resolution": 16,
            "layers": [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": 0}},
                       {"basecoat": {"thickness_um": d, "ior": 1.5, "particles": parts}},
                       {"primer": {"color": "gray"}}]}


def test_tinter_medium_is_the_custom_medium_of_the_same_optics(catalog):
    """A flat tinter at φ = 0.005 in 20 µm: σ_t = 0.005 × 8 = 0.04 /µm, optical depth 0.8, albedo 0.75, HG 0.3;
    the custom medium with those numbers must give the same BSDF (one physics path)."""
    a = recipe([{"species": "t-flat", "volume_fraction": 0.005}])
    b = recipe([{"custom": {"kind": "medium", "albedo": 0.75, "phase": {"hg": 0.3}}, "optical_depth": 0.8}])
    pa = predict(recipe_from_doc(a, "a", catalog), E2194_GEOMETRIES, 16, catalog)
    pb = predict(recipe_from_doc(b, "b", catalog), E2194_GEOMETRIES, 16, catalog)
    np.testing.assert_allclose(pa.rf, pb.rf, rtol=1e-12, atol=1e-15)
    # linear in φ: twice the volume fraction is twice the optical depth (and a different colour)
    c = recipe([{"species": "t-flat", "volume_fraction": 0.01}])
    d = recipe([{"custom": {"kind": "medium", "albedo": 0.75, "phase": {"hg": 0.3}}, "optical_depth": 1.6}])
    pc = predict(recipe_from_doc(c, "c", catalog), E2194_GEOMETRIES, 16, catalog)
    pd = predict(recipe_from_doc(d, "d", catalog), E2194_GEOMETRIES, 16, catalog)
    np.testing.assert_allclose(pc.rf, pd.rf, rtol=1e-12, atol=1e-15)
    assert np.abs(pc.rf - pa.rf).max() > 1e-3


def test_tables_read_per_band_and_mixed(catalog):
    """σ_t per band = φ (σ_a/φ + σ_s/φ) linearly interpolated (at 450 nm: a = 3 − 2.5/3, s = 1 + 0.5/3), in a
    mixture with a Mie white that keeps its own medium."""
    doc = recipe([{"species": "t-var", "volume_fraction": 0.05},
                  {"species": "titanium-white-r706", "volume_fraction": 0.1}])
    rec = recipe_from_doc(doc, "m", catalog)
    paint = build_paint(rec, catalog)
    med = paint.media["layers[1].basecoat.particles[0]"]
    wl = np.arange(400.0, 701.0, 20.0)
    a = np.interp(wl, WL, [3.0, 0.5, 0.1])
    s = np.interp(wl, WL, [1.0, 1.5, 2.0])
    np.testing.assert_allclose(med.sigma_t_per_um, 0.05 * (a + s), rtol=1e-14)
    np.testing.assert_allclose(med.albedo, s / (a + s), rtol=1e-14)
    assert med.phase == ("hg", 0.4)
    slab = [sl for sl in paint.slabs if hasattr(sl, "medium")][-1]
    assert isinstance(slab.medium, Mixture) and slab.medium.components[0] is med
    comp = [c for c in paint.components if c.get("kind") == "tinter"][0]
    assert comp["species"] == "t-var" and comp["volume_fraction"] == 0.05


def test_with_media_replaces_only_the_named_particle(catalog):
    doc = recipe([{"species": "t-var", "volume_fraction": 0.05},
                  {"species": "titanium-white-r706", "volume_fraction": 0.1}])
    paint = build_paint(recipe_from_doc(doc, "m", catalog), catalog)
    new = tinter_medium(np.ones(16), np.ones(16), 0.0, 0.01)
    p2 = with_media(paint, {"layers[1].basecoat.particles[0]": new})
    mix1 = [sl for sl in paint.slabs if hasattr(sl, "medium")][-1].medium
    mix2 = [sl for sl in p2.slabs if hasattr(sl, "medium")][-1].medium
    assert mix2.components[0] is new and mix2.components[1] is mix1.components[1]
    assert mix1.components[0] is paint.media["layers[1].basecoat.particles[0]"]  # the original is untouched
    assert p2.media["layers[1].basecoat.particles[0]"] is new


def test_tinter_medium_closed_form():
    m = tinter_medium([3.0, 0.0], [1.0, 0.0], 0.4, 0.02)
    assert isinstance(m, PhaseMedium)
    np.testing.assert_allclose(m.sigma_t_per_um, [0.08, 0.0], rtol=1e-15)
    np.testing.assert_allclose(m.albedo, [0.25, 0.0], rtol=1e-15)


def test_rgb_mode(catalog):
    """RGB mode maps σ_t and σ_s as spectra (a flat tinter stays flat: σ_t 0.16 /µm in every channel)."""
    rec = recipe_from_doc(recipe([{"species": "t-flat", "volume_fraction": 0.02}], mode="rgb", step=10), "r", catalog)
    med = build_paint(rec, catalog).media["layers[1].basecoat.particles[0]"]
    np.testing.assert_allclose(med.sigma_t_per_um, 0.16, rtol=1e-6)
    np.testing.assert_allclose(med.albedo, 0.75, rtol=1e-6)


def test_catalogue_checks(catalog):
    bad = copy.deepcopy(catalog)
    bad["particles"]["t-bad"] = tinter()
    bad["particles"]["t-bad"]["specific_absorption_per_um"]["value"] = [1.0, 2.0]
    assert any("particles.t-bad.specific_absorption_per_um" in p and "make them equal" in p for p in validate_catalog(bad))
    bad["particles"]["t-bad"] = tinter(g=0.99)
    assert any("asymmetry_g" in p for p in validate_catalog(bad))
    bad["particles"]["t-bad"] = tinter(a=(1.0, -1.0, 1.0))
    assert any("specific_absorption_per_um.value" in p for p in validate_catalog(bad))
    bad["particles"]["t-bad"] = tinter(wl=[400.0, 700.0, 550.0])
    assert any("strictly increasing" in p for p in validate_catalog(bad))


def test_recipe_checks(catalog):
    with pytest.raises(RecipeError, match=r"particles\[0\]\.median_diameter_um: 't-var' is a tinter.*no particle size"):
        recipe_from_doc(recipe([{"species": "t-var", "volume_fraction": 0.05, "median_diameter_um": 0.3}]), "x", catalog)
    doc = recipe([{"species": "t-var", "volume_fraction": 0.05}])
    doc["spectral"]["range_nm"] = [380, 780]
    doc["spectral"]["step_nm"] = 10
    with pytest.raises(RecipeError, match=r"covers 400-700 nm, the grid 380-780 nm \(hint: narrow spectral.range_nm\)"):
        recipe_from_doc(doc, "x", catalog)


def test_store_leaves_tinters_out(catalog, tmp_path):
    rec = recipe_from_doc(recipe([{"species": "t-var", "volume_fraction": 0.05},
                                  {"species": "titanium-white-r706", "volume_fraction": 0.1}]), "s", catalog)
    assert [p.species for p in catalog_species(rec)] == ["titanium-white-r706"]
    path = tmp_path / "user.yaml"
    path.write_text(yaml.safe_dump(catalog, sort_keys=False))
    req = make_request(catalog_path=str(path), n=16)
    assert "t-var" not in req.species and "titanium-white-r706" in req.species
    with pytest.raises(ValueError, match="t-var: a tinter is computed directly"):
        make_request(species=["t-var"], catalog_path=str(path), n=16)


def test_species_list_and_show(catalog, tmp_path):
    path = tmp_path / "user.yaml"
    path.write_text(yaml.safe_dump(catalog, sort_keys=False))
    r = CliRunner().invoke(cli, ["species", "list", "--json", "--catalog", str(path)])
    assert r.exit_code == 0, r.output
    rows = json.loads(r.output)
    rows = rows if isinstance(rows, list) else rows["species"]
    row = [x for x in rows if x["name"] == "t-var"][0]
    assert row["kind"] == "tinter" and row["source"] == "tests"
    r = CliRunner().invoke(cli, ["species", "show", "t-var", "--catalog", str(path)])
    assert r.exit_code == 0, r.output
    line = [ln for ln in r.output.splitlines() if ln.strip().startswith("550")][0].split()
    assert [float(v) for v in line[1:]] == pytest.approx([0.5, 1.5, 0.75, 0.4])
